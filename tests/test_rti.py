"""The real-time-iteration optimizer: its box QP against the KKT conditions, the predictors'
sensitivities against finite differences, its steps against the search, its fallback rule, and the
optimizer ablation of the study."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import random_model

from controllers.base import Measurement
from controllers.box_qp import MAX_VARIABLES, solve_box_qp
from controllers.native import NativePredictiveController
from controllers.nn_config import NNConfig
from controllers.nn_model import load_model
from controllers.predictive import (
    MAX_QP_ITERATIONS,
    HorizonOptimizer,
    HorizonSettings,
    PredictiveController,
    RealTimeIteration,
    RtiSettings,
    doubling_blocks,
)
from controllers.predictors import (
    AveragedModelPredictor,
    CircuitParameters,
    NNPredictor,
    PredictionContext,
    SwitchedModelPredictor,
)
from cosim.design.experiments import NOMINAL_OPERATING_POINT as OPERATING_POINT
from cosim.design.vocabulary import NOMINAL, SWITCHING_PERIOD
from cosim.study.vocabulary import PAPER_SPEC
from plant_fmu.table_ii import TABLE_II

TS = SWITCHING_PERIOD
FIXTURES = Path(__file__).parent / "fixtures"
PARASITICS = CircuitParameters(inductance=264e-6, capacitance=8e-6, inductor_resistance=0.15,
                               switch_on_resistance=0.1, diode_forward_voltage=0.7, capacitor_esr=0.05)


# ------------------------------------------------------------------------------------------ box QP


def kkt_violation(h, g, lower, upper, x) -> float:
    """The largest violation of the box QP's optimality conditions at x (feasibility and multiplier signs)."""
    gradient = h @ x + g
    worst = max(0.0, float(np.max(lower - x)), float(np.max(x - upper)))
    for i in range(len(x)):
        at_lower, at_upper = x[i] <= lower[i] + 1e-12, x[i] >= upper[i] - 1e-12
        if at_lower and at_upper:
            continue
        if at_lower:
            worst = max(worst, -gradient[i])  # the gradient must push against the bound
        elif at_upper:
            worst = max(worst, gradient[i])
        else:
            worst = max(worst, abs(gradient[i]))
    return worst


@pytest.mark.parametrize("n", range(1, MAX_VARIABLES + 1))
def test_box_qp_solves_random_problems_to_their_kkt_point(n):
    rng = np.random.default_rng(n)
    for trial in range(40):
        a = rng.normal(size=(n, n))
        h = a @ a.T + 10.0 ** rng.uniform(-3, 1) * np.eye(n)  # condition numbers up to ~1e4
        g = rng.normal(scale=10.0 ** rng.uniform(-1, 2), size=n)
        lower = -rng.uniform(0, 1, n)
        upper = rng.uniform(0, 1, n)
        lower[rng.uniform(size=n) < 0.2] = 0.0  # the current plan on a duty limit
        x, iterations, converged = solve_box_qp(h, g, lower, upper, 50)
        x = np.array(x)
        assert converged and iterations <= 3 * n + 1
        scale = float(np.abs(h).max() + np.abs(g).max())
        assert kkt_violation(h, g, lower, upper, x) <= 1e-9 * scale
        # no feasible point on a fine random cloud does better
        cloud = rng.uniform(lower, upper, (2000, n))
        values = 0.5 * np.einsum("ki,ij,kj->k", cloud, h, cloud) + cloud @ g
        assert 0.5 * x @ h @ x + g @ x <= values.min() + 1e-12 * scale


def test_box_qp_stops_at_its_iteration_cap_with_a_feasible_improving_point():
    h = np.diag([1.0, 2.0, 3.0, 4.0])
    g = np.array([-5.0, 5.0, -5.0, 5.0])  # the unconstrained optimum lies outside on every axis
    lower, upper = -np.ones(4), np.ones(4)
    x, iterations, converged = solve_box_qp(h, g, lower, upper, 2)
    assert not converged and iterations == 2
    x = np.array(x)
    assert np.all(x >= lower) and np.all(x <= upper)
    assert 0.5 * x @ h @ x + g @ x < 0.0  # better than the start (x = 0)
    full, _, done = solve_box_qp(h, g, lower, upper, 20)
    assert done and np.allclose(full, [1.0, -1.0, 1.0, -1.0])


def test_box_qp_refuses_more_variables_than_its_c_twin_holds():
    with pytest.raises(ValueError, match="at most 8"):
        solve_box_qp(np.eye(9), np.ones(9), -np.ones(9), np.ones(9), 10)


# ------------------------------------------------------------------------------------------ sensitivities


