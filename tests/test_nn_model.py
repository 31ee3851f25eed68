"""The NN plant model: datasets, identification of a known system, inference paths, safe files."""

from __future__ import annotations

import pickle
import zipfile

import numpy as np
import pandas as pd
import pytest
import torch

from controllers.nn_config import NNConfig, TrainingSettings
from controllers.nn_model import build_dataset, load_model, save_model, train
from cosim.base.errors import ModelFileError
from cosim.study.vocabulary import PAPER_SPEC

PHI = np.array([[0.9, -0.05], [0.3, 0.8]])  # a stable linear "plant", sampled
GAIN = np.array([2.0, 4.0])


def linear_plant_frame(n=3000, seed=0):
    """x(k) = PHI x(k-1) + GAIN d(k-1), with a random duty; columns as the data collector writes."""
    rng = np.random.default_rng(seed)
    duty = np.repeat(rng.uniform(0.0, 1.0, n // 10 + 1), 10)[:n]
    x = np.zeros((n, 2))
    for k in range(1, n):
        x[k] = PHI @ x[k - 1] + GAIN * duty[k - 1]
    return pd.DataFrame({"time": np.arange(n) * 1e-3, "measured_inductor_current": x[:, 0],
                         "measured_output_voltage": x[:, 1], "duty_cycle": duty,
                         "load_conductance": np.full(n, 1 / 6), "load_current": x[:, 1] / 6, "measured_load_current": x[:, 1] / 6,
                         "input_voltage": np.full(n, 48.0)})


@pytest.fixture(scope="module")
def frame():
    return linear_plant_frame()


@pytest.fixture(scope="module")
def model(frame):
    return train(frame, NNConfig(hidden=(12,)), TrainingSettings(seed=3), metadata={"control_period_s": 1e-3})


def test_dataset_pairs_inputs_at_k_minus_1_with_state_at_k(frame):
    x, y = build_dataset(frame, NNConfig())
    assert x.shape == (len(frame) - 1, 3) and y.shape == (len(frame) - 1, 2)
    k = 57
    assert x[k - 1].tolist() == [frame["measured_inductor_current"][k - 1], frame["measured_output_voltage"][k - 1],
                                 frame["duty_cycle"][k - 1]]
    assert y[k - 1].tolist() == [frame["measured_inductor_current"][k], frame["measured_output_voltage"][k]]
    x2, y2 = build_dataset(frame, NNConfig(delays=2, extra_signals=("load_conductance",)))
    assert x2.shape == (len(frame) - 2, 7)
    assert x2[0, 3:6].tolist() == [frame["measured_inductor_current"][0], frame["measured_output_voltage"][0],
                                   frame["duty_cycle"][0]]
    assert NNConfig(delays=2, extra_signals=("load_conductance",)).input_names[-1] == "load_conductance[k-1]"


def test_training_identifies_a_known_linear_plant(model):
    rmse = model.metadata["held_out_rmse"]
    assert rmse["one_step_rmse_current_A"] < 0.01 and rmse["one_step_rmse_voltage_V"] < 0.01
    assert rmse["10_step_rmse_voltage_V"] < 0.05
    grid = np.array([[0.5, 2.0, 0.3], [1.0, 3.0, 0.7]])
    np.testing.assert_allclose(model.predict(grid), (PHI @ grid[:, :2].T).T + np.outer(grid[:, 2], GAIN), atol=0.02)
    training = model.metadata["training"]
    assert training["test_samples"] == 600 and training["best_iteration"] <= training["iterations"]


def test_training_is_deterministic_for_a_seed(frame):
    settings = TrainingSettings(seed=5, max_iterations=100)
    a, b = (train(frame, NNConfig(), settings) for _ in range(2))
    for (name, pa), pb in zip(a.network.state_dict().items(), b.network.state_dict().values()):
        assert torch.equal(pa, pb), name


def test_numpy_inference_matches_torch_and_shared_rollout_matches_batched(model):
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 5, (50, 3))
    np.testing.assert_allclose(model.predict(x), model.predict_torch(x), rtol=1e-12, atol=1e-12)
    history = np.array([[1.0, 2.0, 0.0]])
    duties = rng.uniform(0, 1, (7, 5))
    shared = model.rollout_shared(history, duties)
    batched = model.rollout(np.repeat(history[None], 7, axis=0), duties)
    np.testing.assert_allclose(shared, batched, rtol=1e-13)


@pytest.mark.parametrize("config", [NNConfig(residual=True, extra_signals=("load_conductance",)),
                                    NNConfig(delays=2, activation="relu")])
def test_configurable_networks_train_and_roll_out_consistently(frame, config):
    m = train(frame.iloc[:800], config, TrainingSettings(max_iterations=100))
    history = np.tile([[1.0, 2.0, 0.4]], (config.delays, 1))
    extras = np.array([1 / 6]) if config.extra_signals else None
    duties = np.full((2, 3), 0.4)
    one = m.rollout_shared(history, duties, extras)
    x0 = np.concatenate([history.ravel(), extras if extras is not None else []])[None]
    np.testing.assert_allclose(one[0, 0], m.predict(x0)[0], rtol=1e-12)


def test_save_and_load_round_trip(model, tmp_path):
    path = save_model(model, tmp_path / "model.pt")
    back = load_model(path, expect_period=1e-3, expect_config=model.config)
    x = np.random.default_rng(2).uniform(0, 5, (20, 3))
    assert np.array_equal(back.predict(x), model.predict(x))
    assert back.metadata["held_out_rmse"] == model.metadata["held_out_rmse"]


def test_load_refuses_missing_truncated_and_foreign_files(model, tmp_path):
    with pytest.raises(ModelFileError, match=r"model file .*nothing.pt does not exist"):
        load_model(tmp_path / "nothing.pt")
    path = save_model(model, tmp_path / "model.pt")
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    with pytest.raises(ModelFileError, match=r"truncated.pt is not a model written by buck-cosim train"):
        load_model(truncated)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(ModelFileError, match=r"foreign.pt is not a buck-cosim NN plant model"):
        load_model(foreign)


def test_load_detects_changed_weights(model, tmp_path):
    path = save_model(model, tmp_path / "model.pt")
    payload = torch.load(path, weights_only=True)
    first = next(iter(payload["state_dict"]))
    payload["state_dict"][first][0] += 0.01
    torch.save(payload, tmp_path / "tampered.pt")
    with pytest.raises(ModelFileError, match=r"tampered.pt fails its SHA-256 check"):
        load_model(tmp_path / "tampered.pt")


class _Exploit:
    def __reduce__(self):
        import os

        return (os.system, ("touch EXPLOITED_MARKER",))


def test_load_never_executes_code_from_the_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "evil.pt"
    with zipfile.ZipFile(path, "w") as archive:  # the layout torch.save uses, with a hostile pickle
        archive.writestr("evil/data.pkl", pickle.dumps({"format": _Exploit()}, protocol=2))
        archive.writestr("evil/version", "3\n")
    with pytest.raises(ModelFileError, match=r"evil.pt cannot be read"):
        load_model(path)
    assert not (tmp_path / "EXPLOITED_MARKER").exists()


def test_load_refuses_a_model_made_for_other_inputs_or_rate(model, tmp_path):
    path = save_model(model, tmp_path / "model.pt")
    with pytest.raises(ModelFileError, match=r"was trained for inputs 3-12-2 tanh, 1 delay\(s\); expected 4-7-2"):
        load_model(path, expect_config=NNConfig(extra_signals=("load_conductance",)))
    with pytest.raises(ModelFileError, match=r"trained at a control period of 1000 us; the controller samples every 13.33 us"):
        load_model(path, expect_period=1 / 75e3)


@pytest.mark.parametrize("kwargs,message", [
    ({"hidden": ()}, "hidden layers"), ({"activation": "swish"}, "activation 'swish' is unknown"),
    ({"delays": 0}, "delays = 0 is invalid"), ({"extra_signals": ("temperature",)}, "extra signal 'temperature'"),
])
def test_invalid_configurations_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        NNConfig(**kwargs)


# ------------------------------------------------------------------------------------------ simulation error


@pytest.fixture(scope="module")
def switched_data():
    """PI identification data on the switched plant at one switching period (seeded, 4000 samples)."""
    from controllers.pi import PIController
    from cosim.design.data_collection import collect
    from cosim.design.experiments import collection_settings
    from cosim.design.plants import plant_binding

    period = 1 / 75e3
    pi = PIController(0.336 / 48, 0.111 / (period * 48), period)
    return collect(plant_binding("nominal", "switched"), pi,
                   collection_settings(period, 4000, seed=0, region="paper", spec=PAPER_SPEC))


SWITCHED_NN = NNConfig(hidden=(7,), delays=2, extra_signals=("load_conductance",))


def test_simulation_error_training_lowers_the_held_out_10_step_error(switched_data):
    """The network trained on one-step errors drifts off over a 10-sample open-loop rollout; the
    second stage over the horizon (from the same one-step solution, same seed) cuts that error."""
    one = train(switched_data, SWITCHED_NN, TrainingSettings(seed=0, max_iterations=400))
    multi = train(switched_data, SWITCHED_NN, TrainingSettings(seed=0, max_iterations=400, multi_step_horizon=23,
                                                               multi_step_stride=4, multi_step_iterations=150))
    a, b = one.metadata["held_out_rmse"], multi.metadata["held_out_rmse"]
    assert b["10_step_rmse_voltage_V"] < 0.8 * a["10_step_rmse_voltage_V"], (a, b)
    assert b["horizon_mean_rmse_voltage_V"] < a["horizon_mean_rmse_voltage_V"]
    stage = multi.metadata["training"]["multi_step"]
    assert stage["horizon"] == 23 and stage["validation_loss"] < stage["validation_loss_before"]
    assert one.metadata["training"]["multi_step"] is None


def test_simulation_error_training_is_deterministic(switched_data):
    settings = TrainingSettings(seed=4, max_iterations=50, multi_step_horizon=8, multi_step_stride=8,
                                multi_step_iterations=25)
    a, b = (train(switched_data, SWITCHED_NN, settings) for _ in range(2))
    for (name, pa), pb in zip(a.network.state_dict().items(), b.network.state_dict().values()):
        assert torch.equal(pa, pb), name


def test_refining_keeps_the_normalisation_and_uses_the_extra_records(switched_data):
    base = train(switched_data.iloc[:2000], SWITCHED_NN, TrainingSettings(seed=0, max_iterations=100))
    settings = TrainingSettings(seed=0, multi_step_horizon=6, multi_step_stride=4, multi_step_iterations=25)
    refined = train(switched_data.iloc[:2000], SWITCHED_NN, settings, extra_frames=[switched_data.iloc[2000:]],
                    initial=base)
    np.testing.assert_array_equal(refined.input_mean, base.input_mean)
    training = refined.metadata["training"]
    assert training["refined_from_initial"] and training["iterations"] == 0  # no one-step stage
    assert training["extra_samples"] == 2000 and training["test_samples"] == 400  # held out: the first record's tail
    with pytest.raises(ValueError, match="the initial model is a 3-7-2"):
        train(switched_data, SWITCHED_NN, settings, initial=train(switched_data.iloc[:500], NNConfig(),
                                                                  TrainingSettings(max_iterations=10)))


def test_the_10_step_report_feeds_the_recorded_load(switched_data):
    """With a load step inside a window, holding the load at its first value is a model error the
    network cannot avoid; the simulation error feeds the recorded load estimate at every step."""
    model = train(switched_data, SWITCHED_NN, TrainingSettings(seed=0, max_iterations=200))
    rmse = model.metadata["held_out_rmse"]
    assert rmse["10_step_rmse_voltage_V"] < rmse["10_step_rmse_voltage_V_held_extras"]
    frame = switched_data.iloc[3200:]
    steady = frame.assign(load_conductance=frame["load_conductance"].iloc[0])  # no change: both the same
    report = model.rmse_report(steady, 10)
    assert report["10_step_rmse_voltage_V"] == report["10_step_rmse_voltage_V_held_extras"]


@pytest.mark.parametrize("kwargs", [{"multi_step_horizon": 0}, {"multi_step_stride": 0},
                                    {"multi_step_iterations": -1}])
def test_invalid_training_settings_are_refused(kwargs):
    with pytest.raises(ValueError):
        TrainingSettings(**kwargs)


def test_the_configuration_module_is_torch_free_and_names_the_activations_the_network_builds():
    """controllers/nn_config.py is what commands check their arguments against before torch loads: it must not
    import torch; the torch layers (nn_model.TORCH_ACTIVATIONS) are the same activations, in the order the C twins
    number them (native.py passes list(ACTIVATIONS).index)."""
    import subprocess
    import sys

    from controllers.nn_config import ACTIVATIONS
    from controllers.nn_model import TORCH_ACTIVATIONS

    probe = "import sys, controllers.nn_config; print('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert done.stdout.strip() == "False", done.stdout + done.stderr
    assert list(TORCH_ACTIVATIONS) == list(ACTIVATIONS) == ["tanh", "relu", "sigmoid"]
    z = np.linspace(-4.0, 4.0, 81)
    for name, layer in TORCH_ACTIVATIONS.items():  # the numpy evaluation and the trained layer agree
        assert np.allclose(ACTIVATIONS[name](z), layer()(torch.from_numpy(z)).numpy(), rtol=0, atol=1e-15), name
