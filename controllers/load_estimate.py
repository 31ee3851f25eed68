"""The load estimate: the one definition of how the workbench infers the load from its sensors.

The predictive controllers need the load for the steady-state current iref = vref / R of eq. 23
and the circuit models, and the NNPC's network takes the load conductance 1/R as an input. Both
the controller at run time and the identification data use :func:`estimate_conductance`, so the
network is trained on exactly the feature it is fed:

    G = io / vo      from the (period-mean) load-current and output-voltage sensors;
    G = iL / vo      without a load-current sensor (in steady state iL = io);
    G = previous     while vo <= MIN_VOLTAGE or the current <= MIN_CURRENT (nothing to divide),
                     starting from the nominal load's conductance.
"""

from __future__ import annotations

import math

import numpy as np

MIN_VOLTAGE = 0.05  # [V] below this the ratio is noise (start-up from rest)
MIN_CURRENT = 1e-6  # [A] below this the load looks open: keep the previous estimate


def estimate_conductance(output_voltage: float, load_current: float, inductor_current: float,
                         previous: float) -> float:
    """The load conductance 1/R [S] from one sample of the sensors (NaN: no such sensor)."""
    if output_voltage > MIN_VOLTAGE:
        current = load_current if math.isfinite(load_current) else inductor_current
        if current > MIN_CURRENT:  # False for NaN too
            return current / output_voltage
    return previous


def conductance_series(output_voltage: np.ndarray, load_current: np.ndarray, inductor_current: np.ndarray,
                       initial: float) -> np.ndarray:
    """:func:`estimate_conductance` applied sample by sample from ``initial``, vectorised."""
    vo = np.asarray(output_voltage, dtype=float)
    io, il = np.asarray(load_current, dtype=float), np.asarray(inductor_current, dtype=float)
    current = np.where(np.isfinite(io), io, il)
    with np.errstate(invalid="ignore"):
        valid = (vo > MIN_VOLTAGE) & (current > MIN_CURRENT)
    values = np.full(len(vo), np.nan)
    values[valid] = current[valid] / vo[valid]
    last = np.maximum.accumulate(np.where(valid, np.arange(len(vo)), -1))  # index of the last valid sample
    return np.where(last >= 0, values[np.maximum(last, 0)], initial)