NN_CONFIGS = [NNConfig(), NNConfig(extra_signals=("load_conductance",)),
              NNConfig(delays=2, hidden=(10,), extra_signals=("load_conductance",)),
              NNConfig(delays=2, hidden=(10,), extra_signals=("load_conductance", "input_voltage")),  # 13.33 us
              NNConfig(hidden=(5, 6), activation="sigmoid", residual=True),
              NNConfig(hidden=(9,), activation="relu", delays=3, extra_signals=("load_current", "input_voltage"))]


def predictors():
    for config in NN_CONFIGS:
        yield pytest.param(NNPredictor(random_model(config, config.delays + len(config.hidden))), id=config.label)
    yield pytest.param(NNPredictor(load_model(FIXTURES / "nnpc_mismatch_switched_13p33us.pt", expect_period=TS)),
                       id="fixture-13us")
    for period in (TS, 1e-3):
        yield pytest.param(AveragedModelPredictor(PARASITICS, period), id=f"averaged-{period:.3g}")
    yield pytest.param(SwitchedModelPredictor(PARASITICS, TS, TABLE_II.switching_frequency), id="switched-sawtooth")
    yield pytest.param(SwitchedModelPredictor(NOMINAL, TS, TABLE_II.switching_frequency, carrier="triangle",
                                              sensor="period_start"), id="switched-triangle")


@pytest.mark.parametrize("predictor", list(predictors()))
def test_linearize_rolls_out_like_rollout_and_its_jacobian_matches_finite_differences(predictor):
    rng = np.random.default_rng(5)
    blocks = doubling_blocks(23)
    of_step = np.repeat(np.arange(len(blocks)), blocks)
    for trial in range(3):
        history = np.column_stack([rng.uniform(0.5, 3, predictor.delays), rng.uniform(5, 14, predictor.delays),
                                   rng.uniform(0.1, 0.6, predictor.delays)])
        ctx = PredictionContext(history=history, input_voltage=48.0, load_resistance=6.0, load_conductance=1 / 6.0,
                                load_current=1.8, previous_duty=float(history[0, 2]))
        moves = rng.uniform(0.05, 0.95, len(blocks))
        moves[rng.integers(len(blocks))] = 0.0  # a block at the duty limit
        disturbance = rng.normal(0, 0.05, 2)
        states, jacobian = predictor.linearize(ctx, moves[of_step], disturbance, of_step, len(blocks))
        np.testing.assert_allclose(states, predictor.rollout(ctx, moves[of_step][None], disturbance)[0],
                                   rtol=1e-12, atol=1e-12)
        step = 1e-6
        for b in range(len(blocks)):
            up, down = moves.copy(), moves.copy()
            up[b] += step
            down[b] -= step
            if down[b] < 0:  # one-sided at the limit
                down[b] = moves[b]
            difference = (predictor.rollout(ctx, up[of_step][None], disturbance)[0]
                          - predictor.rollout(ctx, down[of_step][None], disturbance)[0]) / (up[b] - down[b])
            scale = max(1.0, float(np.abs(jacobian).max()))
            assert np.abs(difference - jacobian[:, :, b]).max() <= 1e-5 * scale, b
            assert np.all(jacobian[:of_step.tolist().index(b), :, b] == 0.0)  # no effect before the block starts


# ------------------------------------------------------------------------------------------ the optimizer and the controller


def rti_controller(predictor, settings: RtiSettings = RtiSettings(), horizon: int = 23) -> PredictiveController:
    return PredictiveController(predictor, TS, HorizonSettings(horizon=horizon), name="RTI", **OPERATING_POINT,
                                rti=settings)


def test_rti_settings_are_validated_by_name():
    for field, value, message in (("iterations", 4, "RTI iterations = 4 is invalid: expected 1, 2 or 3"),
                                  ("smoothing", 0.0, "RTI smoothing = 0.0 is invalid"),
                                  ("step_limit", 1.5, "RTI step_limit = 1.5 is invalid"),
                                  ("reference_step", -1.0, r"RTI reference_step = -1.0 is invalid: expected a finite value >= 0"),
                                  ("move_damping", 1.0, r"RTI move_damping = 1.0 is invalid: expected 0 <= rho < 1")):
        with pytest.raises(ValueError, match=message):
            RtiSettings(**{field: value})
    with pytest.raises(ValueError, match="at most 8 move blocks"):
        rti_controller(AveragedModelPredictor(NOMINAL, TS), horizon=30).settings  # noqa: B018
        PredictiveController(AveragedModelPredictor(NOMINAL, TS), TS, HorizonSettings(horizon=9, blocks=(1,) * 9),
                             **OPERATING_POINT, rti=RtiSettings())


def test_the_every_seed_evaluation_takes_rti_settings_by_name_and_type():
    from cosim.design.experiments import rti_changes

    assert rti_changes(["iterations=2", "line_search=False", "regularization=1e-3"]) == \
        {"iterations": 2, "line_search": False, "regularization": 1e-3}
    assert rti_changes([]) == {}
    for item, message in (("steps=2", r"--rti steps=2: 'steps' is not an RTI setting \(expected one of iterations, "),
                          ("iterations=two", "--rti iterations=two: expected an integer"),
                          ("line_search=yes", "--rti line_search=yes: expected true or false"),
                          ("smoothing=", "--rti smoothing=: expected a number"),
                          ("iterations=5", "RTI iterations = 5 is invalid: expected 1, 2 or 3")):
        with pytest.raises(ValueError, match=message):
            rti_changes([item])


