"""The converter spec: the one definition of "the converter under study".

A design made for one converter is wrong for another: a PI tuned at 48 V has half the loop gain at 24 V, a network
identified on 4-10 Ohm loads extrapolates at 2.5 Ohm. Every design step and every shipped scenario therefore reads
the operating points it works at from a :class:`ConverterSpec` -- never from the paper's numbers -- and the paper's
Table II is the spec of the built-in plant (:mod:`plant_fmu.table_ii`) and nothing more.

A plant-binding file gives its converter's spec in a ``[converter]`` table (SI units throughout)::

    [converter]
    label = "MyBuck24"                 # optional: how reports and figures name the converter
    input_voltage = 24.0               # [V]   nominal supply  (default: the start value of the input_voltage role)
    output_voltage = 5.0               # [V]   nominal output, the regulated reference
    load_resistance = 3.0              # [Ohm] nominal load    (default: the start value of the load_resistance role)
    input_voltage_range = [20.0, 28.0] # [V]   the operating envelope: supplies ...
    output_voltage_range = [2.0, 8.0]  # [V]   ... references ...
    load_resistance_range = [2.0, 30.0]  # [Ohm] ... and loads
    control_periods = [1e-3, 1e-5]     # [s]   the rates it is controlled at (default: none named)
    duty_limits = [0.0, 0.95]          # [1]   the duty's range (default: [0, 1])
    inductor_current_limit = 8.0       # [A]   optional: the inductor current the design may not exceed

    [converter.circuit]                # optional: the nominal circuit, for the designs that need a model
    inductance = 100e-6                # [H]  a number, or the name of an FMU parameter: inductance = "L"
    capacitance = 47e-6                # [F]
    switching_frequency = 100e3        # [Hz]
    inductor_resistance = 0.0          # [Ohm] parasitics, each 0 unless given
    switch_on_resistance = 0.0         # [Ohm]
    diode_forward_voltage = 0.0        # [V]
    capacitor_esr = 0.0                # [Ohm]

A circuit value given as text names an FMU parameter: its value is the binding's ``[parameters]`` value if it sets
one, else the FMU's start value (``{ parameter = "L_uH", scale = 1e6 }`` for one in other units:
``fmu_value = scale * SI value``). Everything is checked when the file is read: a missing, negative, inverted
(min > max) or unit-confused value (a load in kOhm, a period in ms, an inductance in uH) is refused in one line naming
the file, the key and its line. A key a design needs and neither the spec nor the FMU gives is refused when that design
is asked for (:meth:`ConverterSpec.require`), naming the key -- no design falls back on the paper's numbers.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from fractions import Fraction
from typing import Mapping

from cosim.base.errors import ConfigError
from cosim.base.toml_files import finite_number

#: the operating-point keys: nominal value -> its range key, unit and what it is
OPERATING_KEYS = {
    "input_voltage": ("input_voltage_range", "V", "nominal supply"),
    "output_voltage": ("output_voltage_range", "V", "nominal output voltage (the regulated reference)"),
    "load_resistance": ("load_resistance_range", "Ohm", "nominal load resistance"),
}
#: the circuit keys, their units and what a value in a wrong unit would look like (lowest, highest plausible SI)
CIRCUIT_KEYS = {
    "inductance": ("H", (1e-9, 1.0), "a value in uH or mH?"),
    "capacitance": ("F", (1e-12, 1.0), "a value in uF or nF?"),
    "switching_frequency": ("Hz", (1e3, 1e9), "a value in kHz or MHz?"),
    "inductor_resistance": ("Ohm", (0.0, 100.0), "a value in mOhm?"),
    "switch_on_resistance": ("Ohm", (0.0, 100.0), "a value in mOhm?"),
    "diode_forward_voltage": ("V", (0.0, 10.0), "a value in mV?"),
    "capacitor_esr": ("Ohm", (0.0, 100.0), "a value in mOhm?"),
}
REQUIRED_CIRCUIT = ("inductance", "capacitance", "switching_frequency")
TOP_KEYS = {"label", "input_voltage", "output_voltage", "load_resistance", "input_voltage_range",
            "output_voltage_range", "load_resistance_range", "control_periods", "duty_limits",
            "inductor_current_limit", "circuit"}
#: plausible magnitudes of the operating-point quantities in SI; outside them a value is taken for a unit mix-up
PLAUSIBLE = {"V": (1e-3, 1e4, "a value in mV or kV?"), "Ohm": (1e-3, 1e6, "a load in kOhm or mOhm?")}
#: control periods outside this range [s] are taken for a unit mix-up (ms or us written as s)
PERIOD_RANGE = (1e-8, 0.1)


@dataclass(frozen=True)
class ConverterSpec:
    """The converter under study (SI units): nominal operating point, operating envelope, control periods, limits and
    the optional nominal circuit. A field that is None was given neither by the spec nor by the FMU; a design that
    needs it asks :meth:`require`, which refuses with the key's name."""

    label: str
    input_voltage: float | None = None  # [V]
    output_voltage: float | None = None  # [V]
    load_resistance: float | None = None  # [Ohm]
    input_voltage_range: tuple[float, float] | None = None  # [V]
    output_voltage_range: tuple[float, float] | None = None  # [V]
    load_resistance_range: tuple[float, float] | None = None  # [Ohm]
    control_periods: tuple[float, ...] | None = None  # [s]
    duty_limits: tuple[float, float] = (0.0, 1.0)
    inductor_current_limit: float | None = None  # [A]
    inductance: float | None = None  # [H]
    capacitance: float | None = None  # [F]
    switching_frequency: float | None = None  # [Hz]
    inductor_resistance: float = 0.0  # [Ohm]
    switch_on_resistance: float = 0.0  # [Ohm]
    diode_forward_voltage: float = 0.0  # [V]
    capacitor_esr: float = 0.0  # [Ohm]
    #: where the spec comes from, for messages: "binding file my24.toml [converter]"
    origin: str = "the converter spec"
    #: key -> "file:line" (or how the FMU gave it), for messages; not part of the spec's identity
    places: Mapping[str, str] = field(default_factory=dict, compare=False, repr=False)

    def __reduce__(self):  # a mapping proxy would not pickle (worker processes): plain dicts
        return (_rebuild, (self.identity(), self.origin, dict(self.places)))

    def identity(self) -> dict:
        """The spec's values (JSON-ready): what a design that reads the spec may depend on."""
        values = {}
        for f in fields(self):
            if f.name in ("origin", "places"):
                continue
            value = getattr(self, f.name)
            values[f.name] = list(value) if isinstance(value, tuple) else value
        return values

    def describe(self) -> dict:
        """JSON-ready description for metadata."""
        return {**self.identity(), "origin": self.origin}

    def place(self, key: str) -> str:
        return self.places.get(key) or self.origin

    # -------------------------------------------------------------- what designs ask of it
    def require(self, key: str, purpose: str):
        """The value of ``key``; None there refuses ``purpose`` in one line naming the key (never a default)."""
        value = getattr(self, key)
        if value is None:
            table = "[converter.circuit]" if key in CIRCUIT_KEYS else "[converter]"
            raise ConfigError(f"{self.origin}: {purpose} needs {key}, which neither {table} nor the FMU gives: add it "
                              f"under {table}, e.g. {key} = {_example(key)}")
        return value

    @property
    def switching_period(self) -> float | None:
        """1 / f_sw [s], None without a switching frequency."""
        return None if self.switching_frequency is None else 1.0 / self.switching_frequency

    def circuit(self, purpose: str) -> dict[str, float]:
        """The nominal circuit's values (L, C and the parasitics) for ``purpose``; refused without L or C."""
        self.require("inductance", purpose)
        self.require("capacitance", purpose)
        return {name: getattr(self, name) for name in ("inductance", "capacitance", "inductor_resistance",
                                                        "switch_on_resistance", "diode_forward_voltage",
                                                        "capacitor_esr")}

    def samples_once_per_pwm_period(self, control_period: float) -> bool:
        """True when ``control_period`` [s] is one PWM period of the converter (False where no switching frequency
        is given): the rate of the explicit NNPC, the classical designs, the loop-gain measurement and the map."""
        return self.switching_frequency is not None and abs(control_period * self.switching_frequency - 1) <= 1e-9

    def operating_range(self, key: str, purpose: str) -> tuple[float, float]:
        """The envelope of ``key`` (input_voltage, output_voltage or load_resistance), refused where not given."""
        return self.require(OPERATING_KEYS[key][0], purpose)

    def outside(self, signal: str, value: float) -> str | None:
        """How a scenario value of ``signal`` leaves the spec's range, as a warning's text; None inside or unranged."""
        range_key = OPERATING_KEYS.get("output_voltage" if signal == "reference" else signal, (None,))[0]
        bounds = getattr(self, range_key) if range_key else None
        if bounds is None or signal == "reference" and value == 0.0:  # a rest (0 V) is no operating point
            return None
        low, high = bounds
        if low - 1e-12 * abs(low) <= value <= high + 1e-12 * abs(high):
            return None
        unit = OPERATING_KEYS["output_voltage" if signal == "reference" else signal][1]
        return f"{signal} {value:g} {unit} is outside {self.origin}'s {range_key} [{low:g}, {high:g}] {unit}"

    def resolve(self, template: str, signal: str, where: str) -> float:
        """A scenario template value of ``signal``: ``"nominal"`` or ``"nominal * F"`` (F a number or a fraction a/b),
        the spec's nominal value of the signal times F -- computed in exact fractions, so 6 Ohm * 5/6 is 5 Ohm."""
        factor = parse_template(template, where)
        key = "output_voltage" if signal == "reference" else signal
        nominal = self.require(key, f"{where} ({signal} = {template!r})")
        return float(Fraction(nominal) * factor)


