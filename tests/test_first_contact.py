"""Issue 23: the defects a new user meets in the first two hours, each with the test that would have
caught it (docs: guide/runs.md "Cached designs", guide/command-line.md, guide/python-controller.md)."""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

import pytest

from cosim.cli import main
from cosim.study.vocabulary import PAPER_SPEC

# ------------------------------------------------------------------ 1. cached designs keyed by what they depend on


@pytest.fixture
def quick_tuning(monkeypatch):
    """The PI tuning on a 2 x 2 grid and 6 Nelder-Mead evaluations (its design key says so, so a cached
    tuning is reused under the same patch): the tests need a tuning, not a good one."""
    import cosim.design.pi_tuning as tuning

    monkeypatch.setattr(tuning, "GRID_A", (0.0, 0.1))
    monkeypatch.setattr(tuning, "GRID_B", (0.01, 0.3))
    monkeypatch.setattr(tuning, "_nelder_mead_evaluations", lambda quick: 6)


@pytest.fixture
def own_plant(tmp_path, buck_fmu) -> Path:
    """A user's plant: a copy of the built-in FMU behind a drafted binding file (averaged mode)."""
    from cosim.fmi.binding_file import write_draft_binding

    fmu = tmp_path / "my.fmu"
    shutil.copy(buck_fmu, fmu)
    toml = write_draft_binding(fmu, tmp_path / "my.toml")
    toml.write_text(toml.read_text().replace("# output_voltage = 12.0 ", "output_voltage = 12.0 "))  # its converter
    return Path(toml)


def run_pi(toml: Path, out: Path, capsys) -> tuple[dict, str]:
    """``buck-cosim run reference_down --plant TOML`` (PI tuned on demand): the run's metadata and stderr."""
    assert main(["--no-progress", "run", "reference_down", "--plant", str(toml), "--out", str(out),
                 "--no-figures"]) == 0
    meta = json.loads(next((out / "runs").glob("reference_down__pi__*.json")).read_text())
    return meta, capsys.readouterr().err


def test_a_changed_plant_retunes_the_cached_pi_and_says_so(own_plant, tmp_path, quick_tuning, capsys):
    out = tmp_path / "out"
    first, err = run_pi(own_plant, out, capsys)
    tuning_file = out / "tuning" / "pi__bound-my__1ms.json"
    stored = json.loads(tuning_file.read_text())
    key = stored["design"]["key"]
    assert first["controller"]["tuning"]["design_key"] == key  # the run names the design it ran
    assert stored["design"]["inputs"]["plant"]["fmu_sha256"] == first["plant"]["fmu_sha256"]
    # defect 5: the tuning is announced with its size, an estimate and its totals, under --no-progress too
    assert "tuning the PI for" in err and "at most 10 evaluations x 3 scenarios" in err
    assert "the tuning takes about" in err and f"evaluations, {3 * stored['evaluations']} simulations)" in err
    assert f"design key {key}" in err

    again, err = run_pi(own_plant, out, capsys)  # nothing changed: reused, silently
    assert again["controller"]["tuning"]["design_key"] == key and "tuning the PI" not in err

    # L = 330 uH under [parameters]: the same binding label and tag, another plant
    own_plant.write_text(own_plant.read_text().replace("# inductance = 220e-6", "inductance = 330e-6"))
    changed, err = run_pi(own_plant, out, capsys)
    lines = [line for line in err.splitlines() if "does not fit" in line]
    assert len(lines) == 1 and "plant parameters changed" in lines[0] and "re-tuning the PI" in lines[0], err
    new_key = changed["controller"]["tuning"]["design_key"]
    assert new_key != key and f"{key} -> {new_key}" in lines[0]
    assert json.loads(tuning_file.read_text())["design"]["inputs"]["plant"]["parameters"]["inductance"] == 330e-6

    # the FMU rebuilt (other bytes, same file name): tuned again
    with zipfile.ZipFile(tmp_path / "my.fmu", "a") as archive:
        archive.comment = b"rebuilt"
    rebuilt, err = run_pi(own_plant, out, capsys)
    assert "plant FMU (SHA-256) changed" in err and "re-tuning the PI" in err
    assert rebuilt["controller"]["tuning"]["design_key"] not in (key, new_key)


def test_a_tuning_file_of_an_older_version_is_not_reused(own_plant, tmp_path, quick_tuning, capsys):
    out = tmp_path / "out"
    run_pi(own_plant, out, capsys)
    tuning_file = out / "tuning" / "pi__bound-my__1ms.json"
    old = json.loads(tuning_file.read_text())
    del old["design"]  # what buck-cosim wrote before design keys
    old["kp"] = 123.0
    tuning_file.write_text(json.dumps(old))
    meta, err = run_pi(own_plant, out, capsys)
    assert "has no design key" in err and meta["controller"]["kp_per_V"] != 123.0


