"""Controllers as FMUs: the workbench's PI and predictive controllers exported as FMI 2.0
co-simulation units (hand-written C, generated data), driven by the master through the one
controller adapter, and externally authored controller FMUs through controller-binding files."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import fmpy
import fmpy.validation
import numpy as np
import pytest
from conftest import CONTROLLER_ROLES, cli, raw_callbacks, role_named_binding
from fmpy.fmi2 import FMU2Slave

from controllers.pi import PIController
from cosim.base.errors import ConfigError
from cosim.design.experiments import nnpc, scenarios_for
from cosim.design.plants import plant_binding
from cosim.design.vocabulary import SWITCHING_PERIOD
from cosim.fmi.controller import FmuController, builtin_controller_binding, load_controller_binding, open_controller
from cosim.fmi.controller_export import MODEL_DIR, VARIABLES, export_controller
from cosim.master import simulate
from cosim.scenarios import PAPER_SCENARIOS, load_scenario
from cosim.study.vocabulary import PAPER_SPEC

FIXTURES = Path(__file__).parent / "fixtures"
CORPUS = Path(__file__).parent / "corpus"
DUTY_TOLERANCE = 1e-9


@pytest.fixture(scope="module")
def out(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("controller-fmus")


@pytest.fixture(scope="module")
def pi() -> PIController:
    return PIController(0.0015, 15.6, 1e-3, duty_limits=(0.0, 0.95))


@pytest.fixture(scope="module")
def nnpc_fast():
    """The reproduction's kind of NNPC at one switching period: 2 delays, horizon 23, move blocking."""
    from controllers.nn_model import load_model

    return nnpc(load_model(FIXTURES / "nnpc_mismatch_switched_13p33us.pt", expect_period=SWITCHING_PERIOD),
                SWITCHING_PERIOD)


@pytest.fixture(scope="module")
def nnpc_fast_search(nnpc_fast):
    """The same NNPC with the search at every sample (the RTI's fallback, and the optimizer it is measured against)."""
    return nnpc(nnpc_fast.predictor.model, SWITCHING_PERIOD, optimizer="search")


@pytest.fixture(scope="module")
def fmus(out, pi, nnpc_1ms, nnpc_fast, nnpc_fast_search) -> dict[str, Path]:
    return {name: export_controller(controller, out / f"{name}.fmu")[0]
            for name, controller in (("pi", pi), ("nnpc_1ms", nnpc_1ms), ("nnpc_fast", nnpc_fast),
                                     ("nnpc_fast_search", nnpc_fast_search))}


# ------------------------------------------------------------------ the FMUs themselves


def test_value_references_in_the_header_match_the_model_description(fmus):
    header = (MODEL_DIR / "controller_variables.h").read_text()
    numbered = {m.group(1).lower(): int(m.group(2)) for m in re.finditer(r"VR_(\w+) = (\d+)", header)}
    assert numbered == {v.name: v.value_reference for v in VARIABLES}
    for name, path in fmus.items():
        md = fmpy.read_model_description(str(path))
        expected = {v.name: v.value_reference for v in VARIABLES if name == "pi" or not v.pi_only}
        assert {v.name: v.valueReference for v in md.modelVariables} == expected
        assert md.coSimulation is not None and md.modelExchange is None
        duty = next(u for u in md.outputs if u.variable.name == "duty_cycle")
        assert {d.name for d in duty.dependencies} == {v.name for v in VARIABLES if v.causality == "input"}


def test_fmpy_validation_reports_nothing_and_the_source_fmu_has_no_binary(fmus):
    import zipfile

    for path in fmus.values():
        assert fmpy.validation.validate_fmu(str(path)) == []
        with zipfile.ZipFile(path.with_name(f"{path.stem}-source.fmu")) as z:
            names = z.namelist()
        assert not any(n.startswith("binaries/") for n in names)
        assert {"sources/fmi2_glue.c", "sources/controller_fmu.c", "sources/predictive.c",
                "sources/controller_config.h"} <= set(names)


