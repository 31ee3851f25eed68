"""The sweep's controllers: designed once on the nominal plant (here), rebuilt on every worker.

That is the robustness question a tolerance study asks: the PI is tuned, the NNPC identified and
the MPC parameterised for the plant on paper, and the sweep runs them unchanged on the units that
get built. Each kind is one entry of :data:`KINDS` -- a ``design`` (in the workbench's process:
tuning, identification, reading a given model file or controller FMU) and a ``build`` (on a
worker, from the recipe). A controller FMU is designed elsewhere: its "design" reads the FMU (and
its controller-binding file) into the recipe, and its build writes the FMU's bytes to the worker's
own folder and opens it through the checks :func:`cosim.fmi.controller.controller_binding` and
:class:`~cosim.fmi.controller.FmuController` make.
"""

from __future__ import annotations

import json
import math
import tempfile
import threading
from dataclasses import asdict
from pathlib import Path
from typing import Callable, NamedTuple

from controllers.predictors import CircuitParameters
from cosim.base.digests import canonical, digest
from cosim.base.errors import ConfigError, ModelFileError
from cosim.design.design_cache import model_file
from cosim.design.sweeps.recipes import ControllerRecipe
from cosim.design.sweeps.spec import ControllerEntry
from cosim.design.vocabulary import DEFAULT_IMPLEMENTATION
from cosim.fmi.binding import PlantBinding


def _json(settings: dict) -> str:
    return canonical(settings)


# ---------------------------------------------------------------------------------------------
# design: in the workbench's process, once per sweep


def _design_pi(entry: ControllerEntry, binding: PlantBinding, period: float, work_dir: Path,
               progress: bool) -> ControllerRecipe:
    if entry.kp is not None:
        settings = {"kp_per_V": entry.kp, "ki_per_V_s": entry.ki,
                    "tuning": {"method": entry.origin or "given in the sweep file"}}
    else:
        from cosim.design.controller_factory import tuned_pi

        tuning = tuned_pi(binding, period, work_dir, progress)
        settings = {"kp_per_V": tuning.kp, "ki_per_V_s": tuning.ki,
                    "tuning": {"method": tuning.method, "cost_V2s": tuning.cost, "plant": tuning.plant,
                               "design_key": tuning.design_key}}
    return ControllerRecipe("pi", entry.name, period, _json(settings))


def _design_nn(entry: ControllerEntry, binding: PlantBinding, period: float, work_dir: Path,
               progress: bool) -> ControllerRecipe:
    from controllers.nn_model import load_model
    from cosim.design.controller_factory import trained_model
    from cosim.design.experiments import nn_configs

    config = nn_configs(period)[entry.kind]
    if entry.model is not None:  # a given network runs with the inputs it was trained for (its file says which)
        try:
            model = load_model(entry.model, expect_period=period)
        except ModelFileError as error:
            raise ConfigError(f"{entry.place}: {error}") from None
        path, origin = Path(entry.model), entry.origin or f"model file {Path(entry.model).name}"
        config = model.config
    else:
        if not binding.has("inductor_current"):
            raise ConfigError(f"{entry.place}: {entry.kind} needs the inductor_current role, which {binding.origin} "
                              "does not bind")
        model = trained_model(entry.kind, binding, period, work_dir, samples=entry.samples, seed=entry.seed,
                              model_path=None, progress=progress)
        path = model_file(work_dir, binding.tag, period, entry.kind)
        origin = f"identified on the nominal plant ({entry.samples} samples, seed {entry.seed})"
    blob = path.read_bytes()
    rmse = model.metadata.get("held_out_rmse", {})
    settings = {"network": config.label, "origin": origin,
                "held_out_one_step_rmse_V": rmse.get("one_step_rmse_voltage_V"),
                "held_out_one_step_rmse_A": rmse.get("one_step_rmse_current_A")}
    if entry.policy is not None:  # the explicit NNPC in shadow: its first move on the NNPC's own states
        import base64

        settings["shadow_policy"] = base64.b64encode(Path(entry.policy).read_bytes()).decode()
    return ControllerRecipe(entry.kind, entry.name, period, _json({**settings, **_optimizer_settings(entry)}), blob)


