"""Group do-mpc: the same NNPC problem solved by do-mpc (CasADi + IPOPT) next to the workbench's C RTI."""

from __future__ import annotations

import numpy as np

from cosim.base.labels import period_text
from cosim.benchmarks.common import BenchRow, _p99
from cosim.benchmarks.subjects import _nn_model
from cosim.study.vocabulary import NNPC, SWITCHING_PERIOD


def bench_dompc(quick: bool) -> list[BenchRow]:
    """The workbench's C RTI NNPC and do-mpc on the same problem (network, cost, horizon, blocks, bounds,
    estimation: cosim/study/dompc_peer.py), each in closed loop on the nominal switched plant FMU through the
    paper's start-up and load change at 13.33 us: time per step (the C RTI's by the C harness replaying its
    own closed loop's measurements, one pass before do-mpc's closed loop and two after it, so that its passes
    span do-mpc's solves on a machine whose speed drifts; do-mpc's solve timed in-process), IAE and the eq. 16
    cost of the plans."""
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
        before = replay_warm(rti, measurements, 1, warm_up=not quick)
        peer = DoMpcNnpc(model, period, horizon_settings(period), **NOMINAL_OPERATING_POINT)
        costed_peer = PlanCosts(peer, lambda solver: solver.best_cost)
        result_peer = simulate(binding, costed_peer, scenario, record_period=period)
        costs, peer_costs = twin.inner.costs, costed_peer.costs
        # the same RTI without its reweightings (RtiSettings.reweightings: one QP per sample), for their share
        plain = nnpc(model, period, NNPC, optimizer="rti", rti_changes={"reweightings": 0})
        iae_plain = run_metrics(simulate(binding, implemented(plain), scenario, record_period=period))["iae_Vs"]
        solve = np.array(peer.solve_times[1:] or peer.solve_times) * 1e6  # the first includes IPOPT's set-up
        timed = replay_warm(rti, measurements, 1 if quick else 2, warm_up=not quick)  # after do-mpc's loop
        c_ns = np.concatenate([before.ns, timed.ns]) * 1e-3
        reweighted_share = float(np.mean(timed.reweighted[timed.rti] > 0)) if timed.rti.any() else 0.0
        iae_rti, iae_peer = run_metrics(result_rti)["iae_Vs"], run_metrics(result_peer)["iae_Vs"]
        label = f"{scenario.name}, {period_text(period, ascii_only=True)}, nominal switched plant"
        rows += [
            BenchRow(f"C RTI NNPC step, {label} ({len(measurements)} samples)", float(np.median(c_ns)),
                     _p99(c_ns), "us", note=f"NN: {origin}; every step, the {int(np.count_nonzero(~timed.rti))} the "
                                            "search planned (the cold start, the start-up region) included"),
            BenchRow(f"do-mpc (IPOPT) step on the same problem, {label} ({len(solve)} solves after the first)",
                     float(np.median(solve)), _p99(solve), "us",
                     note=f"the first solve (IPOPT's set-up included) took {peer.solve_times[0] * 1e3:.4g} ms"),
            BenchRow(f"do-mpc step / C RTI step, {label} (p50)", float(np.median(solve)) / float(np.median(c_ns)),
                     None, "ratio", ">= 1000", float(np.median(solve)) / float(np.median(c_ns)) >= 1000),
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


class PlanCosts:
    """A controller in the closed loop, keeping after each step ``plan_cost(controller)``: the eq. 16 cost of the
    plan it applied (``costs``, one per step since the last reset)."""

    def __init__(self, controller, plan_cost):
        self.controller, self.plan_cost = controller, plan_cost
        self.name, self.sample_period, self.duty_limits = (controller.name, controller.sample_period,
                                                           controller.duty_limits)
        self.costs: list[float] = []

    def reset(self):
        self.controller.reset()
        self.costs = []

    def step(self, m):
        duty = self.controller.step(m)
        self.costs.append(self.plan_cost(self.controller))
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
