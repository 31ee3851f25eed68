"""The trained artefacts of tests/test_numeric_env.py, written by one process: ``python numeric_env_job.py OUT``,
or ``python numeric_env_job.py train DATA OUT`` for the training alone (the emulated-CPU test).

Run in a subprocess per kernel environment: the identification of the NNPC (the quick profile's
recipe on the nominal averaged plant at 1 ms, seed 1) -> ``OUT/identified.pt``; a small DAgger
distillation of the test expert -> ``OUT/policy.pt``; the quick profile's seed job 1 of that pipeline
(identification again, closed-loop runs) -> ``OUT/metrics/`` and ``OUT/pipelines/``. The PI tuning is
read from ``OUT/tuning/`` when the caller put it there.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

from controllers.explicit_policy import save_policy  # noqa: E402
from controllers.nn_model import load_model, save_model  # noqa: E402
from cosim.design.distillation import SMALL_DISTILLATION, distill  # noqa: E402
from cosim.design.experiments import nn_configs  # noqa: E402
from cosim.design.identification import identify  # noqa: E402
from cosim.design.vocabulary import PAPER_PERIOD, SWITCHING_PERIOD  # noqa: E402
from cosim.study.reproduce import QUICK, Pipeline, _recipe, _tuned, run_seed  # first: pins the kernels

EXPERT = Path(__file__).parent / "fixtures" / "nnpc_nominal_averaged_13p33us.pt"
PIPELINE = Pipeline("nominal", "averaged", PAPER_PERIOD)
SEED = 1
TINY_DISTILLATION = replace(SMALL_DISTILLATION, rounds=1, episodes=1, samples=100)


#: the training of the emulated-CPU test: the one-step stage on the full profile's 1 ms data, two checks of
#: 25 L-BFGS iterations (enough: with torch's own line search the weights differed between an AVX-512 and an
#: AVX2 CPU after its first 25)
TRAINING_ITERATIONS = 50


def train_only(data: Path, out: Path) -> None:
    """The NNPC's one-step training on the samples in ``data`` (Parquet) -> ``out/trained.pt``."""
    import pandas as pd
    import torch

    from controllers.nn_model import train
    from cosim.design.identification import training_settings

    torch.set_num_threads(1)
    settings = replace(training_settings(PAPER_PERIOD, 2), max_iterations=TRAINING_ITERATIONS, multi_step_horizon=1)
    model = train(pd.read_parquet(data), nn_configs(PAPER_PERIOD)["nnpc"], settings, metadata={})
    out.mkdir(parents=True, exist_ok=True)
    save_model(model, out / "trained.pt")


def main(out: Path) -> None:
    import torch

    torch.set_num_threads(1)
    binding = PIPELINE.binding()
    pi = _tuned(PIPELINE, out, QUICK)
    identified = identify(binding, pi.controller(), PAPER_PERIOD, nn_configs(PAPER_PERIOD)["nnpc"], SEED,
                          _recipe(QUICK))
    save_model(identified.model, out / "identified.pt")
    expert = load_model(EXPERT, expect_period=SWITCHING_PERIOD)
    save_policy(distill(expert, binding, SWITCHING_PERIOD, TINY_DISTILLATION,
                        log=None), out / "policy.pt")
    run_seed(PIPELINE, out, QUICK, SEED)


if __name__ == "__main__":
    if sys.argv[1] == "train":
        train_only(Path(sys.argv[2]), Path(sys.argv[3]))
    else:
        main(Path(sys.argv[1]))