def _optimizer_settings(entry: ControllerEntry) -> dict:
    """A predictive controller's optimizer and RTI changes as the file gave them (only then: the recipes and ids
    of sweeps that give none stay what they were)."""
    given = {"optimizer": entry.optimizer} if entry.optimizer is not None else {}
    return {**given, "rti": dict(entry.rti)} if entry.rti else given


def _planned(recipe: ControllerRecipe) -> dict:
    """``optimizer`` and ``rti_changes`` for the factories of :mod:`cosim.design.experiments`: the recipe's own, else
    its kind's (:func:`~cosim.design.experiments.planned_with`)."""
    from cosim.design.experiments import planned_with

    return planned_with(recipe.kind, recipe.settings.get("optimizer"), recipe.settings.get("rti"))


def _design_mpc(entry: ControllerEntry, binding: PlantBinding, period: float, work_dir: Path,
                progress: bool) -> ControllerRecipe:
    from cosim.design.controller_factory import nominal_circuit, true_parameters

    # the nominal plant's circuit: Table II with the variant's parasitics for the built-in FMU; for an external FMU the
    # nominal circuit of its converter spec (refused, naming the key, where the spec gives none)
    circuit = true_parameters(binding) if binding.source is None else nominal_circuit(binding, entry.kind)
    return ControllerRecipe("mpc-nominal", entry.name, period,
                            _json({"circuit": asdict(circuit), **_optimizer_settings(entry)}))


def _design_oracle(entry: ControllerEntry, binding: PlantBinding, period: float, work_dir: Path,
                   progress: bool) -> ControllerRecipe:
    """The MPC with the plant's own circuit: the oracle where no axis changes the plant (the sweep plan
    refuses it beside [parameters] axes)."""
    from cosim.design.controller_factory import true_parameters

    try:
        circuit = true_parameters(binding)
    except ConfigError as error:
        raise ConfigError(f"{entry.place}: {error}") from None
    return ControllerRecipe("mpc-oracle", entry.name, period,
                            _json({"circuit": asdict(circuit), **_optimizer_settings(entry)}))


def _design_explicit(entry: ControllerEntry, binding: PlantBinding, period: float, work_dir: Path,
                     progress: bool) -> ControllerRecipe:
    """The explicit NNPC of a policy file (``policy``), else distilled on the nominal plant from its NNPC."""
    from controllers.explicit_policy import load_policy

    if entry.policy is not None:
        try:
            load_policy(Path(entry.policy), expect_period=period)
        except ModelFileError as error:
            raise ConfigError(f"{entry.place}: {error}") from None
        path, origin = Path(entry.policy), entry.origin or f"policy file {Path(entry.policy).name}"
    else:
        from cosim.design.controller_factory import distilled_policy, trained_model

        model = trained_model("nnpc", binding, period, work_dir, samples=entry.samples, seed=entry.seed,
                              model_path=None, progress=progress)
        distilled_policy(model, binding, period, work_dir, seed=entry.seed, progress=progress)
        path = model_file(work_dir, binding.tag, period, "nnpc-explicit")
        origin = "distilled on the nominal plant"
    return ControllerRecipe("nnpc-explicit", entry.name, period, _json({"origin": origin}), path.read_bytes())


