"""The C benchmark harness (cosim.benchmark_harness): the step it times is the controller's own
C step (same duties and candidate evaluations as the in-process twin), and its operation counts
match what the Python reference actually evaluates."""

from __future__ import annotations

import re
import types
from pathlib import Path

import numpy as np
import pytest

import controllers.nn_model as nn_model_module
from controllers.base import Measurement
from controllers.pi import PIController
from cosim.benchmark_harness import (
    CORTEX_M4F,
    CostModel,
    cortex_m4f_cycles,
    operation_counts,
    record_measurements,
    replay,
)
from cosim.design.experiments import implemented, nnpc, scenarios_for
from cosim.design.plants import plant_binding
from cosim.study.vocabulary import PAPER_SPEC

FIXTURES = Path(__file__).parent / "fixtures"


@pytest.fixture(scope="module")
def measurements(nnpc_1ms):
    scenario = scenarios_for(1e-3, ["load_change"], spec=PAPER_SPEC)[0]
    return record_measurements(plant_binding("nominal", "averaged"), implemented(nnpc_1ms), scenario)


def test_the_replayed_c_step_is_the_twin_step(nnpc_1ms, measurements):
    result = replay(nnpc_1ms, measurements, repeats=2)
    assert len(result.ns) == 2 * len(measurements) and (result.ns > 0).all()
    twin = implemented(nnpc_1ms)
    twin.reset()
    duties, evaluations = [], []
    for row in measurements:
        duties.append(twin.step(Measurement(*row)))
        evaluations.append(twin.state.evaluations)
    np.testing.assert_array_equal(result.duty, duties)
    np.testing.assert_array_equal(result.evaluations, evaluations)
    # the RTI plans every step but the cold start's, which the search plans (its candidate evaluations)
    assert list(result.rti) == [False] + [True] * (len(measurements) - 1)
    assert (result.evaluations[0] > 0) and (result.evaluations[1:] == 0).all() and (result.passes >= 0).all()


def test_the_replayed_pi_matches_the_python_pi(measurements):
    pi = PIController(0.0015, 15.6, 1e-3, duty_limits=(0.0, 0.95))
    result = replay(pi, measurements, repeats=1)
    pi.reset()
    expected = [pi.step(Measurement(*row)) for row in measurements]
    np.testing.assert_array_equal(result.duty, expected)
    assert (result.evaluations == 0).all()


def test_tanh_counts_match_what_the_python_reference_evaluates(nnpc_1ms, measurements, monkeypatch):
    """Count the elements numpy's tanh is given while the Python NNPC steps through the same inputs;
    the harness's counts from its candidate evaluations must equal them step by step."""
    counted = []

    def counting_tanh(z, *args, **kwargs):
        counted[-1] += np.size(z)
        return np.tanh(z, *args, **kwargs)

    proxy = types.SimpleNamespace(**{name: getattr(np, name) for name in dir(np) if not name.startswith("__")})
    proxy.tanh = counting_tanh
    monkeypatch.setattr(nn_model_module, "np", proxy)
    controller = nnpc(nnpc_1ms.predictor.model, 1e-3, optimizer="search")  # the RTI's counts: the test below
    controller.reset()
    evaluations = []
    for row in measurements:
        counted.append(0)
        controller.step(Measurement(*row))
        evaluations.append(controller.optimizer.evaluations)
    counts = operation_counts(controller, np.array(evaluations))
    np.testing.assert_array_equal(counts["tanh"], counted)
    hidden, horizon = controller.predictor.model.config.hidden[0], controller.settings.horizon
    assert controller.predictor.model.config.delays == 1  # the shared fast path: 3H, then 5H MACs a step
    np.testing.assert_array_equal(counts["macs"], np.array(evaluations) * (3 * hidden + 5 * hidden * (horizon - 1)
                                                                          + 3 * horizon))
    np.testing.assert_array_equal(counts["sqrt"], np.array(evaluations) * horizon)


