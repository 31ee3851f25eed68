"""The do-mpc peer of the benchmark suite (cosim/study/dompc_peer.py): the CasADi export of the network
against the workbench's forward pass, and a short closed loop on the plant FMU."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import random_model

from controllers.nn_config import NNConfig
from controllers.nn_model import load_model
from cosim.design.vocabulary import SWITCHING_PERIOD
from cosim.study.vocabulary import PAPER_SPEC

FIXTURES = Path(__file__).parent / "fixtures"


@pytest.mark.parametrize("config", [NNConfig(delays=2, hidden=(10,), extra_signals=("load_conductance", "input_voltage")),
                                    NNConfig(hidden=(5, 6), activation="sigmoid", residual=True),
                                    NNConfig(hidden=(9,), activation="relu", delays=3)], ids=lambda c: c.label)
def test_casadi_export_of_the_network_matches_the_workbench_forward_pass(config):
    from cosim.study.dompc_peer import casadi_network

    model = random_model(config, 7)
    network = casadi_network(model)
    x = np.random.default_rng(1).normal(size=(200, config.n_inputs)) * model.input_std + model.input_mean
    exported = np.array(network(x.T)).T  # casadi maps the columns
    expected = model.predict(x)
    assert np.max(np.abs(exported - expected)) <= 1e-12 * max(1.0, float(np.max(np.abs(expected))))


def test_the_export_reads_the_model_file():
    from cosim.study.dompc_peer import casadi_network_from_file

    path = FIXTURES / "nnpc_mismatch_switched_13p33us.pt"
    model = load_model(path, expect_period=SWITCHING_PERIOD)
    network = casadi_network_from_file(path, expect_period=SWITCHING_PERIOD)
    x = np.random.default_rng(2).normal(size=(100, model.config.n_inputs)) * model.input_std + model.input_mean
    assert np.max(np.abs(np.array(network(x.T)).T - model.predict(x))) <= 1e-12 * 20


def test_do_mpc_drives_the_plant_with_the_workbenchs_problem():
    """A short start-up at 13.33 us: do-mpc's plans hold the move blocks and the duty bounds, their eq. 16
    cost is what the workbench's rollout gives, and the closed loop lands near the RTI NNPC's IAE (the RTI
    alone from the cold start on: without the start-up region, where the search would plan): the RTI within
    issue 24's 2 % of do-mpc's or better (measured 0.356 against 0.410 mV s), do-mpc within 25 % of the RTI's."""
    from cosim.design.experiments import NOMINAL_OPERATING_POINT, horizon_settings, nnpc
    from cosim.design.plants import plant_binding
    from cosim.master import simulate
    from cosim.metrics import run_metrics
    from cosim.scenarios import load_scenario
    from cosim.study.dompc_peer import DoMpcNnpc

    model = load_model(FIXTURES / "nnpc_mismatch_switched_13p33us.pt", expect_period=SWITCHING_PERIOD)
    peer = DoMpcNnpc(model, SWITCHING_PERIOD, horizon_settings(SWITCHING_PERIOD), **NOMINAL_OPERATING_POINT)
    scenario = replace(load_scenario("startup", PAPER_SPEC), duration=0.0004)
    binding = plant_binding("mismatch", "switched")
    rti = nnpc(model, SWITCHING_PERIOD, optimizer="rti")
    rti.rti = replace(rti.rti, startup_region=0.0)
    runs = [simulate(binding, c, scenario, record_period=SWITCHING_PERIOD) for c in (peer, rti)]
    plan = peer._warm
    blocks = np.repeat(np.arange(len(peer.settings.blocks)), peer.settings.blocks)
    for b in range(len(peer.settings.blocks)):
        assert np.ptp(plan[blocks == b]) <= 1e-6  # held over each block
    assert np.all((plan >= 0.0) & (plan <= 1.0)) and peer.last_solver == "do-mpc"
    peer.plan(*peer._problem[:4], "")
    assert len(peer.solve_times) == len(runs[0].frame[runs[0].frame["control_sample"]]) + 1
    iae = [run_metrics(r)["iae_Vs"] for r in runs]
    assert iae[1] <= 1.02 * iae[0] and iae[0] <= 1.25 * iae[1]
    assert peer.describe()["optimizer"].startswith("do-mpc")


def test_a_c_pass_follows_every_one_of_the_peers_steps():
    """bench_dompc's PlanCosts with ``after_step``: it runs after every step, the duties and the plan costs pass
    through unchanged, and a reset restarts the costs."""
    from cosim.benchmarks.dompc import PlanCosts

    class Counting:
        name, sample_period, duty_limits = "probe", 1e-3, (0.0, 1.0)

        def __init__(self):
            self.steps = 0

        def reset(self):
            self.steps = 0

        def step(self, m):
            self.steps += 1
            return 0.1 * self.steps

        def describe(self):
            return {"name": self.name}

    calls = []
    inner = Counting()
    loop = PlanCosts(inner, lambda c: 2.0 * c.steps, after_step=lambda: calls.append(inner.steps))
    duties = [loop.step(None) for _ in range(10)]
    assert duties == [0.1 * k for k in range(1, 11)] and calls == list(range(1, 11))
    assert loop.costs == [2.0 * k for k in range(1, 11)]
    assert (loop.name, loop.sample_period, loop.duty_limits, loop.describe()) == ("probe", 1e-3, (0.0, 1.0),
                                                                                 {"name": "probe"})
    loop.reset()
    [loop.step(None) for _ in range(4)]
    assert calls == [*range(1, 11), 1, 2, 3, 4] and loop.costs == [2.0, 4.0, 6.0, 8.0]


def test_the_ratio_pairs_each_solve_with_the_c_pass_right_after_it():
    """paired_ratio: a VM at two speeds (the C step's p50 5 us or 10 us, the solve 6 ms or 12 ms with it) gives each
    pair 1 200 x whatever the mix of speeds or their order; mismatched lengths raise."""
    from cosim.benchmarks.dompc import paired_ratio

    solve = np.array([6000.0, 6000.0, 12000.0, 12000.0, 12000.0])
    pass_p50 = np.array([5.0, 5.0, 10.0, 10.0, 10.0])
    assert paired_ratio(solve, pass_p50) == pytest.approx(1200.0, rel=1e-12)
    assert paired_ratio(solve[::-1], pass_p50[::-1]) == pytest.approx(1200.0, rel=1e-12)
    with pytest.raises(ValueError, match="paired_ratio: 5 solves and 4 C passes"):
        paired_ratio(solve, pass_p50[:4])
