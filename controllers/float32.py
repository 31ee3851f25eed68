"""How far the float32 build of a C twin may be from its double build in one step: a derived bound.

The float32 build (``-DBUCKC_FLOAT32``, ``controllers/c/buckc.h``) runs the same operations as the
double build in IEEE binary32. Each operation then rounds with relative error at most
``u = 2**-24`` (round to nearest), each input and state value is rounded to float on the way
in, and its tanh (``buckc_tanhf``, ``controllers/c/buckc_tanhf.h``: not libm's ``tanhf``, a clamped
exp-based form, 63 cycles a call on a Cortex-M4F against 210) is within :data:`TANH_ERROR` of tanh. Forward error
analysis (Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd ed., ch. 3) turns that
into a bound on the step's output, evaluated at the step's own numbers:

* a sum of n products plus a bias: error <= gamma(n+1) (|b| + sum |w_i x_i|) + sum |w_i| e_i, with
  gamma(k) = k u / (1 - k u) and e_i the bound of input i; weights and biases rounded to float
  add u |w_i x_i| and u |b|;
* tanh: error <= sech^2(max(0, |s| - e_s)) e_s (tanh's slope on the interval the argument may lie
  in) + TANH_ERROR (buckc_tanhf's, absolute) + 2 ulp of the double build's libm tanh;
* a subtraction, a product, a division: the operands' bounds propagated to first order, plus u of
  the result;
* clipping to the duty limits is 1-Lipschitz (the limits, rounded to float, add u |limit|).

Branches: where a decision (the load estimate's thresholds, the integral band) is within the
rounding bound of its threshold, either outcome is possible, and the bound adds the jump
between them -- so it holds on every step, not only on the steps far from a threshold.

The bound is first order in u (terms in u**2, below 1e-14 relative here, are left out) and covers
the double build's own rounding too (``u`` is the sum of both precisions' unit roundoffs). It
assumes the float32 build starts the step from the double build's state rounded to float: it is
the *per-step* tolerance. Over a replay the states drift apart within their own feedback (the
integral, the previous duty); that is what the closed-loop test measures on the plant FMU.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from controllers.load_estimate import MIN_CURRENT, MIN_VOLTAGE

#: unit roundoff of binary32 plus that of binary64 (the double build is not exact either)
U = 2.0 ** -24 + 2.0 ** -53


def _tanhf_error() -> float:
    """BUCKC_TANHF_ERROR of controllers/c/buckc_tanhf.h (the one definition)."""
    header = (Path(__file__).parent / "c" / "buckc_tanhf.h").read_text()
    match = re.search(r"^#define\s+BUCKC_TANHF_ERROR\s+([0-9.eE+-]+)", header, flags=re.M)
    return float(match.group(1))


#: |buckc_tanhf(x) - tanh(x)| for every float x, absolute (the float32 build's tanh; tests/test_float32.py
#: checks it on every float from 2**-7 to 9.5 and samples the rest)
TANH_ERROR = _tanhf_error()


def gamma(n: int) -> float:
    """Higham's gamma_n = n u / (1 - n u): the relative bound of n roundings."""
    return n * U / (1.0 - n * U)


def _f32(value: float) -> float:
    return float(np.float32(value))


