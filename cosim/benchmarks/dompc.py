"""Group do-mpc: the same NNPC problem solved by do-mpc (CasADi + IPOPT) next to the workbench's C RTI."""

from __future__ import annotations

import numpy as np

from cosim.base.labels import period_text
from cosim.benchmarks.common import BenchRow, _p99, instruction_row
from cosim.benchmarks.subjects import _nn_model
from cosim.study.vocabulary import NNPC, SWITCHING_PERIOD


def bench_dompc(quick: bool) -> list[BenchRow]:
    """The workbench's C RTI NNPC and do-mpc on the same problem (network, cost, horizon, blocks, bounds,
    estimation: cosim/study/dompc_peer.py), each in closed loop on the nominal switched plant FMU through the
    paper's start-up and load change at 13.33 us: time per step (the C RTI's by the C harness replaying its
    own closed loop's measurements, do-mpc's solve timed in-process), IAE and the eq. 16 cost of the plans.

    The C passes are interleaved with do-mpc's solves: one before its closed loop, one after every
    ceil(samples / :data:`C_PASSES`) of its samples, one after it, so that both steps' medians are taken over the
    same stretch of time. This VM's speed steps between two levels (cosim/benchmark_harness/
    instruction_count.py): with one C pass before do-mpc's loop and two after it, one run of today's code measured
    the load change's ratio 800 x, its C step's p50 7.8 us there and 4.3 us in the start-up. The ratio row's note
    gives the C passes' medians' spread; each scenario's instructions per RTI step (callgrind) are a row of their
    own, the step's cost whatever the VM's speed."""
    from cosim.benchmark_harness import Recorder, replay_warm
    from cosim.master import simulate
    from cosim.metrics import run_metrics
    from cosim.study.dompc_peer import DoMpcNnpc
    from cosim.study.experiments import (
        NOMINAL_OPERATING_POINT,
        horizon_settings,
        implemented,
        nnpc,
        scenarios_for,
    )
    from cosim.study.plants import plant_binding

    period = SWITCHING_PERIOD
    binding = plant_binding("nominal", "switched")
    model, origin = _nn_model("nnpc", period, quick)
    rows = []
    for scenario in scenarios_for(period, ("startup", "load_change")):
        if quick:
            scenario = replace_scenario(scenario, 0.0003)
        rti = nnpc(model, period, NNPC, optimizer="rti")
        twin = Recorder(PlanCosts(implemented(rti), _rti_plan_cost))  # one closed loop: its costs and the
        result_rti = simulate(binding, twin, scenario, record_period=period)  # measurements the harness replays
        measurements = np.array(twin.rows, dtype=float)
        peer = DoMpcNnpc(model, period, horizon_settings(period), **NOMINAL_OPERATING_POINT)
        replays = []  # each C pass (its step times and the RTI's counters), in time order

        def time_c_pass(replays=replays, rti=rti, measurements=measurements):  # this scenario's, bound now
            replays.append(replay_warm(rti, measurements, 1, warm_up=not quick))

        costed_peer = PlanCosts(peer, lambda solver: solver.best_cost, every=-(-len(measurements) // C_PASSES),
                                between=time_c_pass)  # ceil: <= C_PASSES passes inside the loop
        time_c_pass()
        result_peer = simulate(binding, costed_peer, scenario, record_period=period)
        time_c_pass()
        costs, peer_costs = twin.inner.costs, costed_peer.costs
        # the same RTI without its reweightings (RtiSettings.reweightings: one QP per sample), for their share
        plain = nnpc(model, period, NNPC, optimizer="rti", rti_changes={"reweightings": 0})
        iae_plain = run_metrics(simulate(binding, implemented(plain), scenario, record_period=period))["iae_Vs"]
        solve = np.array(peer.solve_times[1:] or peer.solve_times) * 1e6  # the first includes IPOPT's set-up
        timed = replays[-1]  # the RTI's counters: every pass replays the same steps from a reset
        passes = [replay.ns * 1e-3 for replay in replays]  # [us]
        c_us = np.concatenate(passes)
        ratio = float(np.median(solve)) / float(np.median(c_us))
        pass_medians = [float(np.median(p)) for p in passes]
        reweighted_share = float(np.mean(timed.reweighted[timed.rti] > 0)) if timed.rti.any() else 0.0
        iae_rti, iae_peer = run_metrics(result_rti)["iae_Vs"], run_metrics(result_peer)["iae_Vs"]
        label = f"{scenario.name}, {period_text(period, ascii_only=True)}, nominal switched plant"
        rows += [
            BenchRow(f"C RTI NNPC step, {label} ({len(measurements)} samples x {len(passes)} passes)",
                     float(np.median(c_us)), _p99(c_us), "us",
                     note=f"NN: {origin}; every step, the {int(np.count_nonzero(~timed.rti))} the search planned (the "
                          "cold start, the start-up region) included; the passes interleaved with do-mpc's solves"),
            instruction_row(f"x86-64 instructions per C RTI step, {label}", rti, measurements, timed.rti),
            BenchRow(f"do-mpc (IPOPT) step on the same problem, {label} ({len(solve)} solves after the first)",
                     float(np.median(solve)), _p99(solve), "us",
                     note=f"the first solve (IPOPT's set-up included) took {peer.solve_times[0] * 1e3:.4g} ms"),
            BenchRow(f"do-mpc step / C RTI step, {label} (p50)", ratio, None, "ratio", ">= 1000", ratio >= 1000,
                     f"the C step's p50 over its {len(passes)} passes interleaved with do-mpc's solves; each pass's "
                     f"p50 {min(pass_medians):.3g}-{max(pass_medians):.3g} us"),
            BenchRow(f"closed-loop IAE, C RTI / do-mpc, {label}", iae_rti / iae_peer, None, "ratio", "<= 1.02",
                     iae_rti / iae_peer <= 1.02, f"IAE {iae_rti:.4g} V s (RTI), {iae_peer:.4g} V s (do-mpc); the RTI's "
                                                 f"reweighted QPs at {100 * reweighted_share:.2g} % of its samples"),
            BenchRow(f"closed-loop IAE, C RTI without reweightings / do-mpc, {label}", iae_plain / iae_peer, None,
                     "ratio", note="one box QP per sample (RtiSettings.reweightings = 0)"),
            BenchRow(f"eq. 16 cost of the plan per step, C RTI, {label}", float(np.mean(costs)),
                     float(np.percentile(costs, 99)), "V (discounted sum)", note="mean in the median column"),
            BenchRow(f"eq. 16 cost of the plan per step, do-mpc, {label}", float(np.mean(peer_costs)),
                     float(np.percentile(peer_costs, 99)), "V (discounted sum)",
                     note="mean in the median column; do-mpc minimises the smoothed norm (eps = "
                          f"{peer.smoothing} V), the cost is the exact eq. 16 of its plan"),
        ]
    return rows


#: at most this many C passes interleaved with do-mpc's closed loop, besides one before it and one after
#: (bench_dompc)
C_PASSES = 12


class PlanCosts:
    """A controller in the closed loop, keeping after each step ``plan_cost(controller)``: the eq. 16 cost of the
    plan it applied (``costs``, one per step since the last reset). With ``between``, it also calls ``between()``
    after every ``every``-th step: do-mpc's solves with C passes timed between them. ``between`` runs outside
    do-mpc's solve timing (``solve_times``) but inside this wrapper's step, so the master's compute column and a
    harness error are the wrapper's, a benchmark's instrument, not a controller of the study."""

    def __init__(self, controller, plan_cost, every: int = 1, between=None):
        self.controller, self.plan_cost, self.every, self.between = controller, plan_cost, every, between
        self.name, self.sample_period, self.duty_limits = (controller.name, controller.sample_period,
                                                           controller.duty_limits)
        self.costs: list[float] = []

    def reset(self):
        self.controller.reset()
        self.costs = []

    def step(self, m):
        duty = self.controller.step(m)
        self.costs.append(self.plan_cost(self.controller))
        if self.between is not None and len(self.costs) % self.every == 0:
            self.between()
        return duty

    def describe(self):
        return self.controller.describe()


def _rti_plan_cost(twin) -> float:
    """The C RTI's plan cost: NaN where it did not roll its plan out (no line search), evaluated then."""
    cost = twin.best_cost
    return cost if np.isfinite(cost) else twin.cost(twin.plan_sequence)[0]


def replace_scenario(scenario, duration: float):
    """``scenario`` cut to ``duration`` [s] (its events that fall inside kept): the quick profile."""
    from dataclasses import replace

    return replace(scenario, duration=duration, events=tuple(e for e in scenario.events if e.time < duration))
