"""Discrete PI voltage controller with duty limits and anti-windup.

    e(k) = v_ref(k) - v_o(k)
    I(k) = I(k-1) + K_i T_s e(k)      -- kept only if it does not push a saturated duty further
    d(k) = clip(K_p e(k) + I(k), d_min, d_max)

The integral uses the current error (backward Euler), so a pure integral loop acts on the very
first sample; with K_i T_s = 1/V_s it is the dead-beat controller of a plant that settles within
one sample period.

Conditional integration (clamping) keeps the integrator from winding up while the duty is
saturated, e.g. during start-up, so the output does not overshoot when it leaves saturation.
"""

from __future__ import annotations

import math

import numpy as np

from controllers.base import Measurement, check_duty_limits, check_sample_period


def check_gains(kp: float, ki: float) -> tuple[float, float]:
    """Finite, non-negative gains (NaN and infinities refused); raise ValueError naming them."""
    kp, ki = float(kp), float(ki)
    if not (math.isfinite(kp) and math.isfinite(ki) and kp >= 0 and ki >= 0):
        raise ValueError(f"PI gains kp = {kp}, ki = {ki} are invalid: expected finite values >= 0")
    return kp, ki


class PIController:
    """PI voltage loop. ``kp`` in 1/V (duty per volt of error), ``ki`` in 1/(V s)."""

    def __init__(self, kp: float, ki: float, sample_period: float = 1e-3,
                 duty_limits: tuple[float, float] = (0.0, 1.0), name: str = "PI",
                 tuning: dict | None = None):
        self.kp, self.ki = check_gains(kp, ki)
        self.sample_period = check_sample_period(sample_period, "PI")
        self.duty_limits = check_duty_limits(duty_limits, "PI")
        self.name = name
        self.tuning = tuning or {}
        self.integral = 0.0

    def reset(self) -> None:
        self.integral = 0.0

    def step(self, measurement: Measurement) -> float:
        error = measurement.reference - measurement.output_voltage
        low, high = self.duty_limits
        integral = self.integral + self.ki * self.sample_period * error
        unclamped = self.kp * error + integral
        duty = min(max(unclamped, low), high)
        pushing_high = unclamped > high and error > 0
        pushing_low = unclamped < low and error < 0
        if not (pushing_high or pushing_low):
            self.integral = integral
        return duty

    def linear_model(self, input_voltage: float | None = None):
        """d = C(z) (r - vo) with C(z) = kp + ki Ts z / (z - 1), unsaturated (:mod:`controllers.small_signal`)."""
        from controllers.small_signal import LinearController, pi_polynomials

        num, den = pi_polynomials(self.kp, self.ki, self.sample_period)
        return LinearController(reference=num, current=np.zeros(1), voltage=num, den=den)

    def describe(self) -> dict:
        return {
            "type": "PI",
            "name": self.name,
            "kp_per_V": self.kp,
            "ki_per_V_s": self.ki,
            "sample_period_s": self.sample_period,
            "duty_limits": list(self.duty_limits),
            "anti_windup": "conditional integration (clamping)",
            "tuning": self.tuning,
        }
