"""Online adaptation of the NNPC's output layer: it learns a drifted plant, and its guards hold.

The plant here is itself a network: the offline model's hidden layer with another output layer
(the "drifted" plant), so the exact answer of the adaptation is known.
"""

from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from controllers.adaptation import AdaptationSettings, AdaptiveNNPC
from controllers.base import Measurement
from controllers.nn_config import NNConfig
from controllers.nn_model import NNPlantModel, PlantNetwork

CONFIG = NNConfig(hidden=(6,), delays=2, extra_signals=("load_conductance",))
LOAD = 6.0


def network_model(seed: int = 0) -> NNPlantModel:
    torch.manual_seed(seed)
    network = PlantNetwork(CONFIG)
    mean = np.array([2.0, 12.0, 0.3, 2.0, 12.0, 0.3, 1 / LOAD])
    std = np.array([1.0, 5.0, 0.2, 1.0, 5.0, 0.2, 0.05])
    return NNPlantModel(CONFIG, network, mean, std, np.array([2.0, 12.0]), np.array([1.0, 5.0]))


class ScriptedNNPC:
    """Stands in for the NNPC being adapted: a duty schedule, the attributes the adaptation reads."""

    name = "scripted"
    sample_period = 1 / 75e3
    duty_limits = (0.0, 1.0)

    def __init__(self, model: NNPlantModel, duties):
        self.predictor = SimpleNamespace(model=model)
        self.duties = duties
        self.k = 0

    def reset(self):
        self.k = 0

    def step(self, measurement):
        duty = self.duties(self.k)
        self.k += 1
        return duty

    def describe(self):
        return {"type": "scripted"}


def drifted(model: NNPlantModel, change: float = 0.15, seed: int = 1) -> np.ndarray:
    """Another output layer [W; b] for ``model``'s hidden layer: the plant after a drift."""
    rng = np.random.default_rng(seed)
    theta = np.vstack([model._weights[-1], model._biases[-1][None, :]])
    return theta * (1 + change * rng.standard_normal(theta.shape))


def simulate(adaptive: AdaptiveNNPC, plant_theta: np.ndarray, samples: int, duties) -> list[float]:
    """Closed loop with a plant that is the offline hidden layer + ``plant_theta``; returns the
    one-step errors of the adapted model on each sample."""
    hidden = adaptive._hidden_layers
    state = np.array([2.0, 12.0])
    previous = (state[0], state[1], duties(0))
    errors = []
    adaptive.reset()
    for k in range(samples):
        m = Measurement(k * adaptive.sample_period, 12.0, state[1], state[0], state[1] / LOAD, 48.0)
        duty = adaptive.step(m)
        x = np.array([state[0], state[1], duty, *previous, 1 / LOAD])
        h = x
        for w, b in hidden:
            h = np.tanh(h @ w + b)
        phi = np.append(h, 1.0)
        new = phi @ plant_theta
        errors.append(float(np.abs(new - phi @ adaptive.output_weights).max()))
        previous = (state[0], state[1], duty)
        state = np.clip(new, [0.0, 0.0], [5.0, 20.0])
    return errors


def varied(k: int) -> float:
    return 0.3 + 0.25 * np.sin(0.37 * k) * np.cos(0.05 * k)


def adaptive_for(model: NNPlantModel, duties, **settings) -> AdaptiveNNPC:
    own = copy.deepcopy(model)
    return AdaptiveNNPC(ScriptedNNPC(own, duties), own, AdaptationSettings(**settings), nominal_load=LOAD)


