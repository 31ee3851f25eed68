"""The explicit NNPC on every seed (scripts/explicit_every_seed.py, results/explicit-every-seed.csv and .md): the
verdict over seeds, the command's checks, seed 0 against the committed reproduction, and the policy cache."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import pandas as pd
import pytest
from conftest import script, script_refusal

from cosim.base.errors import ConfigError
from cosim.study import explicit_every_seed as ees

ROOT = Path(__file__).resolve().parents[1]
FAST = "nominal-switched__13p33us"


def row(seed, scenario, ratio, overshoot=1.0, error=0.01, online_overshoot=0.5):
    return {"pipeline": "p", "seed": seed, "scenario": scenario, "iae_online_Vs": 1e-3, "iae_explicit_Vs": 1e-3 * ratio,
            "iae_ratio": ratio, "overshoot_online_pct": online_overshoot, "overshoot_explicit_pct": overshoot,
            "steady_state_error_online_pct": 0.0, "steady_state_error_explicit_pct": error,
            "settling_time_online_ms": 0.1, "settling_time_explicit_ms": 0.1, "policy": "distilled here"}


def test_a_target_holds_only_for_every_seed_and_the_spread_is_over_the_seeds(tmp_path):
    rows = [row(0, "startup", 0.95, overshoot=8.22, online_overshoot=0.36), row(0, "load_change", 1.03, error=-0.05),
            row(1, "startup", 1.01, overshoot=2.0), row(1, "load_change", 1.07),
            row(2, "startup", 0.99, overshoot=4.0), row(2, "load_change", 1.00)]
    lines = {line["key"]: line for line in ees.verdict(rows)}
    assert lines["iae_ratio"]["values"] == {0: 1.03, 1: 1.07, 2: 1.00}  # each seed's worst scenario
    assert lines["iae_ratio"]["spread"] == (1.00, 1.03, 1.07) and lines["iae_ratio"]["missed"] == [1]
    assert lines["overshoot"]["values"] == {0: 8.22, 1: 2.0, 2: 4.0} and lines["overshoot"]["missed"] == [0]
    assert lines["steady_state_error"]["values"] == {0: 0.05, 1: 0.01, 2: 0.01} and lines["steady_state_error"]["met"]
    assert not lines["iae_ratio"]["met"] and not lines["overshoot"]["met"]
    ees.write_tables(tmp_path, rows, complete=True, command="scripts/explicit_every_seed.py --out results")
    csv = pd.read_csv(tmp_path / ees.TABLE_NAME)
    assert list(csv.columns) == list(ees.COLUMNS) and csv["iae_ratio"].tolist() == [0.95, 1.03, 1.01, 1.07, 0.99, 1.0]
    text = (tmp_path / ees.REPORT_NAME).read_text()
    assert text.splitlines()[0] == "# The explicit NNPC on every seed"
    assert ("| p | IAE <= 1.05 x online NNPC, every scenario (worst scenario) | **no** | 1.000 / 1.030 / 1.070 | "
            "0: 1.030; 1: 1.070; 2: 1.000 | 1 |") in text
    assert "| p | start-up overshoot <= 5 % | **no** | 2.00 / 4.00 / 8.22 % | 0: 8.22; 1: 2.00; 2: 4.00 | 0 |" in text
    assert "| p | steady-state error <= 0.2 %, every scenario | yes | 0.010 / 0.010 / 0.050 % |" in text
    assert text.rstrip().splitlines()[-1] == "| p | 8.22 (0.36) | 2.00 (0.50) | 4.00 (0.50) |"
    assert "INCOMPLETE" in ees.report(rows[:2], complete=False, command="c").splitlines()[0]


def run_script(argv, capsys):
    return script_refusal("explicit_every_seed", argv, capsys)


def test_the_command_refuses_bad_arguments_in_one_line_before_any_simulation(tmp_path, capsys):
    assert run_script(["--seeds", "0,7"], capsys) == (
        2, "explicit_every_seed.py: error: --seeds: '7' is not a study seed (expected some of 0, 1, 2, 3, 4)")
    code, line = run_script(["--pipelines", "nominal-switched__1ms"], capsys)
    assert code == 2 and line == ("explicit_every_seed.py: error: --pipelines: 'nominal-switched__1ms' is not a "
                                  "pipeline of the reproduction at one switching period (expected one of "
                                  "nominal-averaged__13p33us, nominal-switched__13p33us, mismatch-switched__13p33us)")
    assert run_script(["--results", str(tmp_path)], capsys) == (
        2, f"explicit_every_seed.py: error: --results {tmp_path}: no models/nominal-averaged__13p33us__nnpc.pt there "
           "(run make reproduce first)")
    assert run_script(["--workers", "0"], capsys) == (
        2, "explicit_every_seed.py: error: --workers 0: expected at least 1")
    assert run_script(["--expert-optimizer", "newton"], capsys) == (
        2, "explicit_every_seed.py: error: argument --expert-optimizer: invalid choice: 'newton' (choose from 'rti', "
           "'search')")


def test_seed_0_is_the_committed_reproductions_explicit_and_online_nnpc(tmp_path):
    """Seed 0 takes the reproduction's policy: its four runs give the committed metrics of NNPC and NNPC-explicit
    (the same C twins, plant and record period), so the every-seed table extends the report rather than redoing it."""
    explicit_every_seed = script("explicit_every_seed")
    assert explicit_every_seed.main(["--results", str(ROOT / "results"), "--pipelines", FAST, "--seeds", "0",
                                     "--workers", "1", "--cache", str(tmp_path / "cache"), "--out", str(tmp_path)]) == 0
    rows = pd.read_csv(tmp_path / ees.TABLE_NAME)
    assert len(rows) == 4 and set(rows["policy"]) == {"reproduction"} and not (tmp_path / "cache").exists()
    committed = pd.read_csv(ROOT / "results" / "metrics" / f"metrics__{FAST}.csv").set_index(["scenario", "controller"])
    for r in rows.itertuples():
        for controller, iae, overshoot, error in (
                ("NNPC", r.iae_online_Vs, r.overshoot_online_pct, r.steady_state_error_online_pct),
                ("NNPC-explicit", r.iae_explicit_Vs, r.overshoot_explicit_pct, r.steady_state_error_explicit_pct)):
            expected = committed.loc[(r.scenario, controller)]
            assert (iae, overshoot, error) == pytest.approx(
                (expected["iae_Vs"], expected["overshoot_pct"], expected["steady_state_error_pct"]),
                rel=1e-9, abs=1e-12)
    assert "INCOMPLETE" not in (tmp_path / ees.REPORT_NAME).read_text()


def test_a_seed_0_policy_of_another_network_is_refused_before_any_job(tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(ROOT / "results" / "models" / f"{FAST}__nnpc__seed1.pt", models / f"{FAST}__nnpc.pt")
    shutil.copy(ROOT / "results" / "models" / f"{FAST}__nnpc-explicit.pt", models)
    with pytest.raises(ConfigError, match=rf"{FAST}__nnpc-explicit.pt: distilled from another network \(expert "
                                          r"[0-9a-f]{16}\) than .*models/" + FAST + r"__nnpc.pt \([0-9a-f]{16}\): run "
                                          "make reproduce again"):
        ees.every_seed(tmp_path, tmp_path / "cache", pipelines=[FAST], seeds=(0,),
                       log=lambda line: pytest.fail(f"a job ran: {line}"))


def fake_distillation(calls: list):
    """A stand-in for cosim.design.distillation.distill that returns the committed policy under the metadata a
    distillation writes and appends (seed, expert optimizer) of each call to ``calls``."""
    from controllers.explicit_policy import load_policy
    from cosim.design import distillation

    def fake_distill(model, binding, period, settings, *, log=None, metadata=None):
        calls.append((settings.seed, settings.expert_optimizer))
        policy = load_policy(ROOT / "results" / "models" / f"{FAST}__nnpc-explicit.pt")
        policy.metadata = {**policy.metadata, "expert_model": distillation.expert_fingerprint(model),
                           "distillation": {**distillation.settings_dict(settings), "labels": 1, "history": []}}
        return policy

    return fake_distill


def test_a_seeds_policy_is_distilled_once_and_taken_from_the_cache_while_its_expert_and_budget_match(tmp_path,
                                                                                                      monkeypatch):
    """The distillation itself is the reproduction's (tests/test_distillation.py); here it is replaced by one that
    returns the committed policy under the metadata a distillation writes, to count the calls."""
    from controllers.nn_model import load_model
    from cosim.design import distillation

    calls = []
    monkeypatch.setattr(distillation, "distill", fake_distillation(calls))
    (pipeline,) = ees.fast_pipelines([FAST])
    model = load_model(ROOT / "results" / "models" / f"{FAST}__nnpc__seed1.pt")
    origins = [ees.seed_policy(pipeline, 1, model, ROOT / "results", tmp_path)[1] for _ in range(2)]
    assert origins == ["distilled", "cache"] and calls == [(1, "rti")]
    assert ees.cached_policy_path(tmp_path, FAST, 1, distillation.expert_fingerprint(model), "rti").is_file()
    monkeypatch.setattr(distillation, "FULL_DISTILLATION", replace(distillation.FULL_DISTILLATION, rounds=5))
    assert ees.seed_policy(pipeline, 1, model, ROOT / "results", tmp_path)[1] == "distilled"  # another budget
    assert calls == [(1, "rti")] * 2


def test_with_another_expert_optimizer_every_seed_0_too_is_distilled_with_it_and_cached_apart(tmp_path, monkeypatch):
    """--expert-optimizer search: seed 0 is distilled here (not the reproduction's RTI-labelled file), with the search
    labelling the states, cached under its own name beside the RTI's; the tables are named for the labels and say
    so; naming the reproduction's optimizer is the reproduction's labels; an unknown optimizer is refused before
    any work."""
    from controllers.nn_model import load_model
    from cosim.design import distillation

    used = []
    monkeypatch.setattr(distillation, "distill", fake_distillation(used))
    (pipeline,) = ees.fast_pipelines([FAST])
    model = load_model(ROOT / "results" / "models" / f"{FAST}__nnpc.pt")
    expert = distillation.expert_fingerprint(model)
    for named in (None, "rti"):
        assert ees.seed_policy(pipeline, 0, model, ROOT / "results", tmp_path, expert_optimizer=named)[1] == \
            "reproduction"
    assert used == []
    origins = [ees.seed_policy(pipeline, 0, model, ROOT / "results", tmp_path, expert_optimizer="search")[1]
               for _ in range(2)]
    assert origins == ["distilled", "cache"] and used == [(0, "search")]
    assert ees.cached_policy_path(tmp_path, FAST, 0, expert, "search").name == (
        f"{FAST}__seed0__nnpc-explicit__expert-{expert}__search-labels.pt")
    assert ees.cached_policy_path(tmp_path, FAST, 0, expert, "search").is_file()
    assert ees.file_names("search") == ("explicit-every-seed-search-labels.csv", "explicit-every-seed-search-labels.md")
    assert ees.file_names("rti") == ees.file_names(None) == (ees.TABLE_NAME, ees.REPORT_NAME)
    rows = [{"pipeline": FAST, "seed": 0, "scenario": "startup", "iae_online_Vs": 1.0, "iae_explicit_Vs": 1.0,
             "iae_ratio": 1.0, "overshoot_online_pct": 1.0, "overshoot_explicit_pct": 2.0,
             "steady_state_error_online_pct": 0.0, "steady_state_error_explicit_pct": 0.0,
             "settling_time_online_ms": 1.0, "settling_time_explicit_ms": 1.0, "policy": "distilled here"}]
    ees.write_tables(tmp_path, rows, complete=True, command="c", expert_optimizer="search")
    text = (tmp_path / "explicit-every-seed-search-labels.md").read_text()
    assert text.startswith("# The explicit NNPC on every seed, its labels from the search\n")
    assert "distilled here with the online NNPC planned by the search labelling the states instead of the " \
           "reproduction's RTI" in text
    assert pd.read_csv(tmp_path / "explicit-every-seed-search-labels.csv")["overshoot_explicit_pct"].tolist() == [2.0]
    assert not (tmp_path / ees.REPORT_NAME).exists()
    with pytest.raises(ConfigError, match="expert optimizer 'newton' is unknown: expected one of rti, search"):
        ees.seed_policy(pipeline, 1, model, ROOT / "results", tmp_path, expert_optimizer="newton")


def test_the_explicit_nnpc_guide_quotes_the_committed_every_seed_table():
    """docs/guide/explicit-nnpc.md copies the every-seed spreads by hand: each cell must be the committed
    results/explicit-every-seed.csv's (min / median / max as the .md rounds them), in bold where a seed misses."""
    import re

    rows = pd.read_csv(ROOT / "results" / ees.TABLE_NAME).to_dict("records")
    text = (ROOT / "docs" / "guide" / "explicit-nnpc.md").read_text()
    table = text[text.index("| target (every seed) |"):].split("\n\n")[0].splitlines()
    columns = ["nominal-switched__13p33us", "mismatch-switched__13p33us", "nominal-averaged__13p33us"]
    keys = {"IAE": "iae_ratio", "start-up overshoot": "overshoot", "steady-state error": "steady_state_error"}
    checked = 0
    for line in table[2:]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        key = next(k for prefix, k in keys.items() if cells[0].startswith(prefix))
        for tag, cell in zip(columns, cells[1:]):
            verdict = {v["key"]: v for v in ees.verdict([r for r in rows if r["pipeline"] == tag])}[key]
            digits = ".2f" if key == "overshoot" else ".3f"
            quoted = [float(x) for x in re.findall(r"\d+\.\d+", cell.replace("**", ""))[:3]]
            assert quoted == [float(f"{v:{digits}}") for v in verdict["spread"]], (tag, key, cell)
            assert ("**" in cell) == bool(verdict["missed"]), (tag, key, cell)
            checked += 1
    assert checked == 9
