"""Training data for the NN plant model, collected as in the paper (Section IV).

The PI loop drives the plant FMU while the output-voltage reference and the load take random
values held for random intervals (some references are 0 V, so the data holds repeated start-ups
from rest); every control period one sample is kept: the measured
inductor current and output voltage, and the duty applied until the next sample (the paper's
3 x 10 000 matrix of iL, vc, d), plus reference, load, supply and load current. A small seeded
random dither on the PI's duty (``excitation``) widens the data beyond the PI's own trajectories,
which the optimizer will explore; set it to 0 for the paper's plain PI data.

Two more settings make the data cover an operating envelope (the 13.33 us recipe,
:func:`cosim.design.experiments.collection_settings`): ``input_voltage_range`` draws the supply as a
third held random level (uniform), and ``dither = "am-prbs"`` replaces the white Gaussian dither by an
amplitude-modulated random binary sequence -- a level +-a held for a random ``dither_hold`` samples,
a new amplitude a ~ U(0, ``excitation``) at every flip -- whose energy sits at and below the LC
resonance (a white dither at 75 kHz puts most of its power far above it, where the plant filters it
away) and whose held full-amplitude runs are the full-duty and braking moves the NNPC plans.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from fractions import Fraction

import numpy as np
import pandas as pd

from controllers.base import Measurement, check_duty_limits
from controllers.load_estimate import conductance_series
from cosim.base.errors import ConfigError, RunInterrupted
from cosim.converter_spec import ConverterSpec
from cosim.fmi.binding import PlantBinding
from cosim.fmi.plant import open_plant
from cosim.master import run
from cosim.recorder import UNITS
from cosim.results import write_parquet
from cosim.scenarios import Scenario, ScenarioEvent

SAMPLE_COLUMNS = ("time", "measured_inductor_current", "measured_output_voltage", "duty_cycle", "reference",
                  "load_resistance", "input_voltage", "load_current", "measured_load_current", "load_conductance",
                  "inductor_current", "output_voltage")


MIN_SAMPLES = 100  # a data set smaller than this cannot be split into training, validation and test
MAX_EXCITATION = 0.5  # [1] a dither this large would be the signal, not a perturbation of the PI
#: the dither's shapes: white Gaussian (standard deviation ``excitation``) or the amplitude-modulated random
#: binary sequence (levels +-a, a ~ U(0, ``excitation``), each held ``dither_hold`` samples)
DITHERS = ("gaussian", "am-prbs")


@dataclass(frozen=True)
class CollectionSettings:
    samples: int = 10_000
    #: [V], uniform; None: the paper's region of the plant's converter (:func:`paper_region`)
    reference_range: tuple[float, float] | None = None
    load_range: tuple[float, float] | None = None  # [Ohm], log-uniform; None: as reference_range
    hold_range: tuple[int, int] = (5, 40)  # control periods a random level is held, uniform
    excitation: float = 0.01  # standard deviation of the duty dither [1]
    rest_probability: float = 0.15  # chance that a new reference level is 0 V, so start-ups recur
    #: [V] the supply (its first level with input_voltage_range); None: the converter's nominal supply
    input_voltage: float | None = None
    seed: int = 0
    input_voltage_range: tuple[float, float] | None = None  # [V], uniform held levels; None: the supply is fixed
    dither: str = "gaussian"  # one of DITHERS
    dither_hold: tuple[int, int] = (1, 1)  # samples an am-prbs level is held, uniform

    def check_region(self) -> None:
        """The region's values are given (``collect`` takes what is left out from the plant's converter spec)."""
        for key in ("reference_range", "load_range", "input_voltage"):
            if getattr(self, key) is None:
                raise ConfigError(f"collection settings: {key} is not given (collect() takes it from the plant's "
                                  "converter spec)")

    def check(self) -> None:
        self.check_region()
        if self.samples < MIN_SAMPLES:
            raise ConfigError(f"samples = {self.samples} is too few: expected >= {MIN_SAMPLES}")
        lo, hi = self.reference_range
        if not 0 <= lo < hi:
            raise ConfigError(f"reference range ({lo}, {hi}) V is invalid: expected 0 <= min < max")
        lo, hi = self.load_range
        if not 0 < lo < hi:
            raise ConfigError(f"load range ({lo}, {hi}) Ohm is invalid: expected 0 < min < max")
        lo, hi = self.hold_range
        if not 1 <= lo <= hi:
            raise ConfigError(f"hold range ({lo}, {hi}) periods is invalid: expected 1 <= min <= max")
        if not 0 <= self.excitation < MAX_EXCITATION:
            raise ConfigError(f"excitation = {self.excitation} is invalid: expected 0 <= sigma < {MAX_EXCITATION}")
        if not 0 <= self.rest_probability < 1:
            raise ConfigError(f"rest_probability = {self.rest_probability} is invalid: expected 0 <= p < 1")
        if self.input_voltage_range is not None:
            lo, hi = self.input_voltage_range
            if not 0 < lo < hi:
                raise ConfigError(f"input voltage range ({lo}, {hi}) V is invalid: expected 0 < min < max")
        if self.dither not in DITHERS:
            raise ConfigError(f"dither {self.dither!r} is unknown: expected one of {', '.join(DITHERS)}")
        lo, hi = self.dither_hold
        if not 1 <= lo <= hi:
            raise ConfigError(f"dither hold ({lo}, {hi}) samples is invalid: expected 1 <= min <= max")


#: the paper's experiment scaled to a converter: references from 0 V (rests) to the envelope's highest output, loads
#: from the envelope's smallest to this many times the nominal load (Table II: 0-20 V and 4-10 Ohm at 48 V)
PAPER_LOAD_FACTOR = Fraction(5, 3)


def paper_region(spec: ConverterSpec) -> dict:
    """The paper's identification region (Section IV) for the converter ``spec``: reference_range 0 V to the top of its
    output range, load_range from its smallest load to :data:`PAPER_LOAD_FACTOR` x its nominal load (at most its
    largest), the supply at its nominal value -- on Table II exactly the paper's 0-20 V, 4-10 Ohm at 48 V."""
    purpose = "the identification data's region"
    top = spec.operating_range("output_voltage", purpose)[1]
    low, high = spec.operating_range("load_resistance", purpose)
    nominal_load = spec.require("load_resistance", purpose)
    return {"reference_range": (0.0, top), "load_range": (low, min(float(Fraction(nominal_load) * PAPER_LOAD_FACTOR),
                                                                    high)),
            "input_voltage": float(spec.require("input_voltage", purpose))}


