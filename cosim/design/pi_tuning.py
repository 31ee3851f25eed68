"""Repeatable PI tuning on the plant FMU, redone for every control rate and for the plant's converter.

Method: minimise the total ISE of the start-up and both reference steps (the shipped templates resolved against the
plant's converter spec, :mod:`cosim.converter_spec`: to the nominal output, then up and down by a quarter -- 12 -> 15 V
and 12 -> 9 V on Table II) simulated on the plant FMU at the given control period at the spec's nominal load and
supply, subject to overshoot and undershoot <= 5 % (quadratic penalty) and a steady-state error <= 0.5 % (penalty).
The search runs in the normalised gains a = Kp Vs (proportional loop gain; Vs the spec's nominal supply) and
b = Ki Ts Vs (integral gain per sample): a grid over a in {0, 0.03, 0.1, 0.3} and b log-spaced over [1e-3, 1]
(6 points), then at most 40 Nelder-Mead evaluations from the best grid point. Everything is deterministic, so the
same plant, converter and period give the same gains.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, replace
from fractions import Fraction
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.optimize import minimize

from controllers.pi import PIController
from cosim.base.errors import ConfigError, PlantError, WorkbenchError
from cosim.base.files import json_text
from cosim.converter_spec import ConverterSpec
from cosim.design.design_cache import DesignKey, announce, design_key, stale_reason
from cosim.fmi.binding import PlantBinding
from cosim.fmi.plant import open_plant
from cosim.master import preflight, record_period_of, run
from cosim.metrics import run_metrics
from cosim.scenarios import Scenario, ScenarioEvent, load_scenario

TUNING_SCENARIOS = ("startup", "reference_up", "reference_down")
OVERSHOOT_LIMIT_PCT = 5.0
STEADY_STATE_LIMIT_PCT = 0.5
GRID_A = (0.0, 0.03, 0.1, 0.3)
GRID_B = tuple(np.logspace(-3, 0, 6))
METHOD = (
    "minimise total ISE of start-up and both reference steps on the plant FMU, s.t. overshoot/undershoot "
    "<= 5 % and |steady-state error| <= 0.5 % (quadratic penalties); grid over a = Kp*Vs, b = Ki*Ts*Vs, "
    "then Nelder-Mead"
)
#: the recording step every PI tuning simulates with [s] -- ``run`` and ``tune-pi`` without gains, the reproduction,
#: the study, the sweeps: one tuning per plant and rate, whichever command asks (half the resolution of a run's
#: default: twice as fast, the same gains within the search's tolerance); part of the design key
TUNING_RECORD_PERIOD = 2e-5
#: tuning runs are shortened versions of the paper scenarios: long enough to settle at either rate
TUNING_DURATION = 0.02  # [s]
TUNING_SETTLE = 0.015  # [s]


@dataclass(frozen=True)
class PITuning:
    kp: float  # [1/V]
    ki: float  # [1/(V s)]
    control_period: float  # [s]
    cost: float
    worst_overshoot_pct: float
    evaluations: int
    plant: str
    method: str = METHOD
    design: dict | None = None  # {"key", "inputs"}: what the gains were tuned for (cosim.design.design_cache)

    @property
    def design_key(self) -> str | None:
        return (self.design or {}).get("key")

    def controller(self, duty_limits: tuple[float, float] = (0.0, 1.0), name: str = "PI") -> PIController:
        return PIController(self.kp, self.ki, self.control_period, duty_limits, name=name,
                            tuning={"method": self.method, "cost_V2s": self.cost, "plant": self.plant,
                                    "design_key": self.design_key})

    def to_json(self) -> str:
        return json_text(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> "PITuning":
        return cls(**json.loads(text))


def _tuning_scenarios(spec: ConverterSpec):
    scenarios = []
    for name in TUNING_SCENARIOS:
        s = load_scenario(name, spec)
        events = tuple(e for e in s.events if e.time < TUNING_DURATION)
        scenarios.append(replace(s, duration=TUNING_DURATION, settle=TUNING_SETTLE if s.settle else 0.0,
                                 events=events))
    return scenarios


def _grid(quick: bool) -> list[tuple[float, float]]:
    return [(a, b) for a in ((0.0, 0.1) if quick else GRID_A) for b in ((0.01, 0.3) if quick else GRID_B)]


def _nelder_mead_evaluations(quick: bool) -> int:
    return 6 if quick else 40


def nominal_supply(binding: PlantBinding, input_voltage: float | None, purpose: str) -> float:
    """``input_voltage`` [V] if given, else the nominal supply of the plant's converter spec (refused without one)."""
    return float(input_voltage if input_voltage is not None else binding.converter.require("input_voltage", purpose))


