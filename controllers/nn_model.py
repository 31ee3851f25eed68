"""The neural-network plant model of the NNPC: identification, evaluation, saving and loading.

Paper (eq. 21-22): input [iL(k-1), vc(k-1), d(k-1)] -> output [iL(k), vc(k)], one hidden layer of
7 neurons. Here the hidden layers, the activation and the inputs are configurable: more delayed
samples (``delays``) and extra measured signals at k-1 (``extra_signals``, e.g. the load
current, which tells the network the load). Inputs and outputs are standardised with the
training-set mean and standard deviation; training is full-batch L-BFGS with early stopping on a
validation split, seeded, single-threaded, so the same data give the same weights.

Files are written with ``torch.save`` and read with ``torch.load(weights_only=True)``, which
never executes code from the file; the loader then checks the format, the shapes and a SHA-256
of the weights, and refuses anything else with a one-line :class:`ModelFileError`.
"""

from __future__ import annotations

import hashlib
import io
import math
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from controllers.lbfgs import LBFGS
from controllers.nn_config import ACTIVATIONS, STATE_SIGNALS, NNConfig, TrainingSettings, extra_columns
from cosim.base.errors import ModelFileError

FORMAT = "buck-cosim NN plant model"
VERSION = 1
#: the torch layer of each activation of :data:`controllers.nn_config.ACTIVATIONS`, by the same names
TORCH_ACTIVATIONS = {"tanh": torch.nn.Tanh, "relu": torch.nn.ReLU, "sigmoid": torch.nn.Sigmoid}


def build_dataset(frame, config: NNConfig) -> tuple[np.ndarray, np.ndarray]:
    """Regressors X (n, n_inputs) and targets Y (n, 2) from a sample table in time order.

    One row per control sample: the measured state at k, the duty applied from k to k+1 and the
    extra signals. Sample k's target is the state at k; its inputs are the samples before it.
    """
    states = frame[list(STATE_SIGNALS)].to_numpy(dtype=float)
    duty = frame["duty_cycle"].to_numpy(dtype=float)
    extras = frame[extra_columns(config)].to_numpy(dtype=float) if config.extra_signals else None
    first = config.delays
    rows = []
    for lag in range(1, config.delays + 1):
        rows += [states[first - lag:len(frame) - lag], duty[first - lag:len(frame) - lag, None]]
    if extras is not None:
        rows.append(extras[first - 1:len(frame) - 1])
    x = np.hstack(rows)
    y = states[first:]
    return x, y


class PlantNetwork(torch.nn.Module):
    """Standardised inputs -> hidden layers -> standardised [iL(k), vc(k)]."""

    def __init__(self, config: NNConfig):
        super().__init__()
        layers: list[torch.nn.Module] = []
        width = config.n_inputs
        for size in config.hidden:
            layers += [torch.nn.Linear(width, size, dtype=torch.float64), TORCH_ACTIVATIONS[config.activation]()]
            width = size
        layers.append(torch.nn.Linear(width, 2, dtype=torch.float64))
        self.layers = torch.nn.Sequential(*layers)

    def forward(self, x):
        return self.layers(x)


