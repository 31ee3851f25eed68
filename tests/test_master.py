"""The co-simulation master: CS vs ME, zero-order hold, event timing, multi-rate grids, faults."""

from __future__ import annotations

import math
import re
from dataclasses import replace

import numpy as np
import pytest
from conftest import VS, C, L, R
from scipy.linalg import expm

from controllers.base import Measurement
from controllers.pi import PIController
from cosim.base.errors import ConfigError
from cosim.fmi.binding import RoleMap, builtin_binding
from cosim.fmi.plant import open_plant
from cosim.master import RunFailed, run, simulate
from cosim.scenarios import load_scenario, parse_scenario
from cosim.study.vocabulary import PAPER_SPEC
from cosim.timeline import CONTROL, EVENT, RECORD, build_timeline

DEADBEAT_KI = 0.7 / (VS * 1e-3)  # integral pole 0.3 at 1 ms


class Probe:
    """A controller that returns a fixed duty schedule and remembers what it measured."""

    name = "probe"
    duty_limits = (0.0, 1.0)

    def __init__(self, sample_period=1e-3, duty=lambda k: 0.25):
        self.sample_period = sample_period
        self.duty = duty
        self.seen: list[Measurement] = []

    def reset(self):
        self.seen = []

    def step(self, measurement):
        self.seen.append(measurement)
        return self.duty(len(self.seen) - 1)

    def describe(self):
        return {"type": "probe", "name": self.name, "duty_limits": list(self.duty_limits)}


def scenario(text_events="", duration=0.02, settle=0.0, reference=12.0):
    return parse_scenario(f"""
name = "test"
duration = {duration}
settle = {settle}
[initial]
reference = {reference}
{text_events}
""", spec=PAPER_SPEC)


@pytest.fixture(scope="module")
def averaged():
    return builtin_binding("averaged")


def test_cs_and_me_agree_on_a_pi_start_up(averaged):
    pi = PIController(0.0, DEADBEAT_KI, 1e-3)
    startup = load_scenario("startup", PAPER_SPEC)
    cs = simulate(averaged, pi, startup, interface="cs").frame
    me = simulate(averaged, pi, startup, interface="me", relative_tolerance=1e-9).frame
    assert len(cs) == len(me)
    np.testing.assert_allclose(me["output_voltage"], cs["output_voltage"], rtol=1e-3, atol=1e-3 * 12)
    np.testing.assert_allclose(me["inductor_current"], cs["inductor_current"], rtol=1e-3, atol=1e-3 * 2)
    np.testing.assert_allclose(me["duty_cycle"], cs["duty_cycle"], rtol=1e-6)  # same decisions at every sample


def test_switched_cs_and_me_agree_on_a_pi_start_up():
    binding = builtin_binding("switched")
    pi = PIController(0.0, DEADBEAT_KI, 1e-3)
    short = replace(load_scenario("startup", PAPER_SPEC), duration=0.006)
    cs = simulate(binding, pi, short, interface="cs").frame
    me = simulate(binding, pi, short, interface="me", relative_tolerance=1e-9).frame
    np.testing.assert_allclose(me["output_voltage"], cs["output_voltage"], rtol=1e-3, atol=1e-3 * 12)


def test_duty_is_held_between_samples_and_the_plant_sees_exactly_that(averaged):
    probe = Probe(duty=lambda k: 0.25 if k < 5 else 0.3)
    frame = simulate(averaged, probe, scenario(duration=0.01)).frame
    control = frame[frame["control_sample"]]
    assert np.allclose(control["time"], np.arange(11) * 1e-3)
    # held: within each control period the duty column is constant
    period = np.floor(frame["time"].to_numpy() / 1e-3 + 1e-9)
    for k in range(10):
        assert frame["duty_cycle"][period == k].nunique() == 1
    # and the plant integrated eq. 3 with that held duty: compare one period with expm
    a = np.array([[0.0, -1.0 / L], [1.0 / C, -1.0 / (R * C)]])
    rows = frame[(frame["time"] >= 5e-3 - 1e-12) & (frame["time"] <= 6e-3 + 1e-12)]
    x0 = rows[["inductor_current", "output_voltage"]].to_numpy()[0]
    b = np.array([0.3 * VS / L, 0.0])
    x_eq = -np.linalg.solve(a, b)
    expected = np.array([x_eq + expm(a * (t - 5e-3)) @ (x0 - x_eq) for t in rows["time"]])
    np.testing.assert_allclose(rows[["inductor_current", "output_voltage"]].to_numpy(), expected, rtol=1e-9)