def test_a_changed_plant_identifies_the_cached_network_again(tmp_path, quick_tuning, capsys):
    """The network of ``run --controller nnpc`` is cached under its design key (which names the PI's)."""
    from dataclasses import replace

    import cosim.design.controller_factory as factory
    from cosim.fmi.binding import builtin_binding

    binding = builtin_binding("averaged")
    first = factory.trained_model("nnpc-paper", binding, 1e-3, tmp_path, samples=300, seed=1, model_path=None)
    err = capsys.readouterr().err
    design = first.metadata["design"]
    [tuning_file] = (tmp_path / "tuning").glob("pi__*.json")
    assert design["inputs"]["depends_on"]["pi"] == json.loads(tuning_file.read_text())["design"]["key"]
    data = Path(first.metadata["data_file"])
    assert data.is_file() and str(data) in err and "held-out one-step RMSE" in err  # data file and RMSE printed
    again = factory.trained_model("nnpc-paper", binding, 1e-3, tmp_path, samples=300, seed=1, model_path=None)
    assert again.metadata["design"]["key"] == design["key"] and "does not fit" not in capsys.readouterr().err
    bigger = replace(binding, parameters={**binding.parameters, "inductance": 330e-6})  # same label and tag
    other = factory.trained_model("nnpc-paper", bigger, 1e-3, tmp_path, samples=300, seed=1, model_path=None)
    err = capsys.readouterr().err
    assert other.metadata["design"]["key"] != design["key"]
    assert sum("does not fit" in line for line in err.splitlines()) == 2, err  # the PI's line and the network's
    assert "plant parameters changed" in err and "identifying" in err


def test_design_keys_name_what_changed():
    from cosim.design.design_cache import changed_inputs

    plant = {"fmu_sha256": "a", "roles": {}, "parameters": {"L": 1}, "interface": None, "max_step_s": None}
    stored = {"plant": plant, "control_period_s": 1e-3, "seed": 0, "settings": {"x": 1}}
    wanted = {**stored, "plant": {**plant, "fmu_sha256": "b"}, "seed": 1}
    assert changed_inputs(stored, wanted) == ["plant FMU (SHA-256)", "seed"]
    assert changed_inputs(stored, stored) == []


# ------------------------------------------------------------------ 8. sweep output


def _summary(rows, axes=("capacitor_esr",), controllers=("PI",), scenarios=("load_change",), thresholds=()):
    """A sweep summary of hand-made rows (the parts of a spec, plan and recipes it reads)."""
    from types import SimpleNamespace as NS

    from cosim.design.sweeps.summary import _Summary

    spec = NS(name="study", scenarios=[NS(name=s) for s in scenarios], thresholds=thresholds, control_period=1e-3,
              samples=len(rows) // max(1, len(controllers) * len(scenarios)), grid_points=1)
    plan = NS(axes=[NS(axis=NS(name=a), unit="Ohm") for a in axes], spec=spec)
    return _Summary(spec, plan, [NS(name=c) for c in controllers], rows, Path("."), "id")


def _rows(n=24, seed=3):
    import numpy as np
    import pandas as pd

    rng = np.random.default_rng(seed)
    esr = np.linspace(0.0, 0.1, n)
    return pd.DataFrame({"controller": "PI", "scenario": "load_change", "status": "ok", "capacitor_esr": esr,
                         "overshoot_pct": 2.0 + 30.0 * esr,  # a real effect: 3 % over the range
                         "steady_state_error_pct": 1e-10 * (1 + esr),  # rounding: rho = +1, span 1e-11 %
                         "settling_time_ms": rng.normal(1.0, 0.1, n),  # noise: no correlation
                         "iae_Vs": 4.5e-3 + 1e-4 * esr + rng.normal(0, 1e-6, n),
                         "point": 0, "sample": np.arange(n), "run_id": [f"r{i}" for i in range(n)]})


def test_the_most_influential_parameter_needs_significance_and_a_magnitude():
    table = _summary(_rows()).influence_table().set_index("metric")
    assert table.loc["overshoot_pct", "axis"] == "capacitor_esr" and table.loc["overshoot_pct", "p_value"] < 1e-6
    noise = table.loc["steady_state_error_pct"]
    assert noise["axis"] == "none" and noise["spearman_rho"] == pytest.approx(1.0) and "spans" in noise["reason"]
    assert table.loc["settling_time_ms", "axis"] == "none" and "not significant" in table.loc["settling_time_ms",
                                                                                                 "reason"]


def test_the_sweep_panels_keep_every_label_inside_the_figure(monkeypatch, tmp_path):
    import matplotlib.pyplot as plt

    from cosim.design.sweeps.spec import Threshold

    figures, close = [], plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: figures.append(fig))  # kept open to be measured
    summary = _summary(_rows(), thresholds=(Threshold("overshoot_pct", 5.0),))
    summary.out_dir = tmp_path
    summary.figures(vector=False)
    assert len(figures) == 3  # distributions, influence, yield
    for fig in figures:
        fig.canvas.draw()
        width, height = fig.canvas.get_width_height()
        for ax in fig.axes:
            (x0, x1), (y0, y1) = sorted(ax.get_xlim()), sorted(ax.get_ylim())
            texts = [ax.yaxis.label, ax.xaxis.label,  # and the tick labels drawn (inside the view limits)
                     *[t for v, t in zip(ax.get_yticks(), ax.get_yticklabels()) if y0 <= v <= y1],
                     *[t for v, t in zip(ax.get_xticks(), ax.get_xticklabels()) if x0 <= v <= x1]]
            for text in texts:
                if text.get_text():
                    box = text.get_window_extent()
                    assert box.x0 >= 0 and box.x1 <= width and box.y0 >= 0 and box.y1 <= height, text.get_text()
        close(fig)


