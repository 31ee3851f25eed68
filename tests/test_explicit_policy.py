"""The explicit NNPC: policy files, the Python and C twins (directly and through the exported FMU
driven by the master), DAgger distillation on a small budget, the map's bookkeeping, the CLI."""

from __future__ import annotations

import io
import math
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from controllers.base import Measurement
from controllers.explicit_policy import (
    FEATURES,
    N_FEATURES,
    ExplicitPolicy,
    PolicyConfig,
    load_policy,
    save_policy,
)
from controllers.nn_model import load_model
from cosim.base.errors import ConfigError, ModelFileError
from cosim.cli import build_parser, main
from cosim.design.distillation import FULL_DISTILLATION, SMALL_DISTILLATION, distill
from cosim.design.experiments import explicit_nnpc, implemented, nnpc, scenarios_for
from cosim.design.plants import plant_binding
from cosim.design.vocabulary import SWITCHING_PERIOD
from cosim.master import simulate
from cosim.metrics import run_metrics
from cosim.study.vocabulary import PAPER_SPEC

FIXTURES = Path(__file__).parent / "fixtures"
EXPERT = FIXTURES / "nnpc_nominal_averaged_13p33us.pt"


def random_policy(hidden=(12,), seed=0, gain=2000.0, limits=(0.0, 1.0), period=SWITCHING_PERIOD) -> ExplicitPolicy:
    rng = np.random.default_rng(seed)
    widths = [N_FEATURES, *hidden, 1]
    weights = [rng.normal(0, 0.5, (a, b)) for a, b in zip(widths[:-1], widths[1:])]
    biases = [rng.normal(0, 0.2, b) for b in widths[1:]]
    biases[-1] = biases[-1] + 0.25
    return ExplicitPolicy(PolicyConfig(hidden=hidden, integral_gain=gain), weights, biases, period, limits,
                          {"control_period_s": period})


