"""The averaged small-signal model of the buck converter in discrete time, in closed form, and the
loop gains, margins and closed-loop responses of the linear (classical) controllers on it.

Why a model of its own: a classical design is made from the small-signal model, not by search, and
the frequency-response measurement on the plant FMU (:mod:`cosim.design.frequency_response`) is
checked against exactly this closed form.

**Plant.** The averaged CCM model with parasitics linearised at an operating point
(:class:`OperatingPoint`: output voltage, load, supply)::

    L diL/dt = d (Vs + V_F) - V_F - (d R_on + R_L + k R_esr) iL - k vC + k R_esr i_x
    C dvC/dt = k iL - vC / (R + R_esr) - k i_x,         vo = k (vC + R_esr iL - R_esr i_x)

(k = R / (R + R_esr); i_x a small load current drawn beside the load R, the port of the output
impedance), so the small-signal duty gain is Vs + V_F - R_on I_L and the state matrix is
:func:`controllers.predictors.circuit_matrix` at the operating duty D.

**Sampling.** The controller samples every Ts and holds its duty until the next sample (zero-order
hold: exact for the averaged plant FMU, whose duty is a piecewise-constant input). The model is
discretised exactly with matrix exponentials (:func:`scipy.linalg.expm` of block matrices), and the
sensor is either a *sample* of the state at t_k or the *average* over the last period
[t_(k-1), t_k] (the built-in switched FMU's averaging ADC: half a sample of lag):

    x(k+1) = Phi x(k) + Gamma u(k),                   u = [d, i_x]
    sample:  y(k) = C x(k) + D u(k)
    average: y(k) = (C Mi x(k-1) + C Gamma2 u(k-1)) / Ts + D u(k-1)

with Mi = int_0^Ts e^(A t) dt and Gamma2 = int_0^Ts e^(A t) (Ts - t) dt B. Every transfer function is
then a ratio of polynomials in z (2x2 adjugate over det(zI - Phi)), kept as numpy coefficient
arrays (highest power first), so responses are evaluated at z = e^(j w Ts) exactly and closed-loop
stability is the roots of one characteristic polynomial.

**Controllers.** A linear controller in its unsaturated region is :class:`LinearController`:
d(z) = (N_r r - N_i iL - N_v vo) / D, polynomials in z over one common denominator (its
computation delay is a factor z in D). The PI, the current-mode controller and the Type-III
compensator each give theirs (``linear_model``).

**Loop gain** at the duty (the loop broken at the plant's duty input, where
``buck-cosim frequency-response`` injects): L(z) = (N_i P_i + N_v P_v) / D, with P_i, P_v the
plant's duty -> measured iL, vo. Margins (:func:`margins`): the phase margin at every gain crossover
(the smallest is reported) and the gain margin at every phase crossover below 0 dB (the smallest),
on a log grid up to the Nyquist frequency.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from controllers.predictors import CircuitParameters, circuit_matrix, measured_from_state

SENSORS = ("average", "sample")
#: how the duty reaches the circuit: held over the period (the averaged FMU's input), or a sawtooth
#: (trailing-edge) PWM whose small-signal duty perturbation is a pulse at the falling edge D Ts
MODULATORS = ("zoh", "trailing-edge")
#: outputs and inputs of :class:`DiscretePlant` (indices)
CURRENT, VOLTAGE = 0, 1
DUTY, LOAD_CURRENT = 0, 1


@dataclass(frozen=True)
class OperatingPoint:
    """Where the converter is linearised (SI units)."""

    output_voltage: float  # [V]
    load_resistance: float  # [Ohm]
    input_voltage: float  # [V]

    def describe(self) -> str:
        return f"{self.output_voltage:g} V, {self.load_resistance:g} Ohm, {self.input_voltage:g} V supply"


def steady_duty(p: CircuitParameters, op: OperatingPoint) -> float:
    """The CCM duty that holds ``op`` (the parasitics' drops included)."""
    current = op.output_voltage / op.load_resistance
    return (op.output_voltage + p.diode_forward_voltage + p.inductor_resistance * current) / (
        op.input_voltage + p.diode_forward_voltage - p.switch_on_resistance * current)


def continuous_model(p: CircuitParameters, op: OperatingPoint):
    """(A, B, C, D) of the linearised averaged model: state [iL, vC], inputs [d, i_x], outputs [iL, vo]."""
    r = op.load_resistance
    duty = steady_duty(p, op)
    current = op.output_voltage / r
    k = r / (r + p.capacitor_esr)
    a = circuit_matrix(p, r, duty * p.switch_on_resistance)
    gain = op.input_voltage + p.diode_forward_voltage - p.switch_on_resistance * current
    b = np.array([[gain / p.inductance, k * p.capacitor_esr / p.inductance],
                  [0.0, -k / p.capacitance]])
    c = measured_from_state(p, r)
    d = np.array([[0.0, 0.0], [0.0, -k * p.capacitor_esr]])
    return a, b, c, d


def padd(*polys) -> np.ndarray:
    out = np.zeros(1)
    for p in polys:
        out = np.polyadd(out, p)
    return out


def pmul(*polys) -> np.ndarray:
    out = np.ones(1)
    for p in polys:
        out = np.polymul(out, p)
    return out


Z = np.array([1.0, 0.0])  # the polynomial z


def zpow(n: int) -> np.ndarray:
    """z^n (n >= 0) as a coefficient array."""
    return np.concatenate([[1.0], np.zeros(n)])


@dataclass(frozen=True)
class DiscretePlant:
    """The converter sampled every ``sample_period`` seen through ``sensor``: y = num[o][i] / den u."""

    num: tuple[tuple[np.ndarray, ...], ...]  # [output][input] numerator polynomials in z
    den: np.ndarray  # the common denominator
    sample_period: float
    sensor: str
    operating_point: OperatingPoint
    modulator: str = "zoh"

    def response(self, output: int, input_: int, z) -> np.ndarray:
        return np.polyval(self.num[output][input_], z) / np.polyval(self.den, z)


def _integral(a: np.ndarray, t: float) -> np.ndarray:
    """int_0^t e^(A s) ds (block matrix exponential)."""
    n = len(a)
    block = np.zeros((2 * n, 2 * n))
    block[:n, :n], block[:n, n:] = a, np.eye(n)
    return expm(block * t)[:n, n:]


def discrete_plant(p: CircuitParameters, op: OperatingPoint, sample_period: float,
                   sensor: str = "average", modulator: str = "zoh") -> DiscretePlant:
    """The exact discretisation of :func:`continuous_model` with the sensor (module docstring). With
    ``modulator = "trailing-edge"`` (the switched FMU's sawtooth PWM: on for [0, D Ts)), a duty
    perturbation moves the falling edge: a pulse of Ts dd at D Ts instead of a level held over the
    period -- the sampled-data model of the modulator, which leads the hold by (1/2 - D) Ts."""
    if sensor not in SENSORS:
        raise ValueError(f"sensor {sensor!r} is unknown: expected one of {', '.join(SENSORS)}")
    if modulator not in MODULATORS:
        raise ValueError(f"modulator {modulator!r} is unknown: expected one of {', '.join(MODULATORS)}")
    a, b, c, d = continuous_model(p, op)
    ts = sample_period
    n = 2
    block = np.zeros((3 * n, 3 * n))  # [[A, B, 0], [0, 0, I], [0, 0, 0]]
    block[:n, :n], block[:n, n:2 * n], block[n:2 * n, 2 * n:] = a, b, np.eye(n)
    e = expm(block * ts)
    phi, gamma, gamma2 = e[:n, :n], e[:n, n:2 * n].copy(), e[:n, 2 * n:].copy()
    mi = _integral(a, ts)  # int_0^Ts e^(A t) dt
    if modulator == "trailing-edge":
        rest = (1.0 - steady_duty(p, op)) * ts  # from the falling edge to the period's end
        gamma[:, DUTY] = expm(a * rest) @ b[:, DUTY] * ts
        gamma2[:, DUTY] = ts * _integral(a, rest) @ b[:, DUTY]  # Ts x the period mean of the pulse's response
    q = np.array([[-phi[1, 1], phi[0, 1]], [phi[1, 0], -phi[0, 0]]])  # adj(zI - Phi) = z I + Q
    det = np.array([1.0, -np.trace(phi), np.linalg.det(phi)])
    if sensor == "sample":
        first, second, feed = c @ gamma, c @ q @ gamma, d  # y = (z C G + C Q G) / det + D
        den = det
    else:
        first, second = c @ mi @ gamma / ts, c @ mi @ q @ gamma / ts
        feed = c @ gamma2 / ts + d  # y = z^-1 [(z F + S) / det + feed]
        den = np.polymul(det, Z)
    num = tuple(tuple(padd(np.array([first[o, i], second[o, i]]), feed[o, i] * det) for i in range(2))
                for o in range(2))
    return DiscretePlant(num=num, den=den, sample_period=ts, sensor=sensor, operating_point=op, modulator=modulator)


@dataclass(frozen=True)
class LinearController:
    """d(z) = (N_r r - N_i iL - N_v vo) / D in the controller's unsaturated region (polynomials in z)."""

    reference: np.ndarray
    current: np.ndarray
    voltage: np.ndarray
    den: np.ndarray


def pi_polynomials(kp: float, ki: float, sample_period: float) -> tuple[np.ndarray, np.ndarray]:
    """kp + ki Ts z / (z - 1): the workbench's PI (backward-Euler integral of the current error)."""
    return np.array([kp + ki * sample_period, -kp]), np.array([1.0, -1.0])


def delay_polynomial(samples: int) -> np.ndarray:
    """The factor of a controller's denominator for its computation delay (z^samples)."""
    return zpow(samples)


@dataclass(frozen=True)
class Margins:
    crossover_hz: float  # the highest gain crossover (|L| falls through 1), NaN if none
    phase_margin_deg: float  # the smallest over the gain crossovers
    gain_margin_db: float  # the smallest over the phase crossovers with |L| < 1 (inf: none)
    phase_crossover_hz: float  # where that gain margin is read (NaN: none)
    crossovers_hz: tuple[float, ...]  # every gain crossover
    stable: bool  # every closed-loop pole inside the unit circle

    def describe(self) -> dict:
        def number(x):
            return float(x) if math.isfinite(x) else None

        return {"crossover_hz": number(self.crossover_hz), "phase_margin_deg": number(self.phase_margin_deg),
                "gain_margin_db": number(self.gain_margin_db), "phase_crossover_hz": number(self.phase_crossover_hz),
                "gain_crossovers_hz": [float(f) for f in self.crossovers_hz], "closed_loop_stable": self.stable}


def frequency_grid(sample_period: float, low: float = 10.0, points: int = 4000) -> np.ndarray:
    """Log-spaced frequencies [Hz] from ``low`` to just below the Nyquist frequency."""
    return np.geomspace(low, 0.4999 / sample_period, points)


def unit_circle(frequency, sample_period: float):
    return np.exp(2j * np.pi * np.asarray(frequency, dtype=float) * sample_period)


def margins(loop, sample_period: float, stable: bool = True, low: float = 10.0) -> Margins:
    """Crossover, phase and gain margins of ``loop`` (a function z -> L(z)) on :func:`frequency_grid`."""
    f = frequency_grid(sample_period, low)
    values = loop(unit_circle(f, sample_period))
    magnitude = np.log(np.abs(values))
    phase = np.unwrap(np.angle(values))
    crossings = []
    for i in np.nonzero(np.sign(magnitude[:-1]) != np.sign(magnitude[1:]))[0]:
        w = magnitude[i] / (magnitude[i] - magnitude[i + 1])
        freq = math.exp(math.log(f[i]) + w * (math.log(f[i + 1]) - math.log(f[i])))
        angle = phase[i] + w * (phase[i + 1] - phase[i])
        crossings.append((freq, (math.degrees(angle) + 180.0 + 180.0) % 360.0 - 180.0, magnitude[i] > 0))
    down = [c[0] for c in crossings if c[2]]
    pm = min((c[1] for c in crossings), default=math.nan)
    gm, gm_at = math.inf, math.nan
    turns = np.floor((phase + np.pi) / (2 * np.pi))  # the phase crosses -180 deg (mod 360) where this changes
    for i in np.nonzero(turns[:-1] != turns[1:])[0]:
        boundary = (max(turns[i], turns[i + 1])) * 2 * np.pi - np.pi
        w = (boundary - phase[i]) / (phase[i + 1] - phase[i])
        level = magnitude[i] + w * (magnitude[i + 1] - magnitude[i])
        if level < 0 and -20 * level / math.log(10) < gm:
            gm = -20 * level / math.log(10)
            gm_at = math.exp(math.log(f[i]) + w * (math.log(f[i + 1]) - math.log(f[i])))
    return Margins(crossover_hz=max(down) if down else math.nan, phase_margin_deg=pm, gain_margin_db=gm,
                   phase_crossover_hz=gm_at, crossovers_hz=tuple(c[0] for c in crossings), stable=stable)


class Loop:
    """A linear controller on a discrete plant: loop gain, stability, closed-loop responses."""

    def __init__(self, plant: DiscretePlant, controller: LinearController):
        self.plant, self.controller = plant, controller
        num = plant.num
        self.characteristic = padd(pmul(plant.den, controller.den), pmul(controller.current, num[CURRENT][DUTY]),
                                   pmul(controller.voltage, num[VOLTAGE][DUTY]))

    @property
    def poles(self) -> np.ndarray:
        return np.roots(self.characteristic)

    @property
    def stable(self) -> bool:
        return bool(np.all(np.abs(self.poles) < 1.0 - 1e-9))

    def loop_gain(self, z) -> np.ndarray:
        """L(z) at the duty: -(controller output) / (duty at the plant) with the loop broken there."""
        c, p = self.controller, self.plant
        return (np.polyval(c.current, z) * p.response(CURRENT, DUTY, z)
                + np.polyval(c.voltage, z) * p.response(VOLTAGE, DUTY, z)) / np.polyval(c.den, z)

    def margins(self, low: float = 10.0) -> Margins:
        return margins(self.loop_gain, self.plant.sample_period, self.stable, low)

    def reference_to_output(self, z) -> np.ndarray:
        """Measured vo / reference in closed loop."""
        c, p = self.controller, self.plant
        return p.response(VOLTAGE, DUTY, z) * np.polyval(c.reference, z) / np.polyval(c.den, z) / (1 + self.loop_gain(z))

    def output_impedance(self, z) -> np.ndarray:
        """-vo / io of the converter in closed loop [Ohm], both as the sensor reads them (the load R
        itself excluded): the response to a small load current i_x drawn beside R."""
        c, p = self.controller, self.plant
        k_i, k_v, den = np.polyval(c.current, z), np.polyval(c.voltage, z), np.polyval(c.den, z)
        duty = -(k_i * p.response(CURRENT, LOAD_CURRENT, z) + k_v * p.response(VOLTAGE, LOAD_CURRENT, z)) \
            / den / (1 + self.loop_gain(z))
        vo = p.response(VOLTAGE, LOAD_CURRENT, z) + p.response(VOLTAGE, DUTY, z) * duty
        ix = 1.0 if p.sensor == "sample" else 1.0 / z  # the sensor's reading of i_x (the period mean lags)
        io = vo / p.operating_point.load_resistance + ix
        return -vo / io


def inner_loop_gain(plant: DiscretePlant, current_controller: np.ndarray, den: np.ndarray):
    """L_i(z) = (N_i / D) P_i: a current loop alone (an outer loop's output held)."""
    return lambda z: np.polyval(current_controller, z) * plant.response(CURRENT, DUTY, z) / np.polyval(den, z)