def test_reference_events_reach_the_controller_at_the_next_sample(averaged):
    probe = Probe()
    text = "[[events]]\ntime = 0.0105\nreference = 15.0\n"
    frame = simulate(averaged, probe, scenario(text)).frame
    seen = {round(m.time * 1e3): m.reference for m in probe.seen}
    assert seen[10] == 12.0 and seen[11] == 15.0
    at = frame.set_index(frame["time"].round(9))["reference"]
    assert at[0.01049] == 12.0 and at[0.0105] == 15.0  # the recorded reference steps at the event time


def test_load_events_act_on_the_plant_at_their_exact_time(averaged):
    text = "[[events]]\ntime = 0.01003\nload_resistance = 3.0\n"  # between recording points
    frame = simulate(averaged, Probe(), scenario(text)).frame
    row = frame[np.isclose(frame["time"], 0.01003, atol=1e-12)]
    assert len(row) == 1  # the event instant was added to the grid
    assert row["load_resistance"].iloc[0] == 3.0
    assert row["load_current"].iloc[0] == pytest.approx(row["output_voltage"].iloc[0] / 3.0, rel=1e-12)
    before = frame[frame["time"] < 0.01003 - 1e-12].iloc[-1]
    assert before["load_resistance"] == 6.0


def test_periods_that_do_not_divide_each_other_are_merged():
    s = scenario(duration=0.001)
    timeline = build_timeline(s, 1 / 75e3, 1e-5)
    control = timeline.times[(timeline.flags & CONTROL) != 0]
    record = timeline.times[(timeline.flags & RECORD) != 0]
    assert len(control) == 76 and len(record) == 101
    assert np.all(np.diff(timeline.times) > 0)
    both = (timeline.flags & (CONTROL | RECORD)) == (CONTROL | RECORD)
    assert np.isclose(timeline.times[both], np.arange(0, 0.001 + 1e-12, 4e-5)).all()  # lcm = 40 us


def test_every_control_sample_is_recorded_with_its_compute_time(averaged):
    pi = PIController(0.02, 170.0, 1 / 75e3)
    frame = simulate(averaged, pi, scenario(duration=0.002), record_period=1e-5).frame
    control = frame[frame["control_sample"]]
    assert len(control) == 151
    assert control["controller_compute_time"].notna().all()
    assert frame.loc[~frame["control_sample"], "controller_compute_time"].isna().all()
    assert np.all(np.diff(frame["time"]) > 0)


def test_settle_interval_is_not_recorded_and_shifts_time(averaged):
    pi = PIController(0.0, DEADBEAT_KI, 1e-3)
    result = simulate(averaged, pi, load_scenario("load_change", PAPER_SPEC))
    frame = result.frame
    assert frame["time"].iloc[0] == 0.0
    assert frame["output_voltage"].iloc[0] == pytest.approx(12.0, abs=0.01)  # settled before t = 0
    assert result.metadata["scenario"]["settle_s"] == 0.015


def test_event_timeline_marks_plant_events():
    s = scenario("[[events]]\ntime = 0.0025\nload_resistance = 5.0\n[[events]]\ntime = 0.003\nreference = 9.0\n")
    timeline = build_timeline(s, 1e-3, 1e-4)
    events = timeline.times[(timeline.flags & EVENT) != 0]
    assert events.tolist() == [0.0025]  # reference changes are not plant events


def test_invalid_periods_are_refused():
    with pytest.raises(ConfigError, match="control period = 0.0 s is invalid"):
        build_timeline(scenario(), 0.0, 1e-5)
    with pytest.raises(ConfigError, match="record period = -1e-05 s is invalid"):
        build_timeline(scenario(), 1e-3, -1e-5)
    with pytest.raises(ConfigError, match="instants; the limit is"):
        build_timeline(scenario(duration=100.0), 1e-3, 1e-7)