def _rebuild(values: dict, origin: str, places: dict) -> ConverterSpec:
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
    return ConverterSpec(**values, origin=origin, places=places)


def _example(key: str) -> str:
    examples = {"input_voltage": "24.0  # V", "output_voltage": "5.0  # V", "load_resistance": "3.0  # Ohm",
                "input_voltage_range": "[20.0, 28.0]  # V", "output_voltage_range": "[2.0, 8.0]  # V",
                "load_resistance_range": "[2.0, 30.0]  # Ohm", "control_periods": "[1e-3]  # s",
                "inductor_current_limit": "8.0  # A", "inductance": "100e-6  # H (or the FMU parameter's name)",
                "capacitance": "47e-6  # F (or the FMU parameter's name)",
                "switching_frequency": "100e3  # Hz (or the FMU parameter's name)"}
    return examples.get(key, "...")


def parse_template(text: str, where: str) -> Fraction:
    """The factor of a template value ``"nominal"`` / ``"nominal * F"`` (F: a decimal number or a fraction a/b > 0)."""
    body = text.strip()
    if body == "nominal":
        return Fraction(1)
    head, star, factor = body.partition("*")
    if head.strip() != "nominal" or not star:
        raise ConfigError(f"{where}: {text!r} is not a template value: expected a number, \"nominal\" or "
                          "\"nominal * F\" (F a number or a fraction a/b)")
    try:
        value = Fraction(factor.strip())
    except (ValueError, ZeroDivisionError):
        raise ConfigError(f"{where}: {text!r}: the factor {factor.strip()!r} is not a number or a fraction a/b") \
            from None
    if value <= 0:
        raise ConfigError(f"{where}: {text!r}: the factor must be > 0")
    return value


