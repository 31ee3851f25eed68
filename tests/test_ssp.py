"""The closed loop as an SSP package: the scenario FMU, the SSP 1.0 archive, and the three engines
that run it (the workbench's master, fmpy's SSP simulation, libcosim)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import fmpy
import fmpy.validation
import numpy as np
import pytest
from fmpy.fmi2 import FMU2Slave

from cosim.scenarios import load_scenario, parse_scenario
from cosim.ssp.scenario_source import OUTPUTS, scenario_fmu, scenario_toml, settle_time
from cosim.study.experiments import scenarios_for


def cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "cosim.cli", "--no-progress", *args], capture_output=True,
                          text=True, cwd=cwd, stdin=subprocess.DEVNULL, timeout=600)


# ------------------------------------------------------------------ the scenario FMU


def _sample_scenario_fmu(path: Path, times: list[float]) -> np.ndarray:
    """The scenario FMU's outputs at each of ``times`` (stepped from one to the next with raw fmpy)."""
    md = fmpy.read_model_description(str(path))
    unzipdir = fmpy.extract(str(path))
    fmu = FMU2Slave(guid=md.guid, unzipDirectory=unzipdir, modelIdentifier=md.coSimulation.modelIdentifier,
                    instanceName="scenario")
    fmu.instantiate()
    fmu.setupExperiment(startTime=0.0)
    fmu.enterInitializationMode()
    fmu.exitInitializationMode()
    values, now = [], 0.0
    for t in times:
        if t > now:
            fmu.doStep(now, t - now)
            now = t
        values.append(fmu.getReal([0, 1, 2]))
    fmu.terminate()
    fmu.freeInstance()
    return np.array(values)


@pytest.mark.parametrize("name", ["supply_dip", "reference_up"])
def test_the_scenario_fmu_follows_the_events_as_the_master_applies_them(name):
    from cosim.timeline import build_timeline, signal_at

    scenario = load_scenario(name)
    path = scenario_fmu(scenario, 1e-3)
    assert fmpy.validation.validate_fmu(str(path)) == []
    md = fmpy.read_model_description(str(path))
    assert [v.name for v in md.modelVariables] == list(OUTPUTS)
    assert all(v.causality == "output" for v in md.modelVariables)
    timeline = build_timeline(scenario, 1e-3, 1e-4)  # control samples, recording points and events
    expected = np.column_stack([signal_at(timeline, scenario.schedule(s)) for s in OUTPUTS])
    got = _sample_scenario_fmu(path, timeline.times.tolist())
    assert np.array_equal(got, expected)  # every instant, including each event instant itself


def test_the_scenario_is_rounded_to_whole_control_periods_and_survives_its_toml_form():
    [scenario] = scenarios_for(1e-3, ["load_change"])
    assert settle_time(scenario, 1e-3) == pytest.approx(0.015)
    assert settle_time(scenario, 0.4e-3) == pytest.approx(0.0152)  # 38 control periods
    again = parse_scenario(scenario_toml(scenario))
    assert (again.initial, again.events, again.duration, again.settle) == \
        (scenario.initial, scenario.events, scenario.duration, scenario.settle)
