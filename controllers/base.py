"""The one protocol every controller block implements.

A controller is sampled every ``sample_period`` seconds. At each sample the master hands it a
:class:`Measurement` and holds the returned duty cycle (zero-order hold) until the next sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable


@dataclass(slots=True)
class Measurement:
    """What a controller sees at a sample instant (SI units; NaN where the plant has no such output).

    Not frozen: it is built at every sample, and frozen dataclasses are several times slower to create.
    """

    time: float  # [s] scenario time
    reference: float  # [V] output-voltage reference in effect
    output_voltage: float  # [V]
    inductor_current: float = math.nan  # [A]
    load_current: float = math.nan  # [A]
    input_voltage: float = math.nan  # [V] supply voltage (known to the controller, e.g. measured)


@runtime_checkable
class Controller(Protocol):
    """A sampled controller: ``reset()`` before a run, ``step()`` at each sample."""

    name: str
    sample_period: float  # [s]
    duty_limits: tuple[float, float]

    def reset(self) -> None:
        """Forget all internal state (integrators, previous moves, estimates)."""

    def step(self, measurement: Measurement) -> float:
        """Return the duty cycle to hold until the next sample."""

    def describe(self) -> dict:
        """JSON-ready settings for run metadata (type, gains, limits, period...)."""


def check_duty_limits(limits: tuple[float, float], owner: str) -> tuple[float, float]:
    """Validate ``(d_min, d_max)`` with 0 <= d_min < d_max <= 1; raise ValueError naming ``owner``."""
    low, high = (float(limits[0]), float(limits[1]))
    if not (0.0 <= low < high <= 1.0):
        raise ValueError(f"{owner}: duty limits ({low}, {high}) are invalid: expected 0 <= min < max <= 1")
    return low, high


def check_sample_period(period: float, owner: str) -> float:
    period = float(period)
    if not (period > 0.0 and math.isfinite(period)):
        raise ValueError(f"{owner}: sample period {period} s is invalid: expected a finite value > 0")
    return period