# ---------------------------------------------------------------------------------------------
# Reading a [converter] table


def _plausible(value: float, key: str, unit: str, place: str, strictly_positive: bool = True) -> float:
    if value < 0 or (strictly_positive and value == 0):
        raise ConfigError(f"{place}: {key} = {value:g} {unit} is invalid: expected "
                          f"{'> 0' if strictly_positive else '>= 0'}")
    low, high, hint = PLAUSIBLE[unit]
    if value and not low <= value <= high:
        raise ConfigError(f"{place}: {key} = {value:g} {unit} is implausible: expected {unit} between {low:g} and "
                          f"{high:g} ({hint})")
    return value


def _range(value, key: str, unit: str, place: str) -> tuple[float, float]:
    if not isinstance(value, list) or len(value) != 2:
        raise ConfigError(f"{place}: {key} = {value!r} is invalid: expected [min, max] in {unit}")
    low = _plausible(finite_number(value[0], f"{key}[0]", place), f"{key}[0]", unit, place)
    high = _plausible(finite_number(value[1], f"{key}[1]", place), f"{key}[1]", unit, place)
    if not low < high:
        raise ConfigError(f"{place}: {key} = [{low:g}, {high:g}] {unit} is inverted or empty: expected min < max")
    return (low, high)


def parse_converter_table(table, origin: str, place, defaults: Mapping[str, tuple[float, str]] | None = None,
                          parameter_value=None, label: str = "") -> ConverterSpec:
    """A ``[converter]`` table (module docstring) as a checked :class:`ConverterSpec`.

    ``place(key, table)`` says where a key is (``file:line``); ``defaults``: key -> (value, how the FMU gives it) for
    the nominal supply and load (the start values of the bound inputs); ``parameter_value(name, scale, where)``: the
    SI value of an FMU parameter a circuit key names (the binding's value, else its start value); ``label``: the
    converter's name where the table gives none."""
    if table is None:
        table = {}
    if not isinstance(table, dict):
        raise ConfigError(f"{place(None, None)}: 'converter' must be a table ([converter])")
    for key in table:
        if key not in TOP_KEYS:
            raise ConfigError(f"{place(key, 'converter')}: unknown key 'converter.{key}': expected one of "
                              f"{', '.join(sorted(TOP_KEYS))}")
    values: dict = {}
    places: dict[str, str] = {}
    label = table.get("label", label)
    if not isinstance(label, str) or not label:
        raise ConfigError(f"{place('label', 'converter')}: converter.label must be text")
    for key, (range_key, unit, _) in OPERATING_KEYS.items():
        at = place(key, "converter")
        if key in table:
            values[key] = _plausible(finite_number(table[key], key, at), key, unit, at)
            places[key] = at
        elif defaults and key in defaults:
            values[key], places[key] = defaults[key]
            try:
                _plausible(values[key], key, unit, f"{origin} ({defaults[key][1]})")
            except ConfigError as error:  # the FMU's value, not the user's: say where to give the right one
                raise ConfigError(f"{error}; give converter.{key} in {unit} under [converter]") from None
        if range_key in table:
            at = place(range_key, "converter")
            values[range_key] = _range(table[range_key], range_key, unit, at)
            places[range_key] = at
    if "control_periods" in table:
        at = place("control_periods", "converter")
        periods = table["control_periods"]
        if not isinstance(periods, list) or not periods:
            raise ConfigError(f"{at}: control_periods = {periods!r} is invalid: expected a list of periods in s, "
                              "e.g. [1e-3, 1e-5]")
        checked = []
        for i, period in enumerate(periods):
            value = finite_number(period, f"control_periods[{i}]", at)
            if not PERIOD_RANGE[0] <= value <= PERIOD_RANGE[1]:
                raise ConfigError(f"{at}: control_periods[{i}] = {value:g} s is implausible: expected seconds between "
                                  f"{PERIOD_RANGE[0]:g} and {PERIOD_RANGE[1]:g} (a period in ms or us?)")
            checked.append(value)
        values["control_periods"] = tuple(checked)
        places["control_periods"] = at
    if "duty_limits" in table:
        at = place("duty_limits", "converter")
        limits = table["duty_limits"]
        if not isinstance(limits, list) or len(limits) != 2:
            raise ConfigError(f"{at}: duty_limits = {limits!r} is invalid: expected [min, max] within [0, 1]")
        low, high = (finite_number(v, "duty_limits", at) for v in limits)
        if not 0 <= low < high <= 1:
            raise ConfigError(f"{at}: duty_limits = [{low:g}, {high:g}] is invalid: expected 0 <= min < max <= 1 "
                              "(a duty in percent?)")
        values["duty_limits"] = (low, high)
        places["duty_limits"] = at
    if "inductor_current_limit" in table:
        at = place("inductor_current_limit", "converter")
        value = finite_number(table["inductor_current_limit"], "inductor_current_limit", at)
        if not 0 < value <= 1e4:
            raise ConfigError(f"{at}: inductor_current_limit = {value:g} A is invalid: expected amperes, > 0 and "
                              "<= 10 000 (a current in mA?)")
        values["inductor_current_limit"] = value
        places["inductor_current_limit"] = at
    circuit = table.get("circuit", {})
    if not isinstance(circuit, dict):
        raise ConfigError(f"{place('circuit', 'converter')}: converter.circuit must be a table ([converter.circuit])")
    for key, entry in circuit.items():
        at = place(key, "converter.circuit")
        if key not in CIRCUIT_KEYS:
            raise ConfigError(f"{at}: unknown key 'converter.circuit.{key}': expected one of "
                              f"{', '.join(CIRCUIT_KEYS)}")
        unit, (low, high), hint = CIRCUIT_KEYS[key]
        if isinstance(entry, (str, dict)):
            name, scale = (entry, 1.0) if isinstance(entry, str) else (entry.get("parameter"), entry.get("scale", 1.0))
            if not isinstance(name, str) or (isinstance(entry, dict) and set(entry) - {"parameter", "scale"}):
                raise ConfigError(f"{at}: converter.circuit.{key} = {entry!r} is invalid: expected a number in {unit}, "
                                  "an FMU parameter's name, or { parameter = \"NAME\", scale = FACTOR }")
            scale = finite_number(scale, f"converter.circuit.{key}.scale", at)
            if scale == 0:
                raise ConfigError(f"{at}: converter.circuit.{key}.scale = 0 is invalid: expected a non-zero factor")
            if parameter_value is None:
                raise ConfigError(f"{at}: converter.circuit.{key} names the FMU parameter {name!r}, but this spec "
                                  "has no FMU to read it from: give the value in " + unit)
            value = parameter_value(name, scale, at)
            at = f"{at} (FMU parameter {name!r})"
        else:
            value = finite_number(entry, f"converter.circuit.{key}", at)
        if value < 0 or (key in REQUIRED_CIRCUIT and value == 0):
            raise ConfigError(f"{at}: converter.circuit.{key} = {value:g} {unit} is invalid: expected "
                              f"{'> 0' if key in REQUIRED_CIRCUIT else '>= 0'}")
        if value and not low <= value <= high:
            raise ConfigError(f"{at}: converter.circuit.{key} = {value:g} {unit} is implausible: expected {unit} "
                              f"between {low:g} and {high:g} ({hint})")
        values[key] = value
        places[key] = at
    spec = ConverterSpec(label=label, origin=origin, places=places, **values)
    check_consistent(spec)
    return spec