def test_the_generated_header_holds_data_only(out, nnpc_1ms):
    from controllers.codegen import config_header

    header = config_header(nnpc_1ms)
    code = [line for line in header.splitlines() if line and not line.startswith(("/*", " *", "#"))]
    assert all(line.startswith("static const ") for line in code), code  # no functions, no statements
    assert "static const BuckcPredictiveConfig PREDICTIVE_CONFIG" in header
    assert repr(float(nnpc_1ms.predictor.model._weights[0][0, 0])) in header  # the folded weights, exactly


# ------------------------------------------------------------------ equivalence with the Python controllers


def _duties(result) -> np.ndarray:
    frame = result.frame
    return frame.loc[frame["control_sample"], "duty_cycle"].to_numpy()


@pytest.mark.parametrize("mode", ["averaged", "switched"])
def test_pi_and_nnpc_fmus_give_the_python_duty_at_every_sample_at_1_ms(fmus, pi, nnpc_1ms, mode):
    binding = plant_binding("nominal", mode)
    for name, python in (("pi", pi), ("nnpc_1ms", nnpc_1ms)):
        fmu = open_controller(str(fmus[name]))
        assert fmu.sample_period == python.sample_period and fmu.duty_limits == python.duty_limits
        for scenario in PAPER_SCENARIOS:
            s = load_scenario(scenario, PAPER_SPEC)
            reference, exported = (_duties(simulate(binding, c, s)) for c in (python, fmu))
            assert len(exported) == len(reference) > 25
            assert np.max(np.abs(exported - reference)) <= DUTY_TOLERANCE, (name, scenario)
        fmu.close()


@pytest.mark.parametrize("mode", ["averaged", "switched"])
def test_the_nnpc_fmu_gives_the_python_duty_at_every_sample_at_one_switching_period(fmus, nnpc_fast, nnpc_fast_search,
                                                                                  mode):
    """No argmin flipped here: the C twin rounds operation by operation like numpy (1e-9 holds). On the switched
    plant (the network's own) the NNPC with the study's default optimizer, the RTI; on the averaged plant the
    one with the search. There the network, identified behind the switched plant's sensor, is a poor model, and
    the RTI exploits it: its duty alternates by about 0.2 from sample to sample (the search holds it), a loop
    so sensitive that the last-bit differences of two equal steps (tests/test_c_twins.py replays them at 1e-9)
    grow to 1e-3 - 1e-2 within 6 ms (start-up, reference step up)."""
    assert nnpc_fast.rti is not None and nnpc_fast_search.rti is None
    binding = plant_binding("mismatch", mode)
    name, python = ("nnpc_fast", nnpc_fast) if mode == "switched" else ("nnpc_fast_search", nnpc_fast_search)
    fmu = open_controller(str(fmus[name]))
    scenarios = scenarios_for(SWITCHING_PERIOD, spec=PAPER_SPEC)
    for scenario in scenarios[:2] if mode == "averaged" else scenarios:
        short = replace(scenario, duration=min(scenario.duration, 0.003), settle=min(scenario.settle, 0.001))
        reference, exported = (_duties(simulate(binding, c, short)) for c in (python, fmu))
        assert len(exported) > 200
        assert np.max(np.abs(exported - reference)) <= DUTY_TOLERANCE, scenario.name
    fmu.close()


# ------------------------------------------------------------------ the sample clock, through fmpy alone


class RawController:
    """A controller FMU stepped through fmpy directly (no workbench adapter)."""

    def __init__(self, path: Path, start=0.0):
        self.md = fmpy.read_model_description(str(path))
        self.vr = {v.name: v.valueReference for v in self.md.modelVariables}
        self.unzipdir = fmpy.extract(str(path))
        self.fmu = FMU2Slave(guid=self.md.guid, unzipDirectory=self.unzipdir,
                             modelIdentifier=self.md.coSimulation.modelIdentifier)
        self.log: list[tuple[int, str]] = []  # (status, message)
        self.fmu.instantiate(callbacks=raw_callbacks(self.log), loggingOn=True)
        self.fmu.setupExperiment(startTime=start)
        self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()
        self.time = start

    def set(self, **values):
        self.fmu.setReal([self.vr[k] for k in values], list(values.values()))

    def duty(self) -> float:
        return self.fmu.getReal([self.vr["duty_cycle"]])[0]

    def step(self, h):
        self.fmu.doStep(self.time, h)
        self.time += h