def convex_problem():
    """The averaged (linear) model on a 6-step horizon of blocks (1, 2, 3) from a context far below the target:
    (settings, predictor, context, weights, target, eq. 16 cost of a batch of duty sequences)."""
    settings = HorizonSettings(horizon=6, blocks=(1, 2, 3))
    predictor = AveragedModelPredictor(NOMINAL, TS)
    ctx = PredictionContext(history=np.array([[1.0, 9.0, 0.0]]), input_voltage=48.0, load_resistance=6.0,
                            load_conductance=1 / 6.0, load_current=1.5, previous_duty=0.2)
    weights = settings.discount ** np.arange(6)
    target = np.array([2.0, 12.0])

    def cost(duties):
        e = predictor.rollout(ctx, duties, np.zeros(2)) - target
        return np.sqrt((e * e).sum(axis=2)) @ weights

    return settings, predictor, ctx, weights, target, cost


@pytest.mark.parametrize("line_search", [True, False])
def test_rti_converges_to_the_optimum_of_a_convex_problem_over_samples_and_respects_the_limits(line_search):
    """The averaged model is linear: each step's linearisation is exact, so repeated RTI steps from a
    poor plan reach the search's (refined) optimum; the plan stays in the duty limits throughout. With
    the line search the plan's exact cost comes with it; without, it is NaN (not rolled out) and the
    first predicted state is still the model's."""
    settings, predictor, ctx, weights, target, cost = convex_problem()
    optimizer = RealTimeIteration(RtiSettings(iterations=3, smoothing=1e-3, line_search=line_search), settings,
                                  (0.1, 0.6), weights)

    def linearize(duties):
        return predictor.linearize(ctx, duties, np.zeros(2), optimizer.block_of_step, 3)

    def evaluate(duties):
        return predictor.rollout(ctx, duties[None], np.zeros(2))[0]

    plan = np.full(6, 0.1)
    previous = cost(plan[None])[0]
    for sample in range(12):  # the same problem: the shift only moves the plan within its own blocks
        plan, exact, first = optimizer.solve(linearize, evaluate, target, plan, plan[0])
        assert np.all((plan >= 0.1) & (plan <= 0.6))
        if line_search:
            assert exact == pytest.approx(cost(plan[None])[0], rel=1e-12)
        else:
            assert math.isnan(exact) and optimizer.accepted == 3
        np.testing.assert_allclose(first, evaluate(plan)[0], rtol=1e-12)
    _, searched = HorizonOptimizer(settings, (0.1, 0.6)).solve(cost, anchor=0.25)
    exact = cost(plan[None])[0]
    assert exact <= searched * 1.001 and exact < previous


def test_reusing_the_first_jacobian_linearises_once_and_on_a_linear_model_plans_as_full_gauss_newton():
    """reuse_jacobian: each sample linearises once and evaluates the further steps' trials by rollouts; on the
    averaged (linear) model the sensitivities do not depend on the plan, so the plans equal the full method's."""
    settings, predictor, ctx, weights, target, cost = convex_problem()
    plans, calls = {}, {}
    for reuse in (False, True):
        optimizer = RealTimeIteration(RtiSettings(iterations=3, smoothing=1e-3, reuse_jacobian=reuse), settings,
                                      (0.1, 0.6), weights)
        counted = {"linearize": 0, "evaluate": 0}

        def linearize(duties, optimizer=optimizer, counted=counted):
            counted["linearize"] += 1
            return predictor.linearize(ctx, duties, np.zeros(2), optimizer.block_of_step, 3)

        def evaluate(duties, counted=counted):
            counted["evaluate"] += 1
            return predictor.rollout(ctx, duties[None], np.zeros(2))[0]

        plan = np.full(6, 0.1)
        for _ in range(4):
            plan, _, _ = optimizer.solve(linearize, evaluate, target, plan, plan[0])
        plans[reuse], calls[reuse] = plan, counted
    # per sample: 3 linearisations and the plan's first state, or 1 linearisation, 2 trial rollouts and the first state
    assert calls[False] == {"linearize": 12, "evaluate": 4} and calls[True] == {"linearize": 4, "evaluate": 12}
    np.testing.assert_allclose(plans[True], plans[False], rtol=0, atol=1e-12)
    assert not np.allclose(plans[True], 0.1)


