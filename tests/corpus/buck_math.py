"""The physics of the test corpus's outside-authored bucks (python_buck.py, FMI 2.0; python_buck3.py, FMI 3.0):
one averaged converter with winding resistance and capacitor ESR, solved exactly over a step (2x2 matrix
exponential), a negative inductor current clipped to zero (the diode) after it. Bundled into each FMU."""

import math


def advance(il, vc, duty, vin, r, inductance, capacitance, rl, rc, h):
    """(iL [A], vC [V]) after h [s] at duty 0..1 (clamped), supply vin [V], load r [Ohm]."""
    k = r / (r + rc)
    a11, a12 = -(rl + k * rc) / inductance, -k / inductance
    a21, a22 = k / capacitance, -1.0 / ((r + rc) * capacitance)
    b0 = min(max(duty, 0.0), 1.0) * vin / inductance
    det = a11 * a22 - a12 * a21
    eq0, eq1 = -a22 * b0 / det, a21 * b0 / det
    s = 0.5 * (a11 + a22)
    m11 = 0.5 * (a11 - a22)
    delta = m11 * m11 + a12 * a21
    if delta < 0:
        w = math.sqrt(-delta)
        c, g = math.cos(w * h), math.sin(w * h) / w
    elif delta > 0:
        w = math.sqrt(delta)
        c, g = math.cosh(w * h), math.sinh(w * h) / w
    else:
        c, g = 1.0, h
    e = math.exp(s * h)
    d0, d1 = il - eq0, vc - eq1
    il = eq0 + e * (c * d0 + g * (m11 * d0 + a12 * d1))
    vc = eq1 + e * (c * d1 + g * (a21 * d0 - m11 * d1))
    return max(il, 0.0), vc


def output_voltage(il, vc, r, rc):
    """vo [V] across the load: the capacitor voltage plus the ESR's drop, divided with the load."""
    return r / (r + rc) * (vc + rc * il)


def substeps(step_size, longest=10e-6):
    """How many equal sub-steps of at most ``longest`` [s] a communication step is solved in."""
    return max(1, math.ceil(step_size / longest - 1e-9))


def off_step(current_time, step_size, step):
    """A fixed-step model's refusal of a communication step other than ``step`` [s] (its message), or None."""
    if abs(step_size - step) <= 1e-9 * step:
        return None
    return f"fixed-step model: communication step {step_size!r} s at t = {current_time!r} s, expected {step!r} s"
