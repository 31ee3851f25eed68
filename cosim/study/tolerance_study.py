"""The reproduction's tolerance study: the 1 ms controllers of the nominal switched pipeline on
production units (L, C +-20 %, capacitor ESR, inductor DCR), through the sweep engine.

The controllers are the pipeline's own -- the PI it tuned and the NNPC it identified on the
nominal switched plant, and the MPC with the nominal circuit -- so the study asks exactly the
robustness question of the report: how do the controllers designed on paper fare on the units that
get built. The sweep file is the shipped study ``tolerance-reproduction`` (600 runs: a small part of
``make reproduce``); the tasks run on the reproduction's own dask cluster,
mixed in with the pipelines still running.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

from cosim.base.errors import ConfigError
from cosim.design.sweeps.designs import design
from cosim.design.sweeps.plan import SweepPlan
from cosim.design.sweeps.spec import ControllerEntry, SweepSpec, load_sweep
from cosim.design.sweeps.sweep import PreparedSweep, check_output
from cosim.design.vocabulary import MPC_NOMINAL, NNPC, PAPER_PERIOD, PI, pipeline_tag, plant_tag
from cosim.study.vocabulary import TOLERANCE_STUDY, TOLERANCE_STUDY_DIR

#: the pipeline whose controllers the study runs (nominal switched plant at the paper's rate)
SOURCE_PIPELINE = pipeline_tag(plant_tag("nominal", "switched"), PAPER_PERIOD)


def study_spec(out_dir: Path, samples: int | None = None) -> SweepSpec:
    """The shipped study with the pipeline's controllers (and ``samples`` draws, if given)."""
    spec = load_sweep(TOLERANCE_STUDY)
    tuning = json.loads((out_dir / "tuning" / f"pi__{SOURCE_PIPELINE}.json").read_text(encoding="utf-8"))
    model = out_dir / "models" / f"{SOURCE_PIPELINE}__nnpc.pt"
    controllers = (
        ControllerEntry("pi", PI, kp=tuning["kp"], ki=tuning["ki"],
                        origin=f"tuned by the reproduction on the nominal switched plant ({tuning['method']})"),
        ControllerEntry("nnpc", NNPC, model=model,
                        origin=f"identified by the reproduction on the nominal switched plant (models/{model.name})"),
        ControllerEntry("mpc-nominal", MPC_NOMINAL),
    )
    return replace(spec, controllers=controllers, samples=samples or spec.samples)


def start(out_dir: Path, resume: bool, samples: int | None = None, progress: bool = False) -> PreparedSweep:
    """The study planned and its controllers designed, ready to submit (``--resume`` keeps its rows;
    a fresh reproduction starts it again)."""
    folder = Path(out_dir) / TOLERANCE_STUDY_DIR
    if not resume and folder.exists():
        shutil.rmtree(folder)
    plan = SweepPlan(study_spec(Path(out_dir), samples))
    try:
        check_output(plan, folder, resume=True)  # the same sweep (its rows are kept), or none yet
    except ConfigError:  # another sweep (other gains, another sample count): start this one afresh
        shutil.rmtree(folder)
    recipes = design(plan.spec.controllers, plan.binding, plan.spec.control_period, folder, progress)
    prepared = PreparedSweep(plan, folder, recipes, progress)
    prepared.write_manifest()
    return prepared


def ready(finished_tags) -> bool:
    """Can the study start: has its source pipeline finished?"""
    return SOURCE_PIPELINE in set(finished_tags)
