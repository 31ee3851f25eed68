"""One NN training in a process of its own, for the benchmark group ``numeric-env``:
``python -m cosim.benchmark_harness.training_job DATA OUT [--line-search torch|exact]``.

A process of its own, because the numeric kernels are chosen when torch and numpy load: the group runs
this job with the workbench's pinned kernel environment, with the libraries' native one
(``BUCK_COSIM_NUMERIC_ENV=native``), and on an emulated CPU (:mod:`cosim.benchmark_harness.cpu_emulation`).
It trains the NNPC's 1 ms network on the samples in DATA (Parquet) for a fixed number of L-BFGS
iterations and writes ``OUT`` (JSON): the training's wall time, its iterations, and the SHA-256 of the
weights. ``--line-search torch`` uses torch's own line search (the behaviour before
:mod:`controllers.lbfgs`), for the cost comparison.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from dataclasses import replace
from pathlib import Path

import cosim  # noqa: F401  (first: pins the numeric kernels unless BUCK_COSIM_NUMERIC_ENV=native)

#: L-BFGS iterations of one timed training (fixed: no early stopping decides the work)
ITERATIONS = 200


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path, help="samples (Parquet, a data collection's table)")
    parser.add_argument("out", type=Path, help="result file (JSON)")
    parser.add_argument("--line-search", choices=("exact", "torch"), default="exact",
                        help="controllers.lbfgs's line search (default) or torch's own")
    parser.add_argument("--iterations", type=int, default=ITERATIONS, help="L-BFGS iterations (default: %(default)s)")
    args = parser.parse_args(argv)

    import pandas as pd
    import torch

    import controllers.nn_model as nn_model
    from cosim.design.experiments import nn_configs
    from cosim.design.identification import training_settings
    from cosim.design.vocabulary import PAPER_PERIOD

    if args.line_search == "torch":
        nn_model.LBFGS = torch.optim.LBFGS  # the optimizer the module used before controllers/lbfgs.py
    data = pd.read_parquet(args.data)
    settings = replace(training_settings(PAPER_PERIOD, 0), max_iterations=args.iterations, multi_step_horizon=1,
                       patience=args.iterations)
    start = time.perf_counter()
    model = nn_model.train(data, nn_configs(PAPER_PERIOD)["nnpc"], settings, metadata={})
    elapsed = time.perf_counter() - start
    weights = b"".join(p.detach().numpy().tobytes() for p in model.network.parameters())
    args.out.write_text(json.dumps({"seconds": elapsed, "iterations": model.metadata["training"]["iterations"],
                                    "threads": torch.get_num_threads(),
                                    "weights_sha256": hashlib.sha256(weights).hexdigest()}))


if __name__ == "__main__":
    main()
