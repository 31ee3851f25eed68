"""Group adaptation: the online adaptation's own cost per control sample."""

from __future__ import annotations

import time

import numpy as np

from cosim.base.labels import period_text
from cosim.benchmarks.common import REPLAY_PASSES, BenchRow, _p99, instruction_row, per_sample_median_row
from cosim.benchmarks.subjects import _mixed_scenario, _nn_model
from cosim.design.vocabulary import SWITCHING_PERIOD


def bench_adaptation(quick: bool) -> list[BenchRow]:
    """The online adaptation's own cost per control sample (recursive least squares on the output
    layer with its guards), apart from the NNPC step it wraps: the adaptive controller's time per
    sample minus its inner NNPC's, on the mixed scenario at one switching period."""
    from controllers.adaptation import AdaptiveNNPC
    from cosim.design.experiments import adaptive_nnpc, implemented
    from cosim.design.plants import plant_binding
    from cosim.fmi.plant import open_plant
    from cosim.master import run

    period = SWITCHING_PERIOD
    samples = 60 if quick else 1500
    model, origin = _nn_model("nnpc", period, quick)
    adaptive = implemented(adaptive_nnpc(model, period))
    inner_times: list[int] = []
    totals: list[int] = []
    learned: list[bool] = []
    inner_step = adaptive.inner.step
    clock = time.perf_counter_ns

    def timed_inner(measurement):
        start = clock()
        duty = inner_step(measurement)
        inner_times.append(clock() - start)
        return duty

    class Timed(AdaptiveNNPC):
        def step(self, measurement):
            updates = self.counters["updates"]
            start = clock()
            duty = super().step(measurement)
            totals.append(clock() - start)
            learned.append(self.counters["updates"] > updates)
            return duty

    timed = Timed(adaptive.inner, adaptive.model, adaptive.settings, adaptive.name, nominal_load=adaptive.nominal_load,
                  nominal_input_voltage=adaptive.nominal_input_voltage)
    timed.inner.step = timed_inner
    with open_plant(plant_binding("nominal", "switched")) as plant:
        run(plant, timed, _mixed_scenario(period, samples), record_period=period)
    overhead = (np.array(totals) - np.array(inner_times)) * 1e-3  # [us]
    updated = overhead[np.array(learned)]
    rate = period_text(period, ascii_only=True)
    rows = [BenchRow(f"online adaptation per control sample, NNPC-adaptive at {rate} ({len(overhead)} samples, "
                     f"{timed.counters['updates']} RLS updates; the NNPC step itself excluded)",
                     float(np.median(overhead)), _p99(overhead), "us", note=f"NN: {origin}")]
    if len(updated):
        rows.append(BenchRow("online adaptation per RLS update (samples that passed the guards)",
                             float(np.median(updated)), _p99(updated), "us"))
    optimizer = "real-time iteration" if adaptive.inner.rti is not None else "search"
    rows.append(BenchRow(f"NNPC step the adaptation wraps (C twin, {optimizer}), same run",
                         float(np.median(inner_times)) * 1e-3, _p99(np.array(inner_times) * 1e-3), "us",
                         note="the Python adaptation around the C NNPC (the drift study's implementation); the "
                              "adaptation's own C twin is timed below"))
    return rows + _adaptive_c_step_rows(model, origin, samples)


def _adaptive_c_step_rows(model, origin: str, samples: int) -> list[BenchRow]:
    """The adaptive NNPC's C step -- the RLS on the output layer (controllers/c/adaptation.c) and the NNPC it
    adapts, with the real-time iteration -- timed in the C harness (Python out of the loop) on measurements of
    the drifted plant (the drift study's mismatch plant) at 13.33 us; issue 24's target is on the samples the RTI
    planned, the search's fallback samples reported apart, as the c-controllers group does."""
    from cosim.benchmark_harness import record_measurements, replay
    from cosim.design.experiments import adaptive_nnpc, implemented
    from cosim.design.plants import plant_binding

    period = SWITCHING_PERIOD
    adaptive = adaptive_nnpc(model, period, optimizer="rti")
    measurements = record_measurements(plant_binding("mismatch", "switched"), implemented(adaptive),
                                       _mixed_scenario(period, samples))
    result = replay(adaptive, measurements, repeats=REPLAY_PASSES)
    us = result.ns.reshape(-1, len(measurements)) * 1e-3
    rti, updated = result.rti, result.rti & result.updated
    planned, learned, searched = us[:, rti], us[:, updated], us[:, ~rti]
    p99 = _p99(planned)
    name = f"C step, NNPC-adaptive (RLS + RTI, controllers/c/adaptation.c), {period_text(period, ascii_only=True)}"
    limit = period * 1e6  # [us] real time: the step within its sample
    rows = [BenchRow(f"{name}: the {int(rti.sum())} of {len(measurements)} samples the RTI planned",
                     float(np.median(planned)), p99, "us", f"p99 <= {limit:.3g} us", p99 <= limit,
                     f"NN: {origin}; mismatch switched plant, {len(us)} passes; the search planned the other "
                     f"{int((~rti).sum())} (cold start, start-up region, reference steps): p50 "
                     f"{float(np.median(searched)):.4g} us, max {float(np.max(searched)):.4g} us")]
    rows.append(per_sample_median_row(f"{name}: the RTI samples", us, rti, limit))
    if updated.any():
        rows.append(BenchRow(f"{name}: the {int(updated.sum())} RTI samples with an RLS update",
                             float(np.median(learned)), _p99(learned), "us",
                             note="the update's share: these against the RTI samples without one"))
    rows.append(instruction_row(f"x86-64 instructions per {name}", adaptive, measurements, rti))
    return rows