def test_reweightings_lower_the_linearised_cost_without_a_new_linearisation_and_stop_at_their_tolerance():
    """RtiSettings.reweightings on the averaged (linear) model, whose linearisation is exact: from a poor plan one
    step's smoothed cost falls with each reweighting (each QP minimises a quadratic that touches the cost from above
    at the current point), the step linearises once whatever their number, and a tolerance above the first QP's
    step leaves none (the plan of no reweighting, bit for bit)."""
    settings, predictor, ctx, weights, target, _ = convex_problem()
    smoothed, plans = [], {}
    for k, tolerance in ((0, 0.0), (1, 0.0), (2, 0.0), (3, 0.0), (3, 0.99)):
        optimizer = RealTimeIteration(RtiSettings(reweightings=k, reweighting_tolerance=tolerance, step_limit=1.0),
                                      settings, (0.1, 0.6), weights)
        calls = []

        def linearize(duties, optimizer=optimizer, calls=calls):
            calls.append(duties)
            return predictor.linearize(ctx, duties, np.zeros(2), optimizer.block_of_step, 3)

        def evaluate(duties):
            return predictor.rollout(ctx, duties[None], np.zeros(2))[0]

        plan, _, _ = optimizer.solve(linearize, evaluate, target, np.full(6, 0.1), 0.1)
        assert len(calls) == 1 and optimizer.reweighted == (k if tolerance == 0 else 0)
        plans[k, tolerance] = plan
        if tolerance == 0:
            smoothed.append(optimizer.costs(evaluate(plan), target)[0])
    assert all(later <= earlier * (1 + 1e-12) for earlier, later in itertools.pairwise(smoothed)), smoothed
    assert smoothed[3] < 0.99 * smoothed[0]  # they move the plan, not by rounding
    np.testing.assert_array_equal(plans[3, 0.99], plans[0, 0.0])


def test_move_damping_adds_a_proximal_term_on_the_first_move_only():
    """The quadratic model with move damping rho is the undamped one plus rho m on H[0, 0] and
    rho m (u_0 - d_prev) on g[0], m = mean(diag H) before the Levenberg-Marquardt term; no other entry moves."""
    rng = np.random.default_rng(11)
    settings = HorizonSettings(horizon=6, blocks=(1, 2, 3))
    predicted, jacobian = rng.normal(size=(6, 2)), rng.normal(size=(6, 2, 3))
    target, weights = np.array([2.0, 12.0]), 0.9 ** np.arange(6)
    plain = RealTimeIteration(RtiSettings(regularization=1e-3), settings, (0.0, 1.0), weights)
    damped = RealTimeIteration(RtiSettings(regularization=1e-3, move_damping=0.2), settings, (0.0, 1.0), weights)
    g0, h0 = plain.model(predicted, jacobian, target, first_move=0.3)  # the undamped model ignores the move
    g_none, h_none = plain.model(predicted, jacobian, target)
    np.testing.assert_array_equal(g0, g_none)
    np.testing.assert_array_equal(h0, h_none)
    g, h = damped.model(predicted, jacobian, target, first_move=0.3)
    m = float(np.trace(h0) - 3e-12) / (3 * 1.001)  # trace(h0) = 3 m + 3 (1e-3 m + 1e-12)
    expected_h, expected_g = h0.copy(), g0.copy()
    expected_h[0, 0] += 0.2 * m
    expected_g[0] += 0.2 * m * 0.3
    np.testing.assert_allclose(h, expected_h, rtol=1e-13)
    np.testing.assert_allclose(g, expected_g, rtol=1e-13)


def test_move_damping_slows_the_applied_move_but_converges_to_the_same_optimum():
    """On the averaged (linear) model from a poor plan: the damped RTI's first applied move is closer to
    the duty applied before, yet over samples (applying each plan's first duty) both reach the search's
    optimum -- at the fixed point u_0 = d_prev and the proximal term vanishes: no steady-state bias."""
    settings, predictor, ctx, weights, target, cost = convex_problem()
    _, searched = HorizonOptimizer(settings, (0.1, 0.6)).solve(cost, anchor=0.25)
    first_moves, final = [], []
    for rho in (0.0, 0.5):
        optimizer = RealTimeIteration(RtiSettings(iterations=2, smoothing=1e-3, move_damping=rho), settings,
                                      (0.1, 0.6), weights)
        blocks = optimizer.block_of_step
        plan = np.full(6, 0.1)
        for sample in range(40):
            plan, _, _ = optimizer.solve(
                lambda d, blocks=blocks: predictor.linearize(ctx, d, np.zeros(2), blocks, 3),
                lambda d: predictor.rollout(ctx, d[None], np.zeros(2))[0], target, plan, plan[0])
            if sample == 0:
                first_moves.append(abs(plan[0] - 0.1))
        final.append(cost(plan[None])[0])
    assert first_moves[1] < 0.8 * first_moves[0]
    assert final[0] <= searched * 1.001 and final[1] <= searched * 1.001