def pi_design(binding: PlantBinding, control_period: float, *, record_period: float = TUNING_RECORD_PERIOD,
              input_voltage: float | None = None, quick: bool = False) -> DesignKey:
    """The design key of :func:`tune_pi` with these arguments: the plant, the rate, the tuning
    scenarios (resolved against the plant's converter spec) and every setting of the search (no tuning is done)."""
    input_voltage = nominal_supply(binding, input_voltage, "the PI tuning")
    record_period = record_period_of(binding, record_period, control_period)  # a fixed-step FMU's grid
    return design_key("pi", binding, control_period, scenarios=_tuning_scenarios(binding.converter),
                      settings={"method": METHOD, "record_period_s": record_period, "input_voltage_V": input_voltage,
                                "grid": _grid(quick), "nelder_mead_evaluations": _nelder_mead_evaluations(quick)})


def tuning_evaluations(quick: bool = False) -> int:
    """Closed-loop evaluations :func:`tune_pi` makes at most: the grid, then Nelder-Mead (each
    simulates every tuning scenario)."""
    return len(_grid(quick)) + _nelder_mead_evaluations(quick)


def tune_pi(binding: PlantBinding, control_period: float, *, record_period: float = TUNING_RECORD_PERIOD,
            input_voltage: float | None = None, progress: bool = False, quick: bool = False,
            on_estimate: Callable[[float], None] | None = None) -> PITuning:
    """Tune a PI for ``binding`` at ``control_period`` by the method in the module docstring.

    ``input_voltage`` [V]: the supply the gains are normalised by (None: the converter spec's nominal supply).
    ``quick`` (smoke tests only) searches a 2 x 2 grid and 6 Nelder-Mead evaluations.
    ``on_estimate``: called once, with the wall-clock seconds of the second evaluation (the first
    also loads the plant), for an estimate of the whole tuning: at most :func:`tuning_evaluations`.
    """
    input_voltage = nominal_supply(binding, input_voltage, "the PI tuning")
    record_period = record_period_of(binding, record_period, control_period)  # a fixed-step FMU's grid
    design = pi_design(binding, control_period, record_period=record_period, input_voltage=input_voltage, quick=quick)
    scenarios = _tuning_scenarios(binding.converter)
    evaluations = 0
    failures: list[str] = []  # the runs that failed, as their errors say
    worst: dict[tuple[float, float], float] = {}

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(desc=f"tuning PI @ {control_period * 1e6:.4g} us", unit="eval", leave=False,
                   total=tuning_evaluations(quick))
    started = None

    with open_plant(binding) as plant:
        for scenario in scenarios:  # what the plant refuses whatever the gains, refused before the search
            preflight(plant, scenario)

        def cost(params: np.ndarray) -> float:
            nonlocal evaluations, started
            if evaluations == 1 and started is None:
                started = time.perf_counter()
            a, b = float(params[0]), float(params[1])
            kp, ki = a / input_voltage, b / (control_period * input_voltage)
            controller = PIController(max(kp, 0.0), max(ki, 0.0), control_period)
            total, worst_os = 0.0, 0.0
            for scenario in scenarios:
                try:
                    metrics = run_metrics(run(plant, controller, scenario, record_period=record_period))
                except ConfigError:
                    raise  # the plant refused its set-up (a binding parameter, an input): no gains can change that
                except WorkbenchError as error:
                    if plant.fatal:
                        raise  # the FMU is unusable: no later evaluation could succeed
                    failures.append(str(error))
                    return 1e6  # these gains drove the plant into a failure: a very bad score
                if not math.isfinite(metrics["ise_V2s"]):
                    return 1e6
                excess = max(metrics["overshoot_pct"], metrics["undershoot_pct"]) - OVERSHOOT_LIMIT_PCT
                sse = abs(metrics["steady_state_error_pct"]) - STEADY_STATE_LIMIT_PCT
                total += metrics["ise_V2s"] + 0.1 * max(0.0, excess) ** 2 + 10.0 * max(0.0, sse) ** 2
                worst_os = max(worst_os, metrics["overshoot_pct"], metrics["undershoot_pct"])
            evaluations += 1
            worst[(a, b)] = worst_os
            if evaluations == 2 and started is not None and on_estimate is not None:
                on_estimate(time.perf_counter() - started)
            if bar is not None:
                bar.update(1)
            return total

        grid = _grid(quick)
        scores = [cost(np.array(p)) for p in grid]
        start = np.array(grid[int(np.argmin(scores))])
        result = minimize(cost, start, method="Nelder-Mead",
                          bounds=[(0.0, 3.0), (1e-4, 1.5)],
                          options={"maxfev": _nelder_mead_evaluations(quick), "xatol": 1e-3, "fatol": 1e-7,
                                   "initial_simplex": [start, start * [1.0, 1.3] + [0.02, 0.0], start * [1.0, 0.8]]})
    if bar is not None:
        bar.close()
    _refuse_if_nothing_ran(evaluations, failures, binding)
    best = result.x if result.fun <= min(scores) else start
    best_cost = float(min(result.fun, min(scores)))
    a, b = float(best[0]), float(best[1])
    return PITuning(kp=a / input_voltage, ki=b / (control_period * input_voltage), control_period=control_period,
                    cost=best_cost, worst_overshoot_pct=float(worst.get((a, b), math.nan)),
                    evaluations=evaluations, plant=binding.label, design=design.describe())


