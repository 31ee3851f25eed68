"""Controllers by name for the command line: PI, NNPC (workbench or paper network), the explicit
NNPC (a policy distilled from the NNPC), MPC baselines."""

from __future__ import annotations

import json
import math
import sys
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING

from controllers.nn_config import TrainingSettings
from controllers.predictors import CircuitParameters
from cosim.base.errors import ConfigError, ModelFileError
from cosim.base.labels import did_you_mean, period_text
from cosim.design.data_collection import collect, save_samples
from cosim.design.design_cache import announce, data_file, design_key, model_file, pi_file, stale_reason
from cosim.design.experiments import (
    adaptive_nnpc,
    check_optimizer,
    collection_settings,
    default_region,
    explicit_nnpc,
    model_mpc,
    network_region,
    nn_configs,
    nnpc,
    own_optimizer,
    planned_with,
    rti_settings,
)
from cosim.fmi.binding import PlantBinding

if TYPE_CHECKING:  # torch loads with the NN model's module: only where a network is trained or read (seconds)
    from controllers.nn_model import NNPlantModel
from cosim.design.identification import Recipe, identify, network_design, write_identification_figure
from cosim.design.pi_tuning import PITuning, cached_tuning, pi_design
from cosim.design.vocabulary import (
    CONTROLLERS,
    MPC_NOMINAL,
    MPC_ORACLE,
    NETWORKS,
    NNPC_EXPLICIT,
    NOMINAL,
    ON_DEMAND_SAMPLES,
    PREDICTIVE_CONTROLLERS,
)


def tuned_pi(binding: PlantBinding, period: float, out_dir: Path, progress: bool = False) -> PITuning:
    """The PI tuned for ``binding`` at ``period`` [s], cached in ``out_dir/tuning`` under its
    design key (:mod:`cosim.design.design_cache`): tuned again, and said so, when the plant or the
    tuning settings changed. Tuning is announced on stderr with its size and an estimate of its
    duration, and ends with the gains and how long it took (progress bars or not)."""
    path = pi_file(out_dir, binding.tag, period)
    tuning = cached_tuning(path, binding, period)
    if tuning is None:
        tuning = announced_tuning(binding, period, path, progress)
    return tuning


def announced_tuning(binding: PlantBinding, period: float, path: Path | None, progress: bool = False) -> PITuning:
    """:func:`cosim.design.pi_tuning.tune_pi`, told on stderr: what it does and at most how many
    simulations, an estimate of its duration after the second evaluation, and the result with the
    time it took; saved to ``path`` (if given)."""
    import time

    from cosim.base.files import atomic_write_text
    from cosim.design.pi_tuning import TUNING_SCENARIOS, tune_pi, tuning_evaluations

    total = tuning_evaluations()
    say(f"tuning the PI for {binding.label} at {period_text(period)}: at most {total} evaluations x "
        f"{len(TUNING_SCENARIOS)} scenarios (give --kp and --ki to skip it)"
        + (f"; saved to {path}" if path is not None else ""))
    start = time.perf_counter()
    tuning = tune_pi(binding, period, progress=progress,
                     on_estimate=lambda seconds: say(f"  one evaluation takes {seconds:.2g} s: the tuning takes "
                                                     f"about {max(1.0, seconds * total):.0f} s"))
    say(f"  tuned in {time.perf_counter() - start:.1f} s ({tuning.evaluations} evaluations, "
        f"{tuning.evaluations * len(TUNING_SCENARIOS)} simulations): Kp = {tuning.kp:.4g} 1/V, "
        f"Ki = {tuning.ki:.4g} 1/(V s), design key {tuning.design_key}")
    if path is not None:
        atomic_write_text(path, tuning.to_json() + "\n")
    return tuning


def say(message: str) -> None:
    """A line of what a long step is doing, on stderr (with or without progress bars)."""
    print(message, file=sys.stderr, flush=True)


