"""Cached designs -- tuned PI gains, identified NN plant models, distilled policies -- keyed by what
they depend on.

A design is valid for one plant and one set of design settings only. Its *design key* is a short
SHA-256 of its inputs (:func:`design_key`):

* the plant: the FMU's bytes (SHA-256), the binding's roles (variable, scale, offset), parameters,
  interface and largest step -- a rebuilt FMU with other component values, or ``L = 0.00033`` added
  under a binding's ``[parameters]``, is another plant;
* the control period, the seed, the scenarios the design simulates and the design's settings
  (the tuning method and its grid, the data collection, the identification recipe and network,
  the distillation budget);
* the designs it builds on (an NN model's key names the PI that collected its data; a policy's,
  the network it imitates).

The key and its inputs are stored in the design's file (``design`` in the JSON of ``tuning/`` and
in the metadata of ``models/*.pt``) and travel into every run's metadata with the controller
(``controller.tuning.design_key``, ``controller.predictor.design_key``, ``controller.design_key``).
A cached file whose key differs from the one wanted is designed again, and :func:`announce` says
so in one line naming the inputs that changed -- never reused silently.

The file names stay ``tuning/pi__<plant tag>__<period>.json`` and
``models/<plant tag>__<period>__<network>.pt``: one design per plant tag and rate, replaced when its
inputs change.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from cosim.base.digests import canonical, digest, file_sha256
from cosim.design.vocabulary import pipeline_tag
from cosim.fmi.binding import PlantBinding
from cosim.results import json_ready

#: hex digits of a design key (64 bits: collisions among one user's designs are not a concern)
KEY_LENGTH = 16

#: how :func:`changed_inputs` names each input in a message
INPUT_NAMES = {
    "fmu_sha256": "plant FMU (SHA-256)",
    "roles": "binding roles",
    "parameters": "plant parameters",
    "interface": "FMI interface",
    "max_step_s": "largest plant step",
    "step_s": "fixed communication step",
    "control_period_s": "control period",
    "seed": "seed",
    "scenarios": "scenarios",
    "settings": "design settings",
    "depends_on": "underlying design",
    "design": "kind of design",
}


def plant_identity(binding: PlantBinding) -> dict:
    """What makes a plant this plant: the FMU's bytes and how the binding drives it (JSON-ready).
    Not its label, file names or whether it runs in a child process: those change no result."""
    return json_ready({
        "fmu_sha256": file_sha256(binding.fmu_path),
        "roles": {role: [m.variable, m.scale, m.offset] for role, m in sorted(binding.roles.items())},
        "parameters": dict(sorted(binding.parameters.items())),
        "interface": binding.interface,
        "max_step_s": binding.max_step,
        **({"step_s": binding.step} if binding.step is not None else {}),  # absent: the keys made before it stand
    })


@dataclass(frozen=True)
class DesignKey:
    """A design's inputs (JSON-ready) and their short digest, the key."""

    inputs: dict

    @property
    def key(self) -> str:
        return digest(canonical(self.inputs))[:KEY_LENGTH]

    def describe(self) -> dict:
        """What the design's file stores: ``{"key": ..., "inputs": ...}``."""
        return {"key": self.key, "inputs": self.inputs}


def design_key(kind: str, binding: PlantBinding, control_period: float, *, seed: int | None = None,
               scenarios=(), settings: dict | None = None, depends_on: dict | None = None) -> DesignKey:
    """The key of a design of ``kind`` (e.g. ``"pi"``, ``"nn-model:nnpc"``) for ``binding`` at
    ``control_period`` [s] from ``seed``, the ``scenarios`` it simulates (:class:`cosim.scenarios.Scenario`),
    its ``settings`` and the keys of the designs it builds on (``depends_on``). A scenario counts by
    its content, not by the path of its file (the same key on every machine)."""
    return DesignKey(json_ready({
        "design": kind,
        "plant": plant_identity(binding),
        "control_period_s": control_period,
        "seed": seed,
        "scenarios": [{k: v for k, v in s.describe().items() if k != "source"} for s in scenarios],
        "settings": settings or {},
        "depends_on": depends_on or {},
    }))


def changed_inputs(stored: dict, wanted: dict) -> list[str]:
    """Names of the inputs that differ between a stored design's inputs and the wanted ones (the
    plant's parts one by one), in a fixed order."""
    names = []
    for part in wanted.keys() | stored.keys():
        if part == "plant":
            old, new = stored.get("plant") or {}, wanted.get("plant") or {}
            names += [INPUT_NAMES.get(k, k) for k in sorted(old.keys() | new.keys()) if old.get(k) != new.get(k)]
        elif stored.get(part) != wanted.get(part):
            names.append(INPUT_NAMES.get(part, part))
    return sorted(names)


def stale_reason(stored: dict | None, wanted: DesignKey) -> str | None:
    """None if a stored design (its ``{"key", "inputs"}`` or None) is the wanted one; else why not."""
    if not isinstance(stored, dict) or "key" not in stored:
        return "it has no design key (written by an older buck-cosim)"
    if stored["key"] == wanted.key:
        return None
    changed = changed_inputs(stored.get("inputs") or {}, wanted.inputs)
    return (f"{', '.join(changed) or 'its inputs'} changed (design key {stored['key']} -> {wanted.key})")


def announce(path: Path, reason: str, action: str) -> None:
    """One line on stderr: a cached design is not reused, why, and what happens instead."""
    print(f"{path} does not fit: {reason}; {action}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------
# Where the designs of a plant and rate are cached (one definition for run, sweeps and the reproduction)


def pi_file(out_dir: Path, plant_tag: str, control_period: float) -> Path:
    """The tuned PI of a plant tag and rate: ``tuning/pi__<tag>__<period>.json``."""
    return Path(out_dir) / "tuning" / f"pi__{pipeline_tag(plant_tag, control_period)}.json"


def data_file(out_dir: Path, plant_tag: str, control_period: float, region: str | None = None) -> Path:
    """The PI data a network of a plant tag and rate is identified from: ``data/<tag>__<period>.parquet``;
    ``region``: data of a collection region other than the rate's default (the paper's network at 13.33 us,
    :func:`cosim.design.experiments.network_region`) have their own, ``data/<tag>__<period>__<region>.parquet``."""
    suffix = f"__{region}" if region else ""
    return Path(out_dir) / "data" / f"{pipeline_tag(plant_tag, control_period)}{suffix}.parquet"


def model_file(out_dir: Path, plant_tag: str, control_period: float, name: str) -> Path:
    """An identified network (``name``: nnpc, nnpc-paper) or distilled policy (nnpc-explicit):
    ``models/<tag>__<period>__<name>.pt``."""
    return Path(out_dir) / "models" / f"{pipeline_tag(plant_tag, control_period)}__{name}.pt"


def seed_model_file(out_dir: Path, plant_tag: str, control_period: float, seed: int) -> Path:
    """The NNPC a reproduction's seed job identified from seed ``seed``'s data, where another job reads it (the
    envelope map, the drift study): ``models/<tag>__<period>__nnpc__seed<seed>.pt``."""
    return model_file(out_dir, plant_tag, control_period, f"nnpc__seed{seed}")
