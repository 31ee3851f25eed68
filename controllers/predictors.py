"""Plant predictors for the predictive controller: one interface, several models.

A predictor rolls the measured state [iL, vo] forward over a horizon for a batch of candidate
duty sequences in one array pass. The optimizer (:mod:`controllers.predictive`) does not know
which model it drives, so NNPC and the MPC baselines share one code path:

* :class:`NNPredictor` -- the identified network (the NNPC);
* :class:`AveragedModelPredictor` -- eq. 3 (plus parasitics) discretised exactly with the matrix
  exponential at the control period (zero-order hold): exact for the averaged plant;
* :class:`SwitchedModelPredictor` -- the switched converter solved exactly per PWM period and
  seen through the controller's sensor (period mean or synchronous sample): exact for the
  switched plant in CCM.

With the plant's true parameters the circuit models are the *oracle* MPC; with other parameters
(e.g. nominal ones on the mismatch plant) the *mismatched* MPC.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:  # the NN predictor takes a trained model; importing torch is not needed for the others
    from controllers.nn_model import NNPlantModel


def expm2_many(a: np.ndarray, times: np.ndarray) -> np.ndarray:
    """exp(A t) of a 2x2 matrix for each t in ``times`` (shape (D,) -> (D, 2, 2)), in closed form.

    With s = tr(A)/2 and M = A - s I, M^2 = delta I, so exp(At) = e^(st) (c I + g M) with
    c, g = cos, sin/w (delta < 0), cosh, sinh/w (delta > 0), or series near delta t^2 = 0
    (vectorised over t; :func:`expm2` is the same for one t).
    """
    t = np.asarray(times, dtype=float)
    s = 0.5 * (a[0, 0] + a[1, 1])
    m = a - s * np.eye(2)
    delta = m[0, 0] * m[0, 0] + m[0, 1] * m[1, 0]
    z = delta * t * t
    small = np.abs(z) < 1e-3
    c = 1 + z / 2 * (1 + z / 12 * (1 + z / 30))
    g = t * (1 + z / 6 * (1 + z / 20 * (1 + z / 42)))
    w = math.sqrt(abs(delta))
    if delta < 0:
        c = np.where(small, c, np.cos(w * t))
        g = np.where(small, g, np.sin(w * t) / (w or 1.0))
        scale = np.exp(s * t)
    elif delta > 0:  # over-damped: e^(st) cosh(wt) etc. from the separate exponentials, so nothing overflows
        e1, e2 = np.exp((s + w) * t), np.exp((s - w) * t)
        scale = np.where(small, np.exp(s * t), 1.0)
        c = np.where(small, c, 0.5 * (e1 + e2))
        g = np.where(small, g, 0.5 * (e1 - e2) / w)
    else:
        scale = np.exp(s * t)
    return scale[:, None, None] * (c[:, None, None] * np.eye(2) + g[:, None, None] * m)


def expm2(a: np.ndarray, t: float) -> np.ndarray:
    """exp(A t) of one 2x2 matrix: :func:`expm2_many`'s formula in scalar arithmetic (a few
    microseconds; numpy's per-call overhead on length-1 arrays would cost several times more)."""
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
    load_resistance: float  # [Ohm] estimated: 1 / load_conductance
    load_conductance: float  # [S] the estimate of controllers.load_estimate
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

    def clear_cache(self) -> None:
        """Forget what was computed for earlier samples (the controller's reset: a cache entry is made
        from the first load estimate that rounds to its key, so a kept one would let a duty depend on
        what the controller computed before)."""

    def linearize(self, context: PredictionContext, duties: np.ndarray, disturbance: np.ndarray,
                  block_of_step: np.ndarray, n_blocks: int) -> tuple[np.ndarray, np.ndarray]:
        """One sequence ``duties`` (N,) rolled out as :meth:`rollout` does, with the Jacobian of the
        states with respect to the blocked moves: (N, 2) and (N, 2, n_blocks), step j's duty being
        block ``block_of_step[j]``'s value (the real-time-iteration optimizer's linearisation)."""


