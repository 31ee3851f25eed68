"""Issue 23: the defects a new user meets in the first two hours, each with the test that would have
caught it (docs: guide/runs.md "Cached designs", guide/command-line.md, guide/python-controller.md)."""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

import pytest

from cosim.cli import main

# ------------------------------------------------------------------ 1. cached designs keyed by what they depend on


@pytest.fixture
def quick_tuning(monkeypatch):
    """The PI tuning on a 2 x 2 grid and 6 Nelder-Mead evaluations (its design key says so, so a cached
    tuning is reused under the same patch): the tests need a tuning, not a good one."""
    import cosim.study.pi_tuning as tuning

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
    assert "tuning the PI for" in err and "at most 10 evaluations x 3 scenarios" in err

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

    import cosim.study.controller_factory as factory
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
    from cosim.study.design_cache import changed_inputs

    plant = {"fmu_sha256": "a", "roles": {}, "parameters": {"L": 1}, "interface": None, "max_step_s": None}
    stored = {"plant": plant, "control_period_s": 1e-3, "seed": 0, "settings": {"x": 1}}
    wanted = {**stored, "plant": {**plant, "fmu_sha256": "b"}, "seed": 1}
    assert changed_inputs(stored, wanted) == ["plant FMU (SHA-256)", "seed"]
    assert changed_inputs(stored, stored) == []