def dense_bound(weights: np.ndarray, bias: np.ndarray, x: np.ndarray, ex: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``s = b + x @ W`` (computed in double) and its float32 bound, given the inputs' bounds ``ex``."""
    w, b = np.asarray(weights, float), np.asarray(bias, float)
    x, ex = np.asarray(x, float), np.asarray(ex, float)
    s = b + x @ w
    magnitude = np.abs(b) + np.abs(x) @ np.abs(w)
    return s, np.abs(w).T @ ex + (gamma(len(x) + 1) + U) * magnitude


def tanh_bound(s: np.ndarray, es: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``tanh(s)`` and the bound of the float32 build's tanh (``buckc_tanhf``) evaluated at an argument within
    ``es`` of ``s``, against the double build's (libm's ``tanh``, 2 ulp of binary64 at most)."""
    t = np.tanh(s)
    slope = 1.0 / np.cosh(np.maximum(0.0, np.abs(s) - es)) ** 2
    return t, slope * es + TANH_ERROR + 2.0 * 2.0 ** -53 * np.abs(t)


def _activation_bound(activation: str, z: np.ndarray, ez: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if activation == "tanh":
        return tanh_bound(z, ez)
    if activation == "relu":  # max(z, 0): exact, 1-Lipschitz
        return np.maximum(z, 0.0), ez
    if activation == "sigmoid":  # 0.5 (1 + tanh(0.5 z)): the halvings are exact
        t, et = tanh_bound(0.5 * z, 0.5 * ez)
        return 0.5 * (1.0 + t), 0.5 * (et + U * np.abs(1.0 + t))
    raise ValueError(f"activation {activation!r} is unknown: expected tanh, relu or sigmoid")


def nn_forward_bound(weights, biases, activation: str, residual: bool, x) -> np.ndarray:
    """The per-output bound of ``buckc_nn_forward`` (``controllers/c/nn_model.c``) in float32 against
    double for the input row ``x`` (rounded to float on the way in): the folded ``weights`` /
    ``biases`` of :class:`controllers.nn_model.NNPlantModel`."""
    x = np.asarray(x, float)
    h, eh = x, U * np.abs(x)
    for w, b in zip(weights[:-1], biases[:-1]):
        z, ez = dense_bound(w, b, h, eh)
        h, eh = _activation_bound(activation, z, ez)
    y, ey = dense_bound(weights[-1], biases[-1], h, eh)
    if residual:  # y + x[:2]
        ey = ey + U * np.abs(x[:2]) + U * np.abs(y + x[:2])
    return ey


def conductance_bound(output_voltage: float, load_current: float, inductor_current: float,
                      previous: float) -> tuple[float, float]:
    """The load estimate (``controllers/c/load_estimate.c``): its double value and its float32 bound
    (either outcome of a threshold decision that rounding may flip included)."""
    vo = output_voltage
    current = load_current if math.isfinite(load_current) else inductor_current
    held = abs(previous), U * abs(previous)

    def divided():
        g = current / vo
        return abs(g), 3.0 * U * abs(g)  # current and vo rounded, one division

    near_voltage = math.isfinite(vo) and abs(vo - MIN_VOLTAGE) <= U * abs(vo) + abs(_f32(MIN_VOLTAGE) - MIN_VOLTAGE)
    near_current = math.isfinite(current) and (abs(current - MIN_CURRENT)
                                               <= U * abs(current) + abs(_f32(MIN_CURRENT) - MIN_CURRENT))
    takes_ratio = vo > MIN_VOLTAGE and current > MIN_CURRENT
    value = current / vo if takes_ratio else previous
    bound = divided()[1] if takes_ratio else held[1]
    if (near_voltage or near_current) and vo != 0.0 and math.isfinite(current):
        other = current / vo if not takes_ratio else previous
        bound = max(bound, abs(other - value) + max(divided()[1], held[1]))
    return value, bound


def policy_step_bound(policy, measurement, state) -> float:
    """The bound on |d_float32 - d_double| of one ``buckc_policy_step`` (``controllers/c/explicit_policy.c``):
    ``policy`` an :class:`controllers.explicit_policy.ExplicitPolicy`'s weights and settings (its
    ``weights``, ``biases``, ``config``, ``sample_period``, ``duty_limits``), ``measurement`` the step's
    :class:`controllers.base.Measurement`, ``state`` the double build's state before the step (the
    ``BuckcPolicy`` fields: have_history, previous_current, previous_voltage, previous_duty,
    conductance, integral), which the float32 build starts from rounded to float."""
    m, s = measurement, state
    r, vo, il = m.reference, m.output_voltage, m.inductor_current
    g, eg = conductance_bound(vo, m.load_current, il, s.conductance)
    pv = s.previous_voltage if s.have_history else vo
    pc = s.previous_current if s.have_history else il
    iref = g * r
    e_iref = eg * abs(r) + U * abs(g) * abs(r) + U * abs(iref)
    x = np.array([vo - r, il - iref, pv - r, pc - iref, s.previous_duty, r, g])
    ex = np.array([U * (abs(vo) + abs(r)) + U * abs(x[0]), U * abs(il) + e_iref + U * abs(x[1]),
                   U * (abs(pv) + abs(r)) + U * abs(x[2]), U * abs(pc) + e_iref + U * abs(x[3]),
                   U * abs(s.previous_duty), U * abs(r), eg])
    h, eh = x, ex
    for w, b in zip(policy.weights[:-1], policy.biases[:-1]):
        z, ez = dense_bound(w, b, h, eh)
        h, eh = tanh_bound(z, ez)
    out, e_out = dense_bound(policy.weights[-1], policy.biases[-1], h, eh)
    u, e_u = float(out[0]), float(e_out[0])
    # the integral term: I + (Ki Ts) e while |e| <= band |r|
    error = r - vo
    e_error = U * (abs(r) + abs(vo)) + U * abs(error)
    gain = policy.config.integral_gain * policy.sample_period
    increment = gain * error
    e_increment = abs(gain) * e_error + abs(error) * 3.0 * U * abs(gain) + U * abs(increment)
    band = policy.config.integral_band * abs(r)
    inside = abs(error) <= band
    integral = s.integral + (increment if inside else 0.0)
    e_integral = U * abs(s.integral) + ((e_increment + U * abs(integral)) if inside else 0.0)
    if abs(abs(error) - band) <= e_error + 3.0 * U * band:  # the band decision may go either way
        e_integral += abs(increment) + e_increment
    unclamped = u + integral
    low, high = policy.duty_limits
    return e_u + e_integral + U * abs(unclamped) + U * max(abs(low), abs(high))


def pi_step_bound(kp: float, ki: float, sample_period: float, duty_limits, integral: float, reference: float,
                  output_voltage: float) -> float:
    """The bound on |d_float32 - d_double| of one ``buckc_pi_step`` (``controllers/c/pi.c``) from the
    double build's ``integral`` (rounded to float by the float32 build)."""
    error = reference - output_voltage
    e_error = U * (abs(reference) + abs(output_voltage)) + U * abs(error)
    gain = ki * sample_period  # (ki Ts) e, as the C
    increment = gain * error
    updated = integral + increment
    e_updated = (U * abs(integral) + abs(gain) * e_error + abs(error) * 3.0 * U * abs(gain) + U * abs(increment)
                 + U * abs(updated))
    proportional = kp * error
    e_proportional = abs(kp) * e_error + 2.0 * U * abs(proportional)
    unclamped = proportional + updated
    return e_proportional + e_updated + U * abs(unclamped) + U * max(abs(duty_limits[0]), abs(duty_limits[1]))