def test_rls_learns_the_drifted_output_layer_and_the_prediction_error_falls():
    model = network_model()
    plant = drifted(model)
    adaptive = adaptive_for(model, varied, max_step=1.0, max_deviation=5.0, min_change_current=0.0,
                            min_change_voltage=0.0)
    errors = simulate(adaptive, plant, 600, varied)
    assert adaptive.counters["updates"] > 500 and adaptive.counters["fallbacks"] == 0
    assert np.mean(errors[-100:]) < 0.02 * np.mean(errors[:5])  # learned: the error fell by 50x or more
    # and the weights moved most of the way to the plant's (not all: the features on one trajectory are
    # close to collinear, so some directions stay unidentified, which the predictions do not need)
    assert np.linalg.norm(adaptive.output_weights - plant) < 0.5 * np.linalg.norm(adaptive._offline - plant)
    # the controller's own network was rewritten in place (the NNPC predicts with the adapted layer)
    np.testing.assert_array_equal(adaptive.inner.predictor.model._weights[-1], adaptive.output_weights[:-1])


def test_saturated_samples_are_refused():
    model = network_model()
    adaptive = adaptive_for(model, lambda k: 1.0, min_change_current=0.0, min_change_voltage=0.0)
    simulate(adaptive, drifted(model), 200, lambda k: 1.0)
    counters = adaptive.counters
    assert counters["updates"] == 0 and counters["saturated"] == counters["samples"] > 190
    np.testing.assert_array_equal(adaptive.output_weights, adaptive._offline)
    # just inside the limits (duty_margin) is saturated too; further in, it learns
    adaptive = adaptive_for(model, lambda k: 0.995, min_change_current=0.0, min_change_voltage=0.0)
    simulate(adaptive, drifted(model), 50, lambda k: 0.995)
    assert adaptive.counters["updates"] == 0


def test_steady_samples_are_refused():
    model = network_model()
    adaptive = adaptive_for(model, lambda k: 0.3)
    simulate(adaptive, np.vstack([model._weights[-1], model._biases[-1][None, :]]), 300, lambda k: 0.3)
    assert adaptive.counters["steady"] > 250  # a constant duty on its own fixed point: nothing to learn


def test_each_update_and_the_total_deviation_are_bounded():
    model = network_model()
    plant = drifted(model, change=1.0)
    adaptive = adaptive_for(model, varied, max_step=0.01, max_deviation=0.1, min_change_current=0.0,
                            min_change_voltage=0.0, fallback_ratio=1e9)
    offline = adaptive._offline.copy()
    norm = np.linalg.norm(offline, axis=0)
    previous = offline.copy()
    steps = []
    original = adaptive._write

    def watch(theta):
        steps.append(np.linalg.norm(theta - previous, axis=0))
        previous[...] = theta
        original(theta)

    adaptive._write = watch
    simulate(adaptive, plant, 300, varied)
    assert adaptive.counters["bounded"] > 0
    assert np.all(np.array(steps[1:]) <= 0.01 * norm * (1 + 1e-9))
    assert np.all(np.linalg.norm(adaptive.output_weights - offline, axis=0) <= 0.1 * norm * (1 + 1e-9))


def test_the_fallback_restores_the_last_good_model_when_the_error_grows():
    model = network_model()
    truth = np.vstack([model._weights[-1], model._biases[-1][None, :]])
    adaptive = adaptive_for(model, varied, min_change_current=0.0, min_change_voltage=0.0, max_step=1.0,
                            max_deviation=10.0, warmup=20, checkpoint_every=50)
    simulate(adaptive, truth, 100, varied)  # a plant equal to the model: the last good model is the offline one
    good = adaptive._good[0].copy()
    # a bad update (as from a corrupted sample): the adapted model now predicts far worse
    adaptive._theta = adaptive._theta + 0.5 * np.abs(truth).max()
    adaptive._write(adaptive._theta)
    learn = adaptive._learn
    fallbacks = []

    def no_update(x, measured, conductance):  # keep the bad weights until the comparison decides
        before = adaptive.counters["fallbacks"]
        learn(x, measured, conductance)
        fallbacks.append(adaptive.counters["fallbacks"] > before)

    adaptive._learn = no_update
    adaptive.settings = AdaptationSettings(**{**adaptive.settings.__dict__, "max_step": 1e-12, "warmup": 20,
                                              "checkpoint_every": 50})
    state = np.array([2.0, 12.0])
    for k in range(40):  # drive it on directly, without the reset of simulate()
        m = Measurement(k / 75e3, 12.0, state[1], state[0], state[1] / LOAD, 48.0)
        adaptive.step(m)
        if any(fallbacks):
            break
    assert any(fallbacks) and adaptive.counters["fallbacks"] >= 1
    np.testing.assert_array_equal(adaptive.output_weights, good)
    np.testing.assert_array_equal(adaptive.inner.predictor.model._weights[-1], good[:-1])


