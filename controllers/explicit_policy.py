"""The explicit NNPC: a small policy network that imitates the online NNPC's first move.

The online NNPC (:mod:`controllers.predictive`) solves a horizon optimisation at every sample --
thousands of network steps. The explicit policy replaces that search by one forward pass of a
small network trained (by :mod:`cosim.design.distillation`, DAgger on the plant FMU) to return the
optimizer's first move. It sees what the online NNPC sees, at sample k:

    features = [vo(k) - r, iL(k) - G r, vo(k-1) - r, iL(k-1) - G r, d(k-1), r, G]

with r the reference [V], vo, iL the measured output voltage [V] and inductor current [A], d(k-1)
the duty applied over the last period and G the load conductance [S] estimated from the sensors by
:func:`controllers.load_estimate.estimate_conductance` (the online NNPC's own estimate; G r is its
steady-state current reference iref). Errors instead of raw signals let one network serve every
reference. The duty is

    u(k) = net(features)                                      (tanh hidden layers, linear output)
    I(k) = I(k-1) + K_i T_s (r - vo(k))    only while |r - vo(k)| <= band * r, and kept only if it
                                           does not push a saturated duty further (as the PI's)
    d(k) = clip(u(k) + I(k), d_min, d_max)

The integral term makes the policy offset-free (the online NNPC is offset-free through its
disturbance estimate, which the network cannot reproduce exactly: a first-move error of 1e-3
would leave about 50 mV). It integrates only near the reference, so it trims the steady state
without winding up in transients.

Inference: :meth:`ExplicitPolicy.evaluate` is a batched numpy pass (for studies and training
checks); the controller's per-sample step (:meth:`ExplicitPolicy.forward`) is scalar Python in
exactly the operation order of the C twin (``controllers/c/explicit_policy.c``), with
``math.tanh`` (the C library's tanh), so the twins agree bit for bit. The input standardisation
and output de-standardisation are folded into the first and last layer. Training uses torch
(full-batch L-BFGS, seeded, one thread). Files are written and checked like the NN plant
model's (:mod:`controllers.nn_model`): ``torch.load(weights_only=True)``, format, shapes,
SHA-256, finite weights, the feature list and the control period; anything else is a one-line
:class:`~cosim.base.errors.ModelFileError` naming the file.
"""

from __future__ import annotations

import io
import math
import zipfile
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from controllers.base import Measurement, check_duty_limits, check_sample_period
from controllers.load_estimate import estimate_conductance
from cosim.base.errors import ModelFileError

FORMAT = "buck-cosim explicit policy"
VERSION = 1
#: the policy's inputs, in order (a file trained for other inputs is refused)
FEATURES = ("output_voltage_error[k]", "inductor_current_error[k]", "output_voltage_error[k-1]",
            "inductor_current_error[k-1]", "duty_cycle[k-1]", "reference[k]", "load_conductance[k]")
N_FEATURES = len(FEATURES)
ACTIVATIONS = ("tanh",)
#: the integral term's default gain per sample, K_i T_s [1/V]: K_i = 200 1/(V s) at 13.33 us (about the
#: tuned PI's there); the same per-sample gain at other rates (a K_i of 200 at 1 ms would add 0.2 duty per
#: volt and sample and make the loop oscillate)
INTEGRAL_GAIN_PER_SAMPLE = 200.0 / 75e3


def default_integral_gain(sample_period: float) -> float:
    """K_i [1/(V s)] of the integral term for a sample period [s] (:data:`INTEGRAL_GAIN_PER_SAMPLE` / T_s)."""
    return INTEGRAL_GAIN_PER_SAMPLE / sample_period


def policy_features(current: float, voltage: float, previous_current: float, previous_voltage: float,
                    previous_duty: float, reference: float, conductance: float) -> list[float]:
    """The policy's inputs (:data:`FEATURES`) from one sample: currents [A], voltages [V], duty [1],
    conductance [S]; the C twin computes them in the same order."""
    current_reference = conductance * reference
    return [voltage - reference, current - current_reference, previous_voltage - reference,
            previous_current - current_reference, previous_duty, reference, conductance]


