"""The second converter (examples/pol_buck/): a 24 V -> 5 V point-of-load buck at 100 kHz, on the workbench's C plant
with other components and as a pythonfmu FMU with its own names and no declared units. Its designs work at its
operating points: the PI meets its constraints at the nominal point and, at one switching period, the NNPC identified
on its envelope beats the PI in every scenario without leaving its data."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from cosim.fmi.binding_file import load_binding
from cosim.scenarios import PAPER_SCENARIOS, load_scenario

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "pol_buck"
PERIOD = 1e-5  # [s] one switching period at 100 kHz


@pytest.fixture(scope="module")
def example(tmp_path_factory, buck_fmu) -> Path:
    """The example's folder with its FMUs built into build/, as make examples builds them."""
    from pythonfmu.builder import FmuBuilder

    folder = tmp_path_factory.mktemp("pol_buck")
    for name in ("pol_builtin.toml", "pol_pythonfmu.toml"):
        shutil.copy(EXAMPLE / name, folder / name)
    (folder / "build").mkdir()
    shutil.copy(buck_fmu, folder / "build" / "BuckConverter.fmu")
    FmuBuilder.build_FMU(EXAMPLE / "pol_buck.py", dest=folder / "build")
    reproducible(folder / "build" / "PolBuck.fmu")  # as make examples leaves it
    return folder


