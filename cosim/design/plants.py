"""The built-in buck FMU as the study's plants: the nominal and the mismatch-study circuit, averaged or switched,
behind an averaging or a synchronous sensor.

Its own module, away from the controllers' factories (:mod:`cosim.design.experiments`): a command that only needs the
plant -- and one that refuses a bad scenario, binding or rate before any work -- does not load torch."""

from __future__ import annotations

from dataclasses import replace

from cosim.base.errors import ConfigError
from cosim.design.vocabulary import PLANT_VARIANTS, SENSORS, plant_tag
from cosim.fmi.binding import PlantBinding, RoleMap, builtin_binding


def plant_binding(variant: str, mode: str, sensor: str = "average") -> PlantBinding:
    """The built-in FMU as the nominal or the mismatch-study plant, averaged or switched.

    ``sensor``: "average" -- controllers read the mean over the last PWM period (an averaging
    ADC: no ripple error, half a period of lag); "synchronous" -- a point sample at the carrier's
    peak with centre-aligned PWM, i.e. mid off-time, where iL equals its mean (no lag, but vo is at
    its ripple crest).
    """
    if variant not in PLANT_VARIANTS:
        raise ConfigError(f"plant variant {variant!r} is unknown: expected one of {', '.join(PLANT_VARIANTS)}")
    if sensor not in SENSORS:
        raise ConfigError(f"sensor {sensor!r} is unknown: expected one of {', '.join(SENSORS)}")
    p = PLANT_VARIANTS[variant]
    parameters = {"inductance": p.inductance, "capacitance": p.capacitance,
                  "inductor_resistance": p.inductor_resistance, "switch_on_resistance": p.switch_on_resistance,
                  "diode_forward_voltage": p.diode_forward_voltage, "capacitor_esr": p.capacitor_esr}
    binding = builtin_binding(mode, parameters)
    if sensor == "synchronous":
        roles = dict(binding.roles)
        roles["measured_output_voltage"] = RoleMap("output_voltage")
        roles["measured_inductor_current"] = RoleMap("inductor_current")
        roles["measured_load_current"] = RoleMap("load_current")
        binding = replace(binding, roles=roles, parameters={**binding.parameters, "pwm_carrier": 1})
    suffix = "" if sensor == "average" else ", synchronous sampling"
    return replace(binding, label=f"BuckConverter ({variant}, {mode}{suffix})",
                   tag_override=plant_tag(variant, mode, sensor))