class NNPredictor:
    """The NNPC's plant model: the trained network, evaluated in plain numpy."""

    def __init__(self, model: NNPlantModel, name: str = "NN"):
        self.model = model
        self.name = name
        self.delays = model.config.delays
        self._extras = model.config.extra_signals

    def rollout(self, context: PredictionContext, duties: np.ndarray, disturbance: np.ndarray) -> np.ndarray:
        return self.model.rollout_shared(context.history, duties, self._extra_values(context), disturbance)

    def _extra_values(self, context: PredictionContext) -> np.ndarray | None:
        if not self._extras:
            return None
        signals = {"load_current": context.load_current, "input_voltage": context.input_voltage,
                   "load_conductance": context.load_conductance}
        return np.array([signals[s] for s in self._extras], dtype=float)

    def linearize(self, context: PredictionContext, duties: np.ndarray, disturbance: np.ndarray,
                  block_of_step: np.ndarray, n_blocks: int) -> tuple[np.ndarray, np.ndarray]:
        """Analytic forward sensitivities of the network (:meth:`NNPlantModel.rollout_sensitivities`)."""
        return self.model.rollout_sensitivities(context.history, duties, self._extra_values(context), disturbance,
                                                block_of_step, n_blocks)

    def clear_cache(self) -> None:
        pass  # nothing is kept between samples

    def describe(self) -> dict:
        meta = self.model.metadata
        return {"type": "neural network", "architecture": self.model.config.label,
                "trained_on": meta.get("plant"), "data_domain": data_domain(meta), "data_file": meta.get("data_file"),
                "held_out_rmse": meta.get("held_out_rmse"), "design_key": (meta.get("design") or {}).get("key")}


@dataclass(frozen=True)
class CircuitParameters:
    """Parameters a circuit-model predictor believes the plant has (SI units; parasitics 0 = ideal).

    No default L and C: the study's nominal circuit (``cosim.study.vocabulary.NOMINAL``) is built
    from Table II (:mod:`plant_fmu.table_ii`), the one place those values live.
    """

    inductance: float
    capacitance: float
    inductor_resistance: float = 0.0
    switch_on_resistance: float = 0.0
    diode_forward_voltage: float = 0.0
    capacitor_esr: float = 0.0



#: the operating signals of a network's data domain, with their units
DOMAIN_UNITS = {"input_voltage": "V", "load_conductance": "S", "reference": "V"}


def data_domain(metadata: dict) -> dict[str, list[float]] | None:
    """The operating ranges a network's identification data were drawn over, from its metadata's ``collection``
    settings (cosim.design.data_collection): the supply [V] (its fixed value or its range), the load conductance 1/R
    [S] (of the load range) and the reference [V] (its range; the rests at 0 V are no operating point). None for a
    network without that record (e.g. trained from a data file of unknown origin)."""
    collection = metadata.get("collection") if isinstance(metadata, dict) else None
    if not isinstance(collection, dict):
        return None
    try:
        supply = collection.get("input_voltage_range") or [collection["input_voltage"]] * 2
        low_load, high_load = collection["load_range"]
        return {"input_voltage": [float(supply[0]), float(supply[1])],
                "load_conductance": [1.0 / float(high_load), 1.0 / float(low_load)],
                "reference": [float(v) for v in collection["reference_range"]]}
    except (KeyError, TypeError, ValueError, ZeroDivisionError):
        return None


def domain_text(domain: dict[str, list[float]]) -> str:
    """A data domain in words: ``supply 36-60 V, loads 4-100 Ohm (0.01-0.25 S), references 0-20 V``."""
    vs, g, r = domain["input_voltage"], domain["load_conductance"], domain["reference"]
    supply = f"{vs[0]:g} V" if vs[0] == vs[1] else f"{vs[0]:g}-{vs[1]:g} V"
    return (f"supply {supply}, loads {1 / g[1]:.4g}-{1 / g[0]:.4g} Ohm ({g[0]:.3g}-{g[1]:.3g} S), "
            f"references {r[0]:g}-{r[1]:g} V")


def circuit_matrix(p: CircuitParameters, load: float, switch_resistance: float) -> np.ndarray:
    """A of d/dt [iL, vC] = A [iL, vC] + [1/L, 0] * (switch-node voltage), for a resistance
    ``switch_resistance`` in series with the inductor (R_on while the switch conducts, d R_on averaged)."""
    k = load / (load + p.capacitor_esr)
    return np.array([[-(switch_resistance + p.inductor_resistance + k * p.capacitor_esr) / p.inductance,
                      -k / p.inductance],
                     [k / p.capacitance, -1.0 / ((load + p.capacitor_esr) * p.capacitance)]])


