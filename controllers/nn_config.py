"""The NN plant model's configuration: what the network sees (:class:`NNConfig`) and how it is identified
(:class:`TrainingSettings`), with the signals and activations they name.

Torch-free on purpose: :mod:`controllers.nn_model` trains, evaluates and stores the network with torch, which
takes seconds to import; a command checks its arguments against these definitions first, so a mistake is
answered before torch loads (a refused ``train`` in about a second).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STATE_SIGNALS = ("measured_inductor_current", "measured_output_voltage")
#: the hidden layers' activations by name, each with the numpy function the network is evaluated with (the C twins
#: number them in this order: nn_model.h's BUCKC_ACTIVATION_*)
ACTIVATIONS = {"tanh": np.tanh,
               "relu": lambda z: np.maximum(z, 0.0),
               "sigmoid": lambda z: 0.5 * (1.0 + np.tanh(0.5 * z))}
#: extra measured inputs: the load conductance io / vo (= 1/R, constant while the load is) tells the
#: network the load; the load current and the input voltage are offered too
EXTRA_SIGNALS = ("load_conductance", "load_current", "input_voltage")
#: the data column of each extra signal: what the controller's sensors read, as it will at run time
EXTRA_COLUMNS = {"load_conductance": "load_conductance", "load_current": "measured_load_current",
                 "input_voltage": "input_voltage"}


def extra_columns(config: "NNConfig") -> list[str]:
    """Data-frame columns that feed ``config.extra_signals``."""
    return [EXTRA_COLUMNS[s] for s in config.extra_signals]


@dataclass(frozen=True)
class NNConfig:
    """Architecture and inputs. The default is the paper's 3-7-2 network."""

    hidden: tuple[int, ...] = (7,)
    activation: str = "tanh"
    delays: int = 1  # samples of [iL, vc, d] fed in: k-1 (paper), k-2, ...
    extra_signals: tuple[str, ...] = ()  # measured at k-1, e.g. ("load_current",)
    residual: bool = False  # learn x(k) - x(k-1) (a skip connection); the paper learns x(k) itself

    def __post_init__(self):
        if not self.hidden or any(int(n) < 1 for n in self.hidden):
            raise ValueError(f"hidden layers {self.hidden} are invalid: expected one or more sizes >= 1")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation {self.activation!r} is unknown: expected one of {', '.join(ACTIVATIONS)}")
        if self.delays < 1:
            raise ValueError(f"delays = {self.delays} is invalid: expected >= 1")
        for name in self.extra_signals:
            if name not in EXTRA_SIGNALS:
                raise ValueError(f"extra signal {name!r} is unknown: expected one of {', '.join(EXTRA_SIGNALS)}")
        object.__setattr__(self, "hidden", tuple(int(n) for n in self.hidden))
        object.__setattr__(self, "extra_signals", tuple(self.extra_signals))

    @property
    def input_names(self) -> list[str]:
        names = []
        for lag in range(1, self.delays + 1):
            names += [f"{s}[k-{lag}]" for s in (*STATE_SIGNALS, "duty_cycle")]
        names += [f"{s}[k-1]" for s in self.extra_signals]
        return names

    @property
    def n_inputs(self) -> int:
        return 3 * self.delays + len(self.extra_signals)

    @property
    def label(self) -> str:
        arch = "-".join(str(n) for n in (self.n_inputs, *self.hidden, 2))
        extra = f", +{'+'.join(self.extra_signals)}" if self.extra_signals else ""
        skip = ", residual" if self.residual else ""
        return f"{arch} {self.activation}, {self.delays} delay(s){extra}{skip}"


@dataclass(frozen=True)
class TrainingSettings:
    """How :func:`train` identifies the network.

    Stage 1 minimises the one-step error (the paper's training). With ``multi_step_horizon`` > 1
    a second stage starts from that solution and minimises the *simulation* error: the network
    rolls out ``multi_step_horizon`` steps from each measured history with the recorded duties
    (and extra signals), its own predictions fed back, and the standardised error is averaged over
    every step -- what the predictive controller does with it over its horizon. Both stages are
    full-batch L-BFGS, seeded and single-threaded, with early stopping on a random validation
    share of the samples (stage 1) or of the windows (stage 2): the same data give the same weights.
    """

    seed: int = 0
    validation_fraction: float = 0.15  # random share of the training span used for early stopping
    test_fraction: float = 0.2  # the last share of the record, held out (time order kept)
    max_iterations: int = 3000  # L-BFGS iterations of the one-step stage
    check_every: int = 25
    patience: int = 8  # checks without validation improvement before stopping
    horizon: int = 10  # steps of the multi-step (open-loop) RMSE report
    multi_step_horizon: int = 1  # steps of the simulation-error stage (1: one-step training only)
    multi_step_iterations: int = 400  # L-BFGS iterations of the simulation-error stage, at most
    multi_step_stride: int = 1  # one window every this many samples (fewer windows: cheaper, coarser)

    def __post_init__(self):
        if self.multi_step_horizon < 1:
            raise ValueError(f"multi_step_horizon = {self.multi_step_horizon} is invalid: expected >= 1 (steps)")
        if self.multi_step_iterations < 0 or self.multi_step_stride < 1:
            raise ValueError("multi_step_iterations must be >= 0 and multi_step_stride >= 1")
