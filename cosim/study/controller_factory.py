"""Controllers by name for the command line: PI, NNPC (workbench or paper network), MPC baselines."""

from __future__ import annotations

import json
import math
import sys
from dataclasses import asdict
from pathlib import Path

from controllers.nn_model import NNPlantModel, TrainingSettings, load_model, save_model, train
from controllers.predictors import CircuitParameters
from cosim.base.errors import ConfigError
from cosim.fmi.binding import PlantBinding
from cosim.study.data_collection import collect, save_samples
from cosim.study.experiments import adaptive_nnpc, collection_settings, model_mpc, nn_configs, nnpc
from cosim.study.identification import Recipe, identify
from cosim.study.pi_tuning import PITuning, load_or_tune
from cosim.study.vocabulary import CONTROLLERS, MPC_NOMINAL, MPC_ORACLE, NETWORKS, NOMINAL, pipeline_tag


def tuned_pi(binding: PlantBinding, period: float, out_dir: Path, progress: bool = False) -> PITuning:
    path = out_dir / "tuning" / f"pi__{pipeline_tag(binding.tag, period)}.json"
    if not path.is_file():
        print(f"tuning the PI for {binding.label} at {period * 1e6:.4g} us (saved to {path}) ...", file=sys.stderr)
    return load_or_tune(path, binding, period, progress=progress)


def trained_model(name: str, binding: PlantBinding, period: float, out_dir: Path, *, samples: int, seed: int,
                  model_path: str | None, progress: bool = False) -> NNPlantModel:
    """Load ``model_path``, or identify the network on this plant (cached in out_dir): the
    workbench's NNPC network by the recipe of :mod:`cosim.study.identification` (PI data, one-step
    and simulation-error training, NNPC-in-the-loop data at fast rates), the paper's network by
    one-step training on the PI data."""
    config = nn_configs(period)[name]
    if model_path:
        return load_model(Path(model_path), expect_period=period)
    path = out_dir / "models" / f"{pipeline_tag(binding.tag, period)}__{name}.pt"
    settings = collection_settings(period, samples, seed)
    collection = json.loads(json.dumps(asdict(settings)))  # as the model file stores it
    recipe = Recipe(samples=samples)
    wanted = json.loads(json.dumps(asdict(recipe)))
    if path.is_file():
        model = load_model(path, expect_period=period, expect_config=config)
        meta = model.metadata
        if meta.get("plant") == binding.label and meta.get("collection") == collection \
                and (name != "nnpc" or meta.get("recipe") == wanted):
            return model  # same plant, identification settings (samples, seed, dither, recipe) and network
    pi = tuned_pi(binding, period, out_dir, progress)
    print(f"collecting {samples} samples on {binding.label} and identifying {config.label} ...", file=sys.stderr)
    data = collect(binding, pi.controller(), settings, progress=progress)
    save_samples(data, out_dir / "data" / f"{pipeline_tag(binding.tag, period)}.parquet")
    meta = {"control_period_s": period, "plant": binding.label, "seed": seed, "collection": collection}
    if name == "nnpc":
        model = identify(binding, pi.controller(), period, config, seed, recipe, metadata={**meta, "recipe": wanted},
                         data=data, progress=progress).model
    else:
        model = train(data, config, TrainingSettings(seed=seed), progress=progress, metadata=meta)
    save_model(model, path)
    return model


def true_parameters(binding: PlantBinding) -> CircuitParameters:
    """Circuit parameters of a built-in plant binding (the oracle's model)."""
    if binding.source is not None:
        raise ConfigError(f"mpc-oracle needs the plant's circuit parameters, which are known only for the built-in "
                          f"FMU; {binding.origin} is external (use mpc-nominal or nnpc)")
    p = binding.parameters
    fields = ("inductance", "capacitance", "inductor_resistance", "switch_on_resistance", "diode_forward_voltage",
              "capacitor_esr")
    return CircuitParameters(**{f: float(p.get(f, getattr(NOMINAL, f))) for f in fields})


def make_controllers(names: list[str], binding: PlantBinding, period: float, out_dir: Path, *,
                     duty_limits: tuple[float, float], kp: float | None = None, ki: float | None = None,
                     model_path: str | None = None, samples: int = 10_000, seed: int = 0,
                     progress: bool = False) -> list:
    from controllers.pi import PIController

    if (kp is None) != (ki is None):
        raise ConfigError("--kp and --ki must be given together (or neither, to tune the PI automatically)")
    if model_path and sum(n in NETWORKS for n in names) > 1:
        raise ConfigError("--model gives one network: run nnpc and nnpc-paper separately when you pass --model")
    if not (period > 0 and math.isfinite(period)):
        raise ConfigError(f"control period {period} s is invalid: expected a finite value > 0")
    controllers = []
    try:
        for name in names:
            if name == "pi":
                if kp is not None:
                    controllers.append(PIController(kp, ki, period, duty_limits,
                                                    tuning={"method": "given on the command line"}))
                else:
                    controllers.append(tuned_pi(binding, period, out_dir, progress).controller(duty_limits))
            elif name in NETWORKS or name == "nnpc-adaptive":
                if not binding.has("inductor_current"):
                    raise ConfigError(f"{name} needs the inductor_current role, which {binding.origin} does not bind")
                network = "nnpc" if name == "nnpc-adaptive" else name
                model = trained_model(network, binding, period, out_dir, samples=samples, seed=seed,
                                      model_path=model_path, progress=progress)
                if name == "nnpc-adaptive":
                    controllers.append(adaptive_nnpc(model, period, CONTROLLERS[name], duty_limits=duty_limits))
                else:
                    controllers.append(nnpc(model, period, CONTROLLERS[name], duty_limits=duty_limits))
            elif name == "mpc-oracle":
                controllers.append(model_mpc(true_parameters(binding), period, MPC_ORACLE, duty_limits, binding))
            elif name == "mpc-nominal":
                controllers.append(model_mpc(NOMINAL, period, MPC_NOMINAL, duty_limits, binding))
            else:
                raise ConfigError(f"controller {name!r} is unknown: expected one of {', '.join(CONTROLLERS)}")
    except ValueError as error:  # invalid gains, limits or periods from the controller constructors
        raise ConfigError(str(error)) from None
    return controllers