def check_consistent(spec: ConverterSpec) -> None:
    """The spec's values against each other: each nominal value within its range, and every operating point of the
    envelope within a buck converter's reach (the output at most the largest duty times the supply)."""
    for key, (range_key, unit, _) in OPERATING_KEYS.items():
        value, bounds = getattr(spec, key), getattr(spec, range_key)
        if value is not None and bounds is not None and not bounds[0] <= value <= bounds[1]:
            raise ConfigError(f"{spec.place(key)}: {key} = {value:g} {unit} is outside {range_key} "
                              f"[{bounds[0]:g}, {bounds[1]:g}] {unit}")
    top = spec.duty_limits[1]
    if spec.output_voltage is not None and spec.input_voltage is not None \
            and spec.output_voltage > top * spec.input_voltage:
        raise ConfigError(f"{spec.place('output_voltage')}: output_voltage = {spec.output_voltage:g} V is out of reach "
                          f"of a buck converter at its nominal supply {spec.input_voltage:g} V (at most "
                          f"{top:g} x the supply)")
    outputs, supplies = spec.output_voltage_range, spec.input_voltage_range
    if outputs is not None and supplies is not None and outputs[1] > top * supplies[0]:
        raise ConfigError(f"{spec.place('output_voltage_range')}: the envelope's corner of output {outputs[1]:g} V at "
                          f"supply {supplies[0]:g} V is out of reach of a buck converter (at most {top:g} x the "
                          "supply): lower output_voltage_range's max or raise input_voltage_range's min")
    if outputs is not None and supplies is None and spec.input_voltage is not None \
            and outputs[1] > top * spec.input_voltage:
        raise ConfigError(f"{spec.place('output_voltage_range')}: output {outputs[1]:g} V is out of reach of a buck "
                          f"converter at the nominal supply {spec.input_voltage:g} V")


def with_values(spec: ConverterSpec, **changes) -> ConverterSpec:
    """``spec`` with some values replaced (SI units, ranges as (min, max)), every value checked again as a
    ``[converter]`` table's is: a variant converter in Python (docs/guide/design-api.md)."""
    changed = replace(spec, **changes)
    values = changed.identity()
    table = {k: v for k, v in values.items() if v is not None and k not in CIRCUIT_KEYS}
    table["circuit"] = {k: values[k] for k in CIRCUIT_KEYS if values[k] is not None}
    if table.get("duty_limits") == [0.0, 1.0]:
        del table["duty_limits"]

    def place(key, _table):
        return f"{changed.origin} ({key})" if key else changed.origin

    checked = parse_converter_table(table, changed.origin, place)
    return replace(checked, places={**spec.places, **checked.places})