def measured_from_state(p: CircuitParameters, load: float) -> np.ndarray:
    """T with [iL, vo] = T [iL, vC]: vo = k (vC + R_esr iL), k = R / (R + R_esr)."""
    k = load / (load + p.capacitor_esr)
    return np.array([[1.0, 0.0], [k * p.capacitor_esr, k]])


class AveragedModelPredictor:
    """Eq. 3 with parasitics, exactly discretised (ZOH) at the control period.

    In CCM: L diL/dt = d (Vs + V_F) - V_F - (d R_on + R_L + k R_esr) iL - k vC, C dvC/dt = k iL - vC/(R + R_esr),
    vo = k (vC + R_esr iL), k = R / (R + R_esr). The d R_on term is frozen at the previous duty so the
    model stays linear; a predicted negative current is clipped to zero (the diode) before the
    disturbance estimate is added. Matrices are
    cached per load estimate (until :meth:`clear_cache`, the controller's reset).
    """

    def __init__(self, parameters: CircuitParameters, sample_period: float, name: str = "averaged model"):
        self.parameters = parameters
        self.sample_period = sample_period
        self.name = name
        self.delays = 1
        self._cache: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}

    def clear_cache(self) -> None:
        self._cache.clear()

    def _discrete(self, load: float, switch_resistance: float) -> tuple[np.ndarray, np.ndarray]:
        key = (round(load, 9), round(switch_resistance, 12))
        cached = self._cache.get(key)
        if cached is not None:
            return cached
        p = self.parameters
        a = circuit_matrix(p, load, switch_resistance)
        phi = expm2(a, self.sample_period)
        gamma = np.linalg.solve(a, (phi - np.eye(2)) @ np.array([1.0 / p.inductance, 0.0]))
        result = (phi, gamma)  # x+ = Phi x + gamma * (switch-node voltage)
        if len(self._cache) > 256:
            self._cache.clear()
        self._cache[key] = result
        return result

    def _measured_step(self, context: PredictionContext) -> tuple[np.ndarray, np.ndarray, float]:
        """(T Phi T^-1, T gamma, Vs + V_F) in measured coordinates y = (iL, vo) = T x, x = (iL, vC):
        y+ = T Phi T^-1 y + T gamma (d (Vs + V_F) - V_F)."""
        p = self.parameters
        load = context.load_resistance
        phi, gamma = self._discrete(load, context.previous_duty * p.switch_on_resistance)
        to_y = measured_from_state(p, load)
        to_x = np.linalg.inv(to_y)
        return to_y @ phi @ to_x, to_y @ gamma, context.input_voltage + p.diode_forward_voltage

    def rollout(self, context: PredictionContext, duties: np.ndarray, disturbance: np.ndarray) -> np.ndarray:
        p = self.parameters
        phi_y, gamma_y, drive = self._measured_step(context)
        phi_y_t = phi_y.T
        m, n = duties.shape
        y = np.empty((m, 2))
        y[:] = context.history[0, :2]
        out = np.empty((m, n, 2))
        for j in range(n):
            node = duties[:, j] * drive - p.diode_forward_voltage
            y = y @ phi_y_t + node[:, None] * gamma_y[None, :]
            np.maximum(y[:, 0], 0.0, out=y[:, 0])  # the diode, on the model's own prediction
            y += disturbance  # so prediction - disturbance is the model alone, as for the NN
            out[:, j] = y
        return out

    def linearize(self, context: PredictionContext, duties: np.ndarray, disturbance: np.ndarray,
                  block_of_step: np.ndarray, n_blocks: int) -> tuple[np.ndarray, np.ndarray]:
        """Analytic and exact: the model is linear, y+ = Phi_y y + gamma_y (d drive - V_F), so a block's
        move enters each step it holds through gamma_y drive and propagates through Phi_y; where the
        diode clips the predicted current, its sensitivity is zero (the clip's slope there)."""
        p = self.parameters
        phi_y, gamma_y, drive = self._measured_step(context)
        n = len(duties)
        i_l, v_o = float(context.history[0, 0]), float(context.history[0, 1])
        out = np.empty((n, 2))
        jacobian = np.zeros((n, 2, n_blocks))
        sensitivity = np.zeros((2, n_blocks))
        forward = p.diode_forward_voltage
        for j in range(n):
            node = duties[j] * drive - forward
            i_next = (i_l * phi_y[0, 0] + v_o * phi_y[0, 1]) + node * gamma_y[0]
            v_next = (i_l * phi_y[1, 0] + v_o * phi_y[1, 1]) + node * gamma_y[1]
            sensitivity = phi_y @ sensitivity
            sensitivity[:, block_of_step[j]] += gamma_y * drive
            if i_next < 0.0:
                i_next = 0.0
                sensitivity[0] = 0.0
            i_l, v_o = i_next + disturbance[0], v_next + disturbance[1]
            out[j] = (i_l, v_o)
            jacobian[j] = sensitivity
        return out, jacobian

    def describe(self) -> dict:
        return {"type": "averaged model (matrix exponential)", "parameters": asdict(self.parameters),
                "sample_period_s": self.sample_period}


