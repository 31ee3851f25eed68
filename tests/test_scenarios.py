"""Scenario files: the shipped ones parse; every mistake names file, key and line."""

from __future__ import annotations

import pytest

from cosim.base.errors import ConfigError
from cosim.scenarios import PAPER_SCENARIOS, load_scenario, parse_scenario, shipped_scenarios
from cosim.study.vocabulary import PAPER_SPEC

GOOD = """\
name = "custom"
description = "a user scenario"
duration = 0.05
settle = 0.01

[initial]
reference = 12.0
load_resistance = 6.0

[[events]]
time = 0.02
reference = 15.0

[[events]]
time = 0.01
load_resistance = 5.0
input_voltage = 40.0
"""


def test_shipped_scenarios_are_the_papers_four_plus_extras():
    names = {s.name for s in shipped_scenarios(PAPER_SPEC)}
    assert set(PAPER_SCENARIOS) <= names
    startup = load_scenario("startup", PAPER_SPEC)
    assert startup.initial == {"reference": 12.0, "load_resistance": 6.0, "input_voltage": 48.0}
    assert startup.events == () and startup.metrics_start == 0.0
    load = load_scenario("load_change", PAPER_SPEC)
    assert load.events[0].changes == {"load_resistance": 5.0} and load.required_roles() == {"load_resistance"}
    assert load_scenario("reference_up", PAPER_SPEC).events[0].changes == {"reference": 15.0}
    assert load_scenario("reference_down", PAPER_SPEC).events[0].changes == {"reference": 9.0}
    ageing = load_scenario("capacitor_ageing", PAPER_SPEC)  # the drift study's: the mismatch plant's C and DCR drift
    drift = [e.parameters for e in ageing.parameter_events]
    assert len(drift) == 8 and drift[-1] == pytest.approx({"capacitance": 5.6e-6, "inductor_resistance": 0.3})
    assert all(a["capacitance"] > b["capacitance"] for a, b in zip(drift, drift[1:]))
    assert ageing.metrics_start > max(e.time for e in ageing.parameter_events)


def test_a_user_scenario_parses_with_sorted_events_and_schedules(tmp_path):
    path = tmp_path / "custom.toml"
    path.write_text(GOOD)
    s = load_scenario(path, PAPER_SPEC)
    assert [e.time for e in s.events] == [0.01, 0.02]
    assert s.schedule("reference") == [(0.0, 12.0), (0.02, 15.0)]
    assert s.schedule("input_voltage") == [(0.0, 48.0), (0.01, 40.0)]
    assert s.required_roles() == {"load_resistance", "input_voltage"}
    assert s.metrics_start == 0.01 and s.source == path


def write(tmp_path, text):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("edit,message", [
    (("settle = 0.01", "setle = 0.01"), r"bad.toml:4: unknown key 'setle'"),
    (("load_resistance = 6.0", "load = 6.0"), r"bad.toml:8: unknown key 'initial.load'"),
    (("reference = 15.0", "refrence = 15.0"), r"bad.toml:12: unknown key 'events\[0\].refrence'"),
    (("duration = 0.05", 'duration = "long"'), r"bad.toml:3: duration = 'long' has the wrong type: expected a number"),
    (("duration = 0.05", "duration = -0.05"), r"bad.toml:3: duration = -0.05 s is invalid: expected > 0"),
    (("settle = 0.01", "settle = -1"), r"bad.toml:4: settle = -1.0 s is negative"),
    (("time = 0.02", "time = 0.08"), r"bad.toml:11: events\[0\].time = 0.08 s is at or after the end of the scenario"),
    (("time = 0.02", "time = -0.01"), r"bad.toml:11: events\[0\].time = -0.01 s is negative"),
    (("load_resistance = 5.0", "load_resistance = 0"), r"bad.toml:16: events\[1\].load_resistance = 0.0 Ohm is invalid"),
    (("reference = 12.0", "reference = true"), r"bad.toml:7: initial.reference = True has the wrong type"),
    (("name = \"custom\"", "name = \"has space\""), r"bad.toml:1: name = 'has space' is invalid"),
    (("duration = 0.05", "duration = 0.05\nduration = 0.06"), r"bad.toml: invalid TOML"),
])
def test_mistakes_name_file_key_and_line(tmp_path, edit, message):
    path = write(tmp_path, GOOD.replace(*edit, 1))
    with pytest.raises(ConfigError, match=message):
        load_scenario(path, PAPER_SPEC)


def test_event_without_changes_and_missing_keys(tmp_path):
    with pytest.raises(ConfigError, match=r"bad.toml:10: events\[0\] changes nothing"):
        load_scenario(write(tmp_path, GOOD.replace("reference = 15.0\n", "")), PAPER_SPEC)
    with pytest.raises(ConfigError, match=r"missing required key 'duration'"):
        load_scenario(write(tmp_path, GOOD.replace("duration = 0.05\n", "")), PAPER_SPEC)
    with pytest.raises(ConfigError, match=r"missing required key 'initial.reference'"):
        load_scenario(write(tmp_path, GOOD.replace("reference = 12.0\n", "")), PAPER_SPEC)


