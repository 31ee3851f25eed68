"""Where a run leaves the operating ranges its network-based controllers were identified over.

A network identified on 48 V data with 4-10 Ohm loads extrapolates at 24 V and 2.5 Ohm: its predictions there are
guesses, and an NNPC planning on them can overshoot where a PI does not. A network records the ranges its data were
drawn over (``data_domain`` in its predictor's description, :func:`controllers.predictors.data_domain`); before a run,
:func:`outside_data_domain` compares the scenario's supplies, load conductances and references with them, and the run
warns once, in one line, and records what it found in its metadata (``outside_data_domain``).
"""

from __future__ import annotations

import sys

from controllers.predictors import DOMAIN_UNITS

#: a value within this relative distance of a bound counts as inside (the bounds are decimal numbers)
TOLERANCE = 1e-9


def _domain_of(controller) -> dict | None:
    try:
        description = controller.describe()
    except Exception:  # a user's controller whose describe() fails has no domain to check here
        return None
    # the NNPC's predictor; the adaptive NNPC's inner NNPC's; the explicit NNPC's expert (the network it imitates:
    # its predictor's description, as the policy file records it)
    if not isinstance(description, dict):
        return None
    inner, expert = description.get("inner"), description.get("expert")
    for predictor in (description.get("predictor"), inner.get("predictor") if isinstance(inner, dict) else None,
                      expert):
        if isinstance(predictor, dict) and predictor.get("data_domain"):
            return predictor["data_domain"]
    return None


def outside_data_domain(controller, scenario) -> list[dict]:
    """Each operating signal of ``scenario`` (supply, load conductance 1/R, nonzero references) outside the data
    domain of ``controller``'s network, as ``{"signal", "value", "unit", "range"}`` with its farthest value; [] for
    a controller without a network or one that records no domain."""
    domain = _domain_of(controller)
    if not domain:
        return []
    values = {"input_voltage": [v for _, v in scenario.schedule("input_voltage")],
              "load_conductance": [1.0 / v for _, v in scenario.schedule("load_resistance")],
              "reference": [v for _, v in scenario.schedule("reference") if v != 0.0]}
    found = []
    for signal, seen in values.items():
        if signal not in domain or not seen:
            continue
        low, high = domain[signal]
        slack = TOLERANCE * max(abs(low), abs(high))
        outside = [v for v in seen if v < low - slack or v > high + slack]
        if outside:
            farthest = max(outside, key=lambda v: max(low - v, v - high))
            found.append({"signal": signal, "value": farthest, "unit": DOMAIN_UNITS[signal], "range": [low, high]})
    return found


def domain_warning(controller_name: str, scenario_name: str, found: list[dict]) -> str:
    """The one warning line of a run that leaves its network's data domain."""
    parts = [f"{f['signal']} {f['value']:.4g} {f['unit']} (data {f['range'][0]:.4g}-{f['range'][1]:.4g} {f['unit']})"
             for f in found]
    return (f"warning: {controller_name} on {scenario_name} runs outside its network's identification data: "
            f"{', '.join(parts)} -- its predictions extrapolate there (identify it on this converter's operating "
            "points: the binding's [converter] table)")


def checked_metadata(controller, scenario, extra: dict | None) -> dict | None:
    """``extra`` run metadata with ``outside_data_domain`` added where the run leaves its network's data domain (and
    the warning line printed on stderr); ``extra`` unchanged otherwise."""
    found = outside_data_domain(controller, scenario)
    if not found:
        return extra
    print(domain_warning(getattr(controller, "name", type(controller).__name__), scenario.name, found),
          file=sys.stderr)
    return {**(extra or {}), "outside_data_domain": found}