CARRIERS = ("sawtooth", "triangle")
SENSOR_MODELS = ("period_average", "period_start")
#: the largest condition number of the switched model's sensor map H it accepts: H^-1 rebuilds the state
#: from a reading, so it multiplies rounding (1e-16) by up to this much. Over the operating envelope
#: (4-100 Ohm, 36-60 V, 1 .. 75 PWM periods per control period) H stays below 1e2; at 1 ms and about
#: 2 Ohm the natural response has decayed by e^-12 over the period, H tends to singular and K = F H^-1
#: would be rounding noise (tests/test_predictive.py)
MAX_SENSOR_CONDITION = 1e8


def ill_conditioned(name: str, load: float, input_voltage: float, periods: int, condition: float) -> str:
    """The line a switched model refuses a load with (the C twin raises the same)."""
    return (f"{name}: at a load of {load:.6g} Ohm and {input_voltage:.6g} V the reading after {periods} PWM "
            f"period(s) no longer tells the state the control period started from (sensor map condition number "
            f"{condition:.3g} > {MAX_SENSOR_CONDITION:g}): this switched model cannot predict there; use a "
            "shorter control period or the averaged model")


def _compose(first: tuple[np.ndarray, np.ndarray], then: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The affine map x -> B (A x + a) + b of ``first`` = (A, a) followed by ``then`` = (B, b), batched."""
    (a_mat, a_vec), (b_mat, b_vec) = first, then
    return b_mat @ a_mat, np.einsum("dij,dj->di", b_mat, a_vec) + b_vec


def _affine_power(step: tuple[np.ndarray, np.ndarray], times: int) -> tuple[np.ndarray, np.ndarray]:
    """``step`` applied ``times`` times (binary powering; all powers of one map commute)."""
    mat, vec = step
    result = (np.broadcast_to(np.eye(2), mat.shape).copy(), np.zeros_like(vec))
    base = (mat, vec)
    while times:
        if times & 1:
            result = _compose(result, base)
        times >>= 1
        if times:
            base = _compose(base, base)
    return result


#: [grid steps] a duty this close to an interior node of the switched model's duty table takes the mean of its two
#: intervals' slopes as the derivative (SwitchedModelPredictor.linearize); 1e-6 of the 1/256 step is 4e-9 in duty,
#: far above the plans' rounding noise (1e-14) and far below any move that matters
NODE_TOLERANCE = 1e-6


class SwitchedModelPredictor:
    """The switched converter solved exactly per PWM period (CCM), as the controller's sensor sees it.

    Between switch transitions the circuit is linear, so one PWM period maps the state
    x = [iL, vC] at its start affinely to its end and to its mean over the period:
    x_end = P(d) x + q(d), mean = Pa(d) x + qa(d), from closed-form 2x2 exponentials and their
    integrals per interval (switch on with R_on from the input voltage, off through the diode's
    forward drop; sawtooth carrier: on for [0, d T_sw); triangle: on-time centred in the period).
    A control period of n whole PWM periods at one duty composes n of them, x(k+1) = F(d) x(k) + f(d),
    and the sensor reads y = [iL, vo] as H(d) x(k) + h(d): the mean over the last PWM period
    ("period_average", the built-in FMU's averaging ADC) or the value at the period start
    ("period_start", a sample synchronous with the carrier, ripple included).

    Like :class:`AveragedModelPredictor` it rolls the *measured* signals forward: the state at
    sample k is rebuilt from the measurement and the duty applied over the last period,
    x(k) = K(d(k-1)) y(k) + kappa(d(k-1)) with K = F H^-1 and kappa = f - K h, so the sensor's lag
    and the carrier's timing are part of the model rather than a model error. The maps are
    tabulated on a duty grid (per load estimate and input voltage) and interpolated linearly; the
    diode's blocking (DCM) is approximated by clipping the predicted current at 0.
    """

    def __init__(self, parameters: CircuitParameters, sample_period: float, switching_frequency: float,
                 carrier: str = "sawtooth", sensor: str = "period_average", name: str = "switched model",
                 grid_points: int = 257):
        periods = sample_period * switching_frequency
        self.periods = round(periods)
        if self.periods < 1 or abs(periods - self.periods) > 1e-6 * periods:
            raise ValueError(f"control period {sample_period:.6g} s is not a whole number of switching periods "
                             f"(1/{switching_frequency:.6g} Hz): the switched model needs one")
        if carrier not in CARRIERS:
            raise ValueError(f"carrier {carrier!r} is unknown: expected one of {', '.join(CARRIERS)}")
        if sensor not in SENSOR_MODELS:
            raise ValueError(f"sensor {sensor!r} is unknown: expected one of {', '.join(SENSOR_MODELS)}")
        self.parameters = parameters
        self.sample_period = sample_period
        self.switching_frequency = switching_frequency
        self.carrier = carrier
        self.sensor = sensor
        self.name = name
        self.delays = 1
        self.duty_grid = np.linspace(0.0, 1.0, grid_points)
        self._cache: dict[tuple[float, float], np.ndarray] = {}

    def clear_cache(self) -> None:
        self._cache.clear()

    def _interval(self, a: np.ndarray, voltage: float, durations: np.ndarray):
        """An interval of constant topology: (state at its end, integral of the state over it) as
        affine maps of the state at its start, for each duration (D,)."""
        p = self.parameters
        eye = np.eye(2)
        a_inv = np.linalg.inv(a)
        drive = np.array([voltage / p.inductance, 0.0])
        end = expm2_many(a, durations)
        integral = a_inv @ (end - eye)  # int_0^tau e^(A s) ds
        end_offset = integral @ drive
        integral_offset = (a_inv @ (integral - durations[:, None, None] * eye)) @ drive
        return (end, end_offset), (integral, integral_offset)

    def _table(self, load: float, input_voltage: float) -> np.ndarray:
        """Per grid duty: K (4), kappa (2), H (4), h (2) -- see the class docstring -- then the
        differences to the next grid point (12)."""
        key = (round(load, 9), round(input_voltage, 9))
        cached = self._cache.get(key)
        if cached is not None:
            return cached
        p, d = self.parameters, self.duty_grid
        period = 1.0 / self.switching_frequency
        on = (circuit_matrix(p, load, p.switch_on_resistance), input_voltage)
        off = (circuit_matrix(p, load, 0.0), -p.diode_forward_voltage)
        if self.carrier == "sawtooth":
            intervals = [(on, d * period), (off, (1 - d) * period)]
        else:
            intervals = [(off, 0.5 * (1 - d) * period), (on, d * period), (off, 0.5 * (1 - d) * period)]
        size = len(d)
        state = (np.broadcast_to(np.eye(2), (size, 2, 2)).copy(), np.zeros((size, 2)))
        mean = (np.zeros((size, 2, 2)), np.zeros((size, 2)))
        for (a, voltage), durations in intervals:
            end, integral = self._interval(a, voltage, durations)
            swept = _compose(state, integral)
            mean = (mean[0] + swept[0], mean[1] + swept[1])
            state = _compose(state, end)
        mean = (mean[0] / period, mean[1] / period)
        before_last = _affine_power(state, self.periods - 1)
        full = _compose(before_last, state)  # x(k+1) = F x(k) + f
        if self.sensor == "period_average":
            seen = _compose(before_last, mean)
        else:
            seen = full
        to_y = measured_from_state(p, load)
        h_mat, h_vec = to_y @ seen[0], seen[1] @ to_y.T
        condition = float(np.max(np.linalg.cond(h_mat)))
        if not condition <= MAX_SENSOR_CONDITION:
            raise ValueError(ill_conditioned(self.name, load, input_voltage, self.periods, condition))
        k_mat = full[0] @ np.linalg.inv(h_mat)
        k_vec = full[1] - np.einsum("dij,dj->di", k_mat, h_vec)
        values = np.concatenate([k_mat.reshape(size, 4), k_vec, h_mat.reshape(size, 4), h_vec], axis=1)
        slopes = np.zeros_like(values)
        slopes[:-1] = np.diff(values, axis=0)
        table = np.concatenate([values, slopes], axis=1)  # one gather per lookup
        if len(self._cache) > 256:
            self._cache.clear()
        self._cache[key] = table
        return table

    def _lookup(self, table: np.ndarray, duties: np.ndarray) -> np.ndarray:
        """Linear interpolation of the tabulated maps at ``duties`` (any shape) -> duties.shape + (12,)."""
        last = len(table) - 1
        position = np.clip(duties, 0.0, 1.0) * last
        index = np.minimum(position.astype(np.intp), last - 1)
        rows = table[index]  # values and slopes to the next grid point
        return rows[..., :12] + (position - index)[..., None] * rows[..., 12:]

    def rollout(self, context: PredictionContext, duties: np.ndarray, disturbance: np.ndarray) -> np.ndarray:
        table = self._table(context.load_resistance, context.input_voltage)
        m, n = duties.shape
        # per step j: duty d(j-1) rebuilds the state from the reading, d(j) predicts the next reading;
        # both compose into one affine map per candidate and step, y(j+1) = S y(j) + c
        applied = np.empty((n + 1, m))
        applied[0] = context.previous_duty
        applied[1:] = duties.T
        rows = self._lookup(table, applied)  # (n + 1, m, 12)
        k, h = rows[:-1], rows[1:]  # K, kappa at d(j-1); H, h at d(j)
        s00 = h[..., 6] * k[..., 0] + h[..., 7] * k[..., 2]
        s01 = h[..., 6] * k[..., 1] + h[..., 7] * k[..., 3]
        s10 = h[..., 8] * k[..., 0] + h[..., 9] * k[..., 2]
        s11 = h[..., 8] * k[..., 1] + h[..., 9] * k[..., 3]
        c0 = h[..., 6] * k[..., 4] + h[..., 7] * k[..., 5] + h[..., 10]
        c1 = h[..., 8] * k[..., 4] + h[..., 9] * k[..., 5] + h[..., 11]
        current, voltage = np.empty((n, m)), np.empty((n, m))
        i_l, v_o = np.full(m, context.history[0, 0]), np.full(m, context.history[0, 1])
        scratch = np.empty(m)
        for j in range(n):
            i_next, v_next = current[j], voltage[j]
            np.multiply(s00[j], i_l, out=i_next)
            i_next += np.multiply(s01[j], v_o, out=scratch)
            i_next += c0[j]
            np.maximum(i_next, 0.0, out=i_next)  # the diode, on the model's own prediction
            np.multiply(s10[j], i_l, out=v_next)
            v_next += np.multiply(s11[j], v_o, out=scratch)
            v_next += c1[j]
            i_next += disturbance[0]
            v_next += disturbance[1]
            i_l, v_o = i_next, v_next
        return np.stack([current.T, voltage.T], axis=2)

    def linearize(self, context: PredictionContext, duties: np.ndarray, disturbance: np.ndarray,
                  block_of_step: np.ndarray, n_blocks: int) -> tuple[np.ndarray, np.ndarray]:
        """Analytic: step j's map y(j+1) = H(d(j)) (K(d(j-1)) y(j) + kappa(d(j-1))) + h(d(j)) depends on
        two duties, through the tabulated maps, whose linear interpolation has the slope
        (table difference) x (grid points - 1) in d -- exact for the interpolated model the rollout
        uses between the 1/256-wide grid nodes. A block's move thus enters at the step it is applied (through
        H, h) and at the next (through K, kappa); the clipped current's sensitivity is zero, as in the averaged
        model. At a node (within :data:`NODE_TOLERANCE` of a grid step) the derivative jumps, and the mean of
        its two intervals' slopes is taken: a plan settled on a node (the ideal model's steady duty 12/48 =
        64/256 is one) dithers about it at rounding level, and one interval's slope or the other's by the sign
        of a 1e-14 rounding error would give the one-step RTI a Jacobian that jumps from sample to sample -- and
        the C twin, whose sums round differently, the other side's (a 7.7e-5 duty difference that an open-loop
        replay never heals, tests/test_c_twins.py)."""
        table = self._table(context.load_resistance, context.input_voltage)
        n = len(duties)
        applied = np.empty(n + 1)
        applied[0] = context.previous_duty
        applied[1:] = duties
        values = self._lookup(table, applied)  # (n + 1, 12)
        last = len(table) - 1
        position = np.clip(applied, 0.0, 1.0) * last
        index = np.minimum(position.astype(np.intp), last - 1)
        slopes = table[index][:, 12:] * last  # d values / d duty on the interval the lookup used
        node = np.rint(position)
        at_node = (np.abs(position - node) <= NODE_TOLERANCE) & (node > 0) & (node < last)
        if at_node.any():  # the mean of the two intervals' slopes (C: buckc_switched_lookup_slope)
            nodes = node[at_node].astype(np.intp)
            slopes[at_node] = (table[nodes - 1, 12:] + table[nodes, 12:]) * 0.5 * last
        out = np.empty((n, 2))
        jacobian = np.zeros((n, 2, n_blocks))
        sensitivity = np.zeros((2, n_blocks))
        i_l, v_o = float(context.history[0, 0]), float(context.history[0, 1])
        for j in range(n):
            k, h = values[j], values[j + 1]  # K, kappa at d(j-1); H, h at d(j)
            dk, dh = slopes[j], slopes[j + 1]
            s = np.array([[h[6] * k[0] + h[7] * k[2], h[6] * k[1] + h[7] * k[3]],
                          [h[8] * k[0] + h[9] * k[2], h[8] * k[1] + h[9] * k[3]]])
            c0 = h[6] * k[4] + h[7] * k[5] + h[10]
            c1 = h[8] * k[4] + h[9] * k[5] + h[11]
            i_next = s[0, 0] * i_l + s[0, 1] * v_o + c0
            v_next = s[1, 0] * i_l + s[1, 1] * v_o + c1
            # the step's map differentiated in d(j) (through H, h) and in d(j-1) (through K, kappa)
            now = np.array([(dh[6] * k[0] + dh[7] * k[2]) * i_l + (dh[6] * k[1] + dh[7] * k[3]) * v_o
                            + dh[6] * k[4] + dh[7] * k[5] + dh[10],
                            (dh[8] * k[0] + dh[9] * k[2]) * i_l + (dh[8] * k[1] + dh[9] * k[3]) * v_o
                            + dh[8] * k[4] + dh[9] * k[5] + dh[11]])
            sensitivity = s @ sensitivity
            sensitivity[:, block_of_step[j]] += now
            if j:
                before = np.array([(h[6] * dk[0] + h[7] * dk[2]) * i_l + (h[6] * dk[1] + h[7] * dk[3]) * v_o
                                   + h[6] * dk[4] + h[7] * dk[5],
                                   (h[8] * dk[0] + h[9] * dk[2]) * i_l + (h[8] * dk[1] + h[9] * dk[3]) * v_o
                                   + h[8] * dk[4] + h[9] * dk[5]])
                sensitivity[:, block_of_step[j - 1]] += before
            if i_next < 0.0:
                i_next = 0.0
                sensitivity[0] = 0.0
            i_l, v_o = i_next + disturbance[0], v_next + disturbance[1]
            out[j] = (i_l, v_o)
            jacobian[j] = sensitivity
        return out, jacobian

    def describe(self) -> dict:
        return {"type": f"switched model (exact per PWM period, {self.carrier} carrier, sensor {self.sensor})",
                "parameters": asdict(self.parameters), "sample_period_s": self.sample_period,
                "switching_frequency_Hz": self.switching_frequency}


def ripple_free_horizon(control_period: float, lc_period: float) -> int:
    """Prediction steps that span about one LC ringing period (at least 3, at most 24)."""
    return int(min(24, max(3, math.ceil(lc_period / control_period))))
