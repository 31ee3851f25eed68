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
from cosim.base.errors import ConfigError, ModelFileError
from cosim.fmi.binding import PlantBinding
from cosim.study.sweeps.recipes import ControllerRecipe, canonical, digest
from cosim.study.sweeps.spec import ControllerEntry
from cosim.study.vocabulary import NOMINAL


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
        from cosim.study.controller_factory import tuned_pi

        tuning = tuned_pi(binding, period, work_dir, progress)
        settings = {"kp_per_V": tuning.kp, "ki_per_V_s": tuning.ki,
                    "tuning": {"method": tuning.method, "cost_V2s": tuning.cost, "plant": tuning.plant}}
    return ControllerRecipe("pi", entry.name, period, _json(settings))


def _design_nn(entry: ControllerEntry, binding: PlantBinding, period: float, work_dir: Path,
               progress: bool) -> ControllerRecipe:
    from controllers.nn_model import load_model
    from cosim.study.controller_factory import trained_model
    from cosim.study.experiments import nn_configs
    from cosim.study.vocabulary import pipeline_tag

    config = nn_configs(period)[entry.kind]
    if entry.model is not None:
        try:
            model = load_model(entry.model, expect_period=period, expect_config=config)
        except ModelFileError as error:
            raise ConfigError(f"{entry.place}: {error}") from None
        path, origin = Path(entry.model), entry.origin or f"model file {Path(entry.model).name}"
    else:
        if not binding.has("inductor_current"):
            raise ConfigError(f"{entry.place}: {entry.kind} needs the inductor_current role, which {binding.origin} "
                              "does not bind")
        model = trained_model(entry.kind, binding, period, work_dir, samples=entry.samples, seed=entry.seed,
                              model_path=None, progress=progress)
        path = work_dir / "models" / f"{pipeline_tag(binding.tag, period)}__{entry.kind}.pt"
        origin = f"identified on the nominal plant ({entry.samples} samples, seed {entry.seed})"
    blob = path.read_bytes()
    rmse = model.metadata.get("held_out_rmse", {})
    settings = {"network": config.label, "origin": origin,
                "held_out_one_step_rmse_V": rmse.get("one_step_rmse_voltage_V"),
                "held_out_one_step_rmse_A": rmse.get("one_step_rmse_current_A")}
    return ControllerRecipe(entry.kind, entry.name, period, _json(settings), blob)


def _design_mpc(entry: ControllerEntry, binding: PlantBinding, period: float, work_dir: Path,
                progress: bool) -> ControllerRecipe:
    from cosim.study.controller_factory import true_parameters

    # the nominal plant's circuit: Table II with the variant's parasitics for the built-in FMU;
    # for an external FMU only Table II is known
    circuit = true_parameters(binding) if binding.source is None else NOMINAL
    return ControllerRecipe("mpc-nominal", entry.name, period, _json({"circuit": asdict(circuit)}))


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
    SHA-256 of the weights, shapes, inputs and control period); cached per process by digest."""
    from controllers.nn_model import load_model
    from cosim.study.experiments import nn_configs

    key = f"{digest(blob)}:{period!r}:{kind}"
    with _models_lock:
        if key not in _models:
            with tempfile.TemporaryDirectory(prefix="buck-cosim-model-") as folder:
                path = Path(folder) / "model.pt"
                path.write_bytes(blob)
                _models[key] = load_model(path, expect_period=period, expect_config=nn_configs(period)[kind])
        return _models[key]


def _build_pi(recipe: ControllerRecipe, binding: PlantBinding):
    from controllers.pi import PIController

    s = recipe.settings
    return PIController(s["kp_per_V"], s["ki_per_V_s"], recipe.control_period, name=recipe.name, tuning=s["tuning"])


def _build_nn(recipe: ControllerRecipe, binding: PlantBinding):
    from cosim.study.experiments import nnpc

    return nnpc(model_from_bytes(recipe.blob, recipe.control_period, recipe.kind), recipe.control_period, recipe.name)


def _build_mpc(recipe: ControllerRecipe, binding: PlantBinding):
    from cosim.study.experiments import model_mpc

    circuit = CircuitParameters(**recipe.settings["circuit"])
    return model_mpc(circuit, recipe.control_period, recipe.name, binding=binding)


def _build_fmu(recipe: ControllerRecipe, binding: PlantBinding):
    """The controller FMU from its bytes: written once per process and digest to the worker's own
    folder (removed at exit), checked (archive, roles, parameters, an instance that initialises),
    and its sample period against the sweep's control period."""
    from cosim.fmi.binding import RoleMap
    from cosim.fmi.controller import ControllerBinding, FmuController, builtin_controller_binding
    from cosim.study.sweeps.spec import PERIOD_MATCH
    from cosim.study.sweeps.worker import process_file

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
}


def design(entries, binding: PlantBinding, period: float, work_dir: Path, progress: bool = False) -> list[ControllerRecipe]:
    """Every controller of the sweep, designed on the nominal plant ``binding`` (tuned gains and
    identified models are cached in ``work_dir``, so a resumed sweep designs nothing again)."""
    if not (period > 0 and math.isfinite(period)):
        raise ConfigError(f"control period {period} s is invalid: expected a finite value > 0")
    return [KINDS[entry.kind].design(entry, binding, period, Path(work_dir), progress) for entry in entries]


def build(recipe: ControllerRecipe, binding: PlantBinding, implementation: str = "c"):
    """The controller a recipe describes, as it runs (its C twin unless ``implementation`` is python)."""
    from cosim.study.experiments import implemented

    return implemented(KINDS[recipe.kind].build(recipe, binding), implementation)


def describe(recipes) -> list[dict]:
    return [json.loads(canonical(r.describe())) for r in recipes]