def measurements(seed: int, count: int = 600):
    """Random sensor readings around a few operating points: saturation, start-up (vo below the load
    estimate's threshold), a missing load-current sensor (NaN), references that change."""
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(count):
        reference = [12.0, 3.0, 20.0, 0.0][(k // 150) % 4]
        vo = max(0.0, reference + rng.normal(0, 0.05 if k % 7 else 2.0))
        if k < 5:
            vo = 0.01 * k
        il = abs(rng.normal(2.0, 1.0))
        io = math.nan if k % 50 < 10 else vo / 6.0
        rows.append(Measurement(k * SWITCHING_PERIOD, reference, vo, il, io, 48.0))
    return rows


# ------------------------------------------------------------------ twins


@pytest.mark.parametrize("hidden,limits", [((12,), (0.0, 1.0)), ((8, 6), (0.05, 0.9)), ((32,), (0.0, 1.0))])
def test_python_and_c_twins_give_the_same_duty_bit_for_bit(hidden, limits):
    python = explicit_nnpc(random_policy(hidden, seed=len(hidden), limits=limits))
    c = implemented(python)
    assert type(c).__name__ == "NativeExplicitPolicyController"
    for seed in (1, 2):
        python.reset()
        c.reset()
        for m in measurements(seed):
            assert c.step(m) == python.step(m)
            assert c.state.integral == python.integral
        assert c.forward(python.last_features) == python.last_output
    x = np.random.default_rng(3).normal(size=(50, N_FEATURES))
    batched = python.policy.evaluate(x)  # numpy (BLAS sums): equal to the scalar step to rounding
    assert np.max(np.abs(batched - [python.policy.forward(list(row)) for row in x])) < 1e-12


def test_the_c_twin_refuses_a_policy_above_its_maxima_by_name():
    from controllers.native import native_twin

    with pytest.raises(ValueError, match=r"hidden layer of 40 units > BUCKC_POLICY_MAX_WIDTH \(32\)"):
        native_twin(explicit_nnpc(random_policy((40,))))
    with pytest.raises(ConfigError, match="run it with --implementation python"):
        implemented(explicit_nnpc(random_policy((40,))))


def test_the_integral_term_removes_the_offset_of_a_policy_with_the_wrong_steady_state_duty():
    """A proportional policy u = 0.3 - 0.1 tanh(vo - r) (about 0.1 per volt near the reference) whose
    steady-state duty is too low for 15 V (about 0.3125 needed) leaves about -0.7 %; the integral
    term removes it."""
    weights = [np.zeros((N_FEATURES, 1)), np.array([[-0.1]])]
    weights[0][0, 0] = 1.0  # the hidden unit sees vo - r
    errors = {}
    for gain in (0.0, 200.0):
        policy = ExplicitPolicy(PolicyConfig(hidden=(1,), integral_gain=gain), weights, [np.zeros(1), np.array([0.3])],
                                SWITCHING_PERIOD)
        result = simulate(plant_binding("nominal", "averaged"), implemented(explicit_nnpc(policy)),
                          replace(scenarios_for(SWITCHING_PERIOD, ("reference_up",), spec=PAPER_SPEC)[0], settle=0.02,
                                  duration=0.02))
        errors[gain] = run_metrics(result)["steady_state_error_pct"]
    assert 0.3 < errors[0.0] < 1.5  # the policy alone: vo below the reference
    assert abs(errors[200.0]) < 0.02


# ------------------------------------------------------------------ files


def test_policy_files_round_trip(tmp_path):
    policy = random_policy((8, 6), gain=1234.5, limits=(0.05, 0.9))
    path = save_policy(policy, tmp_path / "p.pt")
    loaded = load_policy(path, expect_period=SWITCHING_PERIOD)
    assert loaded.config == policy.config and loaded.duty_limits == policy.duty_limits
    x = [0.1, -0.2, 0.3, 0.0, 0.25, 12.0, 1 / 6]
    assert loaded.forward(x) == policy.forward(x)
    assert save_policy(loaded, tmp_path / "q.pt").read_bytes() == path.read_bytes()


def _rewrite(path: Path, edit) -> None:
    payload = torch.load(path, weights_only=True)
    edit(payload)
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    path.write_bytes(buffer.getvalue())


@pytest.mark.parametrize("damage,message", [
    ("missing", "does not exist"),
    ("folder", "is a folder"),
    ("text", "not a policy written by buck-cosim distill"),
    ("truncated", "not a policy written by buck-cosim distill|cannot be read"),
    ("nn-model", r"is not a buck-cosim explicit policy .* \(it is a buck-cosim NN plant model\)"),
    ("features", "was trained for inputs"),
    ("tampered", "fails its SHA-256 check"),
    ("non-finite", "fails its SHA-256 check|non-finite"),
    ("period", r"distilled at a control period of 1000 us; the controller samples every 13.33 us"),
    ("pickle", "contains objects other than plain weights|cannot be read"),
])
def test_bad_policy_files_are_refused_in_one_line_naming_the_file(tmp_path, damage, message):
    path = tmp_path / "policy.pt"
    if damage != "missing":
        save_policy(random_policy(period=1e-3 if damage == "period" else SWITCHING_PERIOD), path)
    if damage == "folder":
        path.unlink()
        path.mkdir()
    elif damage == "text":
        path.write_text("weights = 1, 2, 3\n")
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[:300])
    elif damage == "nn-model":
        path.write_bytes(EXPERT.read_bytes())
    elif damage == "features":
        _rewrite(path, lambda p: p.__setitem__("features", list(FEATURES[:-1])))
    elif damage == "tampered":
        _rewrite(path, lambda p: p["weights"][0].mul_(1.01))
    elif damage == "non-finite":
        _rewrite(path, lambda p: p["biases"][0].__setitem__(0, float("nan")))
    elif damage == "pickle":
        import pickle

        with zipfile.ZipFile(path, "w") as archive:
            archive.writestr("policy/data.pkl", pickle.dumps(Path("/")))
    with pytest.raises(ModelFileError, match=message) as error:
        load_policy(path, expect_period=SWITCHING_PERIOD)
    text = str(error.value)
    assert "\n" not in text and str(path) in text


def test_a_policy_with_non_finite_weights_is_not_saved(tmp_path):
    policy = random_policy()
    policy.biases[0][0] = math.inf
    with pytest.raises(ValueError, match="non-finite"):
        save_policy(policy, tmp_path / "p.pt")
    assert not (tmp_path / "p.pt").exists()


# ------------------------------------------------------------------ distillation


@pytest.fixture(scope="module")
def expert():
    return load_model(EXPERT, expect_period=SWITCHING_PERIOD)


@pytest.fixture(scope="module")
def distilled(expert) -> ExplicitPolicy:
    """The small budget of the tests: 3 rounds x 2 episodes x 300 samples = 1800 labels."""
    return distill(expert, plant_binding("nominal", "averaged"), SWITCHING_PERIOD, SMALL_DISTILLATION, log=None)


def test_a_small_distillation_regulates_the_averaged_plant_at_one_switching_period(expert, distilled):
    """1800 labels: every paper scenario within 0.2 % steady-state error, 10 % overshoot, 0.5 ms 2 %
    settling and twice the IAE of the online NNPC it imitates (the default's, the RTI, whose first moves are its
    labels; four times in the load change, where that NNPC is nearly dead-beat).
    The overshoot bound is the small budget's: with the quasi-static-current averaged model its reference
    step overshoots 7.3 % (the online NNPC: 0.004 %), a coarse policy's error; the reproduction's full
    budget is held to its targets table."""
    rounds = distilled.metadata["distillation"]["history"]
    assert [r["round"] for r in rounds] == [0, 1, 2] and distilled.metadata["distillation"]["labels"] == 1800
    assert rounds[0]["policy_share"] == 0 and 0 < rounds[1]["policy_share"] < rounds[2]["policy_share"] < 1
    assert distilled.metadata["training"]["validation_rms_duty"] < 0.05
    binding = plant_binding("nominal", "averaged")
    explicit = implemented(explicit_nnpc(distilled))
    online = implemented(nnpc(expert, SWITCHING_PERIOD))
    assert distilled.metadata["distillation"]["expert_optimizer"] == "rti"
    for scenario in scenarios_for(SWITCHING_PERIOD, spec=PAPER_SPEC):
        ours, theirs = (run_metrics(simulate(binding, c, scenario)) for c in (explicit, online))
        assert abs(ours["steady_state_error_pct"]) <= 0.2, scenario.name
        assert ours["overshoot_pct"] <= 10.0, scenario.name
        assert ours["settling_time_ms"] <= 0.5, scenario.name
        # the small budget's bound; the reproduction's full budget is held to 1.05 (its targets table). In the load
        # change the online RTI NNPC is nearly dead-beat on the averaged plant (8.6 uV s) and the policy's integral
        # term trims its last 1e-3 of duty over a fraction of a ms: 3.7 x here (1.8 x the search's online IAE)
        limit = 4.0 if scenario.name == "load_change" else 2.0
        assert ours["iae_Vs"] <= limit * theirs["iae_Vs"], scenario.name


def test_distillation_is_deterministic(expert, tmp_path):
    """The same inputs give the same policy file byte for byte, with or without the wall-clock timings asked for
    (which go to the caller's dict, split into the labelled episodes and the trainings, never into the file)."""
    tiny = replace(SMALL_DISTILLATION, rounds=1, episodes=1, samples=100)
    timings = {"identification_nnpc_s": 1.0}
    files = [save_policy(distill(expert, plant_binding("nominal", "averaged"), SWITCHING_PERIOD, tiny, log=None,
                                 timings=timings if i else None), tmp_path / f"{i}.pt") for i in range(2)]
    assert files[0].read_bytes() == files[1].read_bytes()
    assert set(timings) == {"identification_nnpc_s", "distillation_episodes_s", "distillation_training_s"}
    assert timings["distillation_episodes_s"] > 0 and timings["distillation_training_s"] > 0


def test_the_expert_labels_with_the_default_optimizer_unless_told_another(expert, monkeypatch):
    """DistillationSettings.expert_optimizer None: the expert plans with the workbench's default optimizer at the
    time of the distillation (the RTI; the search inside default_optimizer("search"), as the benchmark's search run
    does), a named one whatever the default; the policy file records which; an unknown name is refused first."""
    from cosim.design import distillation
    from cosim.design.experiments import default_optimizer

    built = []
    real_nnpc = distillation.nnpc

    def spy(model, period, *args, optimizer=None, **kwargs):
        built.append(optimizer)
        return real_nnpc(model, period, *args, optimizer=optimizer, **kwargs)

    monkeypatch.setattr(distillation, "nnpc", spy)
    tiny = replace(SMALL_DISTILLATION, rounds=0, episodes=1, samples=100)
    binding = plant_binding("nominal", "averaged")
    recorded = []
    for settings, default in ((tiny, "rti"), (tiny, "search"), (replace(tiny, expert_optimizer="search"), "rti")):
        with default_optimizer(default):
            policy = distill(expert, binding, SWITCHING_PERIOD, settings, log=None)
        recorded.append(policy.metadata["distillation"]["expert_optimizer"])
    assert built[0] == recorded[0] == "rti" and built[1] == recorded[1] == "search"
    assert built[2] == recorded[2] == "search"
    with pytest.raises(ConfigError, match="expert optimizer 'newton' is unknown: expected one of rti, search"):
        distill(expert, binding, SWITCHING_PERIOD, replace(tiny, expert_optimizer="newton"), log=None)
    assert len(built) == 3


def test_the_exported_fmu_driven_by_the_master_gives_the_python_duty_at_every_sample(distilled, tmp_path):
    from cosim.fmi.controller import open_controller
    from cosim.fmi.controller_export import export_controller

    python = explicit_nnpc(distilled)
    binary, source = export_controller(python, tmp_path / "explicit.fmu")
    assert binary.is_file() and source.is_file()
    fmu = open_controller(str(binary))
    for mode in ("averaged", "switched"):
        for scenario in scenarios_for(SWITCHING_PERIOD, ("startup", "load_change"), spec=PAPER_SPEC):
            short = replace(scenario, duration=0.002, settle=min(scenario.settle, 0.001))
            duties = [simulate(plant_binding("nominal", mode), c, short).frame for c in (python, fmu)]
            reference, exported = (f.loc[f["control_sample"], "duty_cycle"].to_numpy() for f in duties)
            assert len(exported) == len(reference) > 100
            assert np.array_equal(exported, reference), (mode, scenario.name)
    fmu.close()


# ------------------------------------------------------------------ command line


@pytest.mark.parametrize("args,message", [
    (["distill", "--model", "missing.pt", "--out", "p.pt"], "model file missing.pt does not exist"),
    (["distill", "--model", str(EXPERT), "--out", "p.pt", "--control-period", "1e-3"],
     "was trained at a control period of 13.33 us"),
    (["distill", "--model", str(EXPERT), "--out", "p.pt", "--hidden", "0"], "--hidden: 0 is invalid"),
    (["distill", "--model", str(EXPERT), "--out", "p.pt", "--rounds", "x"], "--rounds: 'x' is invalid"),
    (["distill", "--model", str(EXPERT), "--out", "p.pt", "--integral-gain", "nan"], "--integral-gain: nan is invalid"),
    (["run", "startup", "--controller", "pi", "--policy", "p.pt", "--kp", "0", "--ki", "14"],
     "--policy gives the explicit NNPC's policy: add --controller nnpc-explicit"),
    (["run", "startup", "--controller", "nnpc-explicit", "--policy", str(EXPERT), "--control-period", "1/75e3"],
     "is not a buck-cosim explicit policy"),
    (["export-controller", "nnpc-explicit", "--policy", "nothing.pt", "--control-period", "1/75e3", "--out", "e.fmu"],
     "policy file nothing.pt does not exist"),
])
def test_command_line_mistakes_end_in_one_line(tmp_path, monkeypatch, capsys, args, message):
    monkeypatch.chdir(tmp_path)
    extra = [] if args[0] == "distill" else ["--out" if args[0] == "run" else "--work-dir", str(tmp_path / "w")]
    try:
        code = main(["--no-progress", *args, *extra])
    except SystemExit as stop:  # argparse's usage errors
        code = stop.code
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ")
    assert __import__("re").search(message, err), err


def test_distill_defaults_on_the_command_line_are_the_reproductions_budget():
    args = build_parser().parse_args(["distill", "--model", "m.pt", "--out", "p.pt"])
    assert (args.rounds, args.episodes, args.samples, tuple(args.hidden), args.seed) == (
        FULL_DISTILLATION.rounds, FULL_DISTILLATION.episodes, FULL_DISTILLATION.samples,
        FULL_DISTILLATION.policy.hidden, FULL_DISTILLATION.seed)
    assert FULL_DISTILLATION.labels == 33_600 and FULL_DISTILLATION.policy.macs() == 114


def test_distill_then_run_and_export_from_the_command_line(tmp_path, capsys):
    policy = tmp_path / "policy.pt"
    assert main(["--no-progress", "distill", "--model", str(EXPERT), "--control-period", "1/75e3", "--out", str(policy),
                 "--rounds", "1", "--episodes", "1", "--samples", "100"]) == 0
    out = capsys.readouterr().out
    assert "7-14-1 tanh policy (114 MACs per step): 2 DAgger rounds, 200 labels" in out
    assert load_policy(policy, expect_period=SWITCHING_PERIOD).metadata["distillation"]["labels"] == 200
    assert main(["--no-progress", "run", "startup", "--controller", "nnpc-explicit", "--policy", str(policy),
                 "--control-period", "1/75e3", "--out", str(tmp_path / "runs"), "--no-figures"]) == 0
    assert "NNPC-explicit" in capsys.readouterr().out
    assert main(["--no-progress", "export-controller", "nnpc-explicit", "--policy", str(policy), "--control-period",
                 "1/75e3", "--out", str(tmp_path / "e.fmu"), "--work-dir", str(tmp_path / "w")]) == 0
    assert (tmp_path / "e.fmu").is_file()


def test_nnpc_explicit_on_demand_is_distilled_once_and_then_read_from_the_cache(tmp_path, monkeypatch, capsys):
    import cosim.design.distillation as distillation
    from cosim.design.controller_factory import make_controllers

    monkeypatch.setattr(distillation, "FULL_DISTILLATION", replace(SMALL_DISTILLATION, rounds=1, episodes=1,
                                                                    samples=100))
    made = []
    for _ in range(2):
        [controller] = make_controllers(["nnpc-explicit"], plant_binding("nominal", "averaged"), SWITCHING_PERIOD,
                                        tmp_path, duty_limits=(0.0, 1.0), model_path=str(EXPERT))
        made.append(controller)
    assert capsys.readouterr().err.count("distilling the NNPC into an explicit policy") == 1
    assert (tmp_path / "models" / "nominal-averaged__13p33us__nnpc-explicit.pt").is_file()
    x = [0.1, -0.2, 0.3, 0.0, 0.25, 12.0, 1 / 6]
    assert made[0].policy.forward(x) == made[1].policy.forward(x)
    assert made[0].describe()["design_key"] and made[0].describe()["design_key"] == made[1].describe()["design_key"]
    # another plant under the same tag (issue 23): distilled again, and said so in one line
    plant = plant_binding("nominal", "averaged")
    other = replace(plant, parameters={**plant.parameters, "capacitance": 12e-6})
    [again] = make_controllers(["nnpc-explicit"], other, SWITCHING_PERIOD, tmp_path, duty_limits=(0.0, 1.0),
                               model_path=str(EXPERT))
    err = capsys.readouterr().err
    assert err.count("does not fit: plant parameters changed") == 1 and "distilling again" in err
    assert again.describe()["design_key"] != made[0].describe()["design_key"]