def trained_model(name: str, binding: PlantBinding, period: float, out_dir: Path, *, samples: int, seed: int,
                  model_path: str | None, progress: bool = False) -> NNPlantModel:
    """Load ``model_path``, or identify the network on this plant (cached in out_dir under its
    design key: the plant, rate, seed, collection, recipe and network, and the PI that collects the
    data -- identified again, and said so, when any of them changed): the workbench's NNPC network
    by the recipe of :mod:`cosim.design.identification` (PI data, one-step and simulation-error
    training, NNPC-in-the-loop data at fast rates), the paper's network by one-step training on the
    PI data. The data file and the held-out RMSE are printed."""
    from controllers.nn_model import load_model, save_model, train

    config = nn_configs(period)[name]
    if model_path:
        return load_model(Path(model_path), expect_period=period)
    path = model_file(out_dir, binding.tag, period, name)
    recipe = Recipe(samples=samples) if name == "nnpc" else None
    wanted = network_design(name, binding, period, config, seed, samples, recipe=recipe,
                            training=None if recipe else TrainingSettings(seed=seed),
                            pi_key=pi_design(binding, period).key)
    if path.is_file():
        try:
            model = load_model(path, expect_period=period, expect_config=config)
            reason = stale_reason(model.metadata.get("design"), wanted)
        except ModelFileError as error:
            reason = f"it cannot be read ({str(error).splitlines()[0]})"
        if reason is None:
            return model
        announce(path, reason, f"identifying {config.label} again")
    pi = tuned_pi(binding, period, out_dir, progress)
    region = network_region(name, period)
    settings = collection_settings(period, samples, seed, region=region, spec=binding.converter)
    say(f"collecting {samples} samples on {binding.label} and identifying {config.label} (saved to {path}) ...")
    data = collect(binding, pi.controller(), settings, progress=progress)
    data_path = data_file(out_dir, binding.tag, period, None if region == default_region(period) else region)
    data.attrs["metadata"]["seed"] = seed
    save_samples(data, data_path)
    meta = {"control_period_s": period, "plant": binding.label, "seed": seed, "converter": binding.converter.describe(),
            "collection": json.loads(json.dumps(asdict(settings))), "data_file": str(data_path),
            "design": wanted.describe()}
    if name == "nnpc":
        model = identify(binding, pi.controller(), period, config, seed, recipe,
                         metadata={**meta, "recipe": json.loads(json.dumps(asdict(recipe)))}, data=data,
                         progress=progress).model
    else:
        model = train(data, config, TrainingSettings(seed=seed), progress=progress, metadata=meta)
    save_model(model, path)
    figure = write_identification_figure(model, data, path)
    rmse = model.metadata.get("held_out_rmse", {})
    say(f"  {config.label}: held-out one-step RMSE {rmse.get('one_step_rmse_voltage_V', math.nan) * 1e3:.2f} mV, "
        f"{rmse.get('one_step_rmse_current_A', math.nan) * 1e3:.2f} mA; data {data_path}, model {path} "
        f"(identification figure {figure.name}), design key {wanted.key}")
    return model


def distilled_policy(model: NNPlantModel, binding: PlantBinding, period: float, out_dir: Path, *, seed: int,
                     progress: bool = False):
    """The explicit policy distilled from ``model``'s NNPC on this plant (cached in out_dir/models
    under its design key: the plant, rate, seed, budget and the expert network)."""
    from controllers.explicit_policy import load_policy, save_policy
    from cosim.design.distillation import FULL_DISTILLATION, distill, expert_fingerprint, settings_dict

    settings = replace(FULL_DISTILLATION, seed=seed).for_converter(binding.converter)
    path = model_file(out_dir, binding.tag, period, "nnpc-explicit")
    wanted = design_key("nnpc-explicit", binding, period, seed=seed, settings=settings_dict(settings),
                        depends_on={"expert_weights": expert_fingerprint(model),
                                    "expert": model.metadata.get("design", {}).get("key")})
    if path.is_file():
        try:
            policy = load_policy(path, expect_period=period)
            reason = stale_reason(policy.metadata.get("design"), wanted)
        except ModelFileError as error:
            reason = f"it cannot be read ({str(error).splitlines()[0]})"
        if reason is None:
            return policy
        announce(path, reason, "distilling again")
    say(f"distilling the NNPC into an explicit policy on {binding.label} ({settings.labels} labels, saved to "
        f"{path}) ...")
    policy = distill(model, binding, period, settings, progress=progress, metadata={"design": wanted.describe()})
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


def nominal_circuit(binding: PlantBinding, purpose: str) -> CircuitParameters:
    """The nominal circuit of the plant's converter spec (``[converter.circuit]``; Table II for the built-in plant) that
    a model-based design of ``purpose`` believes -- refused, naming the key, where the spec gives no L or C."""
    return CircuitParameters(**binding.converter.circuit(purpose))