def test_a_period_below_100_ns_is_taken_for_a_unit_slip():
    """1e-9 s for 1 us would make 3e7 steps of a 30 ms scenario (gigabytes before anything is written): refused, the
    message asking about the unit; 100 ns itself is accepted."""
    from cosim.timeline import plan_timeline

    with pytest.raises(ConfigError, match=r"^control period = 1e-09 s is invalid: expected >= 1e-07 s \(one switching "
                                          r"period of the paper's converter is 13.3 us\): was it given in another unit\?$"):
        build_timeline(scenario(), 1e-9, 1e-5)
    with pytest.raises(ConfigError, match=r"^record period = 5e-08 s is invalid: expected >= 1e-07 s"):
        build_timeline(scenario(), 1e-3, 5e-8)
    plan = plan_timeline(scenario(), 1e-3, 1e-7)
    assert plan.record_count == round(scenario().duration / 1e-7) + 1


def test_controller_returning_nan_stops_the_run_and_keeps_the_rows(averaged):
    probe = Probe(duty=lambda k: 0.25 if k < 3 else math.nan)
    with pytest.raises(RunFailed, match=r"controller probe returned duty cycle nan at t = 0.003 s") as info:
        simulate(averaged, probe, scenario())
    partial = info.value.partial
    assert not partial.complete and partial.metadata["error"].startswith("controller probe returned")
    assert partial.frame["time"].max() == pytest.approx(0.003 - 1e-5)
    assert info.value.exit_code == 3


def test_controller_exception_is_reported_with_its_time_and_line(averaged):
    def explode(k):
        if k == 2:
            raise ZeroDivisionError("boom")
        return 0.2

    line = explode.__code__.co_firstlineno + 2
    with pytest.raises(RunFailed, match=rf"controller probe raised ZeroDivisionError at t = 0.002 s "
                                        rf"\({re.escape(__file__)}:{line}\): boom") as failed:
        simulate(averaged, Probe(duty=explode), scenario())
    assert isinstance(failed.value.cause.__cause__, ZeroDivisionError)  # kept, for --debug


def test_scenario_needing_a_missing_role_is_refused_before_the_run(averaged):
    roles = {k: v for k, v in averaged.roles.items() if k != "load_resistance"}
    reduced = replace(averaged, roles=roles)
    with pytest.raises(ConfigError, match=r"scenario load_change changes load_resistance, but plant FMU .* "
                                          r"binds no variable to the role 'load_resistance'"):
        simulate(reduced, Probe(), load_scenario("load_change", PAPER_SPEC))


def test_one_plant_instance_serves_many_runs_identically(averaged):
    pi = PIController(0.0, DEADBEAT_KI, 1e-3)
    s = load_scenario("reference_up", PAPER_SPEC)
    with open_plant(averaged) as plant:
        first = run(plant, pi, s).frame
        second = run(plant, pi, s).frame
    cols = [c for c in first.columns if c != "controller_compute_time"]
    assert first[cols].equals(second[cols])


def test_role_scaling_converts_units(averaged):
    roles = dict(averaged.roles)
    roles["inductor_current"] = RoleMap("inductor_current", scale=1.0, offset=0.0)
    with open_plant(replace(averaged, roles=roles)) as plant:
        plant.initialize([0.25, VS, R])
        plant.advance_to(0.01)
        direct = plant.outputs()
    roles["output_voltage"] = RoleMap("output_voltage", scale=1000.0)  # pretend the FMU reports mV
    with open_plant(replace(averaged, roles=roles)) as plant:
        plant.initialize([0.25, VS, R])
        plant.advance_to(0.01)
        scaled = plant.outputs()
    assert scaled[0] == pytest.approx(direct[0] / 1000.0, rel=1e-15)


def test_windows_partition_the_timeline_exactly():
    from cosim.timeline import plan_timeline

    s = load_scenario("load_change", PAPER_SPEC)
    for control, record in ((1e-3, 1e-5), (1 / 75e3, 1e-5), (1e-3, 3e-6)):
        whole = build_timeline(s, control, record)
        parts = list(plan_timeline(s, control, record).windows(size=1000))
        assert len(parts) > 3
        assert np.array_equal(np.concatenate([w.times for w in parts]), whole.times)
        assert np.array_equal(np.concatenate([w.flags for w in parts]), whole.flags)