def test_an_rti_step_never_plans_worse_than_the_shifted_warm_start():
    """The line search's accept test: whatever the quadratic model says, the plan applied is predicted no
    worse (smoothed cost) than the previous plan shifted -- here from plans far off on the NN model."""
    model = load_model(FIXTURES / "nnpc_mismatch_switched_13p33us.pt", expect_period=TS)
    predictor = NNPredictor(model)
    settings = HorizonSettings(horizon=23)
    rng = np.random.default_rng(3)
    optimizer = RealTimeIteration(RtiSettings(iterations=2, line_search=True), settings, (0.0, 1.0),
                                  settings.discount ** np.arange(23))
    target = np.array([2.0, 12.0])
    for trial in range(20):
        history = np.array([[rng.uniform(0, 4), rng.uniform(0, 16), 0.0], [rng.uniform(0, 4), rng.uniform(0, 16),
                                                                          rng.uniform(0, 1)]])
        ctx = PredictionContext(history=history, input_voltage=48.0, load_resistance=6.0, load_conductance=1 / 6.0,
                                load_current=2.0, previous_duty=float(history[1, 2]))
        disturbance = rng.normal(0, 0.05, 2)
        warm = rng.uniform(0, 1, 23)

        def linearize(duties):
            return predictor.linearize(ctx, duties, disturbance, optimizer.block_of_step, optimizer.n_blocks)

        def evaluate(duties):
            return predictor.rollout(ctx, duties[None], disturbance)[0]

        shifted = optimizer.expand(optimizer.shifted(warm))
        before = optimizer.costs(evaluate(shifted), target)[0]
        plan, exact, _ = optimizer.solve(linearize, evaluate, target, warm, warm[0])
        assert optimizer.smoothed_cost <= before * (1 + 1e-12)
        assert 0 <= optimizer.accepted <= 2 and optimizer.qp_iterations >= 2


def test_without_a_line_search_the_step_is_taken_and_only_the_first_state_is_predicted():
    """The default RTI (one step, no line search): the QP's step is the plan, whether or not the model
    predicts it better; the first predicted state is the model's for that plan; the cost is not known."""
    model = load_model(FIXTURES / "nnpc_mismatch_switched_13p33us.pt", expect_period=TS)
    predictor = NNPredictor(model)
    settings = HorizonSettings(horizon=23)
    rng = np.random.default_rng(5)
    plain = RealTimeIteration(RtiSettings(), settings, (0.0, 1.0), settings.discount ** np.arange(23))
    searched = RealTimeIteration(RtiSettings(line_search=True), settings, (0.0, 1.0), settings.discount ** np.arange(23))
    target = np.array([2.0, 12.0])
    rolled = []
    for trial in range(10):
        history = np.array([[rng.uniform(0, 4), rng.uniform(0, 16), 0.0], [rng.uniform(0, 4), rng.uniform(0, 16),
                                                                          rng.uniform(0, 1)]])
        ctx = PredictionContext(history=history, input_voltage=48.0, load_resistance=6.0, load_conductance=1 / 6.0,
                                load_current=2.0, previous_duty=float(history[1, 2]))
        warm = rng.uniform(0, 1, 23)

        def linearize(duties):
            return predictor.linearize(ctx, duties, np.zeros(2), plain.block_of_step, plain.n_blocks)

        def evaluate(duties):
            rolled.append(len(duties))
            return predictor.rollout(ctx, duties[None], np.zeros(2))[0]

        plan, exact, first = plain.solve(linearize, evaluate, target, warm, warm[0])
        assert math.isnan(exact) and plain.accepted == 1 and rolled[-1] == 1  # the first step only
        np.testing.assert_array_equal(first, predictor.rollout(ctx, plan[None], np.zeros(2))[0, 0])
        checked, _, _ = searched.solve(linearize, evaluate, target, warm, warm[0])
        if searched.accepted:  # the same step where the line search takes it
            np.testing.assert_array_equal(checked, plan)


def test_the_controller_searches_at_a_cold_start_then_iterates_and_falls_back_only_where_enabled():
    predictor = AveragedModelPredictor(PARASITICS, TS)
    ramp = [Measurement(k * TS, 12.0, 11.5 + 0.01 * k, 2.0, 1.9, 48.0) for k in range(20)]
    step = [Measurement((20 + k) * TS, 15.0, 12.0, 2.0, 2.0, 48.0) for k in range(3)]
    plain = rti_controller(predictor)
    for triggered, settings in ((False, RtiSettings(reference_step=0.0)), (True, RtiSettings())):
        controller = rti_controller(predictor, settings)
        solvers = []
        for m in ramp + step:
            controller.step(m)
            solvers.append((controller.last_solver, controller.last_fallback))
        assert solvers[0] == ("search", "cold start")
        assert set(solvers[1:20]) == {("rti", "")}
        assert solvers[20] == (("search", "reference step") if triggered else ("rti", ""))
        assert set(solvers[21:]) == {("rti", "")}
        controller.reset()
        assert controller.step(ramp[0]) == rti_controller(predictor).step(ramp[0])  # reset forgets the plan
        assert controller.last_fallback == "cold start"
    description = plain.describe()["optimizer"]
    assert description["type"].startswith("real-time iteration") and description["iterations"] == 1


