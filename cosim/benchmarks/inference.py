"""Group inference: inference alternatives, same run: what the hot-path choices buy."""

from __future__ import annotations

import numpy as np

from cosim.benchmarks.common import BenchRow, _median_time
from cosim.benchmarks.subjects import _nn_model
from cosim.design.vocabulary import NOMINAL, PAPER_PERIOD
from cosim.study.vocabulary import PAPER_SPEC


def bench_inference(quick: bool) -> list[BenchRow]:
    from scipy.linalg import expm

    from controllers.predictors import circuit_matrix, expm2

    repeats = 50 if quick else 3000
    model, _ = _nn_model("nnpc", PAPER_PERIOD, quick)
    rng = np.random.default_rng(0)
    batch = np.column_stack([rng.uniform(0, 3, 50), rng.uniform(0, 15, 50), rng.uniform(0, 1, 50),
                             np.full(50, 1 / 6)])
    torch_time = _median_time(lambda: model.predict_torch(batch), repeats)
    numpy_time = _median_time(lambda: model.predict(batch), repeats)
    fast_model = model  # one delay: the shared-history fast path applies
    history = np.array([[2.0, 12.0, 0.25]])
    duties = rng.uniform(0, 1, (100, 23))
    extras = np.array([1 / 6])
    generic = _median_time(lambda: fast_model.rollout(np.repeat(history[None], 100, axis=0), duties,
                                                      np.repeat(extras[None], 100, axis=0)), repeats // 10 + 1)
    shared = _median_time(lambda: fast_model.rollout_shared(history, duties, extras), repeats // 10 + 1)
    a = circuit_matrix(NOMINAL, PAPER_SPEC.load_resistance, 0.0)
    scipy_time = _median_time(lambda: expm(a * PAPER_PERIOD), repeats)
    closed_time = _median_time(lambda: expm2(a, PAPER_PERIOD), repeats)
    return [
        BenchRow("NN batch prediction (50 candidates): torch.inference_mode", torch_time * 1e6, None, "us"),
        BenchRow("NN batch prediction (50 candidates): numpy, normalisation folded into the weights",
                 numpy_time * 1e6, None, "us"),
        BenchRow("speed-up of numpy over torch for the NN hot path", torch_time / numpy_time, None, "ratio"),
        BenchRow("NN rollout, 100 sequences x 23 steps: generic batched histories", generic * 1e6, None, "us"),
        BenchRow("NN rollout, 100 sequences x 23 steps: shared-history fast path", shared * 1e6, None, "us"),
        BenchRow("speed-up of the shared-history rollout", generic / shared, None, "ratio"),
        BenchRow("2x2 discretisation: scipy.linalg.expm", scipy_time * 1e6, None, "us"),
        BenchRow("2x2 discretisation: closed form (expm2)", closed_time * 1e6, None, "us"),
        BenchRow("speed-up of the closed-form matrix exponential", scipy_time / closed_time, None, "ratio"),
    ]
