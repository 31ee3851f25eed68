"""Online adaptation of the NNPC's network to a drifting plant, from its own closed-loop data.

:class:`AdaptiveNNPC` wraps an NNPC (the Python :class:`~controllers.predictive.PredictiveController`
or its C twin) and, at every sample, identifies the network's **output layer** by recursive least
squares with forgetting, leaving the hidden layer as identified offline. The output layer is
linear in its parameters, so the update is exact least squares on the recent data, cheap (a few
11 x 11 products for a 10-neuron network) and deterministic; the hidden features the offline
identification found span the local dynamics, so re-weighting them follows a capacitance or a
winding resistance that drifts.

At sample k+1 the regression pair is the network input of sample k, x_k = [iL, vo, d](k), ...,
extras(k) -- exactly what the controller's one-step prediction used -- and the measured state
y_{k+1}; the regressor is phi = [a(x_k), 1] with a the hidden activations. Guards, each counted
in :attr:`AdaptiveNNPC.counters`:

* **saturated** -- no update when a duty in x_k is within ``duty_margin`` of a limit: there the
  loop is open and the data say little about the model the optimizer uses between the limits;
* **non-informative** -- no update in steady state (the state moved less than ``min_change`` and
  the duty did not move), which would only wind up the covariance, and none across a load step
  inside the sample (the load estimate changed: x_k does not describe what the plant saw);
* **bounded** -- each update moves each output column by at most ``max_step`` of its offline
  norm, the total deviation from the offline weights is at most ``max_deviation`` of it, and the
  covariance trace is capped at its initial value;
* **fallback** -- the running (exponentially weighted) one-step error of the adapted model is
  compared with that of the *last good* model, evaluated on the same samples (the hidden layer is
  shared, so that costs one more 11 x 2 product); if it grows past ``fallback_ratio`` times the
  last good one, the weights and covariance return to the last good ones. Every
  ``checkpoint_every`` samples, a model doing at least as well as the last good one becomes it.

Every run starts from the offline weights (:meth:`AdaptiveNNPC.reset`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

from controllers.base import Measurement
from controllers.load_estimate import estimate_conductance
from controllers.nn_config import ACTIVATIONS

if TYPE_CHECKING:  # torch loads with the NN model's module (seconds): only where a network is trained or read
    from controllers.nn_model import NNPlantModel


@dataclass(frozen=True)
class AdaptationSettings:
    forgetting: float = 0.998  # RLS forgetting factor lambda (memory about 1 / (1 - lambda) samples)
    initial_covariance: float = 10.0  # P0 = p0 I on the regressor [hidden activations (-1..1), 1]
    duty_margin: float = 0.01  # a duty this close to a limit counts as saturated
    min_change_current: float = 0.02  # [A] a sample is informative if iL moved more than this ...
    min_change_voltage: float = 0.02  # [V] ... or vo moved more than this ...
    min_change_duty: float = 0.005  # ... or the duty moved more than this
    load_change: float = 0.01  # relative change of the load estimate that marks a load step
    max_step: float = 0.02  # per update: |delta theta| <= max_step |theta_offline|, per output
    max_deviation: float = 0.5  # in total: |theta - theta_offline| <= max_deviation |theta_offline|
    error_memory: float = 0.99  # weight of the running one-step error (about 100 samples)
    fallback_ratio: float = 1.5  # fall back when the running error exceeds this x the last good one
    checkpoint_every: int = 300  # samples between promotions of the current model to "last good"
    warmup: int = 50  # samples of error history before a fallback or a promotion is decided

    def __post_init__(self):
        if not 0 < self.forgetting <= 1:
            raise ValueError(f"forgetting = {self.forgetting} is invalid: expected 0 < lambda <= 1")
        if self.initial_covariance <= 0 or self.max_step <= 0 or self.max_deviation <= 0:
            raise ValueError("initial_covariance, max_step and max_deviation must be > 0")
        if not 0 < self.error_memory < 1 or self.fallback_ratio <= 1 or self.checkpoint_every < 1:
            raise ValueError("error_memory must be in (0, 1), fallback_ratio > 1 and checkpoint_every >= 1")


def output_layer(controller) -> tuple[np.ndarray, np.ndarray]:
    """Writable views of the output layer (rows: last hidden layer's units, columns: [iL, vo]) and
    its bias, in the physical units of the folded network, of a Python or C-twin NNPC."""
    config = getattr(controller, "config", None)
    if config is not None and hasattr(config, "predictor"):  # the C twin: its own copy of the weights
        nn = config.predictor.nn
        layer = nn.n_hidden
        width = nn.hidden[nn.n_hidden - 1]
        weights = np.ctypeslib.as_array(nn.weights)[layer, :width, :2]
        biases = np.ctypeslib.as_array(nn.biases)[layer, :2]
        return weights, biases
    model = controller.predictor.model
    return model._weights[-1], model._biases[-1]


class AdaptiveNNPC:
    """An NNPC whose network's output layer follows the plant (see the module docstring)."""

    def __init__(self, inner, model: NNPlantModel, settings: AdaptationSettings = AdaptationSettings(),
                 name: str | None = None, *, nominal_load: float, nominal_input_voltage: float | None = None):
        """``inner``: the NNPC to adapt (Python or C twin), built on ``model`` -- for the Python
        controller, on its *own copy* of it, since the output layer is rewritten in place.
        ``nominal_load`` [Ohm]: the load assumed until the sensors tell (as the controller's);
        ``nominal_input_voltage`` [V]: the supply a network with the supply as an input is given when the
        measurement has none (default: the inner controller's, as its predictor assumes it)."""
        self.inner = inner
        self.nominal_load = nominal_load
        self.nominal_input_voltage = (nominal_input_voltage if nominal_input_voltage is not None
                                      else getattr(inner, "nominal_input_voltage", math.nan))
        if "input_voltage" in model.config.extra_signals and not math.isfinite(self.nominal_input_voltage):
            raise ValueError("AdaptiveNNPC: the network takes the supply voltage as an input; give "
                             "nominal_input_voltage [V] for samples without a supply reading")
        self.model = model
        self.settings = settings
        self.name = name or f"{inner.name}-adaptive"
        self.sample_period = inner.sample_period
        self.duty_limits = inner.duty_limits
        self._weights, self._biases = output_layer(inner)
        self._hidden_layers = [(w.copy(), b.copy()) for w, b in zip(model._weights[:-1], model._biases[:-1])]
        self._activation = ACTIVATIONS[model.config.activation]
        self._offline = np.vstack([self._weights, self._biases[None, :]]).copy()  # theta (h + 1, 2)
        self._offline_norm = np.linalg.norm(self._offline, axis=0)
        self._scale = 1.0 / np.asarray(model.output_std, dtype=float) ** 2  # error weights per output
        if model.config.residual:
            raise ValueError("AdaptiveNNPC adapts networks that predict the state itself (residual = False)")
        self._delays = model.config.delays
        self._extras = model.config.extra_signals
        self.reset()

    # ------------------------------------------------------------------ protocol
    def reset(self) -> None:
        self.inner.reset()
        size = len(self._offline)
        self._theta = self._offline.copy()
        self._write(self._theta)
        self._covariance = np.eye(size) * self.settings.initial_covariance
        self._good = (self._theta.copy(), self._covariance.copy())
        self._error, self._good_error, self._errors_seen = 0.0, 0.0, 0
        self._since_checkpoint = 0
        self._input = None  # network input of the previous sample
        self._previous_state = None
        self._history: list[tuple[float, float, float]] = []
        self._conductance = 1.0 / self.nominal_load
        self.counters = {"samples": 0, "updates": 0, "saturated": 0, "steady": 0, "load_step": 0, "bounded": 0,
                         "fallbacks": 0, "checkpoints": 0}

    def step(self, m: Measurement) -> float:
        state = (m.inductor_current, m.output_voltage)
        conductance = self._load_conductance(m)
        if self._input is not None and math.isfinite(state[0]):
            self._learn(self._input, np.array(state), conductance)
        duty = self.inner.step(m)
        self._history.insert(0, (state[0], state[1], duty))
        del self._history[self._delays:]
        if len(self._history) == self._delays:
            # a plant without a supply reading: the nominal supply, as the controller's predictor assumes it
            supply = m.input_voltage if math.isfinite(m.input_voltage) else self.nominal_input_voltage
            extras = {"load_conductance": conductance, "load_current": m.load_current, "input_voltage": supply}
            self._input = np.array([v for row in self._history for v in row] + [extras[s] for s in self._extras])
            self._input_conductance = conductance
        self._previous_state = state
        return duty

    def describe(self) -> dict:
        return {"type": "adaptive NNPC (recursive least squares on the network's output layer)", "name": self.name,
                "sample_period_s": self.sample_period, "settings": asdict(self.settings),
                "inner": self.inner.describe()}

    # ------------------------------------------------------------------ adaptation
    def _load_conductance(self, m: Measurement) -> float:
        """The controller's own load estimate (the network's load input), sample by sample."""
        self._conductance = estimate_conductance(m.output_voltage, m.load_current, m.inductor_current,
                                                 self._conductance)
        return self._conductance

    def _features(self, x: np.ndarray) -> np.ndarray:
        h = x
        for w, b in self._hidden_layers:
            h = self._activation(h @ w + b)
        return np.append(h, 1.0)

    def _learn(self, x: np.ndarray, measured: np.ndarray, conductance: float) -> None:
        s, counters = self.settings, self.counters
        counters["samples"] += 1
        phi = self._features(x)
        error = measured - phi @ self._theta
        good_error = measured - phi @ self._good[0]
        memory = s.error_memory
        self._error = memory * self._error + (1 - memory) * float(error * error @ self._scale)
        self._good_error = memory * self._good_error + (1 - memory) * float(good_error * good_error @ self._scale)
        self._errors_seen += 1
        self._since_checkpoint += 1
        if self._errors_seen >= s.warmup:
            if self._error > s.fallback_ratio * self._good_error:  # the adapted model got worse: back to the last good
                self._theta, self._covariance = self._good[0].copy(), self._good[1].copy()
                self._write(self._theta)
                self._error = self._good_error
                counters["fallbacks"] += 1
                self._since_checkpoint = 0
                return
            if self._since_checkpoint >= s.checkpoint_every:
                if self._error <= self._good_error:
                    self._good = (self._theta.copy(), self._covariance.copy())
                    self._good_error = self._error
                    counters["checkpoints"] += 1
                self._since_checkpoint = 0
        low, high = self.duty_limits
        duties = x[2:3 * self._delays:3]
        if np.any(duties <= low + s.duty_margin) or np.any(duties >= high - s.duty_margin):
            counters["saturated"] += 1
            return
        previous = self._input_conductance
        if previous > 0 and abs(conductance - previous) > s.load_change * previous:
            counters["load_step"] += 1
            return
        moved = (abs(measured[0] - x[0]) > s.min_change_current or abs(measured[1] - x[1]) > s.min_change_voltage
                 or (self._delays > 1 and abs(x[2] - x[5]) > s.min_change_duty))
        if not moved:
            counters["steady"] += 1
            return
        p = self._covariance
        p_phi = p @ phi
        gain = p_phi / (s.forgetting + phi @ p_phi)
        step = np.outer(gain, error)
        norms = np.linalg.norm(step, axis=0)
        limit = s.max_step * self._offline_norm
        if np.any(norms > limit):
            step *= np.minimum(1.0, limit / np.maximum(norms, 1e-300))
            counters["bounded"] += 1
        theta = self._theta + step
        deviation = theta - self._offline
        spread = np.linalg.norm(deviation, axis=0)
        allowed = s.max_deviation * self._offline_norm
        if np.any(spread > allowed):
            theta = self._offline + deviation * np.minimum(1.0, allowed / np.maximum(spread, 1e-300))
            counters["bounded"] += 1
        self._theta = theta
        p = (p - np.outer(gain, p_phi)) / s.forgetting
        trace, cap = float(np.trace(p)), s.initial_covariance * len(phi)
        if trace > cap:
            p *= cap / trace
        self._covariance = 0.5 * (p + p.T)
        self._write(theta)
        counters["updates"] += 1

    def _write(self, theta: np.ndarray) -> None:
        self._weights[...] = theta[:-1]
        self._biases[...] = theta[-1]

    @property
    def output_weights(self) -> np.ndarray:
        """The adapted output layer [weights; bias], (hidden + 1, 2), physical units."""
        return self._theta.copy()

    def with_inner(self, inner) -> "AdaptiveNNPC":
        """The same adaptation around another implementation of the inner NNPC (e.g. its C twin)."""
        return AdaptiveNNPC(inner, self.model, self.settings, self.name, nominal_load=self.nominal_load,
                            nominal_input_voltage=self.nominal_input_voltage)