@dataclass
class NNPlantModel:
    """A trained network with its normalisation and metadata; predicts in physical units."""

    config: NNConfig
    network: PlantNetwork
    input_mean: np.ndarray
    input_std: np.ndarray
    output_mean: np.ndarray
    output_std: np.ndarray
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        self._fold()

    def _fold(self) -> None:
        """Fold the normalisation into the first and last layer, for a lean numpy forward pass."""
        linears = [m for m in self.network.layers if isinstance(m, torch.nn.Linear)]
        weights = [m.weight.detach().numpy().copy() for m in linears]
        biases = [m.bias.detach().numpy().copy() for m in linears]
        biases[0] = biases[0] - weights[0] @ (self.input_mean / self.input_std)
        weights[0] = weights[0] / self.input_std
        weights[-1] = weights[-1] * self.output_std[:, None]
        biases[-1] = biases[-1] * self.output_std + self.output_mean
        self._weights = [w.T.copy() for w in weights]  # row-vector convention: x @ W + b
        self._biases = biases
        self._activation = ACTIVATIONS[self.config.activation]
        self._tanh = self.config.activation == "tanh"
        if len(self._weights) == 2 and self.config.delays == 1:  # pieces of the fast path
            w1 = self._weights[0]
            self._fast = (w1[:2].copy(), w1[2].copy(), w1[3:].copy(), self._biases[0], self._weights[1],
                          self._biases[1])

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Batch prediction in physical units: x (M, n_inputs) -> (M, 2) [iL(k), vc(k)]."""
        h = x
        last = len(self._weights) - 1
        for i, (w, b) in enumerate(zip(self._weights, self._biases)):
            h = h @ w + b
            if i < last:
                h = self._activation(h)
        if self.config.residual:
            h = h + x[:, :2]
        return h

    def predict_torch(self, x: np.ndarray) -> np.ndarray:
        """Reference forward pass through torch (the numpy one must agree with it)."""
        with torch.inference_mode():
            z = (torch.from_numpy(x) - torch.from_numpy(self.input_mean)) / torch.from_numpy(self.input_std)
            y = self.network(z).numpy()
        y = y * self.output_std + self.output_mean
        return y + x[:, :2] if self.config.residual else y

    # ------------------------------------------------------------------ evaluation
    def rollout(self, x0_history: np.ndarray, duties: np.ndarray, extras: np.ndarray | None = None,
                disturbance: np.ndarray | None = None) -> np.ndarray:
        """Open-loop prediction from measured history, for one or many duty sequences.

        ``x0_history`` (M, delays, 3): the last ``delays`` samples [iL, vc, d] (most recent first,
        its duty being the first of the sequence is ignored); ``duties`` (M, N); ``extras`` (M, n_extra)
        held constant; ``disturbance`` (2,) is added to every predicted state before it is fed back
        (the offset-free controller's state-disturbance estimate). Returns (M, N, 2): k+1 .. k+N.
        """
        m, n = duties.shape
        delays = self.config.delays
        window = np.array(x0_history, dtype=float, copy=True)  # (M, delays, 3)
        out = np.empty((m, n, 2))
        for j in range(n):
            window[:, 0, 2] = duties[:, j]
            parts = [window.reshape(m, 3 * delays)]
            if extras is not None and extras.shape[1]:
                parts.append(extras)
            state = self.predict(np.hstack(parts) if len(parts) > 1 else parts[0])
            if disturbance is not None:
                state += disturbance
            out[:, j] = state
            if delays > 1:
                window[:, 1:] = window[:, :-1]
            window[:, 0, :2] = state
        return out

    def rollout_shared(self, history: np.ndarray, duties: np.ndarray, extras: np.ndarray | None = None,
                       disturbance: np.ndarray | None = None) -> np.ndarray:
        """:meth:`rollout` for many duty sequences from one measured history (the controller's case).

        For the common network (one delay, one hidden layer) the history's part of the first layer
        is computed once and each step costs a handful of array operations -- the NNPC hot path.
        Other networks take :meth:`rollout` on a broadcast history (as fast, measured, for them).
        """
        if self.config.delays != 1 or len(self._weights) != 2:
            m = duties.shape[0]
            batch = np.empty((m, *history.shape))
            batch[:] = history
            ex = None
            if extras is not None and len(extras):
                ex = np.empty((m, len(extras)))
                ex[:] = extras
            return self.rollout(batch, duties, ex, disturbance)
        w_state, w_duty, w_extra, b1, w2, b2 = self._fast
        if disturbance is not None:
            b2 = b2 + disturbance  # added to every predicted state, as in rollout()
        constant = b1 if extras is None or not len(extras) else b1 + extras @ w_extra
        residual, tanh = self.config.residual, self._tanh
        m, n = duties.shape
        out = np.empty((m, n, 2))
        state = history[0, :2]
        z = (state @ w_state + constant) + duties[:, :1] * w_duty  # the history's part, once
        for j in range(n):
            if j:
                z = out[:, j - 1] @ w_state
                z += duties[:, j:j + 1] * w_duty
                z += constant
            if tanh:
                np.tanh(z, out=z)
            else:
                z = self._activation(z)
            new = z @ w2
            new += b2
            if residual:
                new += out[:, j - 1] if j else state
            out[:, j] = new
        return out

    def rollout_sensitivities(self, history: np.ndarray, duties: np.ndarray, extras: np.ndarray | None,
                              disturbance: np.ndarray | None, block_of_step: np.ndarray,
                              n_blocks: int) -> tuple[np.ndarray, np.ndarray]:
        """One duty sequence rolled out with its forward sensitivities to the blocked moves (the
        real-time-iteration optimizer's linearisation, :mod:`controllers.predictive`).

        ``history`` (delays, 3) as in :meth:`rollout_shared`; ``duties`` (N,) per step, step j holding
        the value of block ``block_of_step[j]``; ``extras`` (n_extra,) held (no sensitivity). Returns
        the states (N, 2) -- :meth:`rollout_shared`'s for this sequence -- and their Jacobian (N, 2,
        n_blocks) with respect to the block values.

        Forward mode through the rollout, analytic: per step, the network's 2 x 3D Jacobian to its
        window inputs (the states and duties of the D delays) comes backwards from its two outputs --
        g = W_last' diag(slope), then g W_l' diag(slope) through further layers, then g W_0' over the
        window's rows (tanh's slope 1 - tanh^2 from the activation itself; sigmoid a (1 - a); relu 1
        where z > 0) -- and the state's sensitivity is that Jacobian times the window's sensitivity
        (the predicted states' fed back like the states, the duties' unit directions). That costs
        about 2 H (3D + c) multiply-accumulates per step with c propagated directions, where pushing
        the c directions forward through the hidden layer cost H c (2D + 3). A block's column is zero
        until its first step, so only the columns up to the current step's block are propagated.
        """
        n = len(duties)
        delays = self.config.delays
        window = np.array(history, dtype=float, copy=True).reshape(delays, 3)
        sensitivity = np.zeros((delays, 3, n_blocks))  # d window / d block values
        constant = extras if extras is not None and len(extras) else np.zeros(0)
        weights, biases = self._weights, self._biases
        last = len(weights) - 1
        activation = self.config.activation
        rows = 3 * delays
        window_weights = weights[0][:rows].T  # (H_0, 3D): W_0' over the window's inputs
        out = np.empty((n, 2))
        jacobian = np.zeros((n, 2, n_blocks))
        for j in range(n):
            active = int(block_of_step[j]) + 1  # columns beyond are still zero
            window[0, 2] = duties[j]
            sensitivity[0, 2, :] = 0.0
            sensitivity[0, 2, block_of_step[j]] = 1.0
            h = np.concatenate([window.ravel(), constant])
            x_state = h[:2]
            slopes = []
            for w, b in zip(weights[:last], biases[:last]):
                z = h @ w + b
                if activation == "tanh":
                    h = np.tanh(z)
                    slopes.append(1.0 - h * h)
                elif activation == "sigmoid":
                    h = 0.5 * (1.0 + np.tanh(0.5 * z))
                    slopes.append(h * (1.0 - h))
                else:
                    h = np.maximum(z, 0.0)
                    slopes.append((z > 0.0).astype(float))
            y = h @ weights[last] + biases[last]
            g = weights[last].T * slopes[-1]  # (2, H_last)
            for i in range(last - 1, 0, -1):
                g = (g @ weights[i].T) * slopes[i - 1]
            inputs = g @ window_weights  # (2, 3D): d output / d window
            dh = inputs @ sensitivity[:, :, :active].reshape(rows, active)
            if self.config.residual:
                y = y + x_state
                dh = dh + sensitivity[0, :2, :active]
            if disturbance is not None:
                y = y + disturbance
            out[j] = y
            jacobian[j, :, :active] = dh
            if delays > 1:
                window[1:] = window[:-1].copy()
                sensitivity[1:] = sensitivity[:-1].copy()
            window[0, :2] = y
            sensitivity[0, :2, :] = jacobian[j]
        return out, jacobian

    def rmse_report(self, frame, horizon: int) -> dict[str, float]:
        """One-step and multi-step (open loop over ``horizon`` samples) RMSE on a sample table.

        The open-loop simulation feeds the recorded duties *and* the recorded extra signals (the
        load estimate) at every step, its own predicted states back: the simulation error of the
        network. ``*_held_extras`` holds the extra signals at their first value instead, as the
        controller does over its horizon: a load step inside the window then counts as model error.
        """
        x, y = build_dataset(frame, self.config)
        one = self.predict(x) - y
        report = {"one_step_rmse_current_A": float(np.sqrt(np.mean(one[:, 0] ** 2))),
                  "one_step_rmse_voltage_V": float(np.sqrt(np.mean(one[:, 1] ** 2)))}
        d = self.config.delays
        if len(frame) - horizon - 1 <= d - 1:
            return report
        windows = simulation_windows(frame, self.config, horizon)
        history = np.concatenate([windows["states"], np.zeros((*windows["states"].shape[:2], 1))], axis=2)
        history[:, 1:, 2] = windows["past_duties"]
        extras = windows["extras"]
        held = self.rollout(history, windows["duties"], extras[:, 0] if extras.shape[2] else None)
        recorded = self._rollout_recorded(history, windows["duties"], extras)
        for suffix, predicted in (("", recorded), ("_held_extras", held)):
            error = predicted - windows["targets"]
            report[f"{horizon}_step_rmse_current_A{suffix}"] = float(np.sqrt(np.mean(error[:, -1, 0] ** 2)))
            report[f"{horizon}_step_rmse_voltage_V{suffix}"] = float(np.sqrt(np.mean(error[:, -1, 1] ** 2)))
            report[f"horizon_mean_rmse_voltage_V{suffix}"] = float(np.sqrt(np.mean(error[:, :, 1] ** 2)))
        return report

    def _rollout_recorded(self, history: np.ndarray, duties: np.ndarray, extras: np.ndarray) -> np.ndarray:
        """:meth:`rollout` with the extra signals given per step, extras (M, N, n_extra)."""
        m, n = duties.shape
        delays = self.config.delays
        window = history.copy()
        out = np.empty((m, n, 2))
        for j in range(n):
            window[:, 0, 2] = duties[:, j]
            flat = window.reshape(m, 3 * delays)
            state = self.predict(np.hstack([flat, extras[:, j]]) if extras.shape[2] else flat)
            out[:, j] = state
            if delays > 1:
                window[:, 1:] = window[:, :-1]
            window[:, 0, :2] = state
        return out


# ---------------------------------------------------------------------------------------------
# Training


def simulation_windows(frame, config: NNConfig, horizon: int, stride: int = 1) -> dict[str, np.ndarray]:
    """Open-loop windows of a sample table for the simulation-error loss (time order kept).

    A window starts at sample s with the measured history (states at s, s-1, ... and the duties
    applied before s) and holds the recorded duties d(s) .. d(s+H-1), the extra signals measured
    at s .. s+H-1 (the inputs the network is fed at each step) and the measured states
    s+1 .. s+H it must predict. Returns arrays keyed ``states`` (W, delays, 2), ``past_duties``
    (W, delays-1), ``duties`` (W, H), ``extras`` (W, H, n_extra) and ``targets`` (W, H, 2).
    """
    states = frame[list(STATE_SIGNALS)].to_numpy(dtype=float)
    duty = frame["duty_cycle"].to_numpy(dtype=float)
    n, d = len(frame), config.delays
    extras = frame[extra_columns(config)].to_numpy(dtype=float) if config.extra_signals else np.zeros((n, 0))
    starts = np.arange(d - 1, n - horizon, stride)
    return {
        "states": np.stack([states[starts - lag] for lag in range(d)], axis=1).reshape(len(starts), d, 2),
        "past_duties": np.stack([duty[starts - lag] for lag in range(1, d)], axis=1) if d > 1
        else np.zeros((len(starts), 0)),
        "duties": np.stack([duty[starts + j] for j in range(horizon)], axis=1),
        "extras": np.stack([extras[starts + j] for j in range(horizon)], axis=1),
        "targets": np.stack([states[starts + j + 1] for j in range(horizon)], axis=1),
    }


def _torch_rollout(network: PlantNetwork, config: NNConfig, norm: tuple, windows: dict) -> torch.Tensor:
    """The network rolled out over each window in physical units, differentiable: (W, H, 2)."""
    in_mean, in_std, out_mean, out_std = norm
    d = config.delays
    recent = [windows["states"][:, lag] for lag in range(d)]  # most recent first
    duties = windows["duties"]
    applied = [duties[:, :1]] + [windows["past_duties"][:, lag:lag + 1] for lag in range(d - 1)]
    extras = windows["extras"]
    outputs = []
    for j in range(duties.shape[1]):
        applied[0] = duties[:, j:j + 1]
        parts = []
        for lag in range(d):
            parts += [recent[lag], applied[lag]]
        if extras.shape[2]:
            parts.append(extras[:, j])
        z = (torch.cat(parts, dim=1) - in_mean) / in_std
        y = network(z) * out_std + out_mean
        if config.residual:
            y = y + recent[0]
        outputs.append(y)
        recent = [y] + recent[:-1]
        applied = [None] + applied[:-1]
    return torch.stack(outputs, dim=1)


def _lbfgs(network, evaluate, validation_of, max_iterations: int, settings: TrainingSettings, bar=None,
           training_of=None):
    """Full-batch L-BFGS with early stopping on ``validation_of``; ``evaluate()`` returns the loss
    with the gradients of ``network``'s parameters set. Returns (best validation loss, iteration
    of the best, iterations run, history) and leaves the best weights in ``network``. ``history``:
    ``[iteration, training loss, validation loss]`` at the start and at every check (the training
    loss from ``training_of``, NaN without it) -- the learning curves of the identification figure."""
    optimizer = LBFGS(network.parameters(), lr=1.0, max_iter=settings.check_every, history_size=20,
                      line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-15)

    def losses() -> tuple[float, float]:
        with torch.no_grad():
            return (float(training_of()) if training_of is not None else math.nan), float(validation_of())

    fit, start = losses()
    history = [[0, fit, start]]
    best = (start, {k: v.clone() for k, v in network.state_dict().items()}, 0)
    checks_without_gain = 0
    iterations = 0
    while iterations < max_iterations:
        optimizer.step(evaluate)
        iterations += settings.check_every
        if bar is not None:
            bar.update(settings.check_every)
        fit, val = losses()
        history.append([iterations, fit, val])
        if val < best[0] * (1 - 1e-4):
            best = (val, {k: v.clone() for k, v in network.state_dict().items()}, iterations)
            checks_without_gain = 0
        else:
            checks_without_gain += 1
            if checks_without_gain >= settings.patience:
                break
    network.load_state_dict(best[1])
    return best[0], best[2], iterations, history


def _autograd(network, loss_of):
    """An ``evaluate`` for :func:`_lbfgs` from a differentiable loss."""
    def evaluate():
        network.zero_grad()
        loss = loss_of()
        loss.backward()
        return loss
    return evaluate


def train(frame, config: NNConfig = NNConfig(), settings: TrainingSettings = TrainingSettings(),
          metadata: dict | None = None, progress: bool = False, extra_frames=(),
          initial: "NNPlantModel | None" = None) -> NNPlantModel:
    """Identify the network from a sample table (time order); RMSEs on the held-out tail in metadata.

    ``extra_frames``: further records used for training only (e.g. data collected with the NNPC
    in the loop); each is its own time series, so no window spans two records, and the held-out
    tail stays the last ``test_fraction`` of ``frame``. ``initial``: a model of the same
    configuration to start from -- its normalisation is kept and the one-step stage is skipped
    (a refinement on more data, e.g. a closed-loop data round).
    """
    n = len(frame)
    if n < 100:
        raise ValueError(f"{n} samples are too few to train on: expected at least 100")
    if initial is not None and initial.config != config:
        raise ValueError(f"the initial model is a {initial.config.label}; expected {config.label}")
    test_start = int(round(n * (1 - settings.test_fraction)))
    train_frame, test_frame = frame.iloc[:test_start], frame.iloc[test_start:]
    columns = [*STATE_SIGNALS, "duty_cycle", *extra_columns(config)]
    for label, records in (("", frame), *((f" of extra records {k + 1}", f) for k, f in enumerate(extra_frames))):
        finite = np.isfinite(records[columns].to_numpy(dtype=float)).all(axis=1)
        if not finite.all():
            raise ValueError(f"{int((~finite).sum())} of {len(records)} samples{label} hold NaN or infinite values in "
                             f"{', '.join(columns)} (first: row {int(np.argmin(finite))}): expected finite measurements")
    segments = [train_frame, *extra_frames]
    pairs = [build_dataset(segment, config) for segment in segments if len(segment) > config.delays]
    x = np.vstack([p[0] for p in pairs])
    y = np.vstack([p[1] for p in pairs])
    if config.residual:
        y = y - x[:, :2]  # the network learns the change over one sample
    rng = np.random.default_rng(settings.seed)
    order = rng.permutation(len(x))
    n_val = max(1, int(round(len(x) * settings.validation_fraction)))
    val_idx, fit_idx = order[:n_val], order[n_val:]
    if initial is None:
        in_mean, in_std = x[fit_idx].mean(axis=0), x[fit_idx].std(axis=0)
        out_mean, out_std = y[fit_idx].mean(axis=0), y[fit_idx].std(axis=0)
        in_std[in_std < 1e-12] = 1.0
        out_std[out_std < 1e-12] = 1.0
    else:
        in_mean, in_std = initial.input_mean.copy(), initial.input_std.copy()
        out_mean, out_std = initial.output_mean.copy(), initial.output_std.copy()
    xn = torch.from_numpy((x - in_mean) / in_std)
    yn = torch.from_numpy((y - out_mean) / out_std)
    fit_x, fit_y, val_x, val_y = xn[fit_idx], yn[fit_idx], xn[val_idx], yn[val_idx]
    states_scale = (y + x[:, :2] if config.residual else y)[fit_idx].std(axis=0)
    states_scale[states_scale < 1e-12] = 1.0

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    bar = None
    try:
        torch.manual_seed(settings.seed)
        network = PlantNetwork(config)
        if initial is not None:
            network.load_state_dict(initial.network.state_dict())
        loss_fn = torch.nn.MSELoss()
        if progress:
            from tqdm import tqdm

            total = (0 if initial is not None else settings.max_iterations) + \
                (settings.multi_step_iterations if settings.multi_step_horizon > 1 else 0)
            bar = tqdm(total=total, desc=f"training {config.label}", unit="it", leave=False, delay=1.0)
        one_step = {"iterations": 0, "best_iteration": 0, "validation_loss_standardised": None, "history": []}
        if initial is None:
            val, best_it, its, history = _lbfgs(network, _autograd(network, lambda: loss_fn(network(fit_x), fit_y)),
                                                lambda: loss_fn(network(val_x), val_y), settings.max_iterations,
                                                settings, bar, training_of=lambda: loss_fn(network(fit_x), fit_y))
            one_step = {"iterations": its, "best_iteration": best_it, "validation_loss_standardised": val,
                        "history": history}
        multi = None
        if settings.multi_step_horizon > 1 and settings.multi_step_iterations > 0:
            multi = _fit_simulation_error(network, config, segments, (in_mean, in_std, out_mean, out_std),
                                          states_scale, settings, bar)
        with torch.no_grad():
            fit_loss = float(loss_fn(network(fit_x), fit_y))
            val_loss = float(loss_fn(network(val_x), val_y))
    finally:
        if bar is not None:
            bar.close()
        torch.set_num_threads(threads)

    model = NNPlantModel(config, network, in_mean, in_std, out_mean, out_std)
    report = model.rmse_report(test_frame, settings.horizon) if len(test_frame) > settings.horizon + 5 else {}
    model.metadata = {
        **(metadata or {}),
        "config": asdict(config),
        "training": {**asdict(settings), "iterations": one_step["iterations"],
                     "best_iteration": one_step["best_iteration"],
                     # [iteration, training loss, validation loss] (standardised) at every check: learning curves
                     "history": one_step["history"],
                     "fit_loss_standardised": fit_loss, "validation_loss_standardised": val_loss,
                     "multi_step": multi, "refined_from_initial": initial is not None,
                     "samples": n, "extra_samples": int(sum(len(f) for f in extra_frames)),
                     "train_samples": int(len(fit_idx)), "validation_samples": int(n_val),
                     "test_samples": int(len(test_frame))},
        "held_out_rmse": report,
    }
    return model


def _fit_simulation_error(network: PlantNetwork, config: NNConfig, segments, norm, states_scale: np.ndarray,
                          settings: TrainingSettings, bar=None) -> dict:
    """Stage 2 of :func:`train`: minimise the standardised simulation error over the horizon."""
    horizon = settings.multi_step_horizon
    parts = [simulation_windows(s, config, horizon, settings.multi_step_stride) for s in segments
             if len(s) > horizon + config.delays]
    windows = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    count = len(windows["duties"])
    order = np.random.default_rng(settings.seed + 1).permutation(count)
    n_val = max(1, int(round(count * settings.validation_fraction)))
    val_idx, fit_idx = np.sort(order[:n_val]), np.sort(order[n_val:])
    fit = {k: torch.from_numpy(np.ascontiguousarray(v[fit_idx])) for k, v in windows.items()}
    val = {k: torch.from_numpy(np.ascontiguousarray(v[val_idx])) for k, v in windows.items()}
    norm = tuple(np.asarray(a, dtype=np.float64) for a in norm)
    norm_t = tuple(torch.from_numpy(a) for a in norm)
    scale = torch.from_numpy(states_scale)

    def loss(part):
        error = (_torch_rollout(network, config, norm_t, part) - part["targets"]) / scale
        return (error * error).mean()

    evaluate = _autograd(network, lambda: loss(fit))
    with torch.no_grad():
        before = float(loss(val))
    best, best_it, its, history = _lbfgs(network, evaluate, lambda: loss(val), settings.multi_step_iterations,
                                         settings, bar, training_of=lambda: loss(fit))
    return {"horizon": horizon, "windows": int(count), "iterations": its, "best_iteration": best_it,
            "validation_loss_before": before, "validation_loss": best, "history": history}


# ---------------------------------------------------------------------------------------------
# Files


def _checksum(state_dict: dict, extra: list[np.ndarray]) -> str:
    digest = hashlib.sha256()
    for name in sorted(state_dict):
        digest.update(name.encode())
        digest.update(state_dict[name].detach().numpy().tobytes())
    for array in extra:
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()


def _non_finite(state: dict, norm: dict) -> str | None:
    """The name of the first weight or normalisation array holding NaN or an infinity, else None."""
    for name in sorted(state):
        if not bool(torch.isfinite(state[name]).all()):
            return name
    for name, array in norm.items():
        if not np.isfinite(array).all():
            return f"normalisation {name}"
    return None


NORMALISATION = ("input_mean", "input_std", "output_mean", "output_std")


def save_model(model: NNPlantModel, path: Path) -> Path:
    """Write the model atomically; only tensors, numbers, strings, lists and dicts go in. A model
    with non-finite weights or normalisation is refused (ValueError): it would command nonsense."""
    from cosim.base.files import atomic_write

    state = {k: v.detach().clone() for k, v in model.network.state_dict().items()}
    norm = [model.input_mean, model.input_std, model.output_mean, model.output_std]
    bad = _non_finite(state, dict(zip(NORMALISATION, norm)))
    if bad is not None:
        raise ValueError(f"the trained network has non-finite values in {bad} (NaN or infinite samples in the "
                         "data?): refusing to save it")
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "config": {"hidden": list(model.config.hidden), "activation": model.config.activation,
                   "delays": model.config.delays, "extra_signals": list(model.config.extra_signals),
                   "residual": model.config.residual},
        "state_dict": state,
        "normalisation": {name: torch.from_numpy(np.asarray(a, dtype=np.float64).copy()) for name, a in
                          zip(("input_mean", "input_std", "output_mean", "output_std"), norm)},
        "metadata": model.metadata,
        "checksum": _checksum(state, norm),
    }
    buffer = io.BytesIO()  # not the temporary file: torch names the archive's folder after the file
    torch.save(payload, buffer)
    return atomic_write(Path(path), lambda tmp: tmp.write_bytes(buffer.getvalue()))


def load_model(path: Path, expect_period: float | None = None,
               expect_config: NNConfig | None = None) -> NNPlantModel:
    """Read a model with ``weights_only=True``; refuse anything that is not exactly what we wrote."""
    path = Path(path)
    if path.is_dir():
        raise ModelFileError(f"model file {path} is a folder: expected a .pt file written by buck-cosim train")
    if not path.is_file():
        raise ModelFileError(f"model file {path} does not exist")
    if not zipfile.is_zipfile(path):  # torch.save writes a zip archive; anything else is not ours
        raise ModelFileError(f"model file {path} is not a model written by buck-cosim train (not a torch zip "
                             "archive: truncated, or another kind of file)")
    try:
        payload = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as error:  # a damaged archive, pickled code refused by weights_only, ...
        text = str(error).strip()
        reason = text.splitlines()[0] if text else type(error).__name__
        if "Unsupported global" in text or "Unsupported operand" in text:
            reason = "it contains objects other than plain weights (refused without running them)"
        raise ModelFileError(f"model file {path} cannot be read: {reason[:200]}") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ModelFileError(f"model file {path} is not a {FORMAT} (missing or wrong 'format')")
    if payload.get("version") != VERSION:
        raise ModelFileError(f"model file {path} has format version {payload.get('version')!r}; expected {VERSION}")
    try:
        raw = payload["config"]
        config = NNConfig(hidden=tuple(raw["hidden"]), activation=raw["activation"], delays=int(raw["delays"]),
                          extra_signals=tuple(raw["extra_signals"]), residual=bool(raw["residual"]))
        norm = {k: payload["normalisation"][k].numpy().astype(np.float64) for k in
                ("input_mean", "input_std", "output_mean", "output_std")}
        network = PlantNetwork(config)
        network.load_state_dict(payload["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as error:
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ModelFileError(f"model file {path} does not match its declared network: {first[:200]}") from None
    expected_shapes = {"input_mean": config.n_inputs, "input_std": config.n_inputs, "output_mean": 2, "output_std": 2}
    for name, size in expected_shapes.items():
        if norm[name].shape != (size,):
            raise ModelFileError(f"model file {path}: normalisation {name} has shape {norm[name].shape}, expected ({size},)")
    checksum = _checksum(network.state_dict(), [norm[k] for k in NORMALISATION])
    if checksum != payload.get("checksum"):
        raise ModelFileError(f"model file {path} fails its SHA-256 check: the weights were changed after saving")
    bad = _non_finite(network.state_dict(), norm)
    if bad is not None:
        raise ModelFileError(f"model file {path} has non-finite values in {bad}: refused (the controller would "
                             "command nonsense)")
    metadata = payload.get("metadata", {})
    if expect_config is not None and expect_config != config:
        raise ModelFileError(f"model file {path} was trained for inputs {config.label}; expected {expect_config.label}")
    period = metadata.get("control_period_s")
    if expect_period is not None and period is None:
        raise ModelFileError(f"model file {path} names no control period (trained on data without the workbench's "
                             "metadata): train it again with --control-period")
    if expect_period is not None and not math.isclose(period, expect_period, rel_tol=1e-9):
        raise ModelFileError(
            f"model file {path} was trained at a control period of {period * 1e6:.4g} us; "
            f"the controller samples every {expect_period * 1e6:.4g} us"
        )
    return NNPlantModel(config, network, norm["input_mean"], norm["input_std"], norm["output_mean"],
                        norm["output_std"], metadata)
