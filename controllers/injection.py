"""A controller wrapped for a frequency-response measurement: a small sine injected at its output (the
duty) or at its reference, and the signals on both sides correlated at the injection frequency.

At each sample t_k (scenario time) the wrapper

* ``point = "duty"``: returns d = clip(u + a sin(w t_k)) where u is the wrapped controller's duty;
* ``point = "reference"``: hands the controller the reference r + a sin(w t_k);
* ``point = "none"``: changes nothing (the scenario perturbs the plant, e.g. its load);

and over the analysis window [start, start + N Ts) -- a whole number of injection periods after the
loop has settled -- accumulates X = (2/N) sum x_k e^(-j w t_k) for the controller's output u, the
applied duty d, the injected signal, and the sensors' vo, iL and io. The ratios of these phasors are
the loop gain (-U/D), the closed-loop reference response (Vo/R) and the output impedance (-Vo/Io) at
w, exactly as a network analyser's or PLECS's AC sweep correlates them. With w on a DFT bin of the
window (an integer number of cycles in N samples), the fsw-periodic ripple and the other harmonics do
not leak into the estimate.
"""

from __future__ import annotations

import cmath
import math

from controllers.base import Measurement

POINTS = ("duty", "reference", "none")
CHANNELS = ("u", "d", "injection", "vo", "il", "io")


class InjectedController:
    """``inner`` with a sine injected at ``point`` (module docstring); ``run_results()`` after a run."""

    def __init__(self, inner, frequency: float, amplitude: float, point: str, start: float, samples: int):
        if point not in POINTS:
            raise ValueError(f"injection point {point!r} is unknown: expected one of {', '.join(POINTS)}")
        if not (frequency > 0 and math.isfinite(frequency)) or not math.isfinite(amplitude) or samples < 1:
            raise ValueError(f"injection at {frequency} Hz, amplitude {amplitude}, {samples} samples is invalid")
        self.inner, self.frequency, self.amplitude, self.point = inner, float(frequency), float(amplitude), point
        self.start, self.samples = float(start), int(samples)
        self.name, self.sample_period, self.duty_limits = inner.name, inner.sample_period, inner.duty_limits
        self.reset()

    def reset(self) -> None:
        self.inner.reset()
        self._sums = dict.fromkeys(CHANNELS, 0j)
        self._count = 0

    def step(self, m: Measurement) -> float:
        t = m.time
        wave = self.amplitude * math.sin(2 * math.pi * self.frequency * t) if t >= -1e-12 else 0.0
        seen = m
        if self.point == "reference":
            seen = Measurement(m.time, m.reference + wave, m.output_voltage, m.inductor_current, m.load_current,
                               m.input_voltage)
        u = self.inner.step(seen)
        d = u + wave if self.point == "duty" else u
        low, high = self.duty_limits
        d = min(max(d, low), high)
        window = self.start - 1e-9 * self.sample_period <= t and self._count < self.samples
        if window:
            rotation = cmath.exp(-2j * math.pi * self.frequency * t)
            for channel, value in (("u", u), ("d", d), ("injection", wave), ("vo", m.output_voltage),
                                   ("il", m.inductor_current), ("io", m.load_current)):
                self._sums[channel] += value * rotation
            self._count += 1
        return d

    def run_results(self) -> dict[str, float]:
        """The phasors (real, imaginary parts) of every channel over the window, and the samples used."""
        out = {"frequency_hz": self.frequency, "correlated_samples": float(self._count)}
        for channel, total in self._sums.items():
            phasor = 2 * total / max(self._count, 1)
            out[f"{channel}_re"], out[f"{channel}_im"] = phasor.real, phasor.imag
        return out

    def describe(self) -> dict:
        return {"type": "injected", "point": self.point, "frequency_hz": self.frequency, "amplitude": self.amplitude,
                "window_start_s": self.start, "window_samples": self.samples, "inner": self.inner.describe()}
