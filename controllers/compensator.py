"""A discrete voltage-mode compensator: the Type-III (two zeros, three poles with one at the origin)
as a difference equation, with input-voltage feed-forward and anti-windup (C twin
``controllers/c/compensator.c``).

The design (:mod:`cosim.design.classical_design`: K-factor placement, Tustin with prewarping)
gives u(z)/e(z) = (b0 + b1 z^-1 + ... + bn z^-n) / (1 + a1 z^-1 + ... + an z^-n) from the voltage
error e = r - vo to u, the switch-node voltage [V] the loop asks for. At each sample, in direct
form II transposed (states s_1..s_n)::

    y = b0 e + s_1
    d = clip(y / Vs, d_min, d_max)               Vs measured (input-voltage feed-forward), else nominal
    s_i <- b_i e - a_i y + s_(i+1)  (s_(n+1) = 0) -- not while d is saturated and e pushes it further

Freezing every state while the output is saturated in the direction the error pushes is the
conditional integration of :class:`controllers.pi.PIController` applied to the whole compensator:
the integrator (its pole at z = 1) cannot wind up during a start-up at full duty. As in
:mod:`controllers.current_mode`, ``computation_delay`` = 1 applies each duty one sample after it
is computed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controllers.base import Measurement, check_duty_limits, check_sample_period
from controllers.small_signal import LinearController, delay_polynomial, pmul

MAX_ORDER = 4  # controllers/c/compensator.h: BUCKC_COMPENSATOR_MAX_ORDER


@dataclass(frozen=True)
class CompensatorCoefficients:
    """u/e = (numerator) / (denominator) in powers of z^-1; denominator[0] = 1."""

    numerator: tuple[float, ...]  # [V/V] b0 .. bn
    denominator: tuple[float, ...]  # 1, a1 .. an
    computation_delay: int = 1  # [samples] 0 or 1

    @property
    def order(self) -> int:
        return len(self.denominator) - 1

    def check(self, owner: str = "compensator") -> None:
        if len(self.numerator) != len(self.denominator):
            raise ValueError(f"{owner}: {len(self.numerator)} numerator and {len(self.denominator)} denominator "
                             "coefficients: expected as many (pad with zeros)")
        if not 1 <= self.order <= MAX_ORDER:
            raise ValueError(f"{owner}: order {self.order} is invalid: expected 1 ... {MAX_ORDER}")
        if self.denominator[0] != 1.0:
            raise ValueError(f"{owner}: denominator[0] = {self.denominator[0]}: expected 1 (normalise)")
        if not all(math.isfinite(c) for c in (*self.numerator, *self.denominator)):
            raise ValueError(f"{owner}: the coefficients must be finite numbers")
        if self.computation_delay not in (0, 1):
            raise ValueError(f"{owner}: computation delay {self.computation_delay} is invalid: expected 0 or 1 "
                             "samples")


class CompensatorController:
    """Voltage-mode control by a discrete compensator (module docstring)."""

    def __init__(self, coefficients: CompensatorCoefficients, sample_period: float,
                 duty_limits: tuple[float, float] = (0.0, 1.0), nominal_input_voltage: float = 48.0,
                 name: str = "Type-III", design: dict | None = None):
        coefficients.check(name)
        self.coefficients = coefficients
        self.sample_period = check_sample_period(sample_period, name)
        self.duty_limits = check_duty_limits(duty_limits, name)
        if not (math.isfinite(nominal_input_voltage) and nominal_input_voltage > 0):
            raise ValueError(f"{name}: nominal input voltage {nominal_input_voltage} V is invalid: expected > 0")
        self.nominal_input_voltage = float(nominal_input_voltage)
        self.name = name
        self.design = design or {}
        self._b = tuple(float(c) for c in coefficients.numerator)
        self._a = tuple(float(c) for c in coefficients.denominator)
        self.reset()

    def reset(self) -> None:
        self.state = [0.0] * self.coefficients.order
        self.pending_duty = 0.0

    def step(self, m: Measurement) -> float:
        b, a, s = self._b, self._a, self.state
        n = len(s)
        error = m.reference - m.output_voltage
        y = b[0] * error + s[0]
        supply = m.input_voltage if (math.isfinite(m.input_voltage) and m.input_voltage > 0) \
            else self.nominal_input_voltage
        unclamped = y / supply
        low, high = self.duty_limits
        duty = min(max(unclamped, low), high)
        if not ((unclamped > high and error > 0) or (unclamped < low and error < 0)):
            for i in range(n - 1):
                s[i] = b[i + 1] * error - a[i + 1] * y + s[i + 1]
            s[n - 1] = b[n] * error - a[n] * y
        if self.coefficients.computation_delay:
            duty, self.pending_duty = self.pending_duty, duty
        return duty

    def linear_model(self, input_voltage: float | None = None) -> LinearController:
        """d = z^-delay (1/Vs) (u/e)(z) (r - vo), unsaturated (:mod:`controllers.small_signal`)."""
        vs = input_voltage or self.nominal_input_voltage
        num = np.array(self._b)  # b0 z^n + ... + bn over z^n + a1 z^(n-1) + ... + an
        den = vs * pmul(delay_polynomial(self.coefficients.computation_delay), np.array(self._a))
        return LinearController(reference=num, current=np.zeros(1), voltage=num, den=den)

    def describe(self) -> dict:
        c = self.coefficients
        return {"type": "discrete compensator (voltage mode)", "name": self.name, "numerator": list(c.numerator),
                "denominator": list(c.denominator), "computation_delay": c.computation_delay,
                "units": "u [V] per error [V] in powers of z^-1; d = u / Vs",
                "sample_period_s": self.sample_period, "duty_limits": list(self.duty_limits),
                "nominal_input_voltage_V": self.nominal_input_voltage, "input_voltage_feedforward": True,
                "anti_windup": "states frozen while the duty is saturated in the error's direction",
                "design": self.design}