def _refuse_if_nothing_ran(evaluations: int, failures: list[str], binding: PlantBinding) -> None:
    """A tuning none of whose gains ran the plant to the end has no result: refuse it, naming the first failure,
    rather than return the search's start as if it were tuned."""
    if evaluations == 0:
        why = (f"the first failure: {failures[0].removeprefix(binding.origin + ': ')}" if failures
               else "their metrics were not finite")
        raise PlantError(f"{binding.origin}: the PI cannot be tuned on this plant: no gains of the search ran it "
                         f"through the tuning scenarios ({why})")


#: the lightly damped point of the envelope PI: this many times the nominal load (25 Ohm on Table II's 6 Ohm, an LC
#: quality factor of about 5 there), at most the envelope's largest load
LIGHT_LOAD_FACTOR = Fraction(25, 6)


def envelope_points(spec: ConverterSpec) -> tuple[tuple[float, float, float], ...]:
    """The envelope PI's operating points of a converter spec: (reference [V], load [Ohm], supply [V]) -- the envelope's
    corners in reference and load at the nominal supply (CCM and deep DCM), the nominal point, a lightly damped load
    (:data:`LIGHT_LOAD_FACTOR` x nominal), and the highest reference at both supply extremes (the smallest load at the
    lowest supply, the largest at the highest). On Table II: (3, 4, 48), (3, 100, 48), (12, 6, 48), (12, 25, 48),
    (20, 4, 36), (20, 100, 60)."""
    purpose = "the envelope PI's operating points"
    r_low, r_high = spec.operating_range("output_voltage", purpose)
    load_low, load_high = spec.operating_range("load_resistance", purpose)
    vs_low, vs_high = spec.operating_range("input_voltage", purpose)
    r, load, vs = (spec.require(key, purpose) for key in ("output_voltage", "load_resistance", "input_voltage"))
    light = min(float(Fraction(load) * LIGHT_LOAD_FACTOR), load_high)
    return ((r_low, load_low, vs), (r_low, load_high, vs), (r, load, vs), (r, light, vs), (r_high, load_low, vs_low),
            (r_high, load_high, vs_high))
