"""The real-time-iteration optimizer: its box QP against the KKT conditions, the predictors'
sensitivities against finite differences, its steps against the search, its fallback rule, and the
optimizer ablation of the study."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from controllers.base import Measurement
from controllers.box_qp import MAX_VARIABLES, solve_box_qp
from controllers.nn_model import NNConfig, NNPlantModel, PlantNetwork, load_model
from controllers.predictive import (
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
from cosim.study.experiments import NOMINAL_OPERATING_POINT as OPERATING_POINT
from cosim.study.vocabulary import NOMINAL, SWITCHING_PERIOD
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


def random_model(config: NNConfig, seed: int) -> NNPlantModel:
    import torch

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    n = config.n_inputs
    return NNPlantModel(config, PlantNetwork(config), rng.normal(0, 3, n), rng.uniform(0.5, 5, n),
                        rng.normal(0, 5, 2), rng.uniform(0.5, 5, 2))


NN_CONFIGS = [NNConfig(), NNConfig(extra_signals=("load_conductance",)),
              NNConfig(delays=2, hidden=(10,), extra_signals=("load_conductance",)),
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