@dataclass(frozen=True)
class PolicyConfig:
    """Network size and the offset-free integral term."""

    hidden: tuple[int, ...] = (14,)  # tanh units per hidden layer (7-14-1: 114 MACs, 14 tanh per step; 7-12-1 from
    # 18 000 labels missed the IAE target on the switched mismatch plant's load change by 2 %, from 33 600 it met it
    # with less margin; two layers of 12 do not fit the Cortex-M4F budget: docs/guide/explicit-nnpc.md)
    activation: str = "tanh"
    integral_gain: float | None = None  # K_i [1/(V s)]: duty per volt-second of error near the reference;
    # None: default_integral_gain(T_s) when trained (200 at 13.33 us; ten times more destabilises a policy
    # of moderate proportional gain)
    integral_band: float = 0.05  # integrate only while |r - vo| <= band * |r| (relative) [1]

    def __post_init__(self):
        if not self.hidden or any(int(n) < 1 for n in self.hidden):
            raise ValueError(f"hidden layers {self.hidden} are invalid: expected one or more sizes >= 1")
        object.__setattr__(self, "hidden", tuple(int(n) for n in self.hidden))
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation {self.activation!r} is unknown: expected one of {', '.join(ACTIVATIONS)}")
        if self.integral_gain is not None and not (math.isfinite(self.integral_gain) and self.integral_gain >= 0):
            raise ValueError(f"integral gain {self.integral_gain} is invalid: expected a finite value >= 0 1/(V s)")
        if not (math.isfinite(self.integral_band) and self.integral_band >= 0):
            raise ValueError(f"integral band {self.integral_band} is invalid: expected a finite value >= 0")

    @property
    def label(self) -> str:
        return "-".join(str(n) for n in (N_FEATURES, *self.hidden, 1)) + f" {self.activation}"

    def macs(self) -> int:
        """Multiply-accumulates per step: the layers, the feature products and the integral term."""
        widths = [N_FEATURES, *self.hidden, 1]
        return sum(a * b for a, b in zip(widths[:-1], widths[1:])) + 1 + 1


@dataclass
class ExplicitPolicy:
    """A trained policy network: folded weights (row-vector convention, ``x @ W + b``), its sample
    period [s], duty limits and metadata (training, DAgger rounds, first-move errors)."""

    config: PolicyConfig
    weights: list[np.ndarray]  # (inputs, outputs) per layer, normalisation folded in
    biases: list[np.ndarray]
    sample_period: float  # [s]
    duty_limits: tuple[float, float] = (0.0, 1.0)
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.config.integral_gain is None:
            raise ValueError("explicit policy: the integral gain must be a number (train_policy sets the default)")
        self.sample_period = check_sample_period(self.sample_period, "explicit policy")
        self.duty_limits = check_duty_limits(self.duty_limits, "explicit policy")
        widths = [N_FEATURES, *self.config.hidden, 1]
        if len(self.weights) != len(widths) - 1 or len(self.biases) != len(widths) - 1:
            raise ValueError(f"explicit policy {self.config.label}: {len(self.weights)} layers, expected "
                             f"{len(widths) - 1}")
        for layer, (w, b) in enumerate(zip(self.weights, self.biases)):
            if w.shape != (widths[layer], widths[layer + 1]) or b.shape != (widths[layer + 1],):
                raise ValueError(f"explicit policy {self.config.label}: layer {layer} has shapes {w.shape}, {b.shape}")
        # plain nested lists for the scalar step (indexing numpy scalars is several times slower)
        self._layers = [(w.tolist(), b.tolist()) for w, b in zip(self.weights, self.biases)]

    def evaluate(self, features: np.ndarray) -> np.ndarray:
        """Network output u (before the integral term and the limits) for a batch (M, 7) -> (M,)."""
        h = np.asarray(features, dtype=float)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = h @ w + b
            if i < last:
                h = np.tanh(h)
        return h[:, 0]

    def forward(self, x: list[float]) -> float:
        """Network output u for one sample, in the C twin's operation order (sum from the bias, inputs
        in order; ``math.tanh``)."""
        h = x
        last = len(self._layers) - 1
        for layer, (w, b) in enumerate(self._layers):
            out = []
            for j in range(len(b)):
                s = b[j]
                for i in range(len(h)):
                    s += h[i] * w[i][j]
                out.append(math.tanh(s) if layer < last else s)
            h = out
        return h[0]


class PolicyInputs:
    """What the policy remembers between samples to form its inputs: iL and vo at the last sample,
    the duty applied since, and the load estimate (starting from the nominal load)."""

    def __init__(self, nominal_load: float):
        self.nominal_load = float(nominal_load)
        if not (self.nominal_load > 0 and math.isfinite(self.nominal_load)):
            raise ValueError(f"nominal load {nominal_load} Ohm is invalid: expected a finite value > 0")
        self.reset()

    def reset(self) -> None:
        self.have_history = False
        self.previous = (0.0, 0.0)  # [A], [V]
        self.previous_duty = 0.0
        self.conductance = 1.0 / self.nominal_load  # [S]

    def features(self, m: Measurement) -> list[float]:
        """The inputs at this sample (:data:`FEATURES`); the state is not advanced."""
        current, voltage = m.inductor_current, m.output_voltage
        conductance = estimate_conductance(voltage, m.load_current, current, self.conductance)
        previous_current, previous_voltage = self.previous if self.have_history else (current, voltage)
        return policy_features(current, voltage, previous_current, previous_voltage, self.previous_duty,
                               m.reference, conductance)

    def advance(self, m: Measurement, features: list[float], duty: float) -> None:
        """Remember this sample and the duty applied until the next one."""
        self.conductance = features[6]
        self.previous = (m.inductor_current, m.output_voltage)
        self.have_history = True
        self.previous_duty = duty