def completed(settings: CollectionSettings, spec: ConverterSpec) -> CollectionSettings:
    """``settings`` with the region values it leaves out (None) from the converter ``spec`` (:func:`paper_region`)."""
    missing = [key for key in ("reference_range", "load_range", "input_voltage") if getattr(settings, key) is None]
    if not missing:
        return settings
    region = paper_region(spec)
    return replace(settings, **{key: region[key] for key in missing})


def random_scenario(settings: CollectionSettings, control_period: float, vary_load: bool = True,
                    vary_supply: bool = True) -> Scenario:
    """Random references and loads (and supplies, with ``input_voltage_range``) held for random whole
    numbers of control periods, each signal on its own schedule.

    ``vary_load=False`` (a plant bound without a load input) keeps the load at its initial value;
    ``vary_supply=False`` (one bound without a supply input) the supply at ``input_voltage``.
    """
    settings.check_region()
    rng = np.random.default_rng(settings.seed)
    duration = (settings.samples - 1) * control_period

    def level(kind: str) -> float:
        if kind == "reference":
            value = float(rng.uniform(*settings.reference_range))
            return 0.0 if rng.random() < settings.rest_probability else value
        if kind == "supply":
            return float(rng.uniform(*settings.input_voltage_range))
        lo, hi = settings.load_range
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))

    initial = {"reference": level("reference"), "load_resistance": level("load"),
               "input_voltage": settings.input_voltage}
    changes: dict[int, dict[str, float]] = {}
    signals = (("reference", "reference"), ("load", "load_resistance")) if vary_load else (("reference", "reference"),)
    if settings.input_voltage_range is not None and vary_supply:  # drawn after the others: theirs stay as they were
        signals += (("supply", "input_voltage"),)
    for kind, key in signals:
        k = 0
        while True:
            k += int(rng.integers(settings.hold_range[0], settings.hold_range[1] + 1))
            if k >= settings.samples - 1:
                break
            changes.setdefault(k, {})[key] = level(kind)
    events = tuple(ScenarioEvent(time=k * control_period, changes=c) for k, c in sorted(changes.items()))
    return Scenario(name="identification", description="random references and loads (paper Section IV)",
                    duration=duration, initial=initial, events=events)


