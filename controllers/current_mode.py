"""Average-current-mode control: an inner inductor-current PI inside an outer output-voltage PI.

The cascaded structure of industrial buck controllers (C twin ``controllers/c/current_mode.c``).
At each sample, from the measured vo and iL (the period means of the averaging sensor)::

    e_v = r - vo
    I_v <- I_v + ki_v Ts e_v                    (kept only if it does not push a limited i_ref further)
    i_ref = clip(kp_v e_v + I_v, 0, I_max)      the current limit is the outer loop's saturation
    e_i = i_ref - iL
    I_i <- I_i + ki_i Ts e_i                    (kept only if it does not push a saturated duty further)
    u = kp_i e_i + I_i                          [V]: the switch-node voltage the inner loop asks for
    d = clip(u / Vs, d_min, d_max)              Vs measured (input-voltage feed-forward), else nominal

Both integrals use the current error (backward Euler) and conditional-integration anti-windup like
:class:`controllers.pi.PIController`. The feed-forward 1/Vs makes the inner loop's gain independent
of the supply (the duty-to-current gain is proportional to Vs), which is what lets one design hold
over the 36-60 V envelope. ``computation_delay`` = 1 holds each computed duty for one sample before
it is applied -- the duty of a microcontroller that samples at the period start, computes during
the period and writes the PWM's shadow register for the next one -- and is part of the
small-signal model the gains are designed on (:mod:`cosim.design.classical_design`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from controllers.base import Measurement, check_duty_limits, check_sample_period
from controllers.small_signal import LinearController, delay_polynomial, pi_polynomials, pmul

COMPUTATION_DELAYS = (0, 1)


@dataclass(frozen=True)
class CurrentModeGains:
    """The two PIs and the current limit (SI units)."""

    kp_voltage: float  # [A/V] outer loop
    ki_voltage: float  # [A/(V s)]
    kp_current: float  # [V/A] inner loop (volts of switch-node voltage per ampere of current error)
    ki_current: float  # [V/(A s)]
    current_limit: float  # [A] the largest inductor-current reference
    computation_delay: int = 1  # [samples] 0 or 1

    def check(self, owner: str = "current-mode controller") -> None:
        values = (self.kp_voltage, self.ki_voltage, self.kp_current, self.ki_current)
        if not all(math.isfinite(v) and v >= 0 for v in values):
            raise ValueError(f"{owner}: gains {values} are invalid: expected finite values >= 0")
        if not (math.isfinite(self.current_limit) and self.current_limit > 0):
            raise ValueError(f"{owner}: current limit {self.current_limit} A is invalid: expected a finite value > 0")
        if self.computation_delay not in COMPUTATION_DELAYS:
            raise ValueError(f"{owner}: computation delay {self.computation_delay} is invalid: expected 0 or 1 "
                             "samples")


class CurrentModeController:
    """Average-current-mode control (module docstring); needs the measured inductor current."""

    def __init__(self, gains: CurrentModeGains, sample_period: float, duty_limits: tuple[float, float] = (0.0, 1.0),
                 nominal_input_voltage: float = 48.0, name: str = "CMC", design: dict | None = None):
        gains.check(name)
        self.gains = gains
        self.sample_period = check_sample_period(sample_period, name)
        self.duty_limits = check_duty_limits(duty_limits, name)
        if not (math.isfinite(nominal_input_voltage) and nominal_input_voltage > 0):
            raise ValueError(f"{name}: nominal input voltage {nominal_input_voltage} V is invalid: expected > 0")
        self.nominal_input_voltage = float(nominal_input_voltage)
        self.name = name
        self.design = design or {}
        self.reset()

    def reset(self) -> None:
        self.voltage_integral = 0.0
        self.current_integral = 0.0
        self.pending_duty = 0.0  # the duty computed at the last sample (applied now, with the delay)

    def step(self, m: Measurement) -> float:
        g, ts = self.gains, self.sample_period
        current = m.inductor_current
        if not math.isfinite(current):
            raise ValueError(f"{self.name} needs the inductor current: the plant binding has no inductor_current role")
        error_v = m.reference - m.output_voltage
        integral_v = self.voltage_integral + g.ki_voltage * ts * error_v
        reference_unclamped = g.kp_voltage * error_v + integral_v
        reference = min(max(reference_unclamped, 0.0), g.current_limit)
        if not ((reference_unclamped > g.current_limit and error_v > 0) or (reference_unclamped < 0.0 and error_v < 0)):
            self.voltage_integral = integral_v
        error_i = reference - current
        integral_i = self.current_integral + g.ki_current * ts * error_i
        node = g.kp_current * error_i + integral_i
        supply = m.input_voltage if (math.isfinite(m.input_voltage) and m.input_voltage > 0) \
            else self.nominal_input_voltage
        unclamped = node / supply
        low, high = self.duty_limits
        duty = min(max(unclamped, low), high)
        if not ((unclamped > high and error_i > 0) or (unclamped < low and error_i < 0)):
            self.current_integral = integral_i
        if g.computation_delay:
            duty, self.pending_duty = self.pending_duty, duty
        return duty

    def linear_model(self, input_voltage: float | None = None) -> LinearController:
        """d = z^-delay (1/Vs) C_i(z) (C_v(z) (r - vo) - iL), unsaturated (:mod:`controllers.small_signal`)."""
        g, ts = self.gains, self.sample_period
        vs = input_voltage or self.nominal_input_voltage
        cv_num, integrator = pi_polynomials(g.kp_voltage, g.ki_voltage, ts)
        ci_num, _ = pi_polynomials(g.kp_current, g.ki_current, ts)
        den = vs * pmul(delay_polynomial(g.computation_delay), integrator, integrator)
        outer = pmul(ci_num, cv_num)
        return LinearController(reference=outer, current=pmul(ci_num, integrator), voltage=outer, den=den)

    def describe(self) -> dict:
        return {"type": "average-current-mode control", "name": self.name, **asdict(self.gains),
                "units": {"kp_voltage": "A/V", "ki_voltage": "A/(V s)", "kp_current": "V/A",
                          "ki_current": "V/(A s)", "current_limit": "A", "computation_delay": "samples"},
                "sample_period_s": self.sample_period, "duty_limits": list(self.duty_limits),
                "nominal_input_voltage_V": self.nominal_input_voltage,
                "input_voltage_feedforward": True,
                "anti_windup": "conditional integration (clamping) in both loops", "design": self.design}