def test_a_run_failure_crosses_process_boundaries_intact(averaged):
    """The reproduction runs pipelines in worker processes: a failure must unpickle there."""
    import pickle

    with pytest.raises(RunFailed) as info:
        simulate(averaged, Probe(duty=lambda k: math.nan), scenario())
    again = pickle.loads(pickle.dumps(info.value))
    assert str(again) == str(info.value) and again.exit_code == 3
    assert again.partial.metadata["complete"] is False


def test_model_exchange_state_restore_replays_exactly():
    with open_plant(builtin_binding("switched"), interface="me") as plant:
        plant.initialize([0.25, VS, R])
        plant.advance_to(1e-3 + 0.1 / 75e3)
        state, saved = plant.get_state(), plant.time
        plant.advance_to(1e-3 + 5.5 / 75e3)
        first = list(plant.outputs())
        plant.set_state(state, saved)
        plant.advance_to(1e-3 + 5.5 / 75e3)
        np.testing.assert_allclose(plant.outputs(), first, rtol=1e-7)
        plant.free_state(state)


def test_parameter_events_act_on_the_plant_at_their_exact_time(averaged):
    """C -30 % and a DCR between recording points, during a held duty: from the state at the event
    the recorded trajectory is the closed form of the new circuit."""
    t_event = 0.01003
    text = f"[[events]]\ntime = {t_event}\nparameters = {{ capacitance = {0.7 * C}, inductor_resistance = 0.3 }}\n"
    frame = simulate(averaged, Probe(duty=lambda k: 0.25 if k < 10 else 0.3), scenario(text)).frame
    at = frame[np.isclose(frame["time"], t_event, atol=1e-12)]
    assert len(at) == 1  # the event instant was added to the grid
    rows = frame[(frame["time"] >= t_event - 1e-12) & (frame["time"] <= 0.011 + 1e-12)]
    x0 = rows[["inductor_current", "output_voltage"]].to_numpy()[0]
    c2, r2 = 0.7 * C, 0.3
    a = np.array([[-r2 / L, -1.0 / L], [1.0 / c2, -1.0 / (R * c2)]])
    x_eq = -np.linalg.solve(a, [0.3 * VS / L, 0.0])
    expected = np.array([x_eq + expm(a * (t - t_event)) @ (x0 - x_eq) for t in rows["time"]])
    np.testing.assert_allclose(rows[["inductor_current", "output_voltage"]].to_numpy(), expected, rtol=1e-9)
    # before the event the old circuit: the same run without the event agrees up to it, and not after
    plain = simulate(averaged, Probe(duty=lambda k: 0.25 if k < 10 else 0.3), scenario()).frame
    before = frame["time"] < t_event - 1e-12
    np.testing.assert_array_equal(frame.loc[before, "output_voltage"].to_numpy(),
                                  plain.loc[plain["time"] < t_event - 1e-12, "output_voltage"].to_numpy())
    assert abs(frame["output_voltage"].iloc[-1] - plain["output_voltage"].iloc[-1]) > 0.05  # the DCR drop


@pytest.mark.parametrize("interface", ["cs", "me"])
def test_a_parameter_event_equals_a_run_with_those_parameters_from_the_start(interface):
    """Switched plant: an event at t = 0 gives the run of a plant bound with those parameters
    before initialisation (co-simulation exactly; model exchange through its event, to CVode's
    tolerance)."""
    new = {"capacitance": 7e-6, "inductor_resistance": 0.2}
    text = "[[events]]\ntime = 0.0\nparameters = { capacitance = 7e-6, inductor_resistance = 0.2 }\n"
    changed = simulate(builtin_binding("switched"), Probe(), scenario(text, duration=0.004), interface=interface,
                       relative_tolerance=1e-10).frame
    from_start = simulate(builtin_binding("switched", new), Probe(), scenario(duration=0.004), interface=interface,
                          relative_tolerance=1e-10).frame
    columns = ["inductor_current", "output_voltage", "measured_output_voltage"]
    tolerance = 1e-12 if interface == "cs" else 1e-7
    np.testing.assert_allclose(changed[columns].to_numpy(), from_start[columns].to_numpy(), rtol=tolerance,
                               atol=tolerance)


