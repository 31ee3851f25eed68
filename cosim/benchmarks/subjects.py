"""What several groups time: the built-in FMU through fmpy alone, the benchmark PI, the NN plant model and
the distilled policy (the reproduction's if the models folder has them, else made here) and the mixed scenario.
The models folder is the one of the results folder written to (``--out``; ``--models`` names another), never
the working directory's: :func:`reading_models_from` sets it for a run of the suite."""

from __future__ import annotations

import shutil
from contextlib import contextmanager
from pathlib import Path

from cosim.design.vocabulary import SWITCHING_PERIOD, transient_within_sample
from cosim.study.vocabulary import PAPER_SPEC

#: where the reproduction's trained models are looked for (:func:`reading_models_from` sets it: ``OUT/models``
#: or ``--models``); a group finds none there and trains or distils its own
_models_dir: Path = Path("results") / "models"


@contextmanager
def reading_models_from(folder: Path):
    """The groups run inside this read the reproduction's models from ``folder``."""
    global _models_dir
    before, _models_dir = _models_dir, Path(folder)
    try:
        yield
    finally:
        _models_dir = before


class _RawSlave:
    """The built-in FMU through fmpy's public API only: the floor the master is compared with."""

    def __init__(self, start_values: dict):
        import fmpy
        from fmpy.fmi2 import FMU2Slave

        from plant_fmu import fmu_path

        path = str(fmu_path())
        self.md = fmpy.read_model_description(path)
        self.vr = {v.name: v.valueReference for v in self.md.modelVariables}
        self.unzipdir = fmpy.extract(path)
        self.fmu = FMU2Slave(guid=self.md.guid, unzipDirectory=self.unzipdir,
                             modelIdentifier=self.md.coSimulation.modelIdentifier)
        self.fmu.instantiate()
        self.fmu.setupExperiment(startTime=0.0)
        for name, value in start_values.items():
            if name == "plant_mode":
                self.fmu.setInteger([self.vr[name]], [value])
            else:
                self.fmu.setReal([self.vr[name]], [value])
        self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()

    def close(self):
        self.fmu.terminate()
        self.fmu.freeInstance()
        shutil.rmtree(self.unzipdir, ignore_errors=True)


def _benchmark_pi(period: float):
    """A PI with gains near the tuned ones at this rate, in the normalised gains a = Kp Vs and
    b = Ki Ts Vs of :mod:`cosim.design.pi_tuning` (the benchmarks time it; they do not tune it)."""
    from controllers.pi import PIController

    a, b = (0.072, 0.75) if transient_within_sample(period) else (0.336, 0.111)
    vs = PAPER_SPEC.input_voltage
    return PIController(a / vs, b / (period * vs), period)


def _mixed_scenario(period: float, samples: int):
    """Random references and loads (and, at 13.33 us, supplies) held for random intervals: transients and steady
    state mixed, drawn like the rate's identification data (:func:`cosim.design.experiments.collection_settings`'
    default region): at 1 ms the paper's region, at 13.33 us the envelope (references 3-20 V, loads 4-100 Ohm,
    supplies 36-60 V), where the NNPC's network is identified and the envelope map runs it. Timings measured before
    the envelope data (issue 25) replayed the paper's region at 13.33 us too."""
    from cosim.design.data_collection import random_scenario
    from cosim.design.experiments import collection_settings

    return random_scenario(collection_settings(period, samples, seed=11, spec=PAPER_SPEC), period)


def _nn_model(name: str, period: float, quick: bool):
    """The reproduction's model if the models folder (:data:`_models_dir`) has it, else one trained here."""
    from controllers.nn_config import TrainingSettings
    from controllers.nn_model import load_model, train
    from cosim.base.errors import ModelFileError
    from cosim.design.data_collection import collect
    from cosim.design.experiments import collection_settings, nn_configs
    from cosim.design.plants import plant_binding
    from cosim.design.vocabulary import pipeline_tag, plant_tag

    config = nn_configs(period)[name]
    path = _models_dir / f"{pipeline_tag(plant_tag('nominal', 'switched'), period)}__{name}.pt"
    if path.is_file() and not quick:
        try:
            return load_model(path, expect_period=period, expect_config=config), str(path)
        except ModelFileError:
            pass

    pi = _benchmark_pi(period)
    data = collect(plant_binding("nominal", "switched"), pi, collection_settings(period, 400 if quick else 3000,
                                                                                spec=PAPER_SPEC))
    return (train(data, config, TrainingSettings(max_iterations=100 if quick else 3000),
                  metadata={"control_period_s": period}), "trained for the benchmark")


def _explicit_policy(quick: bool):
    """The reproduction's distilled policy if the models folder has it, else one distilled here (small budget)."""
    from dataclasses import replace

    from controllers.explicit_policy import load_policy
    from cosim.base.errors import ModelFileError
    from cosim.design.distillation import SMALL_DISTILLATION, distill
    from cosim.design.plants import plant_binding
    from cosim.design.vocabulary import pipeline_tag

    path = _models_dir / f"{pipeline_tag('nominal-switched', SWITCHING_PERIOD)}__nnpc-explicit.pt"
    if path.is_file() and not quick:
        try:
            return load_policy(path, expect_period=SWITCHING_PERIOD), str(path)
        except ModelFileError:
            pass
    model, _ = _nn_model("nnpc", SWITCHING_PERIOD, quick)
    budget = replace(SMALL_DISTILLATION, rounds=1, episodes=1, samples=100) if quick else SMALL_DISTILLATION
    return distill(model, plant_binding("nominal", "switched"), SWITCHING_PERIOD, budget, log=None), \
        "distilled for the benchmark (small budget)"