def test_the_yield_table_names_its_share_columns_once():
    from cosim.design.sweeps.summary import pass_column

    assert pass_column("overshoot_pct") == "pass_overshoot_pct"
    assert pass_column("settling_time_ms") == "pass_settling_time_ms_pct"


# ------------------------------------------------------------------ figures and metrics: the ripple


class FixedDuty:
    """Open loop: the same duty at every sample."""

    name, sample_period, duty_limits = "D = 0.25", 1 / 75e3, (0.0, 1.0)

    def __init__(self, duty=0.25):
        self.duty = duty

    def reset(self):
        pass

    def step(self, m):
        return self.duty

    def describe(self):
        return {"type": "fixed duty", "name": self.name, "duty": self.duty}


@pytest.fixture(scope="module")
def open_loop_switched():
    """The switched plant at D = 0.25 (48 V -> 12 V, 6 Ohm), recorded 40 times per PWM period."""
    from dataclasses import replace

    from cosim import builtin_binding, load_scenario, simulate

    scenario = replace(load_scenario("startup", PAPER_SPEC), duration=6e-3)
    return simulate(builtin_binding("switched"), FixedDuty(), scenario, record_period=1 / 75e3 / 40)


def test_the_ripple_metrics_match_the_closed_form_of_the_switched_plant(open_loop_switched):
    """DESIGN.md: in CCM, delta iL = (Vs - Vo) D Ts / L and delta vo = delta iL / (8 C fsw) with an ideal
    capacitor -- 0.545 A and 90.9 mV at D = 0.25 on Table II."""
    from cosim.metrics import run_metrics
    from plant_fmu.table_ii import TABLE_II as P

    d, vo = 0.25, 0.25 * P.input_voltage
    ripple_i = (P.input_voltage - vo) * d / (P.switching_frequency * P.inductance)
    ripple_v = ripple_i / (8 * P.capacitance * P.switching_frequency)
    assert ripple_i == pytest.approx(0.545, abs=1e-3) and ripple_v == pytest.approx(0.0909, abs=1e-4)
    m = run_metrics(open_loop_switched)
    assert m["inductor_current_ripple_A"] == pytest.approx(ripple_i, rel=0.01)
    assert m["output_voltage_ripple_mV"] == pytest.approx(ripple_v * 1e3, rel=0.02)


def test_the_averaged_plant_has_no_ripple():
    from dataclasses import replace

    from cosim import builtin_binding, load_scenario, run_metrics, simulate

    result = simulate(builtin_binding("averaged"), FixedDuty(),
                      replace(load_scenario("startup", PAPER_SPEC), duration=6e-3))
    m = run_metrics(result)
    assert m["inductor_current_ripple_A"] < 1e-6 and m["output_voltage_ripple_mV"] < 1e-3