def test_reading_the_duty_at_a_sample_instant_computes_without_committing(fmus):
    """Feedthrough: the duty follows the inputs set at the instant; only fmi2DoStep advances the PI."""
    c = RawController(fmus["pi"])
    c.set(reference=12.0, measured_output_voltage=10.0)
    first = c.duty()
    c.set(measured_output_voltage=11.0)
    second = c.duty()
    assert second < first  # recomputed from the new input, not accumulated
    python = PIController(0.0015, 15.6, 1e-3, duty_limits=(0.0, 0.95))
    from controllers.base import Measurement

    assert second == python.step(Measurement(0.0, 12.0, 11.0))  # one sample, once
    c.step(1e-3)
    c.set(measured_output_voltage=11.5)
    assert c.duty() == python.step(Measurement(1e-3, 12.0, 11.5))


def test_any_communication_step_that_lands_on_the_sample_instants_gives_the_same_duties(fmus):
    def trace(substeps: int) -> list[float]:
        c = RawController(fmus["pi"], start=-0.004)
        duties = []
        for k in range(12):
            c.set(reference=12.0, measured_output_voltage=0.5 * k)
            duties.append(c.duty())
            for j in range(substeps):
                c.step(1e-3 / substeps)
                if j < substeps - 1:
                    assert c.duty() == duties[-1]  # held between the sample instants
        return duties

    assert trace(1) == trace(3) == trace(7)


def _python_pi_trace(controller: PIController, period: float, times, reference: float, measured: float):
    """The Python PI sampled at every instant k * period in ``times`` with constant inputs."""
    from controllers.base import Measurement

    controller.reset()
    return [controller.step(Measurement(t, reference, measured)) for t in times]


def test_a_step_spanning_sample_instants_takes_each_with_the_inputs_held(fmus):
    from controllers.base import Measurement

    python = PIController(0.0015, 15.6, 1e-3, duty_limits=(0.0, 0.95))
    c = RawController(fmus["pi"])
    c.set(reference=0.5, measured_output_voltage=0.1)
    c.step(3.5e-3)  # samples at 0, 1, 2 and 3 ms, all with these inputs
    held = [python.step(Measurement(k * 1e-3, 0.5, 0.1)) for k in range(4)]
    assert c.duty() == held[-1]  # t = 3.5 ms: the duty of the 3 ms sample, held
    assert c.fmu.getRealStatus(fmpy.fmi2.fmi2LastSuccessfulTime) == 3.5e-3
    c.step(0.5e-3)  # lands on the 4 ms instant, which the next step takes
    c.set(measured_output_voltage=0.2)
    assert c.duty() == python.step(Measurement(4e-3, 0.5, 0.2))
    c.step(2.5e-3)  # 4, 5 and 6 ms with vo = 0.2 V
    assert c.duty() == [python.step(Measurement(k * 1e-3, 0.5, 0.2)) for k in (5, 6)][-1]
    assert not [m for status, m in c.log if status > 1]


@pytest.mark.parametrize("fmi_version", [2, 3])
def test_plain_fmpy_simulate_fmu_with_default_settings_runs_the_controller_fmu(tmp_path, fmi_version):
    """fmpy's defaults: stop time 1 s, the DefaultExperiment's stepSize (= Ts = 0.1 ms) doubled until there
    are at most 1000 steps, i.e. 1.6 ms = 16 sample instants per communication step."""
    period = 1e-4
    python = PIController(0.0015, 15.6, period, duty_limits=(0.0, 0.95))
    path, _ = export_controller(python, tmp_path / "pi.fmu", fmi_version=fmi_version)
    md = fmpy.read_model_description(str(path))
    assert float(md.defaultExperiment.stepSize) == period
    result = fmpy.simulate_fmu(str(path))  # inputs at their start values: reference 0 V
    assert result["time"][-1] == pytest.approx(1.0) and np.all(result["duty_cycle"] == 0.0)
    result = fmpy.simulate_fmu(str(path), start_values={"reference": 0.002})
    times = result["time"]
    assert len(times) == 626 and times[1] == pytest.approx(16 * period)
    instants = np.arange(int(round(times[-1] / period)) + 1) * period
    trace = _python_pi_trace(python, period, instants, 0.002, 0.0)
    # each output point t = 16 j Ts is a sample instant: the duty read there is that instant's, after the
    # 16 j samples before it (each taken by the FMU inside the communication steps)
    expected = [trace[16 * j] for j in range(len(times))]
    np.testing.assert_allclose(result["duty_cycle"], expected, rtol=0, atol=DUTY_TOLERANCE)
    assert 0.0 < expected[100] < 0.95  # the integrator is still ramping: each sample counted