class ExplicitPolicyController:
    """The explicit NNPC as a controller (:class:`controllers.base.Controller`); see the module docstring."""

    def __init__(self, policy: ExplicitPolicy, name: str = "NNPC-explicit", *, nominal_load: float):
        """``nominal_load`` [Ohm]: the load assumed until the sensors give an estimate (as the NNPC's)."""
        self.policy = policy
        self.name = name
        self.sample_period = policy.sample_period
        self.duty_limits = policy.duty_limits
        self.inputs = PolicyInputs(nominal_load)
        self.nominal_load = self.inputs.nominal_load
        self._ki_ts = policy.config.integral_gain * policy.sample_period  # as the C twin: (Ki Ts) e
        self.reset()

    def reset(self) -> None:
        self.inputs.reset()
        self.integral = 0.0
        self.last_features: list[float] | None = None
        self.last_output = math.nan

    def step(self, m: Measurement) -> float:
        if not math.isfinite(m.inductor_current):
            raise ValueError(f"{self.name} needs the inductor current: the plant binding has no inductor_current role")
        x = self.inputs.features(m)
        u = self.policy.forward(x)
        low, high = self.duty_limits
        error = m.reference - m.output_voltage
        integral = self.integral
        if abs(error) <= self.policy.config.integral_band * abs(m.reference):
            integral = integral + self._ki_ts * error
        unclamped = u + integral
        duty = unclamped
        if low > duty:
            duty = low
        if high < duty:
            duty = high
        pushing_high = unclamped > high and error > 0
        pushing_low = unclamped < low and error < 0
        if not (pushing_high or pushing_low):
            self.integral = integral
        self.inputs.advance(m, x, duty)
        self.last_features, self.last_output = x, u
        return duty

    def describe(self) -> dict:
        meta = self.policy.metadata
        return {"type": "explicit policy (network imitating the online NNPC's first move)", "name": self.name,
                "sample_period_s": self.sample_period, "duty_limits": list(self.duty_limits),
                "network": self.policy.config.label, "macs_per_step": self.policy.config.macs(),
                "integral_gain_per_V_s": self.policy.config.integral_gain,
                "integral_band": self.policy.config.integral_band,
                "distillation": meta.get("distillation"), "expert": meta.get("expert"),
                "design_key": (meta.get("design") or {}).get("key")}


# ---------------------------------------------------------------------------------------------
# Training


@dataclass(frozen=True)
class PolicyTrainingSettings:
    seed: int = 0
    validation_fraction: float = 0.15
    max_iterations: int = 1500  # L-BFGS iterations
    check_every: int = 25
    patience: int = 8  # checks without validation improvement before stopping


def saturation_aware_loss(output, label, low: float, high: float):
    """Squared error of the network output against the expert's move, where a move at a duty limit
    is matched by any output beyond that limit (the output is clipped there anyway)."""
    import torch

    error = output - label
    at_high = label >= high - 1e-9
    at_low = label <= low + 1e-9
    error = torch.where(at_high, torch.clamp(error, max=0.0), error)
    error = torch.where(at_low, torch.clamp(error, min=0.0), error)
    return torch.mean(error * error)