def test_model_exchange_applies_a_parameter_event_mid_run_like_co_simulation():
    text = "[[events]]\ntime = 0.0021\nparameters = { capacitance = 7e-6, capacitor_esr = 0.05 }\n"
    runs = [simulate(builtin_binding("switched"), Probe(), scenario(text, duration=0.004), interface=interface,
                     relative_tolerance=1e-10).frame for interface in ("cs", "me")]
    columns = ["inductor_current", "output_voltage", "measured_output_voltage"]
    np.testing.assert_allclose(runs[1][columns].to_numpy(), runs[0][columns].to_numpy(), rtol=1e-5, atol=1e-5)


def test_a_value_the_fmu_refuses_stops_the_run_before_its_first_step(averaged, tmp_path):
    path = tmp_path / "zero.toml"
    path.write_text('name = "zero"\nduration = 0.01\n[initial]\nreference = 12.0\n\n[[events]]\ntime = 0.005\n'
                    'parameters = { capacitance = 0.0 }\n')
    probe = Probe()
    with pytest.raises(ConfigError, match=r"zero.toml:8: events\[0\].parameters \(capacitance\): the plant FMU "
                                          r"refuses the value: fmi2SetReal: capacitance = 0 F is invalid"):
        simulate(averaged, probe, load_scenario(path, PAPER_SPEC))
    assert probe.seen == []  # not a single step


def test_an_isolated_plant_applies_parameter_events_like_the_in_process_plant(tmp_path):
    """The plant process (binding files' default) forwards parameter events in order with the steps,
    and tries them before the first step like the in-process plant."""
    text = "[[events]]\ntime = 0.0021\nparameters = { capacitance = 7e-6, capacitor_esr = 0.05 }\n"
    runs = [simulate(replace(builtin_binding("switched"), isolate=isolate), Probe(), scenario(text, duration=0.004))
            .frame for isolate in (False, True)]
    columns = ["inductor_current", "output_voltage", "measured_output_voltage"]
    np.testing.assert_array_equal(runs[1][columns].to_numpy(), runs[0][columns].to_numpy())
    path = tmp_path / "zero.toml"
    path.write_text('name = "zero"\nduration = 0.01\n[initial]\nreference = 12.0\n\n[[events]]\ntime = 0.005\n'
                    'parameters = { capacitance = 0.0 }\n')
    with pytest.raises(ConfigError, match=r"zero.toml:8: events\[0\].parameters \(capacitance\): the plant FMU "
                                          r"refuses the value: fmi2SetReal: capacitance = 0 F is invalid"):
        simulate(replace(builtin_binding("averaged"), isolate=True), Probe(), load_scenario(path, PAPER_SPEC))


@pytest.mark.parametrize("isolate", [False, True])
def test_replaced_parameters_give_the_run_of_a_plant_bound_with_them(isolate):
    """A sweep's reuse pattern: one instance, its parameters replaced run by run (set at the next
    initialisation), equals a fresh plant bound with those values; a name the FMU lacks is refused
    naming it, and the instance stays usable."""
    nominal = builtin_binding("switched")
    varied = {**nominal.parameters, "inductance": 250e-6, "capacitance": 8.5e-6}
    columns = ["inductor_current", "output_voltage", "measured_output_voltage"]
    fresh = simulate(builtin_binding("switched", varied), Probe(), scenario(duration=0.004)).frame
    with open_plant(replace(nominal, isolate=isolate)) as plant:
        first = run(plant, Probe(), scenario(duration=0.004)).frame
        plant.replace_parameters(varied)
        reused = run(plant, Probe(), scenario(duration=0.004)).frame
        with pytest.raises(ConfigError, match="no_such_parameter"):
            plant.replace_parameters({**varied, "no_such_parameter": 1.0})
        plant.replace_parameters(dict(nominal.parameters))
        again = run(plant, Probe(), scenario(duration=0.004)).frame
    np.testing.assert_array_equal(reused[columns].to_numpy(), fresh[columns].to_numpy())
    np.testing.assert_array_equal(again[columns].to_numpy(), first[columns].to_numpy())
    assert not np.allclose(reused["output_voltage"], first["output_voltage"])