def test_a_refused_call_leaves_the_instance_usable(fmus):
    """FMI 2.0 status semantics: a call the FMU refuses (a wrong communication point, a parameter set
    after initialisation, a call in the wrong state) returns fmi2Error and changes nothing; a step whose
    sample cannot be computed returns fmi2Discard at fmi2LastSuccessfulTime (stepFailed); either way the
    instance can still be terminated and freed, and after a refusal the run goes on."""
    from fmpy.fmi1 import FMICallException
    from fmpy.fmi2 import fmi2LastSuccessfulTime

    python = PIController(0.0015, 15.6, 1e-3, duty_limits=(0.0, 0.95))
    from controllers.base import Measurement

    c = RawController(fmus["pi"])
    c.set(reference=0.5, measured_output_voltage=0.1)
    with pytest.raises(FMICallException) as refused:
        c.fmu.doStep(0.5e-3, 1e-3)
    assert refused.value.status == fmpy.fmi2.fmi2Error
    assert "currentCommunicationPoint = 0.0005" in c.log[-1][1]
    with pytest.raises(FMICallException):
        c.set(kp=1.0)
    assert "can only be set before fmi2ExitInitializationMode" in c.log[-1][1]
    with pytest.raises(FMICallException):
        c.fmu.enterInitializationMode()
    c.step(1e-3)  # the run goes on
    assert c.duty() == [python.step(Measurement(k * 1e-3, 0.5, 0.1)) for k in range(2)][-1]
    c.fmu.terminate()
    c.fmu.freeInstance()

    c = RawController(fmus["nnpc_1ms"])
    c.set(reference=12.0, measured_output_voltage=1.0, measured_inductor_current=1.0, measured_load_current=2.0)
    c.step(1e-3)
    c.set(measured_inductor_current=float("nan"))
    with pytest.raises(FMICallException) as discarded:
        c.fmu.doStep(1e-3, 2.5e-3)
    assert discarded.value.status == fmpy.fmi2.fmi2Discard
    assert "measured_inductor_current is not finite" in c.log[-1][1]
    assert c.fmu.getRealStatus(fmi2LastSuccessfulTime) == 1e-3
    c.fmu.terminate()  # stepFailed: terminating is allowed
    c.fmu.freeInstance()


def test_fmu_state_round_trips_the_predictive_controller(fmus):
    c = RawController(fmus["nnpc_1ms"])

    def samples(n, start):
        out = []
        for k in range(n):
            c.set(reference=12.0, measured_output_voltage=start + 0.3 * k, measured_inductor_current=1.0 + 0.01 * k,
                  measured_load_current=2.0)
            out.append(c.duty())
            c.step(1e-3)
        return out

    samples(5, 0.0)
    state = c.fmu.getFMUstate()
    time = c.time
    first = samples(6, 5.0)
    c.fmu.setFMUstate(state)
    c.time = time
    assert samples(6, 5.0) == first
    c.fmu.freeFMUstate(state)


# ------------------------------------------------------------------ externally authored controllers


@pytest.fixture(scope="module")
def python_pi_fmu(tmp_path_factory) -> Path:
    from pythonfmu.builder import FmuBuilder

    folder = tmp_path_factory.mktemp("python-pi")
    return Path(FmuBuilder.build_FMU(CORPUS / "python_pi_controller.py", dest=folder))


BINDING = """\
fmu = "{fmu}"
label = "PI (pythonfmu)"

[roles.reference]
variable = "Vref"
[roles.measured_output_voltage]
variable = "Vmeas"
[roles.duty_cycle]
variable = "Dpct"
scale = 100.0
[roles.sample_period]
variable = "Ts"

[parameters]
Kp = 0.0015
Ki = 15.6
Dmax = 95.0
"""