def test_a_scenario_saved_with_a_byte_order_mark_reads_as_without_one(tmp_path):
    """Windows editors save UTF-8 with a BOM; tomllib refused it as an "invalid statement" at line 1."""
    plain = load_scenario(write(tmp_path, GOOD), PAPER_SPEC)
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + GOOD.encode("utf-8"))
    again = load_scenario(path, PAPER_SPEC)
    assert again.events == plain.events and again.duration == plain.duration
    with pytest.raises(ConfigError, match=r"bom.toml:10: events\[0\] changes nothing"):  # its lines count as before
        path.write_bytes(b"\xef\xbb\xbf" + GOOD.replace("reference = 15.0\n", "").encode("utf-8"))
        load_scenario(path, PAPER_SPEC)


def test_two_changes_of_one_signal_at_one_instant_are_refused(tmp_path):
    """The later line used to win silently (12 -> 9 V, the 15 V event dropped); a change of two different signals at
    one instant stays fine."""
    same = ('name = "x"\nduration = 0.02\n[initial]\nreference = 12.0\n[[events]]\ntime = 0.005\nreference = 15.0\n'
            '[[events]]\ntime = 0.005\nreference = 9.0\n')
    with pytest.raises(ConfigError, match=r"^\S*bad.toml:9: events\[1\] sets reference at t = 0.005 s, as events\[0\] "
                                          r"does: one of the two would be dropped"):
        load_scenario(write(tmp_path, same), PAPER_SPEC)
    both = load_scenario(write(tmp_path, same.replace("reference = 9.0", "load_resistance = 9.0")), PAPER_SPEC)
    assert [dict(e.changes) for e in both.events] == [{"reference": 15.0}, {"load_resistance": 9.0}]


def test_unknown_scenario_name_lists_the_shipped_ones():
    with pytest.raises(ConfigError, match=r"'nope' is neither a file nor a shipped scenario \(capacitor_ageing, load_change"):
        load_scenario("nope", PAPER_SPEC)


def test_analysis_start_must_be_inside_the_run():
    with pytest.raises(ConfigError, match=r"analysis_start = 1.0 s is outside"):
        parse_scenario('name = "x"\nduration = 0.1\nanalysis_start = 1.0\n[initial]\nreference = 1.0\n',
                       spec=PAPER_SPEC)


# ------------------------------------------------------------------------------------------ parameter events

DRIFT = """\
name = "drift"
duration = 0.02

[initial]
reference = 12.0

[[events]]
time = 0.005
reference = 13.0

[[events]]
time = 0.01
parameters = { capacitance = 7e-6, inductor_resistance = 0.3 }
"""


def test_parameter_events_parse_with_their_line(tmp_path):
    path = tmp_path / "drift.toml"
    path.write_text(DRIFT)
    s = load_scenario(path, PAPER_SPEC)
    event = s.events[1]
    assert event.parameters == {"capacitance": 7e-6, "inductor_resistance": 0.3} and event.changes == {}
    assert event.where == f"{path}:13" and event.plant_event and not s.events[0].plant_event
    assert s.parameter_events == (event,) and s.required_roles() == set()
    assert s.describe()["events"][1] == {"time_s": 0.01, "parameters": {"capacitance": 7e-6, "inductor_resistance": 0.3}}


@pytest.mark.parametrize("value,message", [
    ('{ capacitance = "big" }', r"drift.toml:13: events\[1\].parameters.capacitance = 'big' has the wrong type"),
    ("{ capacitance = nan }", r"drift.toml:13: events\[1\].parameters.capacitance = nan is not finite"),
    ("{ capacitance = inf }", r"drift.toml:13: events\[1\].parameters.capacitance = inf is not finite"),
    ("{ capacitance = true }", r"drift.toml:13: events\[1\].parameters.capacitance = True has the wrong type"),
    ("{}", r"drift.toml:13: events\[1\].parameters is empty"),
    ("7e-6", r"drift.toml:13: events\[1\].parameters = 7e-06 has the wrong type: expected a table"),
])
def test_parameter_event_mistakes_name_file_key_and_line(tmp_path, value, message):
    path = tmp_path / "drift.toml"
    path.write_text(DRIFT.replace("{ capacitance = 7e-6, inductor_resistance = 0.3 }", value))
    with pytest.raises(ConfigError, match=message):
        load_scenario(path, PAPER_SPEC)


@pytest.mark.parametrize("parameters,message", [
    ("{ switching_frequency = 50e3 }", r"drift.toml:13: events\[1\].parameters.switching_frequency: "
                                       r"'switching_frequency' is a fixed parameter; only tunable Real parameters"),
    ("{ capacitor = 7e-6 }", r"drift.toml:13: events\[1\].parameters.capacitor: plant FMU .* has no variable "
                             r"'capacitor' \(tunable: capacitance, capacitor_esr, diode_forward_voltage"),
    ("{ load_resistance = 5.0 }", r"'load_resistance' is a continuous input"),
    ("{ inductor_resistance = -0.1 }", r"events\[1\].parameters.inductor_resistance = -0.1 Ohm is outside the range "
                                       r"the FMU declares \[0, inf\]"),
])
def test_parameter_events_the_fmu_cannot_take_are_refused_before_the_run(tmp_path, parameters, message):
    from cosim.batch import Batch
    from cosim.fmi.binding import builtin_binding

    path = tmp_path / "drift.toml"
    path.write_text(DRIFT.replace("{ capacitance = 7e-6, inductor_resistance = 0.3 }", parameters))
    with pytest.raises(ConfigError, match=message):
        Batch(builtin_binding("averaged"), [load_scenario(path, PAPER_SPEC)])
