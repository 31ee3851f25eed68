"""Group controllers: controller compute per step, in the co-simulation loop, in both implementations --
the C twin (what the workbench runs by default) and the Python reference."""

from __future__ import annotations

import numpy as np

from cosim.benchmarks.common import BenchRow, _p99
from cosim.benchmarks.subjects import _benchmark_pi, _mixed_scenario, _nn_model
from cosim.design.vocabulary import (
    IMPLEMENTATIONS,
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
    """Each controller's ``controller_compute_time`` over the mixed scenario on the nominal switched plant, as
    the master measures it around the controller's step (for the C twin: its ctypes call included). The NNPC's
    p99 target at 1 ms is on both implementations' rows; the reproduction's timing target reads the C twin's."""
    from cosim.design.experiments import implemented, model_mpc, nnpc
    from cosim.design.plants import plant_binding
    from cosim.fmi.plant import open_plant
    from cosim.master import run
    from cosim.study.targets import NNPC_P99_TARGET_US, controller_compute_benchmark

    rows = []
    binding = plant_binding("nominal", "switched")
    for period in (PAPER_PERIOD, SWITCHING_PERIOD):
        samples = 60 if quick else (3000 if transient_within_sample(period) else 1500)
        scenario = _mixed_scenario(period, samples)
        model, origin = _nn_model("nnpc", period, quick)
        controllers = [_benchmark_pi(period), nnpc(model, period, NNPC),
                       model_mpc(NOMINAL, period, MPC_ORACLE, binding=binding),
                       model_mpc(MISMATCH, period, MPC_MISMATCHED, binding=binding)]
        with open_plant(binding) as plant:
            for controller in controllers:
                for implementation in IMPLEMENTATIONS:
                    frame = run(plant, implemented(controller, implementation), scenario, record_period=period).frame
                    times = frame.loc[frame["control_sample"], "controller_compute_time"].to_numpy()
                    median, p99 = float(np.median(times)), _p99(times)
                    target, met = "", None
                    if controller.name == NNPC and transient_within_sample(period):
                        target, met = f"p99 <= {NNPC_P99_TARGET_US:g} us", p99 * 1e6 <= NNPC_P99_TARGET_US
                    rows.append(BenchRow(
                        f"{controller_compute_benchmark(controller.name, period, implementation)} ({len(times)} "
                        f"samples, {100 * median / period:.2g} % / {100 * p99 / period:.2g} % of the period at "
                        f"p50 / p99)", median * 1e6, p99 * 1e6, "us", target, met,
                        f"NN: {origin}" if controller.name == NNPC else ""))
    return rows