def test_a_pythonfmu_pi_under_other_names_matches_the_built_in_pi(python_pi_fmu, tmp_path, pi):
    path = tmp_path / "pi.toml"
    path.write_text(BINDING.format(fmu=python_pi_fmu))
    controller = FmuController(load_controller_binding(path))
    assert controller.sample_period == 1e-3 and controller.name == "PI (pythonfmu)"
    for scenario in ("startup", "reference_up"):
        s = load_scenario(scenario, PAPER_SPEC)
        reference = _duties(simulate(plant_binding("nominal", "switched"), pi, s))
        other = _duties(simulate(plant_binding("nominal", "switched"), controller, s))
        np.testing.assert_allclose(other, reference, rtol=0, atol=1e-12)


def test_a_sample_period_set_in_the_bindings_parameters_is_the_one_the_master_steps_at(python_pi_fmu, tmp_path):
    """[parameters] Ts = 2e-3 on the FMU's sample-period parameter: the FMU computes with 2 ms, and the master now
    steps it every 2 ms (it stepped it at the start value's 1 ms, halving the integral action); a role the workbench
    writes stays out of [parameters]."""
    path = tmp_path / "pi.toml"
    path.write_text(BINDING.format(fmu=python_pi_fmu) + "Ts = 2e-3\n")
    controller = FmuController(load_controller_binding(path))
    assert controller.sample_period == 2e-3
    controller.close()
    path.write_text(BINDING.format(fmu=python_pi_fmu) + "Vref = 5.0\n")
    with pytest.raises(ConfigError, match=r"pi.toml:\d+: parameter 'Vref' is the variable of role 'reference', which "
                                          r"the workbench sets itself"):
        load_controller_binding(path)


@pytest.mark.parametrize("edit,message", [
    (("[roles.duty_cycle]\nvariable = \"Dpct\"\nscale = 100.0\n", ""), "missing role [roles.duty_cycle]"),
    (('variable = "Vmeas"', 'variable = "Vmeasured"'), r"pi.toml:7: role 'measured_output_voltage' names variable "
                                                      r"'Vmeasured', which PythonPI.fmu does not have"),
    (('variable = "Vref"', 'variable = "Dpct"'), r"pi.toml:5: role 'reference' needs causality input or parameter, "
                                                 r"but 'Dpct' has causality output"),
    (("Kp = 0.0015", 'Kp = "fast"'), r"pi.toml:15: parameter 'Kp' is Real in PythonPI.fmu, got 'fast'"),
    (('variable = "Vmeas"', 'variable = "Vref"'), r"pi.toml:7: role 'measured_output_voltage' names variable 'Vref', "
                                                  r"which role 'reference' names too: the workbench writes "
                                                  r"measured_output_voltage into it"),
    (('label = "PI (pythonfmu)"', 'label = "PI"\nsample_period = 1.5e-3'),
     r"pi.toml:3: sample_period = 0.0015 s is not a whole multiple of the FMU's own sample period 0.001 s"),
    (('label = "PI (pythonfmu)"', 'label = "PI"\nduty_limits = [0.5, 0.2]'), r"pi.toml:3: duty_limits = \[0.5, 0.2\] is invalid: expected 0 <= min < max <= 1"),
    (("[roles.sample_period]\nvariable = \"Ts\"\n", ""), r"no sample period: give sample_period"),
])
def test_controller_binding_mistakes_name_file_key_and_line(python_pi_fmu, tmp_path, edit, message):
    path = tmp_path / "pi.toml"
    path.write_text(BINDING.format(fmu=python_pi_fmu).replace(*edit))
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")
                       if "roles." in message else message):
        FmuController(load_controller_binding(path))