def make_controllers(names: list[str], binding: PlantBinding, period: float, out_dir: Path, *,
                     duty_limits: tuple[float, float], kp: float | None = None, ki: float | None = None,
                     model_path: str | None = None, samples: int | None = None, seed: int = 0,
                     progress: bool = False, policy_path: str | None = None, optimizer: str | None = None,
                     rti_changes: dict | None = None, offered: tuple[str, ...] = PREDICTIVE_CONTROLLERS) -> list:
    """The controllers ``names`` for ``binding`` at ``period``: built-in names (:data:`CONTROLLERS`),
    paths of controller FMUs / controller-binding files, or Python controllers (``module:Class``,
    ``file.py:Class``, :mod:`cosim.python_controller`); those run at their own sample period.
    Everything is checked first (names, gains, duty limits, the period, the roles each controller
    needs, a given model or policy file, controller FMUs and their bindings), then the PI is tuned,
    networks trained and the explicit NNPC distilled where needed -- so a mistake is refused before
    minutes of work. ``policy_path``: a distilled policy for nnpc-explicit (else distilled on demand
    from the nnpc network). ``optimizer`` (``"rti"`` or ``"search"``): the predictive controllers' optimizer
    (None: each one's own, :func:`~cosim.design.experiments.own_optimizer`); ``rti_changes``
    (:func:`~cosim.design.experiments.rti_changes`): fields of the rate's RTI settings replaced for those that plan
    with the RTI; ``offered``: the predictive controllers the calling command offers (named in its messages)."""
    from controllers.base import check_duty_limits
    from controllers.pi import PIController, check_gains
    from cosim.fmi.controller import FmuController, controller_binding
    from cosim.python_controller import is_python_controller, load_python_controller

    twice = next((name for i, name in enumerate(names) if name in names[:i]), None)
    if twice is not None:  # their runs would write the same files: refused before any tuning or training
        raise ConfigError(f"controller {twice} is given twice")
    for name in names:
        if name not in CONTROLLERS and not is_python_controller(name) \
                and Path(name).suffix.lower() not in (".fmu", ".toml"):
            raise ConfigError(f"--controller {name} is unknown{did_you_mean(name, CONTROLLERS)}: expected one of "
                              f"{', '.join(CONTROLLERS)}, a controller FMU (.fmu), a controller-binding file (.toml) "
                              "or a Python controller (module:Class or path/to/file.py:Class)")
    if (kp is None) != (ki is None):
        raise ConfigError("--kp and --ki must be given together (or neither, to tune the PI automatically)")
    if kp is not None and "pi" not in names:
        raise ConfigError(f"--kp and --ki set the PI's gains, but no --controller pi is run (controllers: "
                          f"{', '.join(names)}): drop them or add --controller pi")
    python = {n: load_python_controller(n, sample_period=period, duty_limits=duty_limits)
              for n in names if is_python_controller(n)}  # imported and checked now
    bound = {n: controller_binding(n) for n in names if n not in CONTROLLERS and n not in python}  # FMUs, binding files
    if bound and len(bound) == len(names) and tuple(duty_limits) != (0.0, 1.0):  # an FMU keeps its own limits
        raise ConfigError(f"duty limits {tuple(duty_limits)} apply to the built-in and Python controllers, but only "
                          f"controller FMUs run here ({', '.join(names)}), which limit the duty themselves: drop "
                          "--duty-min/--duty-max")
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
    if designed:
        f_sw = binding.converter.require("switching_frequency",
                                         f"{designed[0]} (designed for one sample per PWM period)")
        if abs(period * f_sw - 1) > 1e-9:
            raise ConfigError(f"{designed[0]} is designed for one sample per PWM period (--control-period 1/{f_sw:g}), "
                              f"not {period:.6g} s")
        binding.converter.circuit(f"{designed[0]} (designed on the nominal circuit)")
    if "mpc-nominal" in names:
        binding.converter.circuit("mpc-nominal (it predicts with the nominal circuit)")
    if needs_current and not binding.has("inductor_current"):
        raise ConfigError(f"{needs_current[0]} needs the inductor_current role, which {binding.origin} does not bind")
    trains = [n for n in names if n in NETWORKS or n == "nnpc-adaptive" or (n == "nnpc-explicit" and not policy_path)]
    by_policy = " (nnpc-explicit runs the policy --policy gives)" if policy_path and "nnpc-explicit" in names else ""
    if model_path and not trains:
        raise ConfigError(f"--model gives the network of nnpc, nnpc-paper, nnpc-adaptive or nnpc-explicit, but no "
                          f"controller run here uses one{by_policy} (controllers: {', '.join(names)}): drop --model")
    if samples is not None and (model_path or not trains):
        why = "--model gives the network" if model_path else f"no controller run here trains one{by_policy}"
        raise ConfigError(f"--samples sizes the data a network is trained on, but {why} (controllers: "
                          f"{', '.join(names)}): drop --samples")
    samples = ON_DEMAND_SAMPLES if samples is None else samples
    if policy_path and "nnpc-explicit" not in names:
        raise ConfigError("--policy gives the explicit NNPC's policy: add --controller nnpc-explicit (or drop --policy)")
    check_optimizer_options(names, period, duty_limits, optimizer, rti_changes, offered)
    oracle = true_parameters(binding) if "mpc-oracle" in names else None  # refuses an external plant now
    if model_path:
        from controllers.nn_model import load_model

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
                factory = adaptive_nnpc if name == "nnpc-adaptive" else nnpc
                controllers.append(factory(model, period, CONTROLLERS[name], duty_limits=duty_limits,
                                           spec=binding.converter, **planned_with(name, optimizer, rti_changes)))
            elif name == "nnpc-explicit":
                if not policy_path:
                    if tuple(duty_limits) != (0.0, 1.0):
                        raise ConfigError("nnpc-explicit is distilled for duty limits (0, 1): give --policy for others")
                    model = given or trained_model("nnpc", binding, period, out_dir, samples=samples, seed=seed,
                                                   model_path=None, progress=progress)
                    policy = distilled_policy(model, binding, period, out_dir, seed=seed, progress=progress)
                controllers.append(explicit_nnpc(policy, NNPC_EXPLICIT, spec=binding.converter))
            elif name in ("current-mode", "type-iii"):
                from cosim.design.classical_design import design_current_mode, design_type_iii, targets_for

                parameters = true_parameters(binding) if binding.source is None else nominal_circuit(binding, name)
                design = (design_current_mode if name == "current-mode" else design_type_iii)(
                    parameters, replace(targets_for(binding, period), duty_limits=tuple(duty_limits)), CONTROLLERS[name])
                controllers.append(design.controller)
            elif name == "pi-envelope":
                from cosim.design.pi_tuning import tune_pi_envelope

                tuning = tune_pi_envelope(binding, period, progress=progress)
                controllers.append(tuning.controller(duty_limits, name=CONTROLLERS[name]))
            elif name in ("mpc-oracle", "mpc-nominal"):
                parameters, label = (oracle, MPC_ORACLE) if name == "mpc-oracle" else \
                    (nominal_circuit(binding, name), MPC_NOMINAL)
                controllers.append(model_mpc(parameters, period, label, duty_limits, binding,
                                             **planned_with(name, optimizer, rti_changes)))
            elif name in python:  # the user's own Python controller, at its own sample period
                controllers.append(python[name])
            else:  # a controller FMU, named NAME (FMU) as the docs say (a binding file's label, if it has one)
                controllers.append(FmuController(bound[name], name=external_name(name)))
    except ValueError as error:  # a setting a controller constructor refuses
        raise ConfigError(str(error)) from None
    return controllers


