"""Plant predictors for the predictive controller: one interface, several models.

A predictor rolls the measured state [iL, vo] forward over a horizon for a batch of candidate
duty sequences in one array pass. The optimizer (:mod:`controllers.predictive`) does not know
which model it drives, so NNPC and the MPC baselines share one code path:

* :class:`NNPredictor` -- the identified network (the NNPC);
* :class:`AveragedModelPredictor` -- eq. 3 (plus parasitics) discretised exactly with the matrix
  exponential at the control period (zero-order hold). With the plant's true parameters this is
  the *oracle* MPC; with nominal parameters on a different plant, the *mismatched* MPC.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Protocol

import numpy as np
from controllers.nn_model import NNPlantModel


def expm2(a: np.ndarray, t: float) -> np.ndarray:
    """exp(A t) of a 2x2 matrix in closed form (tens of microseconds faster than scipy's Pade).

    With s = tr(A)/2 and M = A - s I, M^2 = delta I, so exp(At) = e^(st) (c I + g M) with
    c, g = cos, sin/w (delta < 0), cosh, sinh/w (delta > 0), or series near delta t^2 = 0.
    """
    s = 0.5 * (a[0, 0] + a[1, 1])
    m = a - s * np.eye(2)
    delta = m[0, 0] * m[0, 0] + m[0, 1] * m[1, 0]
    z = delta * t * t
    if abs(z) < 1e-3:
        c = 1 + z / 2 * (1 + z / 12 * (1 + z / 30))
        g = t * (1 + z / 6 * (1 + z / 20 * (1 + z / 42)))
    elif delta < 0:
        w = math.sqrt(-delta)
        c, g = math.cos(w * t), math.sin(w * t) / w
    else:  # over-damped: combine the exponentials first so nothing overflows
        w = math.sqrt(delta)
        e1, e2 = math.exp((s + w) * t), math.exp((s - w) * t)
        return 0.5 * (e1 + e2) * np.eye(2) + 0.5 * (e1 - e2) / w * m
    return math.exp(s * t) * (c * np.eye(2) + g * m)


@dataclass(slots=True)
class PredictionContext:
    """What a predictor may use at sample k (SI units)."""

    history: np.ndarray  # (delays, 3): rows [iL, vo, d], most recent first; row 0's duty is the candidate's
    input_voltage: float
    load_resistance: float  # measured or estimated
    load_current: float
    previous_duty: float


class Predictor(Protocol):
    name: str
    delays: int  # samples of history needed

    def rollout(self, context: PredictionContext, duties: np.ndarray, disturbance: np.ndarray) -> np.ndarray:
        """States [iL, vo] at k+1..k+N for each candidate: duties (M, N) -> (M, N, 2).

        ``disturbance`` (2,) is added to each predicted state before it is fed back, so a constant
        model error neither accumulates nor leaves a steady-state offset.
        """

    def describe(self) -> dict:
        """JSON-ready description for run metadata."""


class NNPredictor:
    """The NNPC's plant model: the trained network, evaluated in plain numpy."""

    def __init__(self, model: NNPlantModel, name: str = "NN"):
        self.model = model
        self.name = name
        self.delays = model.config.delays
        self._extras = model.config.extra_signals

    def rollout(self, context: PredictionContext, duties: np.ndarray, disturbance: np.ndarray) -> np.ndarray:
        extras = None
        if self._extras:
            signals = {"load_current": context.load_current, "input_voltage": context.input_voltage,
                       "load_conductance": 1.0 / context.load_resistance}
            extras = np.array([signals[s] for s in self._extras], dtype=float)
        return self.model.rollout_shared(context.history, duties, extras, disturbance)

    def describe(self) -> dict:
        meta = self.model.metadata
        return {"type": "neural network", "architecture": self.model.config.label,
                "trained_on": meta.get("plant"), "data_file": meta.get("data_file"),
                "held_out_rmse": meta.get("held_out_rmse")}


@dataclass(frozen=True)
class CircuitParameters:
    """Parameters an averaged-model predictor believes the plant has (SI units)."""

    inductance: float = 220e-6
    capacitance: float = 10e-6
    inductor_resistance: float = 0.0
    switch_on_resistance: float = 0.0
    diode_forward_voltage: float = 0.0
    capacitor_esr: float = 0.0

    def scaled(self, inductance: float = 1.0, capacitance: float = 1.0) -> "CircuitParameters":
        from dataclasses import replace

        return replace(self, inductance=self.inductance * inductance, capacitance=self.capacitance * capacitance)


NOMINAL = CircuitParameters()


class AveragedModelPredictor:
    """Eq. 3 with parasitics, exactly discretised (ZOH) at the control period.

    In CCM: L diL/dt = d (Vs + V_F) - V_F - (d R_on + R_L + k R_esr) iL - k vC, C dvC/dt = k iL - vC/(R + R_esr),
    vo = k (vC + R_esr iL), k = R / (R + R_esr). The d R_on term is frozen at the previous duty so the
    model stays linear; a predicted negative current is clipped to zero (the diode) before the
    disturbance estimate is added. Matrices are
    cached per load estimate.
    """

    def __init__(self, parameters: CircuitParameters, sample_period: float, name: str = "averaged model"):
        self.parameters = parameters
        self.sample_period = sample_period
        self.name = name
        self.delays = 1
        self._cache: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}

    def _discrete(self, load: float, switch_resistance: float) -> tuple[np.ndarray, np.ndarray]:
        key = (round(load, 9), round(switch_resistance, 12))
        cached = self._cache.get(key)
        if cached is not None:
            return cached
        p = self.parameters
        k = load / (load + p.capacitor_esr)
        a = np.array([[-(switch_resistance + p.inductor_resistance + k * p.capacitor_esr) / p.inductance,
                       -k / p.inductance],
                      [k / p.capacitance, -1.0 / ((load + p.capacitor_esr) * p.capacitance)]])
        phi = expm2(a, self.sample_period)
        gamma = np.linalg.solve(a, (phi - np.eye(2)) @ np.array([1.0 / p.inductance, 0.0]))
        result = (phi, gamma)  # x+ = Phi x + gamma * (switch-node voltage)
        if len(self._cache) > 256:
            self._cache.clear()
        self._cache[key] = result
        return result

    def rollout(self, context: PredictionContext, duties: np.ndarray, disturbance: np.ndarray) -> np.ndarray:
        p = self.parameters
        load = context.load_resistance
        k = load / (load + p.capacitor_esr)
        phi, gamma = self._discrete(load, context.previous_duty * p.switch_on_resistance)
        m, n = duties.shape
        # work in measured coordinates y = (iL, vo) = T x, x = (iL, vC): y+ = T Phi T^-1 y + T gamma u
        to_y = np.array([[1.0, 0.0], [k * p.capacitor_esr, k]])
        to_x = np.linalg.inv(to_y)
        phi_y_t = (to_y @ phi @ to_x).T
        gamma_y = to_y @ gamma
        y = np.empty((m, 2))
        y[:] = context.history[0, :2]
        out = np.empty((m, n, 2))
        drive = context.input_voltage + p.diode_forward_voltage
        for j in range(n):
            node = duties[:, j] * drive - p.diode_forward_voltage
            y = y @ phi_y_t + node[:, None] * gamma_y[None, :]
            np.maximum(y[:, 0], 0.0, out=y[:, 0])  # the diode, on the model's own prediction
            y += disturbance  # so prediction - disturbance is the model alone, as for the NN
            out[:, j] = y
        return out

    def describe(self) -> dict:
        return {"type": "averaged model (matrix exponential)", "parameters": asdict(self.parameters),
                "sample_period_s": self.sample_period}


def ripple_free_horizon(control_period: float, lc_period: float = 2 * math.pi * math.sqrt(220e-6 * 10e-6)) -> int:
    """Prediction steps that span about one LC ringing period (at least 3, at most 24)."""
    return int(min(24, max(3, math.ceil(lc_period / control_period))))