ENVELOPE_AGGREGATES = ("max", "sum")
METHOD_ENVELOPE = (
    "minimise the {aggregate} over operating points {points} (reference V, load Ohm, supply V) of ISE / r^2 of a "
    "start-up to 0.8 r, a reference step to r and a load step 1.25 R -> R on the plant FMU, plus the penalties of the "
    "nominal method (overshoot/undershoot <= 5 %, |steady-state error| <= 0.5 %); grid over a = Kp*Vs, b = Ki*Ts*Vs, "
    "then Nelder-Mead")


def envelope_scenario(reference: float, load: float, supply: float) -> Scenario:
    """One operating point of the envelope tuning: start-up from rest to 0.8 r at 1.25 R, a reference step to
    r at 4 ms, a load step to R at 8 ms; metrics from the reference step on."""
    return Scenario(name="envelope_point", description=f"start-up to {0.8 * reference:g} V, step to {reference:g} V, "
                    f"load {1.25 * load:g} -> {load:g} Ohm, {supply:g} V supply", duration=12e-3,
                    initial={"reference": 0.8 * reference, "load_resistance": 1.25 * load, "input_voltage": supply},
                    events=(ScenarioEvent(4e-3, {"reference": reference}), ScenarioEvent(8e-3, {"load_resistance": load})))