def _takes_input(input_voltage: float) -> bool:
    return math.isfinite(input_voltage) and input_voltage > 0


def _divided_clipped(numerator: float, e_numerator: float, input_voltage: float, nominal_input_voltage: float,
                     duty_limits) -> float:
    """The bound of ``clip(numerator / supply, low, high)`` given the numerator's bound, the supply being the
    measured input voltage if finite and > 0, else the nominal: the division rounds (u), the supply is an
    input or a configuration value rounded to float (u), the clip is 1-Lipschitz and its limits are rounded
    to float (u |limit|). Which supply each build takes is decided on the input as each build has it, so
    it is known exactly: a voltage that underflows or overflows in float takes the nominal in the float32
    build only, and the bound adds the jump between the two quotients."""
    with np.errstate(over="ignore"):
        single = float(np.float32(input_voltage))
    supply = input_voltage if _takes_input(input_voltage) else nominal_input_voltage
    unclamped = numerator / supply
    bound = e_numerator / abs(supply) + 2.0 * U * abs(unclamped)
    if _takes_input(input_voltage) and not _takes_input(single):  # (the other way round cannot happen)
        bound += abs(unclamped - numerator / nominal_input_voltage)
    low, high = duty_limits
    return bound + U * max(abs(low), abs(high))


def _pi_terms(kp: float, ki: float, sample_period: float, integral: float, error: float, e_error: float):
    """``kp e + (I + (ki Ts) e)`` as the classical twins compute it, and its bound (``integral`` the double
    state, rounded to float by the float32 build; ``e_error`` the error's bound)."""
    gain = ki * sample_period
    e_gain = 3.0 * U * abs(gain)  # ki and Ts rounded, one product
    increment = gain * error
    e_increment = abs(gain) * e_error + abs(error) * e_gain + U * abs(increment)
    updated = integral + increment
    e_updated = U * abs(integral) + e_increment + U * abs(updated)
    proportional = kp * error
    e_proportional = abs(kp) * e_error + 2.0 * U * abs(proportional)
    total = proportional + updated
    return total, e_proportional + e_updated + U * abs(total)