def reproducible(fmu: Path) -> str:
    """scripts/reproducible_fmu.py on ``fmu`` (its new guid)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("reproducible_fmu", EXAMPLE.parents[1] / "scripts" /
                                                  "reproducible_fmu.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.reproducible(fmu)


def test_two_builds_of_the_pythonfmu_plant_give_the_same_bytes_once_made_reproducible(example, tmp_path):
    """pythonfmu stamps each build with a new uuid1 guid and the build time: made reproducible, a second build is the
    same archive byte for byte (the study's design keys hash it), with a guid derived from its contents."""
    import hashlib
    import zipfile

    from pythonfmu.builder import FmuBuilder

    FmuBuilder.build_FMU(EXAMPLE / "pol_buck.py", dest=tmp_path)
    with zipfile.ZipFile(tmp_path / "PolBuck.fmu") as archive:
        stamped = archive.read("modelDescription.xml").decode()
    assert "generationDateAndTime=" in stamped
    guid = reproducible(tmp_path / "PolBuck.fmu")
    built = (example / "build" / "PolBuck.fmu").read_bytes()
    assert hashlib.sha256((tmp_path / "PolBuck.fmu").read_bytes()).digest() == hashlib.sha256(built).digest()
    with zipfile.ZipFile(tmp_path / "PolBuck.fmu") as archive:
        description = archive.read("modelDescription.xml").decode()
        assert {i.date_time for i in archive.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    assert f'guid="{guid}"' in description and "generationDateAndTime" not in description
    assert reproducible(tmp_path / "PolBuck.fmu") == guid  # idempotent


@pytest.mark.parametrize("name", ["pol_builtin", "pol_pythonfmu"])
def test_both_plants_are_the_same_converter_and_nothing_of_the_papers_is_left(example, name):
    spec = load_binding(example / f"{name}.toml").converter
    assert (spec.input_voltage, spec.output_voltage, spec.load_resistance) == (24.0, 5.0, 2.0)
    assert (spec.inductance, spec.capacitance, spec.switching_frequency) == (47e-6, 27e-6, 100e3)
    assert spec.control_periods == (1e-3, PERIOD)
    for scenario in (load_scenario(n, spec) for n in (*PAPER_SCENARIOS, "supply_dip")):
        values = {*scenario.initial.values(), *(v for e in scenario.events for v in e.changes.values())}
        assert not values & {48.0, 6.0, 12.0}, (scenario.name, values)
        assert "48 V" not in scenario.description and "6 Ohm" not in scenario.description


def test_the_pythonfmu_plant_runs_at_its_own_operating_point(example):
    """The third-party FMU's PI (a quick tuning: stepping a Python FMU is slow) at 24 V: the start-up settles at 5 V
    within the PI's constraints."""
    from cosim.design.pi_tuning import tune_pi
    from cosim.master import simulate
    from cosim.metrics import run_metrics

    binding = load_binding(example / "pol_pythonfmu.toml")
    tuning = tune_pi(binding, 1e-3, quick=True)
    assert tuning.design["inputs"]["settings"]["input_voltage_V"] == 24.0
    run = simulate(binding, tuning.controller(), load_scenario("startup", binding.converter))
    metrics = run_metrics(run)
    assert run.frame["input_voltage"].eq(24.0).all() and run.frame["load_resistance"].eq(2.0).all()
    assert metrics["overshoot_pct"] <= 5.0 and abs(metrics["steady_state_error_pct"]) <= 0.5, metrics


def test_on_the_c_plant_the_pi_meets_its_constraints_and_the_nnpc_beats_it_in_every_scenario(example, tmp_path):
    """A reduced study: the PI tuned at the nominal point meets overshoot <= 5 % and |steady-state error| <= 0.5 % in
    the start-up; at one switching period the NNPC (seed 0, identified on the spec's envelope) has a lower IAE than
    the PI in each of the paper's scenarios, and no run leaves its data."""
    from cosim.batch import Batch, run_batch
    from cosim.design.controller_factory import make_controllers
    from cosim.design.experiments import scenarios_for

    binding = load_binding(example / "pol_builtin.toml")
    pi, network = make_controllers(["pi", "nnpc"], binding, PERIOD, tmp_path, duty_limits=(0.0, 1.0), samples=6000)
    scenarios = scenarios_for(PERIOD, spec=binding.converter)
    output = run_batch(Batch(binding, scenarios), [pi, network], tmp_path, figures=False)
    metrics = output.metrics.set_index(["scenario", "controller"])
    startup = metrics.loc[("startup", "PI")]
    assert startup["overshoot_pct"] <= 5.0 and abs(startup["steady_state_error_pct"]) <= 0.5, startup
    for scenario in PAPER_SCENARIOS:
        assert metrics.loc[(scenario, "NNPC"), "iae_Vs"] < metrics.loc[(scenario, "PI"), "iae_Vs"], scenario
    assert not any("outside_data_domain" in r.metadata for r in output.results)
    assert network.predictor.describe()["data_domain"]["input_voltage"] == [18.0, 32.0]


def test_the_quick_study_of_the_second_converter_meets_its_targets_and_never_names_the_papers_converter(example,
                                                                                                        tmp_path):
    """``buck-cosim study --quick`` at one switching period, two seeds: the report's targets (the PI's constraints at
    the nominal point, NNPC < PI in every scenario for every seed, NNPC / MPC-nominal at the median and worst seed,
    no run outside the NNPC's data) are all met; the report states the converter's own values and none of the
    paper's; a second run with --resume keeps every job and writes the same report."""
    import pandas as pd
    from conftest import cli

    out = tmp_path / "study"
    done = cli("study", "--plant", str(example / "pol_builtin.toml"), "--quick", "--control-period", "1e-5", "--out",
               str(out), timeout=900)
    assert done.returncode == 0, done.stderr
    assert "[2/2] " in done.stderr and "converter study finished" in done.stderr  # progress, one line per job
    targets = pd.read_csv(out / "targets.csv")
    assert len(targets) == 5 and (targets["met"] == "yes").all(), targets.to_string()
    assert targets["target"].str.contains("every scenario and seed \\(2 seeds\\)").any()
    report = (out / "REPORT.md").read_text()
    assert "# Study of POL buck 24 V -> 5 V" in report and "| nominal supply | 24 V | 18-32 V |" in report
    assert "L = 47 uH, C = 27 uF, f_sw = 100 kHz" in report and "5 of 5 met" in report
    for paper in ("48 V", "6 Ohm", "12 V", "75 kHz", "220 uH", "13.33"):
        assert paper not in report, paper
    metrics = pd.read_csv(out / "metrics" / "metrics_all.csv")
    assert set(metrics["controller"]) == {"PI", "NNPC", "NNPC (seed 1)", "NNPC-paper", "MPC-nominal",
                                          "NNPC-explicit", "CMC", "Type-III"}
    pi_startup = metrics[(metrics["controller"] == "PI") & (metrics["scenario"] == "startup")].iloc[0]
    assert f"overshoot {pi_startup['overshoot_pct']:.2f} %" in report
    assert (out / "figures" / "iae_by_scenario.png").is_file()
    # the envelope map over the spec's ranges (quick: 2 references x 2 loads at the nominal 24 V)
    shares = pd.read_csv(out / "envelope" / "shares.csv")
    overall = shares[shares["input_voltage_V"] == "all"].set_index("controller")
    assert set(overall.index) == {"NNPC", "NNPC (seed 1)", "NNPC-explicit", "MPC-nominal", "CMC", "Type-III", "PI"}
    assert (overall["points"] == 4).all() and set(shares["input_voltage_V"]) == {"all", "24.0"}
    steps = pd.read_csv(out / "envelope" / "map.csv")
    assert sorted(set(steps["reference_V"])) == [1.5, 8.0] and sorted(set(steps["load_Ohm"])) == [1.5, 50.0]
    assert "## The envelope map" in report and "supplies 24 V, over the spec's ranges" in report
    assert f"| NNPC | {overall.loc['NNPC', 'share_pct']:.3g} |" in report
    assert (out / "figures" / "envelope_map.png").is_file()
    assert "Whole quick study <= 3 min on 2 cores" in (out / "timings.md").read_text()
    assert '"switching_frequency": 100000.0' in (out / "tuning" / "current-mode__bound-pol_builtin__10us.json").read_text()
    again = cli("study", "--plant", str(example / "pol_builtin.toml"), "--quick", "--control-period", "1e-5", "--out",
                str(out), "--resume", timeout=300)
    assert again.returncode == 0, again.stderr
    assert again.stderr.count("finished earlier, kept (--resume)") == 2
    assert (out / "REPORT.md").read_text() == report