def _design_classical(entry: ControllerEntry, binding: PlantBinding, period: float, work_dir: Path,
                      progress: bool) -> ControllerRecipe:
    """The current-mode controller or the Type-III: from a design file (``design``), else designed on
    the nominal plant by :mod:`cosim.design.classical_design`."""
    from cosim.design.classical_design import (
        controller_from_file,
        design_current_mode,
        design_type_iii,
        targets_for,
    )
    from cosim.design.controller_factory import nominal_circuit, true_parameters

    try:
        if entry.design is not None:
            controller = controller_from_file(Path(entry.design), entry.name)
            origin = entry.origin or f"design file {Path(entry.design).name}"
        else:
            parameters = true_parameters(binding) if binding.source is None else nominal_circuit(binding, entry.kind)
            design = (design_current_mode if entry.kind == "current-mode" else design_type_iii)(
                parameters, targets_for(binding, period), entry.name)
            controller, origin = design.controller, "designed on the nominal plant"
    except (ValueError, KeyError, OSError) as error:
        raise ConfigError(f"{entry.place}: {entry.kind}: {error}") from None
    if abs(controller.sample_period - period) > 1e-9 * period:
        raise ConfigError(f"{entry.place}: {entry.kind}: the design samples every {controller.sample_period:.6g} s, "
                          f"not at the sweep's control period {period:.6g} s")
    return ControllerRecipe(entry.kind, entry.name, period, _json({"controller": controller.describe(),
                                                                   "origin": origin}))


def _design_envelope_pi(entry: ControllerEntry, binding: PlantBinding, period: float, work_dir: Path,
                        progress: bool) -> ControllerRecipe:
    if entry.kp is not None:
        settings = {"kp_per_V": entry.kp, "ki_per_V_s": entry.ki,
                    "tuning": {"method": entry.origin or "given in the sweep file"}}
    else:
        from cosim.design.pi_tuning import tune_pi_envelope

        tuning = tune_pi_envelope(binding, period, progress=progress)
        settings = {"kp_per_V": tuning.kp, "ki_per_V_s": tuning.ki,
                    "tuning": {"method": tuning.method, "cost": tuning.cost, "plant": tuning.plant,
                               "design_key": tuning.design_key}}
    return ControllerRecipe("pi-envelope", entry.name, period, _json(settings))


def _design_fmu(entry: ControllerEntry, binding: PlantBinding, period: float, work_dir: Path,
                progress: bool) -> ControllerRecipe:
    """The controller FMU's bytes and, for a controller-binding file, the binding's content (the
    sweep file's reader checked both, and the sample period, before any work)."""
    from cosim.base.errors import WorkbenchError
    from cosim.fmi.controller import controller_binding

    given = Path(entry.path)
    try:
        bound = controller_binding(str(given))
        blob = Path(bound.fmu_path).read_bytes()
    except (WorkbenchError, OSError) as error:
        raise ConfigError(f"{entry.place}: controller {given.name}: {error}") from None
    fmu_name = Path(bound.fmu_path).name
    if given.suffix.lower() == ".toml":
        carried = {"file": given.name, "label": bound.label, "sample_period_s": bound.sample_period,
                   "duty_limits": list(bound.duty_limits) if bound.duty_limits is not None else None,
                   "roles": {r: [m.variable, m.scale, m.offset] for r, m in sorted(bound.roles.items())},
                   "parameters": dict(bound.parameters)}
        origin = f"controller FMU {fmu_name} through controller-binding file {given.name}"
    else:
        carried, origin = None, f"controller FMU {fmu_name}"
    settings = {"fmu": fmu_name, "binding": carried, "origin": entry.origin or origin}
    return ControllerRecipe("fmu", entry.name, period, _json(settings), blob)


# ---------------------------------------------------------------------------------------------
# build: on a worker, from the recipe


_models: dict[str, object] = {}
_models_lock = threading.Lock()


def model_from_bytes(blob: bytes, period: float, kind: str):
    """An NN model from a file's bytes, read through :func:`load_model`'s checks (weights only,
    SHA-256 of the weights, shapes and control period; the inputs are the file's own, as the design
    read them); cached per process by digest."""
    from controllers.nn_model import load_model

    key = f"{digest(blob)}:{period!r}:{kind}"
    with _models_lock:
        if key not in _models:
            with tempfile.TemporaryDirectory(prefix="buck-cosim-model-") as folder:
                path = Path(folder) / "model.pt"
                path.write_bytes(blob)
                _models[key] = load_model(path, expect_period=period)
        return _models[key]