def train_policy(features: np.ndarray, labels: np.ndarray, sample_period: float, config: PolicyConfig = PolicyConfig(),
                 settings: PolicyTrainingSettings = PolicyTrainingSettings(), duty_limits: tuple[float, float] = (0.0, 1.0),
                 metadata: dict | None = None, initial: ExplicitPolicy | None = None) -> ExplicitPolicy:
    """Fit the network to (features (M, 7), expert moves (M,)): full-batch L-BFGS on the
    saturation-aware loss, early stopping on a seeded validation split, one thread, float64."""
    import torch

    x = np.asarray(features, dtype=float)
    y = np.asarray(labels, dtype=float)
    if x.ndim != 2 or x.shape[1] != N_FEATURES or y.shape != (len(x),):
        raise ValueError(f"training data of shapes {x.shape}, {y.shape}: expected (M, {N_FEATURES}) and (M,)")
    if len(x) < 50:
        raise ValueError(f"{len(x)} labelled samples are too few to train a policy on: expected at least 50")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("the labelled samples hold NaN or infinite values")
    low, high = check_duty_limits(duty_limits, "explicit policy")
    if config.integral_gain is None:
        config = replace(config, integral_gain=default_integral_gain(sample_period))
    rng = np.random.default_rng(settings.seed)
    order = rng.permutation(len(x))
    n_val = max(1, int(round(len(x) * settings.validation_fraction)))
    val_idx, fit_idx = order[:n_val], order[n_val:]
    in_mean, in_std = x[fit_idx].mean(axis=0), x[fit_idx].std(axis=0)
    in_std[in_std < 1e-12] = 1.0
    out_mean, out_std = float(y[fit_idx].mean()), float(y[fit_idx].std()) or 1.0
    xn = torch.from_numpy((x - in_mean) / in_std)
    yt = torch.from_numpy(y)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(settings.seed)
        layers: list = []
        width = N_FEATURES
        for size in config.hidden:
            layers += [torch.nn.Linear(width, size, dtype=torch.float64), torch.nn.Tanh()]
            width = size
        layers.append(torch.nn.Linear(width, 1, dtype=torch.float64))
        network = torch.nn.Sequential(*layers)
        if initial is not None and initial.config.hidden == config.hidden:
            _load_folded(network, initial, in_mean, in_std, out_mean, out_std)

        def predict(inputs):
            return network(inputs)[:, 0] * out_std + out_mean

        from controllers.lbfgs import LBFGS  # the same trial steps on every CPU

        optimizer = LBFGS(network.parameters(), lr=1.0, max_iter=settings.check_every, history_size=20,
                          line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-15)
        fit_x, fit_y, val_x, val_y = xn[fit_idx], yt[fit_idx], xn[val_idx], yt[val_idx]

        def closure():
            optimizer.zero_grad()
            loss = saturation_aware_loss(predict(fit_x), fit_y, low, high)
            loss.backward()
            return loss

        best = (math.inf, {k: v.clone() for k, v in network.state_dict().items()}, 0)
        without_gain, iterations = 0, 0
        while iterations < settings.max_iterations:
            optimizer.step(closure)
            iterations += settings.check_every
            with torch.no_grad():
                val = float(saturation_aware_loss(predict(val_x), val_y, low, high))
            if val < best[0] * (1 - 1e-4):
                best = (val, {k: v.clone() for k, v in network.state_dict().items()}, iterations)
                without_gain = 0
            else:
                without_gain += 1
                if without_gain >= settings.patience:
                    break
        network.load_state_dict(best[1])
        with torch.no_grad():
            fit_loss = float(saturation_aware_loss(predict(fit_x), fit_y, low, high))
    finally:
        torch.set_num_threads(threads)
    linears = [m for m in network if isinstance(m, torch.nn.Linear)]
    weights = [m.weight.detach().numpy().T.copy() for m in linears]
    biases = [m.bias.detach().numpy().copy() for m in linears]
    biases[0] = biases[0] - (in_mean / in_std) @ weights[0]
    weights[0] = weights[0] / in_std[:, None]
    weights[-1] = weights[-1] * out_std
    biases[-1] = biases[-1] * out_std + out_mean
    meta = {**(metadata or {}), "config": _config_dict(config), "features": list(FEATURES),
            "control_period_s": sample_period,
            "training": {**asdict(settings), "iterations": iterations, "best_iteration": best[2],
                         "samples": int(len(x)), "fit_rms_duty": math.sqrt(fit_loss),
                         "validation_rms_duty": math.sqrt(best[0])}}
    return ExplicitPolicy(config, weights, biases, sample_period, (low, high), meta)


def _load_folded(network, policy: ExplicitPolicy, in_mean, in_std, out_mean, out_std) -> None:
    """Start training from a previous round's policy (unfold its weights into this round's scaling)."""
    import torch

    weights = [w.copy() for w in policy.weights]
    biases = [b.copy() for b in policy.biases]
    biases[0] = biases[0] + in_mean @ weights[0]
    weights[0] = weights[0] * in_std[:, None]
    weights[-1] = weights[-1] / out_std
    biases[-1] = (biases[-1] - out_mean) / out_std
    linears = [m for m in network if isinstance(m, torch.nn.Linear)]
    with torch.no_grad():
        for module, w, b in zip(linears, weights, biases):
            module.weight.copy_(torch.from_numpy(w.T.copy()))
            module.bias.copy_(torch.from_numpy(b))