def test_the_run_figure_has_a_duty_panel_and_the_transient_with_the_metrics_marked(open_loop_switched):
    """At 13.33 us the start-up is over in about a millisecond of a 6 ms run: the right column shows it,
    the overshoot marker sits on the instantaneous peak the metrics report, the settling instant and band
    are drawn, and the figure says which curve is the PWM-period mean and which the metrics' signal."""
    import matplotlib.pyplot as plt

    from cosim.metrics import run_metrics
    from cosim.plots import scenario_figure

    m = run_metrics(open_loop_switched)
    fig = scenario_figure([open_loop_switched], "start-up", period_means=True)
    try:
        v_full, v_zoom, i_full, i_zoom, d_full, d_zoom = fig.axes[:6]
        assert d_full.get_ylabel() == "duty cycle [1]"
        duty = [line for line in d_full.get_lines() if line.get_drawstyle() == "steps-post"]
        assert len(duty) == 1 and set(duty[0].get_ydata()) == {0.25}
        low, high = v_zoom.get_xlim()
        assert high <= 1.5 * m["settling_time_ms"] * 1.06 and m["settling_time_ms"] < high  # the transient, not 6 ms
        assert v_full.get_xlim()[1] >= 5.9
        frame = open_loop_switched.frame
        [peak] = [line for line in v_zoom.get_lines() if line.get_marker() == "v"]
        assert peak.get_ydata()[0] == pytest.approx(frame["output_voltage"].max())
        assert peak.get_ydata()[0] == pytest.approx(12.0 * (1 + m["overshoot_pct"] / 100))
        [current_peak] = [line for line in i_zoom.get_lines() if line.get_marker() == "v"]
        assert current_peak.get_ydata()[0] == pytest.approx(m["peak_inductor_current_A"])
        settle = [line for line in v_zoom.get_lines() if line.get_linestyle() == ":"]
        assert settle and settle[0].get_xdata()[0] == pytest.approx(m["settling_time_ms"])
        legend = [t.get_text() for t in v_zoom.get_legend().get_texts()]
        assert f"D = 0.25: overshoot {m['overshoot_pct']:.3g} %, settling {m['settling_time_ms']:.3g} ms" in legend
        assert "2 % settling band" in legend
        assert "faint: instantaneous -- the metrics' signal" in fig._suptitle.get_text()
    finally:
        plt.close(fig)


# ------------------------------------------------------------------ NNPC identification plots


def test_identification_writes_learning_curves_and_held_out_predictions_beside_the_model(tmp_path, quick_tuning):
    import matplotlib.pyplot as plt
    import numpy as np
    import pandas as pd

    import cosim.design.controller_factory as factory
    from controllers.nn_model import build_dataset
    from cosim.design.identification import identification_figure
    from cosim.fmi.binding import builtin_binding

    model = factory.trained_model("nnpc-paper", builtin_binding("averaged"), 1e-3, tmp_path, samples=300, seed=1,
                                  model_path=None)
    [model_path] = (tmp_path / "models").glob("*__nnpc-paper.pt")
    figure = model_path.with_name(f"{model_path.stem}.identification.png")
    assert figure.read_bytes()[:4] == b"\x89PNG"
    history = np.asarray(model.metadata["training"]["history"])
    assert history.shape[1] == 3 and history[0, 0] == 0 and len(history) >= 2
    assert history[:, 2].min() < history[0, 2]  # the validation loss fell from the untrained network's

    data = pd.read_parquet(Path(model.metadata["data_file"]))
    fig = identification_figure(model, data)
    try:
        loss, current, voltage = fig.axes
        training, validation = loss.get_lines()[:2]
        assert list(training.get_ydata()) == list(history[:, 1]) and list(validation.get_ydata()) == list(history[:, 2])
        held_out = data.iloc[int(round(len(data) * 0.8)):]
        x, y = build_dataset(held_out, model.config)
        measured, predicted = voltage.get_lines()[:2]
        assert np.allclose(measured.get_ydata(), y[:400, 1]) and np.allclose(predicted.get_ydata(),
                                                                             model.predict(x)[:400, 1])
        rmse = model.metadata["held_out_rmse"]["one_step_rmse_voltage_V"]
        assert np.sqrt(np.mean((model.predict(x)[:, 1] - y[:, 1]) ** 2)) == pytest.approx(rmse)
    finally:
        plt.close(fig)


# ------------------------------------------------------------------ 4. implausible bindings: one warning line