class DitheredController:
    """Wraps a controller and adds a seeded dither to its duty (clipped to the limits): white Gaussian
    noise of standard deviation ``sigma``, or (``shape = "am-prbs"``) levels +-a, a ~ U(0, ``sigma``), each
    held a random number of samples in ``hold`` (module docstring)."""

    def __init__(self, inner, sigma: float, seed: int, shape: str = "gaussian", hold: tuple[int, int] = (1, 1)):
        self.inner = inner
        self.sigma = sigma
        self.seed = seed
        self.shape = shape
        self.hold = hold
        self.name = f"{inner.name}+dither"
        self.sample_period = inner.sample_period
        self.duty_limits = check_duty_limits(inner.duty_limits, self.name)
        self.reset()

    def reset(self) -> None:
        self.inner.reset()
        self._rng = np.random.default_rng(self.seed + 1)
        self._level, self._left = 0.0, 0

    def _dither(self) -> float:
        if self.shape == "gaussian":
            return self.sigma * float(self._rng.standard_normal())
        if self._left == 0:  # a new level: the other sign, a new amplitude, a new hold
            sign = -1.0 if self._level > 0 else 1.0
            self._level = sign * self.sigma * float(self._rng.random())
            self._left = int(self._rng.integers(self.hold[0], self.hold[1] + 1))
        self._left -= 1
        return self._level

    def step(self, measurement: Measurement) -> float:
        duty = self.inner.step(measurement)
        if self.sigma:
            duty += self._dither()
        low, high = self.duty_limits
        return min(max(duty, low), high)

    def describe(self) -> dict:
        shape = {} if self.shape == "gaussian" else {"shape": self.shape, "hold": list(self.hold)}
        return {"type": "dithered", "name": self.name, "sigma": self.sigma, "seed": self.seed, **shape,
                "duty_limits": list(self.duty_limits), "inner": self.inner.describe()}


def collect(binding: PlantBinding, controller, settings: CollectionSettings = CollectionSettings(),
            progress: bool = False) -> pd.DataFrame:
    """Run the identification experiment; return one row per control sample (:data:`SAMPLE_COLUMNS`). Region values
    ``settings`` leaves out come from the plant's converter spec (:func:`completed`)."""
    settings = completed(settings, binding.converter)
    settings.check()
    period = controller.sample_period
    scenario = random_scenario(settings, period, vary_load=binding.has("load_resistance"),
                               vary_supply=binding.has("input_voltage"))
    dithered = DitheredController(controller, settings.excitation, settings.seed, settings.dither, settings.dither_hold)
    with open_plant(binding) as plant:
        try:
            result = run(plant, dithered, scenario, record_period=period, seed=settings.seed, progress=progress)
        except RunInterrupted as stop:  # a partial data set would bias the identification: keep nothing
            at = stop.partial.frame["time"].iloc[-1] if stop.partial is not None and len(stop.partial.frame) else 0.0
            raise RunInterrupted(f"data collection interrupted at t = {at:.6g} s of "
                                 f"{scenario.duration:.6g} s; no data file written") from None
    frame = result.frame[result.frame["control_sample"]].reset_index(drop=True)
    # the controller's own load estimate, sample by sample, so the network learns the feature it is fed
    frame["load_conductance"] = conductance_series(frame["measured_output_voltage"].to_numpy(),
                                                   frame["measured_load_current"].to_numpy(),
                                                   frame["measured_inductor_current"].to_numpy(),
                                                   initial=1.0 / binding.converter.require(
                                                       "load_resistance", "the load estimate's start"))
    frame = frame[list(SAMPLE_COLUMNS)]
    frame.attrs["metadata"] = {
        "description": "NN identification data: one row per control sample (paper Section IV)",
        "plant": binding.label,
        "binding": binding.describe(),
        "control_period_s": period,
        "collection": asdict(settings),
        "controller": dithered.describe(),
        "units": {**{c: UNITS.get(c, "") for c in SAMPLE_COLUMNS}, "load_conductance": "S"},
    }
    return frame


def save_samples(frame: pd.DataFrame, path) -> None:
    write_parquet(frame, frame.attrs.get("metadata", {}), path)