# ---------------------------------------------------------------------------------------------
# Files


def _config_dict(config: PolicyConfig) -> dict:
    return {"hidden": list(config.hidden), "activation": config.activation, "integral_gain": config.integral_gain,
            "integral_band": config.integral_band}


def _checksum(arrays: list[np.ndarray], numbers: list[float]) -> str:
    import hashlib

    digest = hashlib.sha256()
    for array in arrays:
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    digest.update(np.asarray(numbers, dtype=np.float64).tobytes())
    return digest.hexdigest()


def save_policy(policy: ExplicitPolicy, path: Path) -> Path:
    """Write the policy atomically (tensors, numbers, strings, lists and dicts only); a policy with
    non-finite weights is refused (ValueError)."""
    import torch

    from cosim.base.files import atomic_write

    arrays = [*policy.weights, *policy.biases]
    if not all(np.isfinite(a).all() for a in arrays):
        raise ValueError("the trained policy has non-finite weights: refusing to save it")
    numbers = [policy.sample_period, *policy.duty_limits, policy.config.integral_gain, policy.config.integral_band]
    payload = {"format": FORMAT, "version": VERSION, "config": _config_dict(policy.config), "features": list(FEATURES),
               "sample_period_s": policy.sample_period, "duty_limits": list(policy.duty_limits),
               "weights": [torch.from_numpy(w.copy()) for w in policy.weights],
               "biases": [torch.from_numpy(b.copy()) for b in policy.biases],
               "metadata": policy.metadata, "checksum": _checksum(arrays, numbers)}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    return atomic_write(Path(path), lambda tmp: tmp.write_bytes(buffer.getvalue()))


def load_policy(path: Path, expect_period: float | None = None) -> ExplicitPolicy:
    """Read a policy written by :func:`save_policy`; refuse anything else in one line naming the file."""
    import torch

    path = Path(path)
    what = f"policy file {path}"
    if path.is_dir():
        raise ModelFileError(f"{what} is a folder: expected a .pt file written by buck-cosim distill")
    if not path.is_file():
        raise ModelFileError(f"{what} does not exist")
    if not zipfile.is_zipfile(path):
        raise ModelFileError(f"{what} is not a policy written by buck-cosim distill (not a torch zip archive: "
                             "truncated, or another kind of file)")
    try:
        payload = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as error:
        text = str(error).strip()
        reason = text.splitlines()[0] if text else type(error).__name__
        if "Unsupported global" in text or "Unsupported operand" in text:
            reason = "it contains objects other than plain weights (refused without running them)"
        raise ModelFileError(f"{what} cannot be read: {reason[:200]}") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        kind = f" (it is a {payload['format']})" if isinstance(payload, dict) and isinstance(payload.get("format"), str) \
            else ""
        raise ModelFileError(f"{what} is not a {FORMAT} (missing or wrong 'format'){kind}")
    if payload.get("version") != VERSION:
        raise ModelFileError(f"{what} has format version {payload.get('version')!r}; expected {VERSION}")
    features = payload.get("features")
    if features != list(FEATURES):
        raise ModelFileError(f"{what} was trained for inputs {features!r}; expected {list(FEATURES)}")
    try:
        raw = payload["config"]
        config = PolicyConfig(hidden=tuple(raw["hidden"]), activation=raw["activation"],
                              integral_gain=float(raw["integral_gain"]), integral_band=float(raw["integral_band"]))
        weights = [w.numpy().astype(np.float64) for w in payload["weights"]]
        biases = [b.numpy().astype(np.float64) for b in payload["biases"]]
        period = float(payload["sample_period_s"])
        limits = tuple(float(v) for v in payload["duty_limits"])
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ModelFileError(f"{what} does not match its declared network: {first[:200]}") from None
    numbers = [period, *limits, config.integral_gain, config.integral_band]
    if _checksum([*weights, *biases], numbers) != payload.get("checksum"):
        raise ModelFileError(f"{what} fails its SHA-256 check: the weights were changed after saving")
    if not all(np.isfinite(a).all() for a in [*weights, *biases]):
        raise ModelFileError(f"{what} has non-finite weights: refused (the controller would command nonsense)")
    if expect_period is not None and not math.isclose(period, expect_period, rel_tol=1e-9):
        raise ModelFileError(f"{what} was distilled at a control period of {period * 1e6:.4g} us; the controller "
                             f"samples every {expect_period * 1e6:.4g} us")
    try:
        return ExplicitPolicy(config, weights, biases, period, limits, payload.get("metadata", {}))
    except ValueError as error:
        raise ModelFileError(f"{what} does not match its declared network: {error}") from None