def check_optimizer_options(names: list[str], period: float, duty_limits: tuple[float, float],
                            optimizer: str | None, rti_changes: dict | None,
                            offered: tuple[str, ...] = PREDICTIVE_CONTROLLERS) -> None:
    """Refuse --optimizer and --rti where they change nothing, and RTI changes that do not suit the rate's
    settings (e.g. reweightings with the 1 ms line search) -- one ConfigError line, before any tuning or training.
    ``offered``: the predictive controllers the command offers (named in the messages)."""
    predictive = [n for n in names if n in PREDICTIVE_CONTROLLERS]
    if optimizer is not None:
        try:
            check_optimizer(optimizer)
        except ConfigError as error:
            raise ConfigError(f"--optimizer: {error}") from None
        if not predictive:
            raise ConfigError(f"--optimizer {optimizer} chooses the optimizer of the predictive controllers "
                              f"({', '.join(offered)}), but none runs here (controllers: "
                              f"{', '.join(names)}): drop --optimizer")
    if not rti_changes:
        return
    given = " ".join(f"--rti {k}={str(v).lower() if isinstance(v, bool) else v}" for k, v in rti_changes.items())
    if not any(own_optimizer(n, optimizer) == "rti" for n in predictive):
        why = ("--optimizer search" if optimizer == "search" else
               "nnpc-paper plans with the search unless --optimizer rti" if predictive else
               f"none of {', '.join(offered)} runs")
        raise ConfigError(f"{given} changes the real-time iteration's settings, but no controller here plans with it "
                          f"({why}; controllers: {', '.join(names)}): drop --rti")
    try:
        rti_settings(period, "rti", duty_limits, rti_changes)
    except ValueError as error:
        rate = rti_settings(period, "rti", duty_limits)
        kept = [f"{k} = {getattr(rate, k)}" for k in ("reweightings", "line_search")
                if k in str(error) and k not in rti_changes]  # a field of the rate's the user did not set
        hint = f" (the rate's settings have {', '.join(kept)}: change it too)" if kept else ""
        raise ConfigError(f"{given} at the control period {period_text(period)}: {error}{hint}") from None


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

