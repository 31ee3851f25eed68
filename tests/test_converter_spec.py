"""The converter spec: one definition of the converter under study, read from a binding's [converter] table, and the
scenarios, designs and domain checks that take their operating points from it instead of the paper's 48 V / 6 Ohm."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from conftest import one_line_error

from cosim.base.errors import ConfigError
from cosim.fmi.binding_file import load_binding
from cosim.scenarios import PAPER_SCENARIOS, load_scenario, shipped_scenario_names, warn_outside
from cosim.study.vocabulary import PAPER_SPEC

ROOT = Path(__file__).resolve().parents[1]

#: a 24 V -> 5 V converter on the corpus's pythonfmu buck (its own names, duty in %, current in mA)
MY24 = """\
fmu = "{fmu}"
label = "MyBuck24"

[roles.duty_cycle]
variable = "D"
scale = 100.0
[roles.output_voltage]
variable = "Vout"
[roles.inductor_current]
variable = "IL_mA"
scale = 1000.0
[roles.load_resistance]
variable = "Rload"
[roles.input_voltage]
variable = "Vin"
[roles.load_current]
variable = "Iout"

[parameters]
L = 100e-6
C = 47e-6

[converter]
input_voltage = 24.0
output_voltage = 5.0
load_resistance = 3.0
input_voltage_range = [20.0, 28.0]
output_voltage_range = [2.0, 8.0]
load_resistance_range = [2.0, 30.0]
{extra}
[converter.circuit]
inductance = "L"
capacitance = "C"
switching_frequency = 100e3
"""


def my24(tmp_path: Path, fmu: Path, extra: str = "", text: str | None = None) -> Path:
    path = tmp_path / "my24.toml"
    path.write_text(text if text is not None else MY24.format(fmu=fmu, extra=extra))
    return path


@pytest.fixture()
def my24_binding(tmp_path, python_buck_fmu):
    return load_binding(my24(tmp_path, python_buck_fmu))


# ------------------------------------------------------------------ the spec itself


def test_a_binding_file_gives_its_converter_with_the_fmus_values_as_defaults(my24_binding, tmp_path, python_buck_fmu):
    spec = my24_binding.converter
    assert (spec.input_voltage, spec.output_voltage, spec.load_resistance) == (24.0, 5.0, 3.0)
    assert spec.load_resistance_range == (2.0, 30.0) and spec.duty_limits == (0.0, 1.0)
    assert (spec.inductance, spec.capacitance, spec.switching_frequency) == (100e-6, 47e-6, 100e3)  # L, C: [parameters]
    # without them in [converter] the nominal supply and load are the bound inputs' start values (the FMU's 48 V, 6 Ohm)
    text = MY24.format(fmu=python_buck_fmu, extra="").replace("input_voltage = 24.0\n", "").replace(
        "load_resistance = 3.0\n", "").replace("input_voltage_range = [20.0, 28.0]\n", "").replace(
        "load_resistance_range = [2.0, 30.0]\n", "")
    spec = load_binding(my24(tmp_path, python_buck_fmu, text=text)).converter
    assert (spec.input_voltage, spec.load_resistance) == (48.0, 6.0)
    assert "start value of 'Vin'" in spec.places["input_voltage"]


@pytest.mark.parametrize("edit,message", [
    (("output_voltage = 5.0", "output_voltage = -5.0"),
     r"my24.toml:\d+: output_voltage = -5 V is invalid: expected > 0"),
    (("load_resistance = 3.0", "load_resistance = 0.0005"),
     r"my24.toml:\d+: load_resistance = 0.0005 Ohm is implausible: expected Ohm between 0.001 and 1e\+06 "
     r"\(a load in kOhm"),
    (("load_resistance_range = [2.0, 30.0]", "load_resistance_range = [30.0, 2.0]"),
     r"my24.toml:\d+: load_resistance_range = \[30, 2\] Ohm is inverted or empty: expected min < max"),
    (("{extra}", "control_periods = [1.0]"), r"my24.toml:\d+: control_periods\[0\] = 1 s is implausible: expected "
                                             r"seconds between 1e-08 and 0.1 \(a period in ms or us\?\)"),
    (("switching_frequency = 100e3", "switching_frequency = 100"),  # kHz written as Hz
     r"converter.circuit.switching_frequency = 100 Hz is implausible: expected Hz between 1000 and 1e\+09"),
    (("output_voltage_range = [2.0, 8.0]", "output_voltage_range = [0.0, 8.0]"),  # rests at 0 V are no operating point
     r"my24.toml:\d+: output_voltage_range\[0\] = 0 V is invalid: expected > 0"),
    (("switching_frequency = 100e3", "switching_frequency = 100e-3"),
     r"my24.toml:\d+: converter.circuit.switching_frequency = 0.1 Hz is implausible: expected Hz between 1000 and "
     r"1e\+09 "
     r"\(a value in kHz or MHz\?\)"),
    (("inductance = \"L\"", "inductance = 100"), r"converter.circuit.inductance = 100 H is implausible.*uH or mH"),
    (("inductance = \"L\"", "inductance = \"L_uH\""), r"my24.toml:\d+: .* has no Real parameter 'L_uH'"),
    (("output_voltage = 5.0", "output_voltage = 30.0"), r"my24.toml:\d+: output_voltage = 30 V is outside "
                                                         r"output_voltage_range \[2, 8\] V"),
    (("output_voltage_range = [2.0, 8.0]", "output_voltage_range = [2.0, 22.0]"),
     r"my24.toml:\d+: the envelope's corner of output 22 V at supply 20 V is out of reach of a buck converter"),
    (("{extra}", "duty_limits = [0, 95]"), r"my24.toml:\d+: duty_limits = \[0, 95\] is invalid: expected 0 <= min < "
                                           r"max <= 1 \(a duty in percent\?\)"),
    (("{extra}", "nominal_output = 5.0"), r"my24.toml:\d+: unknown key 'converter.nominal_output': expected one of"),
])
def test_a_bad_spec_value_is_refused_in_one_line_naming_file_key_and_line(tmp_path, python_buck_fmu, edit, message):
    path = my24(tmp_path, python_buck_fmu, text=MY24.replace(*edit).format(fmu=python_buck_fmu, extra=""))
    with pytest.raises(ConfigError, match=message) as raised:
        load_binding(path)
    assert "\n" not in str(raised.value)


def test_a_spec_built_in_python_is_checked_like_a_table():
    from cosim.converter_spec import with_values

    assert with_values(PAPER_SPEC) == PAPER_SPEC
    for bad, message in ((dict(inductance=220.0), r"inductance = 220 H is implausible"),
                         (dict(control_periods=(1.0,)), r"control_periods\[0\] = 1 s is implausible"),
                         (dict(output_voltage=50.0), r"output_voltage = 50 V is outside output_voltage_range")):
        with pytest.raises(ConfigError, match=message):
            with_values(PAPER_SPEC, **bad)


def test_a_zero_start_value_is_no_nominal_value(my24_binding):
    """Exported FMUs often start their inputs at 0: that is no nominal load or supply -- not given, so a design that
    needs it names the key, instead of the binding failing to load."""
    from types import SimpleNamespace

    from cosim.base.toml_files import TomlLocator
    from cosim.fmi.binding_file import converter_spec

    variables = [SimpleNamespace(name="Vin", start="0", causality="input", type="Real"),
                 SimpleNamespace(name="Rload", start="not a number", causality="input", type="Real")]
    spec = converter_spec({"output_voltage": 5.0}, my24_binding, SimpleNamespace(modelVariables=variables),
                          TomlLocator(""))
    assert (spec.input_voltage, spec.load_resistance, spec.output_voltage) == (None, None, 5.0)
    with pytest.raises(ConfigError, match=r"the PI tuning needs input_voltage, which neither \[converter\] nor the "
                                          r"FMU gives"):
        spec.require("input_voltage", "the PI tuning")


def test_a_design_needing_a_value_the_spec_does_not_give_is_refused_naming_the_key(tmp_path, python_buck_fmu):
    from cosim.design.controller_factory import make_controllers

    text = MY24.format(fmu=python_buck_fmu, extra="").split("[converter.circuit]")[0]  # no nominal circuit
    binding = load_binding(my24(tmp_path, python_buck_fmu, text=text))
    with pytest.raises(ConfigError, match=r"my24.toml: mpc-nominal \(it predicts with the nominal circuit\) needs "
                                          r"inductance, which neither \[converter.circuit\] nor the FMU gives: add it "
                                          r"under \[converter.circuit\], e.g. inductance = 100e-6"):
        make_controllers(["mpc-nominal"], binding, 1e-3, tmp_path, duty_limits=(0.0, 1.0))
    without_output = text.replace("output_voltage = 5.0\n", "")
    binding = load_binding(my24(tmp_path, python_buck_fmu, text=without_output))
    with pytest.raises(ConfigError, match=r"startup.toml:\d+: initial.reference \(reference = 'nominal'\) needs "
                                          r"output_voltage, which neither \[converter\] nor the FMU gives"):
        load_scenario("startup", binding.converter)


def test_the_cli_refuses_a_bad_spec_before_anything_runs(tmp_path, python_buck_fmu):
    from conftest import cli

    path = my24(tmp_path, python_buck_fmu, text=MY24.replace("load_resistance = 3.0", "load_resistance = -3.0").format(
        fmu=python_buck_fmu, extra=""))
    done = cli("run", "startup", "--plant", str(path), "--out", str(tmp_path / "out"))
    line = one_line_error(done, 2, "my24.toml:")
    assert line.endswith("load_resistance = -3 Ohm is invalid: expected > 0"), line
    assert not (tmp_path / "out" / "runs").exists()


def test_reproduce_on_a_plant_without_a_nominal_circuit_is_refused_before_any_work(tmp_path, python_buck_fmu):
    from conftest import cli

    text = MY24.format(fmu=python_buck_fmu, extra="").split("[converter.circuit]")[0]
    done = cli("reproduce", "--quick", "--plant", str(my24(tmp_path, python_buck_fmu, text=text)), "--out",
               str(tmp_path / "out"))
    line = one_line_error(done, 2, "my24.toml: reproduce --plant (its MPC baseline predicts with the nominal circuit) "
                                   "needs inductance")
    assert "[converter.circuit]" in line and not (tmp_path / "out" / "tuning").exists()


# ------------------------------------------------------------------ scenarios relative to the spec


#: the paper's numbers each shipped scenario held before it became a template: (initial, events' changes)
PAPER_NUMBERS = {
    "startup": ({"reference": 12.0, "load_resistance": 6.0, "input_voltage": 48.0}, []),
    "load_change": ({"reference": 12.0, "load_resistance": 6.0, "input_voltage": 48.0}, [{"load_resistance": 5.0}]),
    "reference_up": ({"reference": 12.0, "load_resistance": 6.0, "input_voltage": 48.0}, [{"reference": 15.0}]),
    "reference_down": ({"reference": 12.0, "load_resistance": 6.0, "input_voltage": 48.0}, [{"reference": 9.0}]),
    "supply_dip": ({"reference": 12.0, "load_resistance": 6.0, "input_voltage": 48.0},
                   [{"input_voltage": 40.0}, {"input_voltage": 48.0}]),
}


@pytest.mark.parametrize("name", sorted(PAPER_NUMBERS))
def test_the_shipped_templates_resolve_to_exactly_the_papers_numbers_on_table_ii(name):
    scenario = load_scenario(name, PAPER_SPEC)
    initial, changes = PAPER_NUMBERS[name]
    assert scenario.initial == initial
    assert [e.changes for e in scenario.events] == changes
    assert "{" not in scenario.description and "12" in scenario.description


def test_the_shipped_templates_resolve_to_the_users_converter(my24_binding):
    spec = my24_binding.converter
    startup, load_change, up, down, dip = (load_scenario(n, spec) for n in (*PAPER_SCENARIOS, "supply_dip"))
    assert startup.initial == {"reference": 5.0, "load_resistance": 3.0, "input_voltage": 24.0}
    assert load_change.events[0].changes == {"load_resistance": 2.5}
    assert up.events[0].changes == {"reference": 6.25} and down.events[0].changes == {"reference": 3.75}
    assert [e.changes["input_voltage"] for e in dip.events] == [20.0, 24.0]
    for scenario in (startup, load_change, up, down, dip):  # nothing of the paper's converter is left
        text = scenario.description
        assert "48 V" not in text and "6 Ohm" not in text and "12 V" not in text, text
    assert load_change.description == "Load change 3 -> 2.5 Ohm at 5 V (paper Fig. 9)"


def test_every_shipped_scenario_resolves_on_the_built_in_spec_without_a_warning(capsys):
    for name in shipped_scenario_names():
        assert warn_outside(load_scenario(name, PAPER_SPEC), PAPER_SPEC) == [], name
    assert capsys.readouterr().err == ""


def test_a_scenario_value_outside_the_envelope_warns_in_one_line_naming_value_and_range(my24_binding, tmp_path,
                                                                                         capsys):
    path = tmp_path / "far.toml"
    path.write_text('name = "far"\nduration = 0.01\n[initial]\nreference = "nominal"\n'
                    '[[events]]\ntime = 0.005\nload_resistance = 1.5\n')
    scenario = load_scenario(path, my24_binding.converter, warn=True)
    assert scenario.initial["input_voltage"] == 24.0  # left out: the converter's nominal supply, not Table II's
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1
    assert "load_resistance 1.5 Ohm is outside binding file" in lines[0]
    assert "load_resistance_range [2, 30] Ohm (at t = 0.005 s)" in lines[0]


def test_a_template_value_outside_a_buck_converters_reach_is_refused(my24_binding, tmp_path):
    path = tmp_path / "high.toml"
    path.write_text('name = "high"\nduration = 0.01\n[initial]\nreference = "nominal * 5"\n')
    with pytest.raises(ConfigError, match=r"high.toml:\d+: the reference 25 V at t = 0 s exceeds the input voltage "
                                          r"24 V"):
        load_scenario(path, my24_binding.converter)
    path = tmp_path / "bad.toml"
    path.write_text('name = "bad"\nduration = 0.01\n[initial]\nreference = "twice nominal"\n')
    with pytest.raises(ConfigError, match=r"bad.toml:\d+: initial.reference: 'twice nominal' is not a template value"):
        load_scenario(path, my24_binding.converter)


# ------------------------------------------------------------------ designs at the spec's operating points


def test_the_pi_is_tuned_at_the_converters_supply_and_scenarios(my24_binding):
    from cosim.design.pi_tuning import pi_design

    inputs = pi_design(my24_binding, 1e-3).inputs
    assert inputs["settings"]["input_voltage_V"] == 24.0  # the loop gain a = Kp Vs at the user's supply, not 48 V
    assert [s["initial"] for s in inputs["scenarios"]] == [
        {"reference": 5.0, "load_resistance": 3.0, "input_voltage": 24.0}] * 3
    assert [e["reference"] for s in inputs["scenarios"] for e in s["events"]] == [6.25, 3.75]
    at_48_volts = pi_design(load_binding(my24_binding.source), 1e-3, input_voltage=48.0)
    assert pi_design(my24_binding, 1e-3).key != at_48_volts.key


def test_the_identification_data_are_drawn_over_the_converters_ranges(my24_binding):
    from cosim.design.data_collection import paper_region
    from cosim.design.experiments import collection_settings

    envelope = collection_settings(13.33e-6, 1000, 0, region="envelope", spec=my24_binding.converter)
    assert (envelope.reference_range, envelope.load_range, envelope.input_voltage_range) == \
        ((2.0, 8.0), (2.0, 30.0), (20.0, 28.0))
    paper = collection_settings(1e-3, 1000, 0, region="paper", spec=my24_binding.converter)
    assert (paper.reference_range, paper.load_range, paper.input_voltage) == ((0.0, 8.0), (2.0, 5.0), 24.0)
    assert paper_region(PAPER_SPEC) == {"reference_range": (0.0, 20.0), "load_range": (4.0, 10.0),
                                        "input_voltage": 48.0}  # Table II: the paper's own experiment


def test_the_envelope_pi_and_the_classical_designs_take_the_converters_points(my24_binding):
    from cosim.design.classical_design import targets_for
    from cosim.design.pi_tuning import envelope_points

    assert envelope_points(my24_binding.converter) == ((2.0, 2.0, 24.0), (2.0, 30.0, 24.0), (5.0, 3.0, 24.0),
                                                       (5.0, 12.5, 24.0), (8.0, 2.0, 20.0), (8.0, 30.0, 28.0))
    with pytest.raises(ConfigError, match=r"the current-mode design's current limit needs inductor_current_limit"):
        targets_for(my24_binding, 1e-5)
    from dataclasses import replace

    binding = replace(my24_binding, spec=replace(my24_binding.converter, inductor_current_limit=6.0))
    targets = targets_for(binding, 1e-5)
    assert (targets.switching_frequency, targets.current_limit) == (100e3, 6.0)
    assert (targets.operating_point.output_voltage, targets.operating_point.input_voltage) == (5.0, 24.0)
    assert targets.envelope.loads == (2.0, 30.0)


def test_the_mpc_baseline_predicts_with_the_converters_circuit_and_starts_at_its_point(my24_binding, tmp_path):
    from cosim.design.controller_factory import make_controllers

    [mpc] = make_controllers(["mpc-nominal"], my24_binding, 1e-3, tmp_path, duty_limits=(0.0, 1.0))
    parameters = mpc.predictor.parameters
    assert (parameters.inductance, parameters.capacitance) == (100e-6, 47e-6)
    assert (mpc.nominal_load, mpc.nominal_input_voltage) == (3.0, 24.0)


# ------------------------------------------------------------------ the NNPC knows its domain


class _Network:
    """A controller whose predictor records the paper's 48 V, 4-10 Ohm data (as an identified network's does)."""

    name = "NNPC"

    def describe(self):
        from controllers.predictors import data_domain

        collection = {"input_voltage": 48.0, "input_voltage_range": None, "load_range": [4.0, 10.0],
                      "reference_range": [0.0, 20.0]}
        return {"predictor": {"data_domain": data_domain({"collection": collection})}}


def test_a_run_outside_the_networks_data_warns_once_and_says_so_in_its_metadata(my24_binding, capsys):
    from cosim.data_domain import checked_metadata, outside_data_domain

    scenario = load_scenario("load_change", my24_binding.converter)  # 24 V, 3 -> 2.5 Ohm (0.33 -> 0.4 S)
    found = outside_data_domain(_Network(), scenario)
    assert [(f["signal"], f["value"]) for f in found] == [("input_voltage", 24.0), ("load_conductance", 0.4)]
    assert found[1]["range"] == [0.1, 0.25]
    metadata = checked_metadata(_Network(), scenario, {"study": "x"})
    assert metadata == {"study": "x", "outside_data_domain": found}
    [line] = capsys.readouterr().err.splitlines()
    assert line.startswith("warning: NNPC on load_change runs outside its network's identification data: "
                           "input_voltage 24 V (data 48-48 V), load_conductance 0.4 S (data 0.1-0.25 S)")
    on_table_ii = load_scenario("load_change", PAPER_SPEC)
    assert outside_data_domain(_Network(), on_table_ii) == []
    assert checked_metadata(_Network(), on_table_ii, None) is None


def test_the_adaptive_and_the_explicit_nnpc_are_checked_against_their_networks_data(my24_binding):
    from cosim.data_domain import outside_data_domain

    class Wrapped:
        def __init__(self, key):
            self.name, self.key = "wrapped", key

        def describe(self):  # the adaptive NNPC nests the NNPC's description, a policy its expert's predictor's
            inner = _Network().describe()
            return {"type": "wrapped", self.key: inner if self.key == "inner" else inner["predictor"]}

    scenario = load_scenario("load_change", my24_binding.converter)
    for key in ("inner", "expert"):  # the adaptive NNPC's inner NNPC; the explicit NNPC's expert
        assert [f["signal"] for f in outside_data_domain(Wrapped(key), scenario)] == ["input_voltage",
                                                                                      "load_conductance"]


def test_the_identification_figure_states_the_datas_true_ranges():
    from controllers.predictors import data_domain, domain_text

    metadata = {"plant": "MyBuck24", "collection": {"input_voltage": 48.0, "input_voltage_range": None,
                                                    "load_range": [4.0, 10.0], "reference_range": [0.0, 20.0]}}
    assert domain_text(data_domain(metadata)) == "supply 48 V, loads 4-10 Ohm (0.1-0.25 S), references 0-20 V"


# ------------------------------------------------------------------ Table II is the built-in plant's spec, nothing more


def test_only_the_built_in_binding_reads_table_ii():
    importers = []
    for path in sorted((ROOT / "cosim").rglob("*.py")) + sorted((ROOT / "controllers").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module == "plant_fmu.table_ii":
                importers.append(path.relative_to(ROOT).as_posix())
    assert importers == ["cosim/fmi/binding.py"]
