"""Controllers by name for the command line: PI, NNPC (workbench or paper network), the explicit
NNPC (a policy distilled from the NNPC), MPC baselines."""

from __future__ import annotations

import json
import math
import sys
from dataclasses import asdict, replace
from pathlib import Path

from controllers.nn_model import NNPlantModel, TrainingSettings, load_model, save_model, train
from controllers.predictors import CircuitParameters
from cosim.base.errors import ConfigError
from cosim.fmi.binding import PlantBinding
from cosim.study.data_collection import collect, save_samples
from cosim.study.experiments import adaptive_nnpc, collection_settings, explicit_nnpc, model_mpc, nn_configs, nnpc
from cosim.study.identification import Recipe, identify
from cosim.study.pi_tuning import PITuning, load_or_tune
from cosim.study.vocabulary import (
    CONTROLLERS,
    MPC_NOMINAL,
    MPC_ORACLE,
    NETWORKS,
    NNPC_EXPLICIT,
    NOMINAL,
    pipeline_tag,
)
from plant_fmu.table_ii import TABLE_II


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


def distilled_policy(model: NNPlantModel, binding: PlantBinding, period: float, out_dir: Path, *, seed: int,
                     progress: bool = False):
    """The explicit policy distilled from ``model``'s NNPC on this plant (cached in out_dir/models
    for the same plant, expert network, budget and seed)."""
    from controllers.explicit_policy import load_policy, save_policy
    from cosim.study.distillation import FULL_DISTILLATION, distill, expert_fingerprint, settings_dict

    settings = replace(FULL_DISTILLATION, seed=seed)
    path = out_dir / "models" / f"{pipeline_tag(binding.tag, period)}__nnpc-explicit.pt"
    expert = expert_fingerprint(model)
    if path.is_file():
        policy = load_policy(path, expect_period=period)
        meta = policy.metadata
        if (meta.get("plant") == binding.label and meta.get("expert_model") == expert
                and {k: v for k, v in meta.get("distillation", {}).items() if k not in ("labels", "history")}
                == json.loads(json.dumps(settings_dict(settings)))):
            return policy
    print(f"distilling the NNPC into an explicit policy on {binding.label} ({settings.labels} labels, saved to "
          f"{path}) ...", file=sys.stderr)
    policy = distill(model, binding, period, settings, progress=progress)
    save_policy(policy, path)
    return policy


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
                     progress: bool = False, policy_path: str | None = None) -> list:
    """The controllers ``names`` for ``binding`` at ``period``: built-in names (:data:`CONTROLLERS`)
    or paths of controller FMUs / controller-binding files (which run at their own sample period).
    Everything is checked first (names, gains, duty limits, the period, the roles each controller
    needs, a given model or policy file, controller FMUs and their bindings), then the PI is tuned,
    networks trained and the explicit NNPC distilled where needed -- so a mistake is refused before
    minutes of work. ``policy_path``: a distilled policy for nnpc-explicit (else distilled on demand
    from the nnpc network)."""
    from controllers.base import check_duty_limits
    from controllers.pi import PIController, check_gains
    from cosim.fmi.controller import FmuController, controller_binding

    bound = {n: controller_binding(n) for n in names if n not in CONTROLLERS}  # FMUs or binding files, checked now
    if (kp is None) != (ki is None):
        raise ConfigError("--kp and --ki must be given together (or neither, to tune the PI automatically)")
    networks = [n for n in names if n in NETWORKS or n == "nnpc-adaptive"]
    if model_path and len(networks) > 1:
        raise ConfigError("--model gives one network: run nnpc, nnpc-paper and nnpc-adaptive separately when you "
                          "pass --model")
    if not (period > 0 and math.isfinite(period)):
        raise ConfigError(f"control period {period} s is invalid: expected a finite value > 0")
    try:
        check_duty_limits(duty_limits, "duty limits")
        if kp is not None:
            check_gains(kp, ki)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    needs_current = [n for n in names if n in (*NETWORKS, "nnpc-adaptive", "nnpc-explicit", "current-mode")]
    designed = [n for n in names if n in ("current-mode", "type-iii")]
    if designed and abs(period * TABLE_II.switching_frequency - 1) > 1e-9:
        raise ConfigError(f"{designed[0]} is designed for one sample per PWM period (--control-period 1/75e3), not "
                          f"{period:.6g} s")
    if needs_current and not binding.has("inductor_current"):
        raise ConfigError(f"{needs_current[0]} needs the inductor_current role, which {binding.origin} does not bind")
    if policy_path and "nnpc-explicit" not in names:
        raise ConfigError("--policy gives the explicit NNPC's policy: add --controller nnpc-explicit (or drop --policy)")
    oracle = true_parameters(binding) if "mpc-oracle" in names else None  # refuses an external plant now
    given = load_model(Path(model_path), expect_period=period) if model_path else None
    if policy_path:
        from controllers.explicit_policy import load_policy

        policy = load_policy(Path(policy_path), expect_period=period)
        if tuple(duty_limits) != tuple(policy.duty_limits):
            raise ConfigError(f"policy file {policy_path} was distilled for duty limits {policy.duty_limits}, not "
                              f"the ({duty_limits[0]}, {duty_limits[1]}) asked for")
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
                network = "nnpc" if name == "nnpc-adaptive" else name
                model = given or trained_model(network, binding, period, out_dir, samples=samples, seed=seed,
                                               model_path=None, progress=progress)
                if name == "nnpc-adaptive":
                    controllers.append(adaptive_nnpc(model, period, CONTROLLERS[name], duty_limits=duty_limits))
                else:
                    controllers.append(nnpc(model, period, CONTROLLERS[name], duty_limits=duty_limits))
            elif name == "nnpc-explicit":
                if not policy_path:
                    if tuple(duty_limits) != (0.0, 1.0):
                        raise ConfigError("nnpc-explicit is distilled for duty limits (0, 1): give --policy for others")
                    model = given or trained_model("nnpc", binding, period, out_dir, samples=samples, seed=seed,
                                                   model_path=None, progress=progress)
                    policy = distilled_policy(model, binding, period, out_dir, seed=seed, progress=progress)
                controllers.append(explicit_nnpc(policy, NNPC_EXPLICIT))
            elif name in ("current-mode", "type-iii"):
                from cosim.study.classical_design import design_current_mode, design_type_iii, targets_for

                parameters = true_parameters(binding) if binding.source is None else NOMINAL
                design = (design_current_mode if name == "current-mode" else design_type_iii)(
                    parameters, replace(targets_for(binding, period), duty_limits=tuple(duty_limits)), CONTROLLERS[name])
                controllers.append(design.controller)
            elif name == "pi-envelope":
                from cosim.study.pi_tuning import tune_pi_envelope

                tuning = tune_pi_envelope(binding, period, progress=progress)
                controllers.append(tuning.controller(duty_limits, name=CONTROLLERS[name]))
            elif name == "mpc-oracle":
                controllers.append(model_mpc(oracle, period, MPC_ORACLE, duty_limits, binding))
            elif name == "mpc-nominal":
                controllers.append(model_mpc(NOMINAL, period, MPC_NOMINAL, duty_limits, binding))
            else:  # a controller FMU
                controllers.append(FmuController(bound[name]))
    except ValueError as error:  # a setting a controller constructor refuses
        raise ConfigError(str(error)) from None
    return controllers