def test_the_search_plans_the_start_up_until_the_output_first_comes_within_the_region():
    """After a cold start the search plans while |vref - vo| > startup_region, then the RTI -- also when the
    error grows again (an overshoot, a reference step: their own rules apply); a reset starts over."""
    predictor = AveragedModelPredictor(PARASITICS, TS)
    voltages = [0.0, 4.0, 8.0, 10.9, 11.2, 12.6, 13.5, 12.5, 12.0]
    run = [Measurement(k * TS, 12.0, v, 2.0, v / 6.0, 48.0) for k, v in enumerate(voltages)]
    for region, expected in ((1.0, ["cold start"] + ["start-up"] * 3 + [""] * 5), (0.0, ["cold start"] + [""] * 8),
                             (5.0, ["cold start", "start-up"] + [""] * 7)):
        controller = rti_controller(predictor, RtiSettings(startup_region=region, reference_step=0.0))
        for _ in range(2):  # the second pass after a reset
            reasons = []
            for m in run:
                controller.step(m)
                reasons.append(controller.last_fallback)
                assert controller.last_solver == ("search" if controller.last_fallback else "rti")
            assert reasons == expected
            controller.reset()
    with pytest.raises(ValueError, match="RTI startup_region = -1.0 is invalid"):
        RtiSettings(startup_region=-1.0)
    with pytest.raises(ValueError, match="RTI duty_resolution = 1.0 is invalid"):
        RtiSettings(duty_resolution=1.0)
    with pytest.raises(ValueError, match="RTI reweightings = 4 is invalid: expected 0, 1, 2 or 3"):
        RtiSettings(reweightings=4)
    with pytest.raises(ValueError, match="RTI reweightings = 1 with line_search is refused"):
        RtiSettings(reweightings=1, line_search=True)
    with pytest.raises(ValueError, match="RTI reweighting_tolerance = 1.0 is invalid"):
        RtiSettings(reweighting_tolerance=1.0)
    RtiSettings(qp_iterations=MAX_QP_ITERATIONS)
    for bad in (0, MAX_QP_ITERATIONS + 1, 2**32 + 1):  # the last would be 1 in the C twin's int
        with pytest.raises(ValueError, match=f"RTI qp_iterations = {bad} is invalid: expected 1 .. 10000"):
            RtiSettings(qp_iterations=bad)
    with pytest.raises(ValueError, match="RTI innovation = inf is invalid: expected a finite value >= 0"):
        RtiSettings(innovation=float("inf"))


def fallback_reasons(predictor, settings: RtiSettings, run: list[Measurement]) -> tuple[list[str], list[str]]:
    """Why each sample of ``run`` used the search ("" where the RTI planned), by the Python controller and by its
    C twin fed the same measurements."""
    controller = rti_controller(predictor, settings)
    twin = NativePredictiveController.from_python(controller)
    reasons, twin_reasons = [], []
    for m in run:
        controller.step(m)
        twin.step(m)
        reasons.append(controller.last_fallback)
        twin_reasons.append(twin.last_fallback)
        assert controller.last_solver == ("search" if controller.last_fallback else "rti")
        assert twin.last_solver == controller.last_solver
    return reasons, twin_reasons


def test_a_reference_step_is_planned_by_the_search_on_its_sample_only():
    """A reference change larger than reference_step is the search's ("reference step") on the sample it
    arrives; the samples after it are the RTI's, however far off the output still is (error_region 0); the
    C twin agrees. A change of at most reference_step, or reference_step 0, never falls back."""
    predictor = AveragedModelPredictor(PARASITICS, TS)
    settle = [(12.0, 12.0)] * 3
    up = [(15.0, 12.0), (15.0, 12.9), (15.0, 13.6), (15.0, 14.2), (15.0, 16.5), (15.0, 15.0)]
    down = [(12.0, 15.0), (12.0, 13.5), (12.0, 12.5)]
    small = [(12.4, 12.5), (12.4, 12.4)]
    run = [Measurement(k * TS, r, v, 2.0, v / 6.0, 48.0) for k, (r, v) in enumerate(settle + up + down + small)]
    step, none = "reference step", ""
    for threshold, expected in ((0.5, ["cold start", none, none, step] + [none] * 5 + [step, none, none, none, none]),
                                (0.0, ["cold start"] + [none] * 13)):
        assert fallback_reasons(predictor, RtiSettings(startup_region=0.0, reference_step=threshold), run) == \
            (expected, expected)
    with pytest.raises(ValueError, match="RTI reference_step = -1.0 is invalid: expected a finite value >= 0"):
        RtiSettings(reference_step=-1.0)