def tune_pi_envelope(binding: PlantBinding, control_period: float, points=None, aggregate: str = "max",
                     *, record_period: float = TUNING_RECORD_PERIOD, input_voltage: float | None = None,
                     quick: bool = False, progress: bool = False) -> PITuning:
    """The PI tuned for the envelope: the nominal method's ISE and penalties at each of ``points`` (None: the
    :func:`envelope_points` of the plant's converter spec),
    normalised by r^2 (so every point weighs alike), aggregated by ``aggregate`` ("max": min-max, or
    "sum"); the same grid and Nelder-Mead search. ``quick`` (smoke tests): a 2 x 2 grid, 6 evaluations."""
    if aggregate not in ENVELOPE_AGGREGATES:
        raise ValueError(f"aggregate {aggregate!r} is unknown: expected one of {', '.join(ENVELOPE_AGGREGATES)}")
    input_voltage = nominal_supply(binding, input_voltage, "the envelope PI's tuning")
    record_period = record_period_of(binding, record_period, control_period)  # a fixed-step FMU's grid
    points = envelope_points(binding.converter) if points is None else points
    scenarios = [(r, envelope_scenario(r, load, vs)) for r, load, vs in points]
    evaluations = 0
    failures: list[str] = []  # the runs that failed, as their errors say
    worst: dict[tuple[float, float], float] = {}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(desc=f"tuning the envelope PI @ {control_period * 1e6:.4g} us", unit="eval", leave=False)
    with open_plant(binding) as plant:
        for _, scenario in scenarios:  # what the plant refuses whatever the gains, refused before the search
            preflight(plant, scenario)

        def cost(params: np.ndarray) -> float:
            nonlocal evaluations
            a, b = float(params[0]), float(params[1])
            controller = PIController(max(a / input_voltage, 0.0), max(b / (control_period * input_voltage), 0.0),
                                      control_period)
            scores, worst_os = [], 0.0
            for reference, scenario in scenarios:
                try:
                    metrics = run_metrics(run(plant, controller, scenario, record_period=record_period))
                except ConfigError:
                    raise  # the plant refused its set-up: no gains can change that
                except WorkbenchError as error:
                    if plant.fatal:
                        raise
                    failures.append(str(error))
                    return 1e6
                if not math.isfinite(metrics["ise_V2s"]):
                    return 1e6
                excess = max(metrics["overshoot_pct"], metrics["undershoot_pct"]) - OVERSHOOT_LIMIT_PCT
                sse = abs(metrics["steady_state_error_pct"]) - STEADY_STATE_LIMIT_PCT
                scores.append(metrics["ise_V2s"] / reference ** 2 * 1e3 + 0.1 * max(0.0, excess) ** 2
                              + 10.0 * max(0.0, sse) ** 2)
                worst_os = max(worst_os, metrics["overshoot_pct"], metrics["undershoot_pct"])
            evaluations += 1
            worst[(a, b)] = worst_os
            if bar is not None:
                bar.update(1)
            return max(scores) if aggregate == "max" else sum(scores)

        grid = _grid(quick)
        scores = [cost(np.array(p)) for p in grid]
        start = np.array(grid[int(np.argmin(scores))])
        result = minimize(cost, start, method="Nelder-Mead", bounds=[(0.0, 3.0), (1e-4, 1.5)],
                          options={"maxfev": _nelder_mead_evaluations(quick), "xatol": 1e-3, "fatol": 1e-7,
                                   "initial_simplex": [start, start * [1.0, 1.3] + [0.02, 0.0], start * [1.0, 0.8]]})
    if bar is not None:
        bar.close()
    _refuse_if_nothing_ran(evaluations, failures, binding)
    best = result.x if result.fun <= min(scores) else start
    a, b = float(best[0]), float(best[1])
    method = METHOD_ENVELOPE.format(aggregate=aggregate, points=", ".join(f"({r:g}, {R:g}, {v:g})" for r, R, v in points))
    design = design_key("pi-envelope", binding, control_period, scenarios=[s for _, s in scenarios],
                        settings={"method": method, "record_period_s": record_period, "input_voltage_V": input_voltage,
                                  "grid": _grid(quick), "nelder_mead_evaluations": _nelder_mead_evaluations(quick)})
    return PITuning(kp=a / input_voltage, ki=b / (control_period * input_voltage), control_period=control_period,
                    cost=float(min(result.fun, min(scores))), worst_overshoot_pct=float(worst.get((a, b), math.nan)),
                    evaluations=evaluations, plant=binding.label, method=method, design=design.describe())


def cached_tuning(path: Path, binding: PlantBinding, control_period: float, **settings) -> PITuning | None:
    """The gains tuned in ``path`` if they were tuned for exactly this plant, rate and ``settings``
    (those of :func:`tune_pi`: the same design key); else None -- and one line on stderr saying why,
    if a file was there."""
    path = Path(path)
    if not path.is_file():
        return None
    wanted = pi_design(binding, control_period, **settings)
    try:
        tuning = PITuning.from_json(path.read_text(encoding="utf-8"))
        reason = stale_reason(tuning.design, wanted)
    except (ValueError, TypeError, KeyError):
        reason = "it is not a tuning file buck-cosim can read"
    if reason is None:
        return tuning
    announce(path, reason, "re-tuning the PI")
    return None


def load_or_tune(path: Path, binding: PlantBinding, control_period: float, *, progress: bool = False,
                 **settings) -> PITuning:
    """Read tuned gains from ``path`` if they were tuned for this plant, rate and ``settings`` (the
    same design key, :mod:`cosim.design.design_cache`); else tune and save them there."""
    from cosim.base.files import atomic_write_text

    tuning = cached_tuning(path, binding, control_period, **settings)
    if tuning is None:
        tuning = tune_pi(binding, control_period, progress=progress, **settings)
        atomic_write_text(Path(path), tuning.to_json() + "\n")
    return tuning