def test_a_parameter_the_controller_fmu_refuses_is_named_at_its_line(fmus, tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(role_named_binding(fmus["pi"], CONTROLLER_ROLES, "ki = 15.6\nkp = -1\n", sample_period=1e-3))
    with pytest.raises(ConfigError, match=r"c.toml:11: parameters.kp = -1: the controller FMU refuses its set-up with "
                                          r"this value \(fmi2ExitInitializationMode failed\): .*kp, ki: expected "
                                          r"finite values >= 0"):
        FmuController(load_controller_binding(path))
    path.write_text(path.read_text().replace("kp = -1", "kp = 0.0015"))  # the same file, a value it takes
    assert FmuController(load_controller_binding(path)).sample_period == 1e-3


# ------------------------------------------------------------------ the command line


def test_export_then_run_from_the_command_line(tmp_path, fmus):
    done = cli("export-controller", "pi", "--kp", "0.0015", "--ki", "15.6", "--out", str(tmp_path / "mine.fmu"))
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "mine.fmu").is_file() and (tmp_path / "mine-source.fmu").is_file()
    done = cli("run", "startup", "--controller", "pi", "--kp", "0.0015", "--ki", "15.6", "--controller",
               str(tmp_path / "mine.fmu"), "--no-figures", "--out", str(tmp_path / "runs"))
    assert done.returncode == 0, done.stderr
    from cosim.results import read_run

    runs = {p.stem.split("__")[1]: read_run(p) for p in (tmp_path / "runs" / "runs").glob("*.parquet")}
    assert set(runs) == {"pi", "mine-fmu"}  # the FMU runs as "mine (FMU)", the docs' NAME (FMU)
    np.testing.assert_array_equal(_duties(runs["pi"]), _duties(runs["mine-fmu"]))
    assert runs["mine-fmu"].metadata["controller"]["type"] == "controller FMU"
    assert runs["mine-fmu"].metadata["controller"]["name"] == "mine (FMU)"
    # duty limits with nothing to apply them to (an FMU limits its duty itself) are refused, not ignored
    done = cli("run", "startup", "--controller", str(tmp_path / "mine.fmu"), "--duty-max", "0.2", "--no-figures",
               "--out", str(tmp_path / "limited"))
    assert done.returncode == 2 and "duty limits (0.0, 0.2) apply to the built-in and Python controllers, but only " \
        "controller FMUs run here" in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr


def test_controller_fmu_faults_end_in_one_line(tmp_path, fmus):
    """A controller FMU missing a role is a configuration error (2); one that fails mid-run (the
    NNPC given no inductor current) a fault (3) with the rows kept and marked incomplete."""
    (tmp_path / "plain.fmu").write_bytes(Path(fmpy.__file__).read_bytes())
    done = cli("run", "startup", "--controller", str(tmp_path / "plain.fmu"), "--out", str(tmp_path / "a"))
    assert done.returncode == 2 and "is not a zip archive" in done.stderr and "Traceback" not in done.stderr
    from cosim.base.errors import ControllerError

    plant = replace(plant_binding("nominal", "averaged"), roles={
        r: m for r, m in plant_binding("nominal", "averaged").roles.items()
        if r not in ("inductor_current", "measured_inductor_current")})
    controller = open_controller(str(fmus["nnpc_1ms"]))
    from cosim.master import RunFailed

    with pytest.raises(RunFailed, match=r"needs a finite inductor current|measured_inductor_current is not finite"
                       ) as failure:
        simulate(plant, controller, load_scenario("startup", PAPER_SPEC))
    assert isinstance(failure.value.cause, ControllerError) and failure.value.exit_code == 3
    assert failure.value.partial.complete is False


def test_a_controller_fmu_without_the_role_names_needs_a_binding_file(python_pi_fmu):
    with pytest.raises(ConfigError, match="has no variable 'reference': a controller FMU without the workbench's "
                                          "role names needs a controller-binding file"):
        builtin_controller_binding(python_pi_fmu)


def test_a_sample_period_the_fmus_unbound_own_contradicts_is_warned_of(fmus, tmp_path, capsys):
    path = tmp_path / "c.toml"
    for period, warned in ((2e-3, True), (1e-3, False)):  # the exported PI's own sample_period starts at 1 ms
        path.write_text(role_named_binding(fmus["pi"], CONTROLLER_ROLES, sample_period=period))
        load_controller_binding(path)
        err = capsys.readouterr().err
        assert (err == f"warning: {path}:2: sample_period = {period:g} s, but the FMU's parameter 'sample_period' "
                       "is 0.001 s and is not bound ([roles.sample_period]): the FMU may compute with its own "
                       "period while the master steps it at this one\n") if warned else err == ""
    # the FMU's period set to the binding's by [parameters]: they agree, nothing to warn of
    path.write_text(role_named_binding(fmus["pi"], CONTROLLER_ROLES, parameters="sample_period = 0.002",
                                       sample_period=2e-3))
    load_controller_binding(path)
    assert capsys.readouterr().err == ""