def external_controllers(paths: list[str], periods: tuple[float, ...]) -> dict[float, tuple[str, ...]]:
    """Controller FMUs / controller-binding files for the reproduction, checked before any work:
    each must open, carry a name no built-in controller has, and sample at one of ``periods`` [s]
    (within 1e-9 relative). Returns the paths by the period whose pipelines run them."""
    from cosim.base.labels import period_text
    from cosim.fmi.controller import FmuController, controller_binding

    builtin = set(CONTROLLERS.values())
    chosen: dict[float, list[str]] = {}
    names: dict[str, str] = {}
    for path in paths:
        controller = FmuController(controller_binding(path), name=external_name(path))
        try:
            if controller.name in builtin or controller.name in names:
                raise ConfigError(f"{path}: the controller name {controller.name!r} is taken (by "
                                  f"{names.get(controller.name, 'a built-in controller')}): give it a 'label' in a "
                                  "controller-binding file")
            names[controller.name] = path
            period = next((p for p in periods if abs(controller.sample_period - p) <= 1e-9 * p), None)
            if period is None:
                raise ConfigError(f"{path}: sample period {controller.sample_period:.6g} s matches no pipeline of the "
                                  f"reproduction (expected one of {', '.join(period_text(p) for p in periods)})")
            chosen.setdefault(period, []).append(str(Path(path).resolve()))
        finally:
            controller.close()
    return {period: tuple(found) for period, found in chosen.items()}


def external_name(path: str) -> str | None:
    """How a controller FMU is named in runs and figures: a binding file's ``label``, else
    ``<file stem> (FMU)`` -- never a built-in controller's name."""
    return None if str(path).endswith(".toml") else f"{Path(path).stem} (FMU)"