def test_the_search_plans_every_sample_whose_error_exceeds_the_error_region():
    """The guard where the model extrapolates: with error_region > 0 any sample more than that many volts off the
    reference is the search's ("large error"), before and after it the RTI plans; the C twin agrees; 0: never."""
    predictor = AveragedModelPredictor(PARASITICS, TS)
    voltages = [12.0, 12.0, 12.3, 12.6, 13.9, 12.4, 11.0, 12.1]
    run = [Measurement(k * TS, 12.0, v, 2.0, v / 6.0, 48.0) for k, v in enumerate(voltages)]
    guard = "large error"
    for region, expected in ((0.5, ["cold start", "", "", guard, guard, "", guard, ""]),
                             (0.0, ["cold start"] + [""] * 7)):
        assert fallback_reasons(predictor, RtiSettings(startup_region=0.0, error_region=region), run) == \
            (expected, expected)
    # a reference step's transient is the guard's while the output is more than error_region off, the overshoot
    # too, checked before the reference-step rule: every reason is the guard's
    settle = [(12.0, 12.0)] * 3
    up = [(15.0, 12.0), (15.0, 12.9), (15.0, 13.6), (15.0, 14.2), (15.0, 16.5), (15.0, 15.0)]
    down = [(12.0, 15.0), (12.0, 13.5), (12.0, 12.5)]
    steps = [Measurement(k * TS, r, v, 2.0, v / 6.0, 48.0) for k, (r, v) in enumerate(settle + up + down)]
    expected = ["cold start", "", "", guard, guard, guard, "", guard, "", guard, guard, ""]
    assert fallback_reasons(predictor, RtiSettings(startup_region=0.0, error_region=1.0), steps) == (expected, expected)
    with pytest.raises(ValueError, match="RTI error_region = -0.5 is invalid: expected a finite value >= 0"):
        RtiSettings(error_region=-0.5)


def test_a_duty_resolution_rounds_the_plan_and_evaluates_the_rounded_plan():
    """With a duty quantum the plan's blocks are multiples of it (within the limits), the first predicted
    state and, with the line search, the exact cost are those of the rounded plan."""
    settings = HorizonSettings(horizon=1)
    predictor = AveragedModelPredictor(NOMINAL, 1e-3)
    ctx = PredictionContext(history=np.array([[2.0, 11.7, 0.0]]), input_voltage=48.0, load_resistance=6.0,
                            load_conductance=1 / 6.0, load_current=1.95, previous_duty=0.25)
    target = np.array([2.0, 12.0])
    quantum = 1 / 10240

    def evaluate(duties):
        return predictor.rollout(ctx, duties[None], np.zeros(2))[0]

    for line_search in (True, False):
        exact_plan = None
        for q in (0.0, quantum):
            optimizer = RealTimeIteration(RtiSettings(iterations=2, line_search=line_search, step_limit=1.0,
                                                      duty_resolution=q), settings, (0.0, 1.0), np.ones(1))
            plan, exact, first = optimizer.solve(
                lambda d: predictor.linearize(ctx, d, np.zeros(2), optimizer.block_of_step, 1), evaluate, target,
                np.array([0.25]), 0.25)
            np.testing.assert_array_equal(first, evaluate(plan)[0])
            if line_search:
                assert exact == pytest.approx(optimizer.costs(evaluate(plan), target)[1], rel=1e-15)
            if q:
                assert plan[0] == np.floor(exact_plan[0] / q + 0.5) * q and plan[0] != exact_plan[0]
            else:
                exact_plan = plan


def test_search_last_sample_leaves_the_controller_as_it_was():
    controller = rti_controller(AveragedModelPredictor(PARASITICS, TS))
    ramp = [Measurement(k * TS, 12.0, 0.3 * k, 0.1 * k, 0.05 * k, 48.0) for k in range(6)]
    twin = rti_controller(AveragedModelPredictor(PARASITICS, TS))
    for m in ramp:
        duty = controller.step(m)
        sequence, cost = controller.search_last_sample()
        assert twin.step(m) == duty and len(sequence) == 23 and cost > 0
    assert np.array_equal(controller._warm, twin._warm) and np.array_equal(controller._bias, twin._bias)


