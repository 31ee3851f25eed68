"""What crosses from the workbench's process to the dask workers: plain, picklable recipes.

A worker may be another machine, so nothing refers to a file that exists only here: the plant FMU,
the NN model and a controller FMU travel as bytes with their SHA-256, and each worker writes them
to a file of its own and loads them through the same checks as a local file
(:func:`cosim.fmi.archive.check_fmu` before anything is extracted, and a controller FMU's roles and
parameters; :func:`controllers.nn_model.load_model`, ``weights_only``). The controllers themselves
are rebuilt on the worker from their settings (C twins hold ctypes state that does not pickle, an
FMU instance is native state too, and the run must use exactly what was designed). A controller
given through a controller-binding file travels as its FMU's bytes and the binding's content
(roles, sample period, duty limits, parameters, label) in the settings, not as the file.

Digests identify what a run used: the plant recipe's (FMU bytes, roles, nominal parameters,
interface) and each controller recipe's (kind, name, settings, model or FMU bytes) go into every
run id.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

from cosim.base.digests import digest
from cosim.converter_spec import ConverterSpec
from cosim.fmi.binding import PlantBinding, RoleMap


@dataclass(frozen=True)
class PlantRecipe:
    """A plant binding without its file system: the FMU's bytes, roles, nominal parameters."""

    fmu_name: str
    fmu_bytes: bytes
    roles: tuple[tuple[str, str, float, float], ...]  # (role, variable, scale, offset)
    parameters: tuple[tuple[str, object], ...]  # the nominal plant's parameters
    interface: str | None
    max_step: float | None
    source: str | None  # the binding file, named in error messages
    label: str
    tag: str
    isolate: bool = False  # step the FMU in a child process (a binding file's default): a crash is that run's row
    step_timeout: float | None = None  # isolated: a step's wall-time limit [s] (None: derived from the step)
    memory_limit: float | None = None  # isolated: the plant process's memory limit [MB] (None: half the machine's)
    #: the converter spec (cosim.converter_spec) the controllers are designed for and start from; not part of
    #: identity(): it decides no plant response (the controllers' recipes hold what they take from it)
    spec: ConverterSpec | None = None
    step: float | None = None  # co-simulation: the one communication step [s] (the binding's ``step``)

    @classmethod
    def of(cls, binding: PlantBinding) -> "PlantRecipe":
        path = Path(binding.fmu_path)
        return cls(fmu_name=path.name, fmu_bytes=path.read_bytes(),
                   roles=tuple((r, m.variable, m.scale, m.offset) for r, m in sorted(binding.roles.items())),
                   parameters=tuple(sorted(binding.parameters.items())), interface=binding.interface,
                   max_step=binding.max_step, source=str(binding.source) if binding.source else None,
                   label=binding.label, tag=binding.tag, isolate=binding.isolate, step_timeout=binding.step_timeout,
                   memory_limit=binding.memory_limit, spec=binding.spec, step=binding.step)

    @cached_property
    def fmu_digest(self) -> str:
        return digest(self.fmu_bytes)

    def binding(self, fmu_path: Path) -> PlantBinding:
        """The nominal plant's binding with the FMU at ``fmu_path`` (the worker's copy)."""
        return PlantBinding(fmu_path=Path(fmu_path), roles={r: RoleMap(v, s, o) for r, v, s, o in self.roles},
                            interface=self.interface, parameters=dict(self.parameters), max_step=self.max_step,
                            source=Path(self.source) if self.source else None, label=self.label,
                            tag_override=self.tag, isolate=self.isolate, step_timeout=self.step_timeout,
                            memory_limit=self.memory_limit, spec=self.spec, step=self.step)

    def identity(self) -> dict:
        """What decides a run's result (not where the files are)."""
        return {"fmu_sha256": self.fmu_digest, "roles": [list(r) for r in self.roles],
                "parameters": {k: v for k, v in self.parameters}, "interface": self.interface,
                "max_step": self.max_step, **({"step": self.step} if self.step is not None else {})}


@dataclass(frozen=True)
class ControllerRecipe:
    """A controller designed once on the nominal plant, to be rebuilt on any worker.

    ``settings`` (JSON text) holds everything but the model: PI gains, circuit parameters, the
    network and its held-out error, a controller FMU's binding; ``blob`` is the model file's bytes
    (NNPC) or the controller FMU's (fmu), or None.
    """

    kind: str
    name: str
    control_period: float  # [s]
    settings_json: str
    blob: bytes | None = None

    @property
    def settings(self) -> dict:
        return json.loads(self.settings_json)

    @cached_property
    def digest(self) -> str:
        return digest(self.kind, self.name, repr(self.control_period), self.settings_json, self.blob or b"")

    @cached_property
    def blob_digest(self) -> str | None:
        return digest(self.blob) if self.blob else None

    def describe(self) -> dict:
        """JSON-ready, for the manifest and the summary (the blob by its SHA-256)."""
        described = {"kind": self.kind, "name": self.name, "control_period_s": self.control_period,
                     "settings": self.settings}
        described["fmu_sha256" if self.kind == "fmu" else "model_sha256"] = self.blob_digest
        return described