def _build_pi(recipe: ControllerRecipe, binding: PlantBinding):
    from controllers.pi import PIController

    s = recipe.settings
    return PIController(s["kp_per_V"], s["ki_per_V_s"], recipe.control_period, name=recipe.name, tuning=s["tuning"])


def _build_nn(recipe: ControllerRecipe, binding: PlantBinding):
    from cosim.design.experiments import nnpc

    controller = nnpc(model_from_bytes(recipe.blob, recipe.control_period, recipe.kind), recipe.control_period,
                      recipe.name, spec=binding.converter, **_planned(recipe))
    shadow = recipe.settings.get("shadow_policy")
    if shadow is None:
        return controller
    import base64

    from cosim.design.distillation import ShadowPolicy
    from cosim.design.experiments import explicit_nnpc, implemented

    policy = _policy_from_bytes(base64.b64decode(shadow), recipe.control_period)
    # the NNPC as the worker implements it (its C twin by default), the policy in shadow beside it
    return ShadowPolicy(implemented(controller, recipe.settings.get("implementation", "c")),
                        explicit_nnpc(policy, spec=binding.converter), start=0.0)


def _build_mpc(recipe: ControllerRecipe, binding: PlantBinding):
    from cosim.design.experiments import model_mpc

    circuit = CircuitParameters(**recipe.settings["circuit"])
    return model_mpc(circuit, recipe.control_period, recipe.name, binding=binding, **_planned(recipe))


def _build_oracle(recipe: ControllerRecipe, binding: PlantBinding):
    return _build_mpc(recipe, binding)


_policies: dict[str, object] = {}


def _policy_from_bytes(blob: bytes, period: float):
    """A distilled policy from a file's bytes, read through :func:`load_policy`'s checks; cached per process."""
    from controllers.explicit_policy import load_policy

    key = f"{digest(blob)}:{period!r}"
    with _models_lock:
        if key not in _policies:
            with tempfile.TemporaryDirectory(prefix="buck-cosim-policy-") as folder:
                path = Path(folder) / "policy.pt"
                path.write_bytes(blob)
                _policies[key] = load_policy(path, expect_period=period)
        return _policies[key]


def _build_explicit(recipe: ControllerRecipe, binding: PlantBinding):
    from cosim.design.experiments import explicit_nnpc

    return explicit_nnpc(_policy_from_bytes(recipe.blob, recipe.control_period), recipe.name, spec=binding.converter)


def _build_classical(recipe: ControllerRecipe, binding: PlantBinding):
    from cosim.design.classical_design import controller_from_description

    return controller_from_description(recipe.settings["controller"], recipe.name)


def injected_recipe(inner: ControllerRecipe, name: str, frequency: float, amplitude: float, point: str, start: float,
                    samples: int, implementation: str = DEFAULT_IMPLEMENTATION) -> ControllerRecipe:
    """A recipe of ``inner`` with a sine injected (:class:`controllers.injection.InjectedController`): one
    point of a frequency response (:mod:`cosim.design.frequency_response`)."""
    settings = {"inner": {"kind": inner.kind, "name": inner.name, "settings_json": inner.settings_json},
                "frequency_hz": frequency, "amplitude": amplitude, "point": point, "start_s": start,
                "samples": samples, "implementation": implementation}
    return ControllerRecipe("injected", name, inner.control_period, _json(settings), inner.blob)


def _build_injected(recipe: ControllerRecipe, binding: PlantBinding):
    from controllers.injection import InjectedController

    s = recipe.settings
    inner = ControllerRecipe(s["inner"]["kind"], s["inner"]["name"], recipe.control_period, s["inner"]["settings_json"],
                             recipe.blob)
    return InjectedController(build(inner, binding, s["implementation"]), s["frequency_hz"], s["amplitude"],
                              s["point"], s["start_s"], s["samples"])


