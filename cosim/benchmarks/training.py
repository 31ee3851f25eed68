"""Group training: identification cost."""

from __future__ import annotations

import time

from cosim.benchmarks.common import BenchRow
from cosim.benchmarks.subjects import _benchmark_pi
from cosim.design.vocabulary import PAPER_PERIOD


def bench_training(quick: bool) -> list[BenchRow]:
    from controllers.nn_config import TrainingSettings
    from controllers.nn_model import train
    from cosim.design.data_collection import CollectionSettings, collect
    from cosim.design.experiments import nn_configs
    from cosim.design.plants import plant_binding

    samples = 500 if quick else 10_000
    start = time.perf_counter()
    data = collect(plant_binding("nominal", "switched"), _benchmark_pi(PAPER_PERIOD),
                   CollectionSettings(samples=samples))
    collection = time.perf_counter() - start
    rows = [BenchRow(f"data collection, {samples} samples at 1 ms (switched plant, PI loop)", collection, None, "s")]
    for name, config in nn_configs(PAPER_PERIOD).items():
        start = time.perf_counter()
        model = train(data, config, TrainingSettings(max_iterations=100 if quick else 3000))
        elapsed = time.perf_counter() - start
        iterations = model.metadata["training"]["iterations"]
        rows.append(BenchRow(f"NN training, {config.label}, {samples} samples ({iterations} L-BFGS iterations, "
                             "early stopping)", elapsed, None, "s"))
    return rows