def test_a_duty_in_percent_bound_without_its_scale_warns_in_inspect_and_run(python_buck_fmu, tmp_path):
    """The pythonfmu plant takes its duty in percent and declares no units: the draft binds it with scale 1.
    inspect says the scales are guesses; the run ends far from the reference with the duty at its limit and
    says so in one warning line (exit 0: the run itself worked)."""
    from conftest import cli

    done = cli("inspect", str(python_buck_fmu), "--draft-binding", "draft.toml", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    warnings = [line for line in done.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "no unit for D (duty_cycle)" in warnings[0] and "scale = 100" in warnings[0]
    draft = (tmp_path / "draft.toml").read_text()
    assert 'variable = "D"' in draft and "scale = 100" not in draft.split('variable = "D"')[1].split("[")[0]
    assert "# output_voltage = 12.0" in draft  # the converter table: every key there, commented out
    draft = draft.replace("# output_voltage = 12.0 ", "output_voltage = 12.0 ")
    (tmp_path / "draft.toml").write_text(draft)

    done = cli("run", "reference_down", "--plant", "draft.toml", "--kp", "0.0017", "--ki", "15.6", "--out", "out",
               "--no-figures", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    warnings = [line for line in done.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1, done.stderr
    assert "implausible runs" in warnings[0] and "reference_down with PI: duty at a limit for" in warnings[0]
    assert "below the reference" in warnings[0] and "a duty in percent needs scale = 100" in warnings[0]

    (tmp_path / "draft.toml").write_text(draft.replace('variable = "D"', 'variable = "D"\nscale = 100.0'))
    done = cli("run", "reference_down", "--plant", "draft.toml", "--kp", "0.0017", "--ki", "15.6", "--out", "out",
               "--no-figures", cwd=tmp_path)
    assert done.returncode == 0 and "warning" not in done.stderr, done.stderr
    # the current in mA (IL_mA) bound without its scale reads 1000 x: a peak of "thousands of amperes"
    assert 'variable = "IL_mA"\nscale = 1000.0' in draft
    (tmp_path / "draft.toml").write_text(draft.replace('variable = "D"', 'variable = "D"\nscale = 100.0')
                                         .replace('variable = "IL_mA"\nscale = 1000.0', 'variable = "IL_mA"'))
    done = cli("run", "reference_down", "--plant", "draft.toml", "--kp", "0.0017", "--ki", "15.6", "--out", "out",
               "--no-figures", cwd=tmp_path)
    [warning] = [line for line in done.stderr.splitlines() if line.startswith("warning:")]
    assert done.returncode == 0 and "reference_down with PI: inductor current " in warning, done.stderr
    assert "x the load current vo/R" in warning and "duty at a limit" not in warning


def test_a_unit_that_contradicts_its_role_is_flagged_when_the_binding_is_read(buck_fmu, tmp_path):
    from conftest import cli

    from cosim.fmi.binding_file import write_draft_binding

    toml = write_draft_binding(buck_fmu, tmp_path / "plant.toml")
    text = toml.read_text()
    text = text.replace('[roles.duty_cycle]   # guessed from name \'duty_cycle\', unit 1\nvariable = "duty_cycle"',
                        '[roles.duty_cycle]\nvariable = "duty_cycle"\nscale = 100.0')
    text = text.replace('variable = "inductor_current"', 'variable = "output_voltage"', 1) \
        if "[roles.inductor_current]" in text else text
    toml.write_text(text)
    done = cli("inspect", str(toml), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    [warning] = [line for line in done.stderr.splitlines() if line.startswith("warning:")]
    assert "implausible binding" in warning
    assert "duty_cycle is 'duty_cycle' in 1 with scale = 100 (a duty in 1 needs scale = 1)" in warning
    assert "inductor_current is 'output_voltage' in V, a voltage, not a current" in warning
    assert "duty_cycle -> duty_cycle x 100" in done.stdout


# ------------------------------------------------------------------ 6. your own Python controller on the command line

INTEGRATOR = '''
from controllers.base import Measurement


class Integrator:
    """duty += gain per volt of error per sample."""

    def __init__(self, sample_period, duty_limits, gain=0.005):
        self.name, self.sample_period, self.duty_limits, self.gain = "integrator", sample_period, duty_limits, gain

    def reset(self):
        self.duty = 0.0

    def step(self, m: Measurement) -> float:
        self.duty = min(max(self.duty + self.gain * (m.reference - m.output_voltage), 0.0), 1.0)
        return self.duty

    def describe(self):
        return {"type": "integrator", "name": self.name, "gain": self.gain}


class Broken:
    name = "broken"
'''


@pytest.mark.parametrize("form", ["path", "module"])
def test_run_takes_a_python_controller_by_file_or_module(tmp_path, form, capsys, monkeypatch):
    (tmp_path / "mine.py").write_text(INTEGRATOR)
    monkeypatch.chdir(tmp_path)
    spec = "mine.py:Integrator" if form == "path" else "mine:Integrator"
    assert main(["--no-progress", "run", "startup", "--controller", spec, "--controller", "pi", "--kp", "0.0017",
                 "--ki", "15.6", "--out", "out", "--no-figures"]) == 0
    out = capsys.readouterr().out
    assert "integrator" in out and "PI" in out
    meta = json.loads((tmp_path / "out" / "runs" / "startup__integrator__nominal-averaged__1ms.json").read_text())
    assert meta["controller"] == {"type": "integrator", "name": "integrator", "gain": 0.005}
    assert meta["complete"] is True


@pytest.mark.parametrize("spec,message", [
    ("missing.py:Integrator", "--controller missing.py:Integrator: missing.py does not exist"),
    ("mine.py:Integrater", "mine.py has no 'Integrater' (did you mean 'Integrator'?)"),
    ("mine.py:Broken", "the controller lacks sample_period, duty_limits, reset, step, describe"),
    ("nosuchmodule:Thing", "no module named 'nosuchmodule'"),
    ("PI", "--controller PI is unknown (did you mean 'pi'?): expected one of pi, nnpc"),
])
def test_controller_mistakes_are_one_line_errors_with_the_valid_names(tmp_path, spec, message):
    from conftest import cli, one_line_error

    (tmp_path / "mine.py").write_text(INTEGRATOR)
    one_line_error(cli("run", "startup", "--controller", spec, "--out", "out", cwd=tmp_path), 2, message)
    assert not (tmp_path / "out" / "runs").exists()


# ------------------------------------------------------------------ 7. the command line says what the docs say


def test_export_controller_offers_only_what_it_can_export(capsys):
    with pytest.raises(SystemExit):
        main(["export-controller", "--help"])
    text = capsys.readouterr().out
    assert "nnpc-explicit" in text and "nnpc-adaptive" not in text


def test_scenarios_lists_parameter_events_with_their_values(capsys):
    assert main(["scenarios"]) == 0
    line = next(line for line in capsys.readouterr().out.splitlines() if "capacitor_ageing" in line)
    assert "6.75 ms: capacitance=7.7e-06, inductor_resistance=0.16875" in line and ": ," not in line


def test_gains_for_a_controller_that_takes_none_are_refused(tmp_path):
    from conftest import cli, one_line_error

    one_line_error(cli("run", "startup", "--controller", "mpc-nominal", "--kp", "0.001", "--ki", "15", "--out", "o",
                       cwd=tmp_path), 2, "--kp and --ki set the PI's gains, but no --controller pi is run")


def test_binding_mistakes_suggest_the_close_name(buck_fmu, tmp_path):
    from conftest import cli, one_line_error

    from cosim.fmi.binding_file import write_draft_binding

    toml = write_draft_binding(buck_fmu, tmp_path / "plant.toml")
    toml.write_text(toml.read_text().replace('variable = "output_voltage"', 'variable = "output_volage"')
                    .replace("# inductance = 220e-6", "inductanse = 330e-6"))
    one_line_error(cli("run", "startup", "--plant", str(toml), "--kp", "0", "--ki", "14", cwd=tmp_path), 2,
                   "names variable 'output_volage', which BuckConverter")
    one_line_error(cli("run", "startup", "--plant", str(toml), "--kp", "0", "--ki", "14", cwd=tmp_path), 2,
                   "does not have (did you mean 'output_voltage'")
    toml.write_text(toml.read_text().replace('variable = "output_volage"', 'variable = "output_voltage"'))
    one_line_error(cli("run", "startup", "--plant", str(toml), "--kp", "0", "--ki", "14", cwd=tmp_path), 2,
                   "(did you mean 'inductance'?)")


def test_a_controller_fmu_runs_under_its_documented_name_and_exports_leave_no_empty_folders(tmp_path):
    from conftest import cli

    done = cli("export-controller", "pi", "--kp", "0.0017", "--ki", "15.6", "--out", "my_pi.fmu", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert not (tmp_path / "results").exists()  # nothing designed, so no cache folder
    done = cli("run", "startup", "--controller", "my_pi.fmu", "--out", "out", "--no-figures", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "my_pi (FMU)" in done.stdout
    meta = json.loads((tmp_path / "out" / "runs" / "startup__my-pi-fmu__nominal-averaged__1ms.json").read_text())
    assert meta["controller"]["name"] == "my_pi (FMU)"
    done = cli("export-ssp", "startup", "--controller", "my_pi.fmu", "--out", "loop.ssp", cwd=tmp_path)
    assert done.returncode == 0 and not (tmp_path / "results").exists(), done.stderr


# ------------------------------------------------------------------ 9. exports


def test_run_files_carry_units_descriptions_parameters_and_pandas_attrs(open_loop_switched, tmp_path):
    import pandas as pd
    import pyarrow.parquet as pq

    from cosim.results import read_run, write_run

    paths = write_run(open_loop_switched, tmp_path, "run")
    frame = pd.read_parquet(paths["parquet"])
    assert frame.attrs == json.loads(paths["json"].read_text())  # the run metadata, via plain pandas
    assert frame.attrs["plant"]["parameter_values"]["switching_frequency"] == 75e3
    assert frame.attrs["plant"]["parameter_values"]["pwm_carrier"] == 0
    assert frame.attrs["plant"]["parameter_values"]["plant_mode"] == 1
    assert frame.attrs["units"]["measured_output_voltage"] == "V"
    described = frame.attrs["descriptions"]["measured_output_voltage"]
    assert described == "output voltage, what the controller's sensor reads"
    assert all(" " not in unit for unit in frame.attrs["units"].values())
    schema = pq.read_schema(paths["parquet"])
    assert schema.field("measured_output_voltage").metadata == {
        b"unit": b"V", b"description": b"output voltage, what the controller's sensor reads"}
    assert b"buck_cosim" in schema.metadata  # the workbench's own key stays
    assert read_run(paths["parquet"]).metadata == frame.attrs


# ------------------------------------------------------------------ plot and compare


def test_plot_and_compare_overlay_runs_from_different_folders_and_formats(tmp_path, open_loop_switched, capsys):
    import pandas as pd

    from cosim import builtin_binding, load_scenario, simulate, write_run
    from cosim.metrics import run_metrics

    # a CSV run from one folder (run --no-figures), a Parquet run from another, a Python controller's run
    assert main(["--no-progress", "run", "startup", "--kp", "0.0017", "--ki", "15.6", "--out", str(tmp_path / "a"),
                 "--no-figures"]) == 0
    assert main(["--no-progress", "run", "startup", "--kp", "0.0008", "--ki", "8", "--out", str(tmp_path / "b"),
                 "--no-figures"]) == 0
    own = simulate(builtin_binding("averaged"), FixedDuty(), load_scenario("startup", PAPER_SPEC))
    write_run(own, tmp_path / "mine", "startup__fixed")
    runs = [str(tmp_path / "a" / "runs" / "startup__pi__nominal-averaged__1ms.csv"),
            str(tmp_path / "b" / "runs" / "startup__pi__nominal-averaged__1ms.parquet"),
            str(tmp_path / "mine" / "startup__fixed.parquet")]
    capsys.readouterr()
    assert main(["plot", *runs, "--out", str(tmp_path / "fig.png")]) == 0
    assert (tmp_path / "fig.png").read_bytes()[:4] == b"\x89PNG" and (tmp_path / "fig.svg").is_file()
    # a dot inside the name is part of it (startup_13.33us was written as startup_13.png), a format plot does not
    # write is refused, not renamed
    assert main(["plot", *runs[:1], "--out", str(tmp_path / "startup_13.33us")]) == 0
    assert (tmp_path / "startup_13.33us.png").is_file() and (tmp_path / "startup_13.33us.svg").is_file()
    assert not (tmp_path / "startup_13.png").exists()
    capsys.readouterr()
    assert main(["plot", *runs[:1], "--out", str(tmp_path / "fig.pdf")]) == 2
    assert not (tmp_path / "fig.pdf").exists()
    assert f"--out {tmp_path / 'fig.pdf'} is invalid: plot writes PNG and SVG" in capsys.readouterr().err
    assert main(["compare", *runs, "--out", str(tmp_path / "cmp")]) == 0
    printed = capsys.readouterr().out
    table = pd.read_csv(tmp_path / "cmp" / "compare.csv")
    assert list(table["run"]) == ["PI (a)", "PI (b)", "D = 0.25"] and "PI (b)" in printed
    svg = (tmp_path / "cmp" / "compare.svg").read_text()
    assert "PI (a)" in svg and "PI (b)" in svg and "D = 0.25" in svg
    for k, path in enumerate(runs):
        from cosim.results import read_run

        expected = run_metrics(read_run(Path(path)))
        assert table.loc[k, "overshoot_pct"] == pytest.approx(expected["overshoot_pct"])
        assert table.loc[k, "iae_Vs"] == pytest.approx(expected["iae_Vs"])
    assert table.loc[0, "overshoot_pct"] != table.loc[1, "overshoot_pct"]  # two different PIs


@pytest.mark.parametrize("make,message", [
    (None, "run file nothere.parquet does not exist"),
    ("csv", "has no x.json beside it"),
    ("folder", "is a folder: expected a run's .parquet or .csv"),
])
@pytest.mark.parametrize("command", [("plot",), ("export",)])
def test_run_file_mistakes_are_the_same_one_line_errors_for_plot_and_export(tmp_path, make, message, command):
    from conftest import cli, one_line_error

    name = {"csv": "x.csv", "folder": "runs", None: "nothere.parquet"}[make]
    if make == "csv":
        (tmp_path / "x.csv").write_text("time,output_voltage\n0,1\n")
    elif make == "folder":
        (tmp_path / "runs").mkdir()
    options = ("--out", "fig") if command == ("plot",) else ("--to", "parquet", "--out", "exported")
    one_line_error(cli(*command, name, *options, cwd=tmp_path), 2, message)
    assert not (tmp_path / "fig").exists() and not (tmp_path / "exported").exists()


def test_the_run_figure_is_public_api(open_loop_switched, tmp_path):
    import cosim

    files = cosim.plot_scenario([open_loop_switched], tmp_path / "mine")
    assert [f.name for f in files] == ["mine.png", "mine.svg"] and files[0].read_bytes()[:4] == b"\x89PNG"


def test_a_users_controllers_are_drawn_apart_from_the_pi_and_each_other(open_loop_switched):
    """Controllers without a style of their own (a user's) get colours no controller of the figure shows and a line
    style of their own -- never the PI's blue, never two alike."""
    from dataclasses import replace

    import matplotlib.colors as colors
    import matplotlib.pyplot as plt

    from cosim.plots import OTHER_LINE_STYLE, figure_styles, scenario_figure
    from cosim.study.vocabulary import STUDY_STYLES

    def renamed(name):
        return replace(open_loop_switched, info=replace(open_loop_switched.info, controller=name))

    runs = [renamed("PI"), renamed("Mine"), renamed("Mine too")]
    chosen = figure_styles([r.info.controller for r in runs], STUDY_STYLES)
    assert chosen["PI"] == STUDY_STYLES["PI"]
    own = [colors.to_hex(chosen[n][0]) for n in ("Mine", "Mine too")]
    builtin = {colors.to_hex(c) for c, _ in STUDY_STYLES.values()}
    assert len(set(own)) == 2 and not set(own) & builtin and chosen["Mine"][1] == OTHER_LINE_STYLE
    fig = scenario_figure(runs, "start-up", styles=STUDY_STYLES)
    try:
        duty = [line for line in fig.axes[4].get_lines() if line.get_drawstyle() == "steps-post"]
        assert len({colors.to_hex(line.get_color()) for line in duty}) == 3
    finally:
        plt.close(fig)


def test_run_without_gains_tunes_the_pi_the_reproduction_tuned(tmp_path):
    """One tuning method, one result per plant and rate: ``run --controller pi`` without gains (the controller
    factory's tuning) gives the design key and gains of results/tuning/ (the reproduction's), not another tuning
    at another recording step."""
    import json

    from cosim.design.controller_factory import tuned_pi
    from cosim.design.pi_tuning import TUNING_RECORD_PERIOD, pi_design
    from cosim.design.plants import plant_binding

    binding = plant_binding("nominal", "averaged")
    committed = json.loads((Path(__file__).resolve().parents[1] / "results" / "tuning" / "pi__nominal-averaged__1ms.json").read_text())
    assert pi_design(binding, 1e-3).inputs["settings"]["record_period_s"] == TUNING_RECORD_PERIOD
    assert pi_design(binding, 1e-3).key == committed["design"]["key"]
    tuning = tuned_pi(binding, 1e-3, tmp_path)
    assert (tuning.kp, tuning.ki) == (committed["kp"], committed["ki"])


def test_the_run_figure_shows_the_whole_run_and_marks_only_what_it_shows():
    """supply_dip at 1 ms: its recovery at 20 ms is in the left column (the whole run, not 11 ms around the first
    event); every mark of the transient column lies inside it; the duty axis spans the duties, not 0..1; the current's
    legend names peak currents, not the voltage's metrics; the transient's legends sit beside the panels."""
    import matplotlib.pyplot as plt

    from controllers.pi import PIController
    from cosim import builtin_binding, load_scenario, simulate
    from cosim.plots import scenario_figure

    result = simulate(builtin_binding("averaged"), PIController(0.0017155, 15.589, 1e-3),
                      load_scenario("supply_dip", PAPER_SPEC))
    fig = scenario_figure([result], "supply dip")
    try:
        v_full, v_zoom, i_full, i_zoom, d_full, d_zoom = fig.axes[:6]
        end_ms = float(result.frame["time"].iloc[-1]) * 1e3
        assert v_full.get_xlim() == pytest.approx((0.0, end_ms))
        low, high = v_zoom.get_xlim()
        assert high <= end_ms + 1e-9
        for ax in (v_zoom, i_zoom):
            for line in ax.get_lines():
                if line.get_marker() in ("v", "^"):
                    assert low <= line.get_xdata()[0] <= high
        duty_low, duty_high = d_full.get_ylim()
        assert duty_high - duty_low < 0.6 and duty_low > 0.0  # 0.2-0.35 here, not the whole 0..1
        current_legend = [t.get_text() for t in i_zoom.get_legend().get_texts()]
        assert current_legend and not any("overshoot" in t or "settling" in t for t in current_legend)
        fig.canvas.draw()
        for ax in (v_zoom, i_zoom):
            assert ax.get_legend().get_window_extent().x0 >= ax.get_window_extent().x1 - 1.0
    finally:
        plt.close(fig)