def _build_fmu(recipe: ControllerRecipe, binding: PlantBinding):
    """The controller FMU from its bytes: written once per process and digest to the worker's own
    folder (removed at exit), checked (archive, roles, parameters, an instance that initialises),
    and its sample period against the sweep's control period."""
    from cosim.design.sweeps.process_files import process_file
    from cosim.design.sweeps.spec import PERIOD_MATCH
    from cosim.fmi.binding import RoleMap
    from cosim.fmi.controller import ControllerBinding, FmuController, builtin_controller_binding

    s = recipe.settings
    path = process_file(s["fmu"], recipe.blob, recipe.blob_digest)
    carried = s["binding"]
    if carried is None:
        bound = builtin_controller_binding(path)
    else:
        roles = {role: RoleMap(variable, scale, offset) for role, (variable, scale, offset) in carried["roles"].items()}
        limits = tuple(carried["duty_limits"]) if carried["duty_limits"] is not None else None
        bound = ControllerBinding(path, roles, carried["sample_period_s"], limits, carried["parameters"],
                                  Path(carried["file"]), carried["label"])
    controller = FmuController(bound, name=recipe.name)
    if abs(controller.sample_period - recipe.control_period) > PERIOD_MATCH * recipe.control_period:
        controller.close()
        raise ConfigError(f"{recipe.name}: the controller FMU's sample period is {controller.sample_period:.6g} s, "
                          f"not the sweep's control period {recipe.control_period:.6g} s")
    return controller


class Kind(NamedTuple):
    design: Callable[..., ControllerRecipe]
    build: Callable[[ControllerRecipe, PlantBinding], object]


KINDS: dict[str, Kind] = {
    "pi": Kind(_design_pi, _build_pi),
    "nnpc": Kind(_design_nn, _build_nn),
    "nnpc-paper": Kind(_design_nn, _build_nn),
    "mpc-nominal": Kind(_design_mpc, _build_mpc),
    "fmu": Kind(_design_fmu, _build_fmu),
    "mpc-oracle": Kind(_design_oracle, _build_oracle),
    "nnpc-explicit": Kind(_design_explicit, _build_explicit),
    "current-mode": Kind(_design_classical, _build_classical),
    "type-iii": Kind(_design_classical, _build_classical),
    "pi-envelope": Kind(_design_envelope_pi, _build_pi),
    "injected": Kind(None, _build_injected),  # built by the frequency response, never from a sweep file
}


def design(entries, binding: PlantBinding, period: float, work_dir: Path, progress: bool = False) -> list[ControllerRecipe]:
    """Every controller of the sweep, designed on the nominal plant ``binding`` (tuned gains and
    identified models are cached in ``work_dir``, so a resumed sweep designs nothing again)."""
    if not (period > 0 and math.isfinite(period)):
        raise ConfigError(f"control period {period} s is invalid: expected a finite value > 0")
    recipes = []
    for entry in entries:
        recipe = KINDS[entry.kind].design(entry, binding, period, Path(work_dir), progress)
        if entry.settle is not None:  # the worker runs this controller's scenarios with its own settle time
            settings = {**recipe.settings, "settle_s": entry.settle}
            recipe = ControllerRecipe(recipe.kind, recipe.name, recipe.control_period, _json(settings), recipe.blob)
        recipes.append(recipe)
    return recipes


def build(recipe: ControllerRecipe, binding: PlantBinding, implementation: str = DEFAULT_IMPLEMENTATION):
    """The controller a recipe describes, as it runs (its C twin unless ``implementation`` is python)."""
    from cosim.design.experiments import implemented

    return implemented(KINDS[recipe.kind].build(recipe, binding), implementation)


def describe(recipes) -> list[dict]:
    return [json.loads(canonical(r.describe())) for r in recipes]