def test_reset_starts_every_run_from_the_offline_weights():
    model = network_model()
    adaptive = adaptive_for(model, varied, min_change_current=0.0, min_change_voltage=0.0)
    simulate(adaptive, drifted(model), 100, varied)
    assert not np.array_equal(adaptive.output_weights, adaptive._offline)
    adaptive.reset()
    np.testing.assert_array_equal(adaptive.output_weights, adaptive._offline)
    np.testing.assert_array_equal(adaptive.inner.predictor.model._weights[-1], adaptive._offline[:-1])


@pytest.mark.parametrize("kwargs", [{"forgetting": 0.0}, {"forgetting": 1.5}, {"max_step": 0.0},
                                    {"fallback_ratio": 1.0}, {"error_memory": 1.0}])
def test_invalid_settings_are_refused(kwargs):
    with pytest.raises(ValueError):
        AdaptationSettings(**kwargs)


def test_a_network_with_the_supply_input_learns_without_a_supply_reading():
    """A plant that reports no supply voltage (NaN): the regressor takes the nominal supply, as the NNPC's
    predictor does, so the least-squares update stays finite and learns the drifted output layer (the plant here
    sees 48 V, the nominal supply)."""
    config = NNConfig(hidden=(6,), delays=2, extra_signals=("load_conductance", "input_voltage"))
    torch.manual_seed(0)
    mean = np.array([2.0, 12.0, 0.3, 2.0, 12.0, 0.3, 1 / LOAD, 48.0])
    std = np.array([1.0, 5.0, 0.2, 1.0, 5.0, 0.2, 0.05, 5.0])
    model = NNPlantModel(config, PlantNetwork(config), mean, std, np.array([2.0, 12.0]), np.array([1.0, 5.0]))
    own = copy.deepcopy(model)
    settings = AdaptationSettings(max_step=1.0, max_deviation=5.0, min_change_current=0.0, min_change_voltage=0.0)
    with pytest.raises(ValueError, match="takes the supply voltage as an input; give nominal_input_voltage"):
        AdaptiveNNPC(ScriptedNNPC(own, varied), own, settings, nominal_load=LOAD)
    adaptive = AdaptiveNNPC(ScriptedNNPC(own, varied), own, settings, nominal_load=LOAD, nominal_input_voltage=48.0)
    plant = drifted(model)
    hidden = adaptive._hidden_layers
    state, previous, errors = np.array([2.0, 12.0]), (2.0, 12.0, varied(0)), []
    for k in range(600):
        duty = adaptive.step(Measurement(k * adaptive.sample_period, 12.0, state[1], state[0], state[1] / LOAD,
                                         float("nan")))
        h = np.array([state[0], state[1], duty, *previous, 1 / LOAD, 48.0])
        for w, b in hidden:
            h = np.tanh(h @ w + b)
        phi = np.append(h, 1.0)
        new = phi @ plant
        errors.append(float(np.abs(new - phi @ adaptive.output_weights).max()))
        previous, state = (state[0], state[1], duty), np.clip(new, [0.0, 0.0], [5.0, 20.0])
    assert adaptive.counters["updates"] > 500 and np.all(np.isfinite(adaptive.output_weights))
    assert np.mean(errors[-100:]) < 0.02 * np.mean(errors[:5])