def current_mode_step_bound(controller, measurement, state) -> float:
    """The bound on |d_float32 - d_double| of the duty one ``buckc_current_mode_step``
    (``controllers/c/current_mode.c``) computes -- the one it returns without a computation delay, the one
    it holds for the next sample with it: ``controller`` the
    :class:`controllers.current_mode.CurrentModeController`, ``measurement`` the step's
    :class:`controllers.base.Measurement`, ``state`` the double build's state before the step
    (``voltage_integral``, ``current_integral``), which the float32 build starts from rounded to float.
    The anti-windup decisions change only the state kept for the next step, not this step's duty; the
    current reference's clip to [0, I_max] is 1-Lipschitz."""
    g, m = controller.gains, measurement
    r, vo, il = m.reference, m.output_voltage, m.inductor_current
    error_v = r - vo
    e_error_v = U * (abs(r) + abs(vo)) + U * abs(error_v)
    reference, e_reference = _pi_terms(g.kp_voltage, g.ki_voltage, controller.sample_period, state.voltage_integral,
                                       error_v, e_error_v)
    reference = min(max(reference, 0.0), g.current_limit)
    e_reference += U * g.current_limit
    error_i = reference - il
    e_error_i = e_reference + U * abs(il) + U * abs(error_i)
    node, e_node = _pi_terms(g.kp_current, g.ki_current, controller.sample_period, state.current_integral, error_i,
                             e_error_i)
    return _divided_clipped(node, e_node, m.input_voltage, controller.nominal_input_voltage, controller.duty_limits)


def compensator_step_bound(controller, measurement, state) -> float:
    """The bound on |d_float32 - d_double| of the duty one ``buckc_compensator_step``
    (``controllers/c/compensator.c``) computes (returned, or held for the next sample with a computation
    delay): ``y = b0 e + s_1``, then ``clip(y / Vs)``; ``state`` the double build's state before the step
    (``state[0]`` = s_1, rounded to float by the float32 build), ``b0`` rounded to float. The states'
    update and its anti-windup decision affect the next step only."""
    m = measurement
    r, vo = m.reference, m.output_voltage
    error = r - vo
    e_error = U * (abs(r) + abs(vo)) + U * abs(error)
    b0, s1 = controller.coefficients.numerator[0], state.state[0]
    product = b0 * error
    y = product + s1
    e_y = abs(b0) * e_error + 2.0 * U * abs(product) + U * abs(s1) + U * abs(y)
    return _divided_clipped(y, e_y, m.input_voltage, controller.nominal_input_voltage, controller.duty_limits)