@pytest.mark.parametrize("iterations", [1, 2])
@pytest.mark.parametrize("line_search", [False, True])
def test_rti_tanh_counts_match_what_the_python_reference_evaluates(monkeypatch, line_search, iterations):
    """The RTI NNPC at 13.33 us (the fixture's 7-10-2, two delays, 6 blocks): numpy's tanh elements counted
    per step equal the cost model's count, at the cold start's search and at every RTI step after it (one
    linearisation per Gauss-Newton step, then the plan's first state -- or, with the line search, its rollout)."""
    from dataclasses import replace

    from controllers.cost_model import rti_operation_counts
    from controllers.nn_model import load_model
    from cosim.design.vocabulary import SWITCHING_PERIOD

    model = load_model(FIXTURES / "nnpc_mismatch_switched_13p33us.pt", expect_period=SWITCHING_PERIOD)
    controller = nnpc(model, SWITCHING_PERIOD, optimizer="rti")
    # (the study's reweightings are refused with the line search; they evaluate no tanh either way)
    controller.rti = replace(controller.rti, line_search=line_search, iterations=iterations,
                             reweightings=0 if line_search else controller.rti.reweightings)
    controller.rti_optimizer.settings = controller.rti
    counted = []

    def counting_tanh(z, *args, **kwargs):
        counted[-1] += np.size(z)
        return np.tanh(z, *args, **kwargs)

    proxy = types.SimpleNamespace(**{name: getattr(np, name) for name in dir(np) if not name.startswith("__")})
    proxy.tanh = counting_tanh
    monkeypatch.setattr(nn_model_module, "np", proxy)
    monkeypatch.setattr(model, "_activation", counting_tanh)  # the generic path's (two delays) activation
    rti, qp, evaluations, reweighted = [], [], [], []
    for k in range(6):
        counted.append(0)
        # within the start-up region's 0.1 V of the reference: the RTI plans every step after the cold start
        controller.step(Measurement(k * SWITCHING_PERIOD, 12.0, 11.95 + 0.01 * k, 2.0, 1.99, 48.0))
        rti.append(controller.last_solver == "rti")
        qp.append(controller.rti_optimizer.qp_iterations if rti[-1] else 0)
        reweighted.append(controller.rti_optimizer.reweighted if rti[-1] else 0)
        evaluations.append(0 if rti[-1] else controller.optimizer.evaluations)
    counts = rti_operation_counts(controller, np.array(rti), np.array(qp), np.array(evaluations), np.array(reweighted))
    assert rti == [False] + [True] * 5
    np.testing.assert_array_equal(counts["tanh"], counted)
    hidden, horizon = model.config.hidden[0], 23
    # each Gauss-Newton step linearises the rollout (horizon states); then the plan is rolled out whole with the
    # line search, else only its first state is predicted
    assert counted[1] == (controller.rti.iterations * horizon + (horizon if line_search else 1)) * hidden
    assert (counts["qp_iterations"][1:] >= 1).all() and counts["macs"][1] > counts["tanh"][1]
    if iterations > 1:
        # the other way to take the second step (a rollout with the first step's sensitivities, or a linearisation):
        # the same tanh, and per RTI step the same number of MACs more for the linearisation than for the rollout
        flipped = types.SimpleNamespace(rti=replace(controller.rti, reuse_jacobian=not controller.rti.reuse_jacobian),
                                        settings=controller.settings, predictor=controller.predictor)
        other = rti_operation_counts(flipped, np.array(rti), np.array(qp), np.array(evaluations), np.array(reweighted))
        np.testing.assert_array_equal(other["tanh"], counts["tanh"])
        extra = (other["macs"] - counts["macs"]) * (1 if controller.rti.reuse_jacobian else -1)
        assert extra[0] == 0 and np.all(extra[1:] == extra[1]) and extra[1] > 0


def test_cycle_estimate_is_the_cost_model_applied_to_the_counts():
    counts = {"macs": np.array([100.0]), "tanh": np.array([10.0]), "sqrt": np.array([4.0]),
              "candidates": np.array([2.0])}
    model = CostModel(mac=1.0, tanh=10.0, sqrt=100.0, candidate=1000.0, interrupt=10000.0)
    assert cortex_m4f_cycles(counts, model)[0] == 100 + 100 + 400 + 2000 + 10000
    assert cortex_m4f_cycles(counts)[0] == pytest.approx(100 * CORTEX_M4F.mac + 10 * CORTEX_M4F.tanh + 4 * CORTEX_M4F.sqrt
                                                         + 2 * CORTEX_M4F.candidate + CORTEX_M4F.interrupt)


def test_the_calibration_takes_the_measured_tanh_and_what_the_forward_pass_leaves_per_mac():
    from controllers.cost_model import calibrated

    model = calibrated(CORTEX_M4F, tanh_cycles=60.0, forward_cycles=1500.0, layer_macs=112, tanh_calls=14)
    assert model.tanh == 60.0 and model.mac == pytest.approx((1500 - 14 * 60) / 112)
    assert (model.sqrt, model.candidate, model.interrupt, model.division) == (
        CORTEX_M4F.sqrt, CORTEX_M4F.candidate, CORTEX_M4F.interrupt, CORTEX_M4F.division)
    with pytest.raises(ValueError, match="calibrates nothing"):
        calibrated(CORTEX_M4F, tanh_cycles=200.0, forward_cycles=1500.0, layer_macs=112, tanh_calls=14)


