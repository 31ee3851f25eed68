"""Group controllers: controller compute per step."""

from __future__ import annotations

import numpy as np

from cosim.benchmarks.common import BenchRow, _p99
from cosim.benchmarks.subjects import _benchmark_pi, _mixed_scenario, _nn_model
from cosim.study.vocabulary import (
    MISMATCH,
    MPC_MISMATCHED,
    MPC_ORACLE,
    NNPC,
    NOMINAL,
    PAPER_PERIOD,
    SWITCHING_PERIOD,
    transient_within_sample,
)


def bench_controllers(quick: bool) -> list[BenchRow]:
    from cosim.fmi.plant import open_plant
    from cosim.master import run
    from cosim.study.experiments import model_mpc, nnpc, plant_binding

    rows = []
    binding = plant_binding("nominal", "switched")
    for period, label in ((PAPER_PERIOD, "1 ms"), (SWITCHING_PERIOD, "13.33 us")):
        samples = 60 if quick else (3000 if transient_within_sample(period) else 1500)
        scenario = _mixed_scenario(period, samples)
        model, origin = _nn_model("nnpc", period, quick)
        controllers = [_benchmark_pi(period), nnpc(model, period, NNPC),
                       model_mpc(NOMINAL, period, MPC_ORACLE, binding=binding),
                       model_mpc(MISMATCH, period, MPC_MISMATCHED, binding=binding)]
        with open_plant(binding) as plant:
            for controller in controllers:
                frame = run(plant, controller, scenario, record_period=period).frame
                times = frame.loc[frame["control_sample"], "controller_compute_time"].to_numpy()
                median, p99 = float(np.median(times)), _p99(times)
                target, met = "", None
                if controller.name == NNPC and transient_within_sample(period):
                    target, met = "p99 <= 100 us", p99 <= 100e-6
                rows.append(BenchRow(
                    f"controller compute per step, {controller.name}, {label} ({len(times)} samples, "
                    f"{100 * median / period:.2g} % / {100 * p99 / period:.2g} % of the period at p50 / p99)",
                    median * 1e6, p99 * 1e6, "us", target, met,
                    f"NN: {origin}" if controller.name == NNPC else ""))
    return rows