def test_optimizer_ablation_reports_both_optimizers_on_the_same_model():
    """The study's comparison on a short start-up and load change at 13.33 us (the fixture's NNPC on the
    mismatch switched plant): both runs exist, the audit compared every RTI sample with the search."""
    from cosim.design.experiments import nnpc
    from cosim.design.plants import plant_binding
    from cosim.scenarios import load_scenario
    from cosim.study.optimizer_ablation import compare, report_lines, verdict

    model = load_model(FIXTURES / "nnpc_mismatch_switched_13p33us.pt", expect_period=TS)
    scenarios = [replace(load_scenario("startup", PAPER_SPEC), duration=0.0008)]
    rows = compare(plant_binding("mismatch", "switched"), lambda optimizer: nnpc(model, TS, optimizer=optimizer),
                   scenarios)
    (row,) = rows
    # the cold start, then the search while the output is more than 0.1 V off (the start-up region)
    startup = row["fallbacks"].get("start-up", 0)
    assert row["samples"] == 61 and set(row["fallbacks"]) == {"cold start", "start-up"} and 1 <= startup <= 10
    assert row["search_samples"] == 1 + startup and len(row["cost_excess"]) == 60 - startup
    assert np.all(np.isfinite(row["cost_excess"])) and row["closed_loop_cost_rti_Vs"] > 0
    assert row["iae_ratio"] == pytest.approx(row["iae_rti_Vs"] / row["iae_search_Vs"])
    assert row["overshoot_difference_points"] == pytest.approx(row["overshoot_rti_pct"] - row["overshoot_search_pct"])
    assert row["cost_excess_median"] == pytest.approx(float(np.median(row["cost_excess"])))
    assert 0.8 < row["iae_ratio"] < 1.2  # the same model, the same plant: close, whichever wins
    # the one-step RTI (13.33 us) is run beside its two-step variant, a run of its own: an IAE and an overshoot
    assert row["iae_rti_two_steps_Vs"] > 0 and row["iae_rti_two_steps_Vs"] != row["iae_rti_Vs"]
    assert np.isfinite(row["overshoot_rti_two_steps_pct"])
    (line,) = [x for x in report_lines(rows) if x.startswith("|  | NNPC | startup")]
    assert line.endswith(f"| {row['iae_rti_two_steps_Vs'] / row['iae_search_Vs']:.3f}, "
                         f"{row['overshoot_rti_two_steps_pct']:.2f} |")
    targets = verdict(rows)
    assert targets["iae_ratio_worst"] == (row["iae_ratio"], row["iae_ratio"] <= 1.02)
    assert targets["startup_overshoot_increase_points_worst"] == (row["overshoot_difference_points"],
                                                                  row["overshoot_difference_points"] <= 0.5)


def test_default_optimizer_switches_the_controllers_without_one_and_restores_the_default():
    """The reproduction's measurement switch (``reproduce(optimizer=...)``): inside it the NNPC and the MPC baselines
    built without an optimizer take the one named; one given keeps its own; the default comes back afterwards, also
    after an error; an unknown name is refused by name before anything changes."""
    from cosim.base.errors import ConfigError
    from cosim.design import experiments
    from cosim.design.experiments import SWITCHING_PERIOD_RTI, default_optimizer, model_mpc, nnpc

    model = load_model(FIXTURES / "nnpc_mismatch_switched_13p33us.pt", expect_period=TS)
    assert nnpc(model, TS).rti == SWITCHING_PERIOD_RTI
    with default_optimizer("search"):
        assert nnpc(model, TS).rti is None and model_mpc(NOMINAL, TS, "MPC").rti is None
        assert nnpc(model, TS, optimizer="rti").rti == SWITCHING_PERIOD_RTI  # its own optimizer
    assert nnpc(model, TS).rti == SWITCHING_PERIOD_RTI and experiments.DEFAULT_OPTIMIZER == "rti"
    with pytest.raises(RuntimeError), default_optimizer("search"):
        raise RuntimeError("a failing reproduction")
    assert experiments.DEFAULT_OPTIMIZER == "rti"
    with pytest.raises(ConfigError, match=r"^optimizer 'gradient' is unknown: expected one of rti, search$"):
        with default_optimizer("gradient"):
            pass
    assert experiments.DEFAULT_OPTIMIZER == "rti"


def test_reproduce_refuses_an_unknown_optimizer_before_any_work(tmp_path):
    from cosim.base.errors import ConfigError
    from cosim.study.reproduce import reproduce

    with pytest.raises(ConfigError, match=r"^optimizer 'grid' is unknown: expected one of rti, search$"):
        reproduce(tmp_path / "out", optimizer="grid")
    assert not (tmp_path / "out").exists()


def test_the_reproductions_workers_take_the_default_optimizer_it_is_given():
    """``reproduce(optimizer=...)`` sets its workers' default with a worker plugin (a restarted worker too); checked
    on a one-worker LocalCluster on loopback."""
    from cosim.design.cluster import dask_client
    from cosim.study.reproduce import _default_optimizer_plugin

    def worker_default():
        from cosim.design import experiments

        return experiments.DEFAULT_OPTIMIZER

    with dask_client(workers=1) as client:
        assert list(client.run(worker_default).values()) == ["rti"]
        client.register_plugin(_default_optimizer_plugin("search"))
        assert list(client.run(worker_default).values()) == ["search"]
        client.restart(timeout=60)
        assert list(client.run(worker_default).values()) == ["search"]