def test_the_classical_controllers_operation_counts_follow_their_c_steps():
    """Current mode: (ki Ts) e and kp e in two loops; a Type-III of order 3: b0 e and two products per state."""
    from controllers.cost_model import compensator_operation_counts, current_mode_operation_counts

    assert current_mode_operation_counts() == {"macs": 6.0, "tanh": 0.0, "sqrt": 0.0, "division": 1.0,
                                               "candidates": 1.0}
    assert compensator_operation_counts(3)["macs"] == 7.0 and compensator_operation_counts(1)["macs"] == 3.0
    counts = compensator_operation_counts(3)
    assert cortex_m4f_cycles(counts) == pytest.approx(7 * CORTEX_M4F.mac + CORTEX_M4F.division
                                                      + CORTEX_M4F.candidate + CORTEX_M4F.interrupt)


def test_operation_counts_refuse_a_circuit_model_predictor():
    from cosim.design.experiments import model_mpc
    from cosim.design.vocabulary import NOMINAL

    with pytest.raises(ValueError, match="NN predictor"):
        operation_counts(model_mpc(NOMINAL, 1e-3, "MPC"), np.array([1]))


@pytest.mark.counted
def test_instruction_counts_are_each_steps_own_and_the_same_in_every_run(nnpc_1ms, measurements):
    """callgrind counts each replayed step alone (cosim/benchmark_harness/instruction_count.py): one count per
    sample, the cold start's search far above the RTI steps after it, an RTI step of the 4-7-2 network in the
    thousands, and the same counts from a second run -- the measure that does not move with the machine's speed."""
    from cosim.benchmark_harness.instruction_count import instruction_counts
    from cosim.benchmarks.common import instruction_row

    rows = measurements[:40]
    counts = instruction_counts(nnpc_1ms, rows)
    planned = replay(nnpc_1ms, rows, repeats=1).rti
    assert counts.shape == (40,) and counts.dtype == np.int64
    assert not planned[0] and planned[1:].all()  # the search's cold start, then the RTI
    assert counts[0] > 5 * counts[1:].max()
    assert 1_000 < np.median(counts[1:]) < 30_000
    assert np.array_equal(instruction_counts(nnpc_1ms, rows), counts)
    row = instruction_row("x86-64 instructions per C RTI step, NNPC, 1 ms", nnpc_1ms, rows, planned)
    assert (row.median, row.p99) == (float(np.median(counts[1:])), float(counts[1:].max()))
    assert "the 39 RTI samples" in row.benchmark and f"p50 {float(counts[0]):.4g}" in row.note


def test_without_valgrind_the_count_says_why_and_the_benchmark_row_says_not_measured(nnpc_1ms, monkeypatch):
    from cosim.benchmark_harness import instruction_count
    from cosim.benchmarks.common import instruction_row

    monkeypatch.setattr(instruction_count.shutil, "which", lambda name: None)
    monkeypatch.setattr("platform.machine", lambda: "x86_64")
    with pytest.raises(instruction_count.InstructionCountError,
                       match=r"^cannot count instructions: valgrind is not installed \(Debian package valgrind; "):
        instruction_count.instruction_counts(nnpc_1ms, np.zeros((3, 6)))
    row = instruction_row("x86-64 instructions per C RTI step, NNPC, 1 ms", nnpc_1ms, np.zeros((3, 6)),
                          np.ones(3, bool))
    assert row.benchmark.endswith(": not measured") and row.note.startswith("valgrind is not installed")
    monkeypatch.setattr("platform.machine", lambda: "aarch64")
    assert instruction_count.problem() == "the host is aarch64, not x86-64"


def test_a_count_callgrind_did_not_write_is_one_line_and_a_not_measured_row(nnpc_1ms, measurements, monkeypatch):
    """A replay whose step profiles are missing (here: a callgrind that wrote none) raises one line saying how many
    it wrote; the benchmark row then says "not measured" with that line instead of failing its group."""
    import subprocess

    from cosim.benchmark_harness import instruction_count
    from cosim.benchmarks.common import instruction_row

    run = subprocess.run

    def callgrind_writing_nothing(argv, **kwargs):  # the compiler still runs
        return subprocess.CompletedProcess(argv, 0, "", "") if argv[0] == instruction_count.VALGRIND else \
            run(argv, **kwargs)

    monkeypatch.setattr(instruction_count, "problem", lambda: None)
    monkeypatch.setattr(instruction_count.subprocess, "run", callgrind_writing_nothing)
    rows = measurements[:3]
    message = "callgrind wrote 0 step profiles for 3 steps (the first missing: step 1)"
    with pytest.raises(instruction_count.InstructionCountError, match=rf"^{re.escape(message)}$"):
        instruction_count.instruction_counts(nnpc_1ms, rows)
    row = instruction_row("x86-64 instructions per C RTI step, NNPC, 1 ms", nnpc_1ms, rows, np.ones(3, bool))
    assert row.benchmark.endswith(": not measured") and row.note == message
    row = instruction_row("x86-64 instructions per C RTI step, NNPC, 1 ms", nnpc_1ms, rows, np.zeros(3, bool))
    assert row.note == "the RTI planned none of the replayed samples"
