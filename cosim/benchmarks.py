"""The benchmark suite: speed claims measured as medians, p99 and same-run ratios.

``buck-cosim bench`` writes ``results/benchmarks.md`` and ``results/benchmarks.csv`` (``--out``). Absolute
times drift on shared machines, so every comparison is a ratio measured within one run, with
interleaved repetitions. ``--quick`` runs each benchmark once on a tiny size (the CI smoke test).
The groups that time the reproduction's trained models read them from the ``models`` folder of the
results folder written to (``--out``; ``--models`` names another), never from the working directory.
"""

from __future__ import annotations

import math
import os
import platform
import shutil
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from cosim.base.files import atomic_write, atomic_write_text
from cosim.results import package_versions
from cosim.study.vocabulary import (
    MISMATCH,
    MPC_MISMATCHED,
    MPC_ORACLE,
    NNPC,
    NOMINAL,
    PAPER_PERIOD,
    PI,
    SWITCHING_PERIOD,
    transient_within_sample,
)
from plant_fmu.table_ii import TABLE_II


@dataclass
class BenchRow:
    benchmark: str
    median: float
    p99: float | None
    unit: str
    target: str = ""
    meets_target: bool | None = None
    note: str = ""
    extra: dict = field(default_factory=dict)
    group: str = ""  # the BENCHMARKS entry that measured it
    command: str = ""  # the command line that measured it


def machine_info() -> dict[str, str]:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": str(os.cpu_count()), "system": f"{platform.system()} {platform.release()}",
            "python": platform.python_version()}


#: where the reproduction's trained models are looked for (:func:`run_benchmarks` sets it: ``OUT/models``
#: or ``--models``); a group finds none there and trains or distils its own
_models_dir: Path = Path("results") / "models"


def _p99(values) -> float:
    return float(np.percentile(values, 99))


# ---------------------------------------------------------------------------------------------
# 1. plant FMU doStep cost


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


def _time_do_steps(mode: int, step: float, count: int) -> np.ndarray:
    slave = _RawSlave({"plant_mode": mode, "duty_cycle": 0.25})
    do_step = slave.fmu.dll.fmi2DoStep  # the C function itself: the FMU's cost, not Python's
    component = slave.fmu.component
    times = np.empty(count)
    t = 0.0
    try:
        for i in range(count):
            start = time.perf_counter_ns()
            do_step(component, t, step, 1)
            times[i] = time.perf_counter_ns() - start
            t = (i + 1) * step
    finally:
        slave.close()
    return times * 1e-9


#: duties of the averaged DCM cost rows: from a 13 fs on-time up (d = 0: the closed-form RC discharge)
DCM_DUTIES = (0.0, 1e-9, 1e-7, 1e-5, 1e-3, 0.1, 0.25)


def _dcm_seconds_per_simulated_second(duty: float, steps: int) -> float:
    """Wall seconds per simulated second of the averaged plant in DCM: 200 Ohm from vo = 47 V at ``duty``
    (the issue-26 case: 1 ms steps at d = 1e-7 used to take minutes each), 1 ms doSteps through the C call."""
    slave = _RawSlave({"plant_mode": 0, "duty_cycle": duty, "capacitor_voltage": 47.0, "load_resistance": 200.0})
    do_step, component = slave.fmu.dll.fmi2DoStep, slave.fmu.component
    try:
        start = time.perf_counter()
        for i in range(steps):
            do_step(component, i * PAPER_PERIOD, PAPER_PERIOD, 1)
        return (time.perf_counter() - start) / (steps * PAPER_PERIOD)
    finally:
        slave.close()


def bench_plant(quick: bool) -> list[BenchRow]:
    n = 3 if quick else 400
    periods_per_ms = 75
    switched = _time_do_steps(1, PAPER_PERIOD, n) / periods_per_ms
    single = _time_do_steps(1, SWITCHING_PERIOD, n * 10)
    averaged = _time_do_steps(0, PAPER_PERIOD, n)
    dcm_steps, repeats = (20, 1) if quick else (20_000, 5)  # 20 s of simulated time per repeat
    dcm = {d: [] for d in DCM_DUTIES}
    for _ in range(repeats):  # interleaved, so the machine's drift hits every duty alike
        for d in DCM_DUTIES:
            dcm[d].append(_dcm_seconds_per_simulated_second(d, dcm_steps))
    dcm_median = {d: statistics.median(v) for d, v in dcm.items()}
    pulsed = [dcm_median[d] for d in DCM_DUTIES if d > 0]
    spread = max(pulsed) / min(pulsed)
    dcm_rows = [BenchRow(f"plant doStep, averaged DCM at d = {d:g} (200 Ohm from vo = 47 V, 1 ms steps), per "
                         "simulated second", dcm_median[d] * 1e3, max(dcm[d]) * 1e3, "ms",
                         note="p99 column: the slowest repeat" + ("; d = 0: the diode blocks, closed-form RC "
                                                                  "discharge" if d == 0 else ""))
                for d in DCM_DUTIES]
    dcm_rows.append(BenchRow("averaged DCM cost spread over d = 1e-9 .. 0.25: max / min per simulated second", spread,
                             None, "ratio", "<= 3 (no dependence on d)", spread <= 3.0,
                             "the DCM current is algebraic (reduced-order model): only vC is integrated, and nothing "
                             "stiff is left; before, d = 1e-7 made one 1 ms step run for minutes"))
    return [
        BenchRow("plant doStep, switched mode, per simulated switching period (1 ms steps / 75)",
                 float(np.median(switched)) * 1e6, _p99(switched) * 1e6, "us",
                 "<= 1 us per switching period", bool(np.median(switched) <= 1e-6),
                 "exact piecewise solution: 2 closed-form intervals per period"),
        BenchRow("plant doStep, switched mode, one switching period per call (incl. ctypes call)",
                 float(np.median(single)) * 1e6, _p99(single) * 1e6, "us"),
        BenchRow("plant doStep, averaged mode, per 1 ms step (incl. ctypes call)",
                 float(np.median(averaged)) * 1e6, _p99(averaged) * 1e6, "us"),
        *dcm_rows,
    ]


# ---------------------------------------------------------------------------------------------
# 2. master overhead against the raw fmpy floor


class _Constant:
    name = "constant"
    duty_limits = (0.0, 1.0)

    def __init__(self, period):
        self.sample_period = period

    def reset(self):
        pass

    def step(self, measurement):
        return 0.25

    def describe(self):
        return {"type": "constant", "name": self.name, "duty_limits": [0.0, 1.0]}


def _raw_floor(step: float, count: int) -> float:
    """Seconds per macro step of the bare loop: fmpy setReal + doStep + getReal."""
    slave = _RawSlave({"plant_mode": 0})
    vr = slave.vr
    inputs, outputs = [vr["duty_cycle"]], [vr["output_voltage"], vr["inductor_current"], vr["load_current"]]
    fmu = slave.fmu
    try:
        start = time.perf_counter()
        for i in range(count):
            fmu.setReal(inputs, [0.25])
            fmu.doStep(i * step, step)
            fmu.getReal(outputs)
        return (time.perf_counter() - start) / count
    finally:
        slave.close()


def _master_step(step: float, count: int, isolate: bool = False) -> float:
    from cosim.fmi.binding import builtin_binding
    from cosim.fmi.plant import open_plant
    from cosim.master import run
    from cosim.scenarios import parse_scenario

    scenario = parse_scenario(f'name = "bench"\nduration = {count * step!r}\n[initial]\nreference = 12.0\n')
    with open_plant(builtin_binding("averaged"), isolate=isolate) as plant:
        start = time.perf_counter()
        result = run(plant, _Constant(step), scenario, record_period=step)
        elapsed = time.perf_counter() - start
    return elapsed / (len(result.frame) - 1)


def bench_master(quick: bool) -> list[BenchRow]:
    step = 1e-5
    count = 200 if quick else 20000
    repeats = 1 if quick else 5
    floors, masters = [], []
    for _ in range(repeats):  # interleaved, so drift hits both alike
        floors.append(_raw_floor(step, count))
        masters.append(_master_step(step, count))
    ratios = [m / f for m, f in zip(masters, floors)]
    ratio = statistics.median(ratios)
    isolated = [_master_step(step, count // 4 if not quick else count, isolate=True) for _ in range(repeats)]
    cost = statistics.median(isolated) - statistics.median(masters)
    return [
        BenchRow("raw fmpy floor: setReal + doStep + getReal per macro step (averaged, 10 us)",
                 statistics.median(floors) * 1e6, None, "us"),
        BenchRow("master per macro step, plant FMU isolated in a child process (--isolate)",
                 statistics.median(isolated) * 1e6, None, "us", "",
                 None, f"isolation adds {cost * 1e6:.3g} us per instant (one pipe round trip); it is the default for "
                       "binding-file plants only, whose FMUs are foreign code and slower per step anyway"),
        BenchRow("isolation cost ratio: isolated / in-process master per macro step",
                 statistics.median(isolated) / statistics.median(masters), None, "ratio"),
        BenchRow("master per macro step (control + record every 10 us, constant controller)",
                 statistics.median(masters) * 1e6, None, "us"),
        BenchRow("master overhead ratio: master / raw fmpy floor (median of interleaved repeats)",
                 ratio, max(ratios), "ratio", "<= 1.5", bool(ratio <= 1.5),
                 "p99 column: worst repeat"),
    ]


# ---------------------------------------------------------------------------------------------
# 3. controller compute per step


def _nn_model(name: str, period: float, quick: bool):
    """The reproduction's model if the models folder has it (:data:`_models_dir`), else one trained here on fresh data."""
    from controllers.nn_model import TrainingSettings, load_model, train
    from cosim.base.errors import ModelFileError
    from cosim.study.data_collection import collect
    from cosim.study.experiments import collection_settings, nn_configs, plant_binding
    from cosim.study.vocabulary import pipeline_tag, plant_tag

    config = nn_configs(period)[name]
    path = _models_dir / f"{pipeline_tag(plant_tag('nominal', 'switched'), period)}__{name}.pt"
    if path.is_file() and not quick:
        try:
            return load_model(path, expect_period=period, expect_config=config), str(path)
        except ModelFileError:
            pass

    pi = _benchmark_pi(period)
    data = collect(plant_binding("nominal", "switched"), pi, collection_settings(period, 400 if quick else 3000))
    return (train(data, config, TrainingSettings(max_iterations=100 if quick else 3000),
                  metadata={"control_period_s": period}), "trained for the benchmark")


def _benchmark_pi(period: float):
    """A PI with gains near the tuned ones at this rate, in the normalised gains a = Kp Vs and
    b = Ki Ts Vs of :mod:`cosim.study.pi_tuning` (the benchmarks time it; they do not tune it)."""
    from controllers.pi import PIController

    a, b = (0.072, 0.75) if transient_within_sample(period) else (0.336, 0.111)
    vs = TABLE_II.input_voltage
    return PIController(a / vs, b / (period * vs), period)


def _mixed_scenario(period: float, samples: int):
    """Random references and loads held for random intervals: transients and steady state mixed."""
    from cosim.study.data_collection import random_scenario
    from cosim.study.experiments import collection_settings

    return random_scenario(collection_settings(period, samples, seed=11), period)


def bench_controllers(quick: bool) -> list[BenchRow]:
    from cosim.fmi.plant import open_plant
    from cosim.master import run
    from cosim.study.experiments import model_mpc, nnpc, plant_binding

    rows = []
    binding = plant_binding("nominal", "switched")
    for period, label in ((PAPER_PERIOD, "1 ms"), (SWITCHING_PERIOD, "13.33 us")):
        samples = 60 if quick else (3000 if transient_within_sample(period) else 1500)
        scenario = _mixed_scenario(period, samples)
        model, origin = _nn_model("nnpc", period, quick)
        controllers = [_benchmark_pi(period), nnpc(model, period, NNPC),
                       model_mpc(NOMINAL, period, MPC_ORACLE, binding=binding),
                       model_mpc(MISMATCH, period, MPC_MISMATCHED, binding=binding)]
        with open_plant(binding) as plant:
            for controller in controllers:
                frame = run(plant, controller, scenario, record_period=period).frame
                times = frame.loc[frame["control_sample"], "controller_compute_time"].to_numpy()
                median, p99 = float(np.median(times)), _p99(times)
                target, met = "", None
                if controller.name == NNPC and transient_within_sample(period):
                    target, met = "p99 <= 100 us", p99 <= 100e-6
                rows.append(BenchRow(
                    f"controller compute per step, {controller.name}, {label} ({len(times)} samples, "
                    f"{100 * median / period:.2g} % / {100 * p99 / period:.2g} % of the period at p50 / p99)",
                    median * 1e6, p99 * 1e6, "us", target, met,
                    f"NN: {origin}" if controller.name == NNPC else ""))
    return rows


def bench_adaptation(quick: bool) -> list[BenchRow]:
    """The online adaptation's own cost per control sample (recursive least squares on the output
    layer with its guards), apart from the NNPC step it wraps: the adaptive controller's time per
    sample minus its inner NNPC's, on the mixed scenario at one switching period."""
    from controllers.adaptation import AdaptiveNNPC
    from cosim.fmi.plant import open_plant
    from cosim.master import run
    from cosim.study.experiments import adaptive_nnpc, implemented, plant_binding

    period = SWITCHING_PERIOD
    samples = 60 if quick else 1500
    model, origin = _nn_model("nnpc", period, quick)
    adaptive = implemented(adaptive_nnpc(model, period))
    inner_times: list[int] = []
    totals: list[int] = []
    learned: list[bool] = []
    inner_step = adaptive.inner.step
    clock = time.perf_counter_ns

    def timed_inner(measurement):
        start = clock()
        duty = inner_step(measurement)
        inner_times.append(clock() - start)
        return duty

    class Timed(AdaptiveNNPC):
        def step(self, measurement):
            updates = self.counters["updates"]
            start = clock()
            duty = super().step(measurement)
            totals.append(clock() - start)
            learned.append(self.counters["updates"] > updates)
            return duty

    timed = Timed(adaptive.inner, adaptive.model, adaptive.settings, adaptive.name, nominal_load=adaptive.nominal_load)
    timed.inner.step = timed_inner
    with open_plant(plant_binding("nominal", "switched")) as plant:
        run(plant, timed, _mixed_scenario(period, samples), record_period=period)
    overhead = (np.array(totals) - np.array(inner_times)) * 1e-3  # [us]
    updated = overhead[np.array(learned)]
    rows = [BenchRow(f"online adaptation per control sample, NNPC-adaptive at 13.33 us ({len(overhead)} samples, "
                     f"{timed.counters['updates']} RLS updates; the NNPC step itself excluded)",
                     float(np.median(overhead)), _p99(overhead), "us", note=f"NN: {origin}")]
    if len(updated):
        rows.append(BenchRow("online adaptation per RLS update (samples that passed the guards)",
                             float(np.median(updated)), _p99(updated), "us"))
    rows.append(BenchRow("NNPC step the adaptation wraps (C twin), same run", float(np.median(inner_times)) * 1e-3,
                         _p99(np.array(inner_times) * 1e-3), "us"))
    return rows


# ---------------------------------------------------------------------------------------------
# 4. identification cost


def bench_training(quick: bool) -> list[BenchRow]:
    from controllers.nn_model import TrainingSettings, train
    from cosim.study.data_collection import CollectionSettings, collect
    from cosim.study.experiments import nn_configs, plant_binding

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


# ---------------------------------------------------------------------------------------------
# 5. inference alternatives, same run: what the hot-path choices buy


def _median_time(function, repeats: int) -> float:
    samples = []
    for _ in range(repeats):
        start = time.perf_counter_ns()
        function()
        samples.append(time.perf_counter_ns() - start)
    return float(np.median(samples)) * 1e-9


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
    a = circuit_matrix(NOMINAL, TABLE_II.load_resistance, 0.0)
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


# ---------------------------------------------------------------------------------------------
# 6. end to end, and the quality ratios of that very run


def bench_reproduction(quick: bool) -> list[BenchRow]:
    import tempfile
    from dataclasses import replace

    from cosim.base.labels import period_label
    from cosim.study.reproduce import FULL, QUICK, reproduce

    # --quick is the suite's smoke test: one 1 ms pipeline of the quick profile, no seed jobs,
    # ablations or drift study (the rows exist and are computed; the numbers mean nothing)
    profile = replace(QUICK, pipelines=("nominal-averaged__1ms",), seeds=(0,), drift=False,
                      ablations=False) if quick else FULL
    times = {}
    for implementation in ("python", "c"):  # the same reproduction, controllers in Python and in C
        with tempfile.TemporaryDirectory(prefix="buck-bench-") as tmp:
            start = time.perf_counter()
            reproduce(Path(tmp), workers=2, profile=profile, implementation=implementation)
            times[implementation] = time.perf_counter() - start
            if implementation == "c":
                metrics = pd.read_csv(Path(tmp) / "metrics" / "metrics_all.csv")
    elapsed = times["c"]
    ratio = times["c"] / times["python"]
    command = "buck-cosim reproduce"
    scope = ", smoke profile: one 1 ms pipeline of --quick" if quick else ""
    rows = [BenchRow(f"end-to-end reproduction ({command}{scope}), 2 workers, controllers as their C twins (the "
                     "default)", elapsed, None, "s", "<= 120 s on 2 cores", elapsed <= 120.0),
            BenchRow(f"end-to-end reproduction ({command} --implementation python{scope}), 2 workers",
                     times["python"], None, "s"),
            BenchRow("reproduction time with the C controllers / with the Python controllers (same run)", ratio, None,
                     "ratio", "<= 0.4", ratio <= 0.4,
                     "the NN predictive controllers at one switching period dominate both: ~1 ms per step in C, "
                     "~1.8 ms in Python (tanh calls: about 7 per network evaluation, thousands per step)")]
    for pipeline in sorted(set(metrics["pipeline"]), key=lambda p: (("13p33us" in p), p)):
        if not pipeline.startswith("nominal"):
            continue
        m = metrics[metrics["pipeline"] == pipeline]
        for scenario in dict.fromkeys(m["scenario"]):
            iae = m[m["scenario"] == scenario].set_index("controller")["iae_Vs"]
            if {NNPC, MPC_ORACLE, PI} <= set(iae.index):
                rate = pipeline.split("__")[1]
                slow = rate == period_label(PAPER_PERIOD)
                target = "<= 1.10" if slow else ""
                ratio = iae[NNPC] / iae[MPC_ORACLE]
                rows.append(BenchRow(f"NNPC IAE / oracle-MPC IAE, {scenario}, {pipeline}", ratio, None, "ratio",
                                     target, ratio <= 1.10 if target else None))
                ratio = iae[NNPC] / iae[PI]
                target = "<= 0.6" if not slow else ""
                rows.append(BenchRow(f"NNPC IAE / PI IAE, {scenario}, {pipeline}", ratio, None, "ratio", target,
                                     ratio <= 0.6 if target else None))
    return rows


# ---------------------------------------------------------------------------------------------
# 7. the C controllers, Python out of the loop


def _c_and_python_step_us(controller, measurements, replayed) -> tuple[float, float, float, float]:
    """The C step times of ``replayed`` (the harness's replay of ``measurements``) and the Python controller's
    on the same inputs, timed here one step at a time: (C p50, C p99, Python p50, Python p99) in us. First
    checks that the in-process C twin gives the harness's duties, so both time the same computation."""
    from controllers.base import Measurement
    from cosim.study.experiments import implemented

    twin = implemented(controller)
    twin.reset()
    assert all(twin.step(Measurement(*row)) == duty for row, duty in zip(measurements, replayed.duty)), \
        "the harness and the in-process twin disagree"
    python = []
    controller.reset()
    for row in measurements:
        start = time.perf_counter_ns()
        controller.step(Measurement(*row))
        python.append(time.perf_counter_ns() - start)
    return (float(np.median(replayed.ns)) * 1e-3, _p99(replayed.ns) * 1e-3, float(np.median(python)) * 1e-3,
            _p99(python) * 1e-3)


def bench_c_controllers(quick: bool) -> list[BenchRow]:
    """ns per step of the C PI and NNPC (the FMU's sources, controllers/c + the generated header)
    replaying recorded closed-loop measurements, next to the Python controller on the same inputs;
    the NNPC's operations counted and a Cortex-M4F cycle estimate (cosim.benchmark_harness)."""
    from cosim.benchmark_harness import CORTEX_M4F, cortex_m4f_cycles, operation_counts, record_measurements, replay
    from cosim.study.experiments import implemented, model_mpc, nnpc, plant_binding

    binding = plant_binding("nominal", "switched")
    rows = []
    for period, label in ((PAPER_PERIOD, "1 ms"), (SWITCHING_PERIOD, "13.33 us")):
        samples = 40 if quick else (3000 if transient_within_sample(period) else 600)
        scenario = _mixed_scenario(period, samples)
        model, origin = _nn_model("nnpc", period, quick)
        controllers = [_benchmark_pi(period), nnpc(model, period, NNPC)]
        if not transient_within_sample(period):
            controllers.append(model_mpc(NOMINAL, period, MPC_ORACLE, binding=binding))
        for controller in controllers:
            measurements = record_measurements(binding, implemented(controller), scenario)
            result = replay(controller, measurements, repeats=1 if quick else 3)
            c_p50, c_p99, py_p50, py_p99 = _c_and_python_step_us(controller, measurements, result)
            budget = period * 1e6
            target, met = "", None
            if controller.name == NNPC:
                target, met = ("p99 <= 5 us", c_p99 <= 5.0) if transient_within_sample(period) else \
                    ("p99 <= 13.3 us (stretch)", c_p99 <= budget)
            rows.append(BenchRow(f"C step, {controller.name}, {label} ({len(measurements)} replayed samples, "
                                 f"{100 * c_p99 / budget:.3g} % of the period at p99)", c_p50, c_p99, "us", target, met,
                                 f"NN: {origin}" if controller.name == NNPC else ""))
            rows.append(BenchRow(f"Python step, {controller.name}, {label} (same inputs)", py_p50, py_p99, "us"))
            rows.append(BenchRow(f"speed-up of C over Python, {controller.name}, {label} (p50)", py_p50 / c_p50, None,
                                 "ratio"))
            if controller.name != NNPC:
                continue
            counts = operation_counts(controller, result.evaluations)
            cycles = cortex_m4f_cycles(counts)
            for key, what in (("candidates", "candidate evaluations"), ("macs", "multiply-accumulates"),
                              ("tanh", "tanh calls")):
                rows.append(BenchRow(f"NNPC {label} per step: {what} (counted)", float(np.median(counts[key])),
                                     float(np.percentile(counts[key], 99)), "count"))
            fraction = float(np.percentile(cycles, 99)) / (CORTEX_M4F.clock_hz * period)
            rows.append(BenchRow(
                f"NNPC {label} per step on a 170 MHz Cortex-M4F (float32 port, estimated cycles)",
                float(np.median(cycles)), float(np.percentile(cycles, 99)), "cycles",
                f"fits {CORTEX_M4F.clock_hz * period:.0f} cycles", fraction <= 1.0,
                f"p99 is {fraction:.3g} x the period; cost model: {CORTEX_M4F.mac} cycles/MAC, {CORTEX_M4F.tanh}/tanh, "
                f"{CORTEX_M4F.sqrt}/sqrt, {CORTEX_M4F.candidate}/candidate, {CORTEX_M4F.interrupt} per sample for "
                "ADC/PWM/ISR (cosim/benchmark_harness); the twins compute in double precision, which the M4F "
                "emulates in software -- a float32 port is assumed"))
    return rows


# ---------------------------------------------------------------------------------------------
# 8. the explicit NNPC: what one forward pass costs


def _explicit_policy(quick: bool):
    """The reproduction's distilled policy if the models folder has it, else one distilled here (small budget)."""
    from dataclasses import replace

    from controllers.explicit_policy import load_policy
    from cosim.base.errors import ModelFileError
    from cosim.study.distillation import SMALL_DISTILLATION, distill
    from cosim.study.experiments import plant_binding
    from cosim.study.vocabulary import pipeline_tag

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


def bench_explicit(quick: bool) -> list[BenchRow]:
    """The explicit NNPC's C step (the FMU's sources) replaying closed-loop measurements, next to its
    Python step and the online NNPC's C step on the same inputs; operations counted and the
    Cortex-M4F cycle estimate (cosim.benchmark_harness, the c-controllers group's cost model)."""
    from cosim.benchmark_harness import (
        CORTEX_M4F,
        cortex_m4f_cycles,
        policy_operation_counts,
        record_measurements,
        replay,
    )
    from cosim.study.experiments import explicit_nnpc, implemented, nnpc, plant_binding
    from cosim.study.vocabulary import NNPC_EXPLICIT

    period, label = SWITCHING_PERIOD, "13.33 us"
    binding = plant_binding("nominal", "switched")
    policy, origin = _explicit_policy(quick)
    controller = explicit_nnpc(policy, NNPC_EXPLICIT)
    samples = 40 if quick else 3000
    measurements = record_measurements(binding, implemented(controller), _mixed_scenario(period, samples))
    result = replay(controller, measurements, repeats=1 if quick else 20)
    c_p50, c_p99, py_p50, py_p99 = _c_and_python_step_us(controller, measurements, result)
    model, _ = _nn_model("nnpc", period, quick)
    online = replay(nnpc(model, period, NNPC), measurements[:40 if quick else 600], repeats=1)
    online_p50 = float(np.median(online.ns)) * 1e-3
    counts = policy_operation_counts(policy.config)
    cycles = float(cortex_m4f_cycles(counts))
    budget = CORTEX_M4F.clock_hz * period
    note = f"policy: {origin}"
    return [
        BenchRow(f"C step, {NNPC_EXPLICIT}, {label} ({len(measurements)} replayed samples x "
                 f"{1 if quick else 20} passes, {100 * c_p99 / (period * 1e6):.3g} % of the period at p99)",
                 c_p50, c_p99, "us", "p99 <= 0.5 us", c_p99 <= 0.5, note),
        BenchRow(f"Python step, {NNPC_EXPLICIT}, {label} (same inputs)", py_p50, py_p99, "us"),
        BenchRow(f"C step time, online NNPC / {NNPC_EXPLICIT}, {label} (same inputs, p50)", online_p50 / c_p50, None,
                 "ratio"),
        BenchRow(f"{NNPC_EXPLICIT} {label} per step: multiply-accumulates (counted)", counts["macs"], None, "count",
                 "<= 300", counts["macs"] <= 300, f"{policy.config.label}: layers + G r + (Ki Ts) e"),
        BenchRow(f"{NNPC_EXPLICIT} {label} per step: tanh calls (counted)", counts["tanh"], None, "count"),
        BenchRow(f"{NNPC_EXPLICIT} {label} per step on a 170 MHz Cortex-M4F: the cost model's prediction (superseded by "
                 "the measurement of the embedded group)", cycles, None, "cycles",
                 note=f"{cycles / budget:.3g} x the period; cost model: {CORTEX_M4F.mac} cycles/MAC, "
                      f"{CORTEX_M4F.tanh}/tanh, {CORTEX_M4F.division}/division, {CORTEX_M4F.candidate} for the features, "
                      f"clip and integral, {CORTEX_M4F.interrupt} per sample for ADC/PWM/ISR (cosim/benchmark_harness); "
                      "measured on the emulated Cortex-M4F: group embedded"),
    ]


# ---------------------------------------------------------------------------------------------
# 8b. the float32 controllers on a Cortex-M4F (QEMU), measured


def _embedded_controllers(quick: bool):
    """What the embedded group measures at 13.33 us: (controller, its operation counts for the cost model,
    where it comes from). A controller with a float32 build and a row in cortex_m4.EMBEDDED_CONTROLLERS
    is one more entry here."""
    from controllers.cost_model import pi_operation_counts, policy_operation_counts
    from cosim.study.experiments import explicit_nnpc
    from cosim.study.vocabulary import NNPC_EXPLICIT

    policy, origin = _explicit_policy(quick)
    pi = _benchmark_pi(SWITCHING_PERIOD)
    return [(pi, pi_operation_counts(), "the benchmark PI gains"),
            (explicit_nnpc(policy, NNPC_EXPLICIT), policy_operation_counts(policy.config), f"policy: {origin}")]


def bench_embedded(quick: bool) -> list[BenchRow]:
    """The float32 builds cross-compiled for a Cortex-M4F (-O2, hard float) and executed in QEMU's
    mps2-an386, replaying recorded closed-loop measurements of the nominal switched plant at 13.33 us:
    duties against the host's float32 build, instructions per step from the execution trace, cycles from
    the executed instruction mix with the Cortex-M4 TRM's table (cosim/benchmark_harness/cortex_m4.py), flash
    and RAM, the stack, and the cost model's prediction against the measurement."""
    from controllers.base import Measurement
    from controllers.cost_model import CORTEX_M4F, cortex_m4f_cycles
    from controllers.native import native_twin
    from cosim.benchmark_harness import record_measurements
    from cosim.benchmark_harness.cortex_m4 import (
        CLOCK_HZ,
        CYCLE_TABLE,
        EXCEPTION_FRAME_BYTES,
        ISR_ALLOWANCE,
        measure,
        toolchain_problem,
    )
    from cosim.study.experiments import plant_binding

    problem = toolchain_problem()
    if problem:
        return [BenchRow("Cortex-M4F measurements (QEMU mps2-an386): not measured", math.nan, None, "", note=problem)]
    period, label = SWITCHING_PERIOD, "13.33 us"
    budget, slow_budget = CLOCK_HZ * period, CLOCK_HZ * PAPER_PERIOD
    binding = plant_binding("nominal", "switched")
    samples = 40 if quick else 600
    scenario = _mixed_scenario(period, samples)
    rows = []
    for controller, counts, origin in _embedded_controllers(quick):
        measurements = record_measurements(binding, native_twin(controller), scenario)
        measured = measure(controller, measurements)
        run, size = measured.replay, measured.footprint
        n = len(measurements)
        host = native_twin(controller, "float32")
        host.reset()
        duties = np.array([host.step(Measurement(*row)) for row in measurements])
        identical = float(np.mean(duties == run.duty)) * 100
        name = f"{controller.name} {label} on a Cortex-M4F (float32, QEMU mps2-an386)"
        worst = float(run.cycles.max())
        predicted = float(cortex_m4f_cycles(counts)) - CORTEX_M4F.interrupt
        library = sum(c for f, c in run.functions.items() if not f.startswith("buckc_")) / n
        table = (f"TRM cycle table, upper reading (P = {CYCLE_TABLE.refill:g}, loads/stores 2, VDIV 14); the "
                 f"lower reading (P = 1, pipelined loads) gives p50 {np.median(run.cycles_low):.0f} / max "
                 f"{run.cycles_low.max():.0f}")
        rows += [
            BenchRow(f"{name}: instructions executed per step ({n} replayed samples; p99 column: max)",
                     float(np.median(run.instructions)), float(run.instructions.max()), "count", note=origin),
            BenchRow(f"{name}: cycles per step from the executed instruction mix (p99 column: max)",
                     float(np.median(run.cycles)), worst, "cycles", note=table),
            BenchRow(f"{name}: max cycles per step + {ISR_ALLOWANCE:.0f}-cycle ISR allowance, 170 MHz", worst
                     + ISR_ALLOWANCE, None, "cycles", f"<= {budget:.0f} (13.33 us)", worst + ISR_ALLOWANCE <= budget,
                     f"{(worst + ISR_ALLOWANCE) / budget:.3g} x the switching period; the library functions "
                     f"(libm: tanhf, expm1f, ...) take {library:.0f} cycles per step on average"),
            BenchRow(f"{name}: the same against a 1 ms sample", worst + ISR_ALLOWANCE, None, "cycles",
                     f"<= {slow_budget:.0f} (1 ms)", worst + ISR_ALLOWANCE <= slow_budget,
                     f"{(worst + ISR_ALLOWANCE) / slow_budget:.3g} x the 1 ms sample"),
            BenchRow(f"{name}: flash the controller adds (code, configuration, library functions)", size.flash,
                     None, "bytes", "<= 16384" if controller.name != PI else "", size.flash <= 16384
                     if controller.name != PI else None,
                     f"text {size.text}, data {size.data} (arm-none-eabi-size of a minimal firmware with and "
                     f"without it); controller.o alone: text {size.object_sizes['text']}, data "
                     f"{size.object_sizes['data']}, bss {size.object_sizes['bss']}"),
            BenchRow(f"{name}: RAM the controller needs (state + stack + exception frame)", size.ram + run.stack_bytes
                     + EXCEPTION_FRAME_BYTES, None, "bytes", "<= 2048" if controller.name != PI else "",
                     size.ram + run.stack_bytes + EXCEPTION_FRAME_BYTES <= 2048 if controller.name != PI else None,
                     f".data + .bss {size.ram}, deepest stack of a step {run.stack_bytes} (painted stack; "
                     f"-fstack-usage frames: " + ", ".join(f"{k} {v}" for k, v in sorted(measured.stack_usage.items())
                                                          if v) + f"), FP exception frame {EXCEPTION_FRAME_BYTES}"),
            BenchRow(f"{name}: duties equal to the host's float32 build, bit for bit", identical, None, "%",
                     note=f"max |difference| {np.max(np.abs(duties - run.duty)):.3g} (newlib's libm on the target, "
                          "glibc's on the host)"),
            BenchRow(f"{name}: cost-model prediction / measured max cycles per step", predicted / worst, None,
                     "ratio", note=f"prediction {predicted:.0f} cycles (controllers/cost_model.py: {CORTEX_M4F.mac} "
                                   f"per MAC, {CORTEX_M4F.tanh} per tanh, ...) against {worst:.0f} measured"),
        ]
        if counts["tanh"]:
            forward = run.functions.get("buckc_policy_forward", 0.0) / n
            layer_macs = counts["macs"] - 2  # policy_operation_counts adds G r and (Ki Ts) e to the layers' MACs
            rows.append(BenchRow(f"{name}: measured cycles per tanh (libm) and per layer MAC (the forward loop)",
                                 library / counts["tanh"], forward / layer_macs, "cycles",
                                 note="median column: per tanhf call incl. expm1f; p99 column: per MAC of "
                                      f"buckc_policy_forward incl. its loop; the cost model assumes {CORTEX_M4F.tanh}"
                                      f" and {CORTEX_M4F.mac}"))
    return rows


# ---------------------------------------------------------------------------------------------
# 9. sweeps on dask: throughput on 1 and 2 workers, against the same runs without dask


SWEEP_SAMPLES = 100  # x 2 controllers (PI, NNPC) x start-up = the 200-run sweep of the benchmark


def _sweep_setup(quick: bool):
    """A 200-run tolerance sweep at 1 ms (L, C +-20 % on the switched plant; PI and NNPC, start-up):
    its plan, its controllers' recipes and its runs."""
    import tempfile

    from controllers.nn_model import save_model
    from cosim.study.sweeps.plan import SweepPlan
    from cosim.study.sweeps.recipes import ControllerRecipe, canonical
    from cosim.study.sweeps.spec import parse_sweep

    samples = 4 if quick else SWEEP_SAMPLES
    spec = parse_sweep(f'scenarios = ["startup"]\ncontrollers = ["pi", "nnpc"]\nsamples = {samples}\nseed = 1\n'
                       '[plant]\nmode = "switched"\n[parameters]\ninductance = { tolerance = 0.2 }\n'
                       'capacitance = { tolerance = 0.2 }\n', None)
    plan = SweepPlan(spec)
    pi = _benchmark_pi(PAPER_PERIOD)
    model, _ = _nn_model("nnpc", PAPER_PERIOD, quick)
    with tempfile.TemporaryDirectory() as folder:  # the model as a worker receives it: a file's bytes
        blob = save_model(model, Path(folder) / "nnpc.pt").read_bytes()
    recipes = [ControllerRecipe("pi", PI, PAPER_PERIOD, canonical({"kp_per_V": pi.kp, "ki_per_V_s": pi.ki,
                                                                    "tuning": {"method": "benchmark gains"}})),
               ControllerRecipe("nnpc", NNPC, PAPER_PERIOD, canonical({"network": model.config.label}), blob)]
    return plan, recipes, plan.runs(recipes)


def _plain_runs(plan, recipes, runs) -> float:
    """Seconds for the runs in this process without dask: one plant, each controller built once,
    parameters set and the run and its metrics computed -- the work a sweep distributes."""
    from cosim.fmi.plant import open_plant
    from cosim.master import run_checked
    from cosim.metrics import run_metrics
    from cosim.study.sweeps.designs import build

    binding = plan.binding
    controllers = {r.name: build(r, binding, "c") for r in recipes}
    scenarios = plan.scenarios
    nominal = dict(binding.parameters)
    with open_plant(binding) as plant:
        plant.replace_parameters({**nominal, **dict(runs[0].parameters)})  # warm: first initialisation
        run_checked(plant, controllers[runs[0].controller], scenarios[runs[0].scenario], record_period=1e-5)
        start = time.perf_counter()
        for r in runs:
            plant.replace_parameters({**nominal, **dict(r.parameters)})
            run_metrics(run_checked(plant, controllers[r.controller], scenarios[r.scenario], record_period=1e-5))
        return time.perf_counter() - start


def _sweep_on(client, plan, recipes, runs, folder: Path) -> tuple[float, float]:
    """Seconds for the same runs through the sweep machinery on ``client`` (tasks, transfer, the
    workers' runs, every part written; the workers warmed up first: imports, FMU, C twins), and the
    runs' own seconds as the workers timed them (summed)."""
    from cosim.study.sweeps import dataset
    from cosim.study.sweeps.execute import SweepExecution, execute
    from cosim.study.sweeps.worker import RunSettings, run_batch

    settings = RunSettings(1e-5, "c", False)
    controllers = {r.name: r for r in recipes}
    tasks = plan.batches(runs)
    warm = [client.submit(run_batch, plan.plant, controllers[t.controller], plan.scenarios[t.scenario], t.runs[:1],
                          settings, workers=[address], pure=False)
            for address in client.scheduler_info()["workers"] for t in tasks[:2]]
    client.gather(warm)
    schema = dataset.row_schema([(i.axis.name, i.unit, i.integer) for i in plan.axes])
    execution = SweepExecution(tasks, plan.plant, controllers, plan.scenarios, settings, schema, folder)
    start = time.perf_counter()
    execute(execution, client, lambda counts: "interrupted")
    elapsed = time.perf_counter() - start
    return elapsed, float(dataset.read_timing(folder)["wall_time_s"].sum())


def bench_sweep(quick: bool) -> list[BenchRow]:
    import tempfile

    from cosim.study.cluster import dask_client

    plan, recipes, runs = _sweep_setup(quick)
    repeats = 1 if quick else 5
    plain, on, machinery = [], {1: [], 2: []}, []
    starts = {}
    with tempfile.TemporaryDirectory(prefix="buck-bench-sweep-") as tmp:
        for workers in (1, 2):
            start = time.perf_counter()
            with dask_client(workers=workers) as client:
                client.wait_for_workers(workers, timeout=120)
                starts[workers] = time.perf_counter() - start
                for repeat in range(repeats):  # interleaved with the plain runs, so drift hits both alike
                    if workers == 1:
                        plain.append(_plain_runs(plan, recipes, runs))
                    elapsed, runs_own = _sweep_on(client, plan, recipes, runs, Path(tmp) / f"{workers}-{repeat}")
                    on[workers].append(elapsed)
                    if workers == 1:  # one worker: the runs' own time is the sweep's minus the machinery's
                        machinery.append(1 - runs_own / elapsed)
    n = len(runs)
    rate = {w: n / statistics.median(t) for w, t in on.items()}
    plain_rate = n / statistics.median(plain)
    scaling = rate[2] / rate[1]
    overhead = statistics.median(on[1]) / statistics.median(plain) - 1
    label = f"{n}-run sweep at 1 ms (PI and NNPC, start-up, switched plant, L and C +-20 %)"
    return [
        BenchRow(f"sweep throughput without dask: the same runs in one process, {label}", plain_rate, None, "runs/s"),
        BenchRow(f"sweep throughput on a LocalCluster of 1 worker, {label}", rate[1], n / max(on[1]), "runs/s",
                 note="p99 column: the slowest repeat; workers warmed up (imports, FMU, C twins) before timing"),
        BenchRow(f"sweep throughput on a LocalCluster of 2 workers, {label}", rate[2], n / max(on[2]), "runs/s",
                 note="p99 column: the slowest repeat"),
        BenchRow("sweep scaling: 2 workers / 1 worker (median runs/s)", scaling, None, "ratio", ">= 1.8 on 2 cores",
                 scaling >= 1.8, "the workbench's process (scheduler, part writing) shares the 2 cores"),
        BenchRow("sweep overhead per run: 1-worker sweep / the same runs without dask - 1", overhead * 100, None, "%",
                 "<= 5 %", overhead <= 0.05, "tasks, transfer, one Parquet part per task, progress; measured "
                 "against runs in another process at another moment, so the shared machine's drift is in it"),
        BenchRow("sweep machinery share of a 1-worker sweep: 1 - (the runs' own time on the worker) / (sweep time)",
                 statistics.median(machinery) * 100, max(machinery) * 100, "%", note="the same sweep timed from "
                 "both sides (no drift between two measurements); p99 column: the worst repeat"),
        BenchRow("LocalCluster start-up, 2 worker processes (until both are ready)", starts[2], None, "s"),
    ]


#: the soak: this many runs on 2 local workers (the issue-26 target: <= 50 MB of growth per worker and in the
#: workbench's own process)
SOAK_RUNS = 10_000
#: a worker's memory is taken as settled after its first runs this many (FMU extracted, C twins loaded, caches warm)
SOAK_WARM_RUNS = 100
SOAK_GROWTH_TARGET_MB = 50.0


def bench_soak(quick: bool) -> list[BenchRow]:
    """A long sweep on 2 local workers, each worker's resident memory after each of its runs read from the
    sweep's timing table (``worker_rss_mb``, ``worker_run``): growth from its run SOAK_WARM_RUNS to its last;
    the workbench's own process measured before and after. PI at 1 ms, the shipped start-up on the averaged
    plant, L +-20 % (a run costs ~20 ms; 10 000 runs take a few minutes)."""
    import tempfile

    from cosim.fmi.isolation import resident_bytes
    from cosim.study.cluster import dask_client
    from cosim.study.sweeps import dataset
    from cosim.study.sweeps.execute import SweepExecution, execute
    from cosim.study.sweeps.plan import SweepPlan
    from cosim.study.sweeps.recipes import ControllerRecipe, canonical
    from cosim.study.sweeps.spec import parse_sweep
    from cosim.study.sweeps.worker import RunSettings, run_batch

    runs_wanted = 2 * (SOAK_WARM_RUNS + 10) if quick else SOAK_RUNS
    spec = parse_sweep(f'scenarios = ["startup"]\ncontrollers = ["pi"]\nsamples = {runs_wanted}\nseed = 2\n'
                       'batch_size = 50\n[plant]\nmode = "averaged"\n[parameters]\n'
                       'inductance = { tolerance = 0.2 }\n', None)
    plan = SweepPlan(spec)
    pi = _benchmark_pi(PAPER_PERIOD)
    recipes = [ControllerRecipe("pi", PI, PAPER_PERIOD, canonical({"kp_per_V": pi.kp, "ki_per_V_s": pi.ki,
                                                                    "tuning": {"method": "benchmark gains"}}))]
    runs = plan.runs(recipes)
    settings = RunSettings(1e-4, "c", False)
    controllers = {r.name: r for r in recipes}
    tasks = plan.batches(runs)
    schema = dataset.row_schema([(i.axis.name, i.unit, i.integer) for i in plan.axes])
    with tempfile.TemporaryDirectory(prefix="buck-bench-soak-") as folder, dask_client(workers=2) as client:
        client.wait_for_workers(2, timeout=120)
        warm = [client.submit(run_batch, plan.plant, controllers[t.controller], plan.scenarios[t.scenario],
                              t.runs[:1], settings, workers=[address], pure=False)
                for address in client.scheduler_info()["workers"] for t in tasks[:1]]
        client.gather(warm)
        own_before = resident_bytes(os.getpid())
        execution = SweepExecution(tasks, plan.plant, controllers, plan.scenarios, settings, schema, Path(folder))
        start = time.perf_counter()
        execute(execution, client, lambda counts: "interrupted")
        elapsed = time.perf_counter() - start
        own_after = resident_bytes(os.getpid())
        timing = dataset.read_timing(Path(folder))
    growth, last = {}, {}
    for worker, rows in timing.groupby("worker"):
        rows = rows.sort_values("worker_run")
        settled = rows[rows["worker_run"] >= SOAK_WARM_RUNS]
        growth[worker] = float(settled["worker_rss_mb"].iloc[-1] - settled["worker_rss_mb"].iloc[0])
        last[worker] = float(rows["worker_rss_mb"].iloc[-1])
    worst = max(growth.values())
    own = (own_after - own_before) / 1e6 if own_before and own_after else math.nan
    label = f"{len(runs)}-run sweep on 2 workers (PI, start-up, averaged plant, L +-20 %)"
    return [
        BenchRow(f"soak: worker resident memory growth over a {label}, worst worker", worst, None, "MB",
                 f"<= {SOAK_GROWTH_TARGET_MB:g} MB", worst <= SOAK_GROWTH_TARGET_MB,
                 f"from each worker's run {SOAK_WARM_RUNS} to its last ({', '.join(f'{g:+.1f}' for g in growth.values())}"
                 f" MB; resident at the end: {', '.join(f'{v:.0f}' for v in last.values())} MB), read from the "
                 "sweep's timing table (worker_rss_mb)"),
        BenchRow(f"soak: the workbench's own process, resident memory growth over the {label}", own, None, "MB",
                 f"<= {SOAK_GROWTH_TARGET_MB:g} MB", own <= SOAK_GROWTH_TARGET_MB,
                 "scheduler, futures, parts written; from after the workers' warm-up to the end"),
        BenchRow(f"soak: throughput of the {label}", len(runs) / elapsed, None, "runs/s"),
    ]


BENCHMARKS: dict[str, Callable[[bool], list[BenchRow]]] = {
    "plant": bench_plant,
    "master": bench_master,
    "controllers": bench_controllers,
    "c-controllers": bench_c_controllers,
    "adaptation": bench_adaptation,
    "explicit": bench_explicit,
    "embedded": bench_embedded,
    "training": bench_training,
    "inference": bench_inference,
    "reproduction": bench_reproduction,
    "sweep": bench_sweep,
    "soak": bench_soak,
}


def run_benchmarks(out_dir: Path, quick: bool = False, only: list[str] | None = None,
                   command: str = "buck-cosim bench", models_dir: Path | None = None) -> tuple[Path, Path]:
    """Run the benchmarks (``only``: some of them) and write the table. With ``only``, the other
    groups' rows of the existing table are kept as they were measured, each with its own command.
    Trained models are read from ``models_dir`` (default: ``out_dir/models``)."""
    global _models_dir
    command += " --quick" if quick else ""
    out_dir = Path(out_dir)
    rows: list[BenchRow] = []
    before, _models_dir = _models_dir, Path(models_dir) if models_dir is not None else out_dir / "models"
    try:
        for name, function in BENCHMARKS.items():
            if only and name not in only:
                continue
            print(f"benchmark: {name} ...", file=sys.stderr)
            for row in function(quick):
                row.group, row.command = name, command
                rows.append(row)
    finally:
        _models_dir = before
    if only:
        kept = [r for r in _read_rows(out_dir / ("benchmarks-quick.csv" if quick else "benchmarks.csv"))
                if r.group not in only]
        order = list(BENCHMARKS)
        rows = sorted(kept + rows, key=lambda r: order.index(r.group))  # stable: measured order kept
    return write_benchmarks(rows, out_dir, quick)


def _read_rows(path: Path) -> list[BenchRow]:
    """Rows of an earlier table that can be merged (those with a known group), else none."""
    try:
        frame = pd.read_csv(path, keep_default_na=False)
    except (OSError, ValueError):
        return []
    if not {"group", "command", "benchmark", "median"} <= set(frame.columns):
        return []

    def optional(value, kind):
        return None if value in ("", None) else kind(value)

    rows = []
    for r in frame.to_dict("records"):
        if r["group"] not in BENCHMARKS:
            continue
        met = r.get("meets_target")
        rows.append(BenchRow(str(r["benchmark"]), float(r["median"]), optional(r.get("p99"), float), str(r["unit"]),
                             str(r.get("target", "")), None if met in ("", None) else str(met) == "True",
                             str(r.get("note", "")), group=r["group"], command=str(r["command"])))
    return rows


def write_benchmarks(rows: list[BenchRow], out_dir: Path, quick: bool) -> tuple[Path, Path]:
    machine = machine_info()
    versions = package_versions()
    frame = pd.DataFrame([{k: v for k, v in asdict(r).items() if k != "extra"} for r in rows])
    frame["machine"] = f"{machine['cpu']} ({machine['cores']} cores)"
    csv_path = atomic_write(out_dir / ("benchmarks-quick.csv" if quick else "benchmarks.csv"),
                            lambda tmp: frame.to_csv(tmp, index=False))
    commands = list(dict.fromkeys(r.command for r in rows))
    lines = [
        "# Benchmarks" + (" (quick smoke run: sizes too small to mean anything)" if quick else ""),
        "",
        (f"Command: `{commands[0]}`  " if len(commands) == 1 else
         "Commands: " + "; ".join(f"`{c}` ({', '.join(dict.fromkeys(r.group for r in rows if r.command == c))})"
                                  for c in commands) + " -- ratios only within one command's rows  "),
        f"Machine: {machine['cpu']}, {machine['cores']} cores, {machine['system']}, Python {machine['python']}  ",
        "Packages: " + ", ".join(f"{k} {v}" for k, v in versions.items() if k != "python"),
        "",
        "Medians over repetitions; p99 where a distribution exists. Ratios are measured within this one run.",
        "",
        "| benchmark | median | p99 | unit | target | met |",
        "|---|---:|---:|---|---|---|",
    ]
    for r in rows:
        p99 = "" if r.p99 is None else f"{r.p99:.4g}"
        met = "" if r.meets_target is None else ("yes" if r.meets_target else "**no**")
        lines.append(f"| {r.benchmark} | {r.median:.4g} | {p99} | {r.unit} | {r.target} | {met} |")
    notes = [r for r in rows if r.note]
    if notes:
        lines += ["", "Notes:", ""] + [f"- {r.benchmark}: {r.note}" for r in notes]
    lines += ["", "## What profiling changed", "",
              "The end-to-end reproduction is dominated by the predictive controllers at one switching period "
              "(a 23-step horizon, thousands of samples). cProfile showed the time in the NN rollout, the "
              "optimizer's array set-up and the model discretisation; the rows above measure each fix "
              "against the code path it replaced, in this run:",
              "",
              "- NN inference in numpy with the normalisation folded into the weights, not torch "
              "(`speed-up of numpy over torch`);",
              "- a rollout that computes the measured history's share of the first layer once for all "
              "candidates (`speed-up of the shared-history rollout`);",
              "- the 2x2 matrix exponential in closed form instead of scipy's Pade (`speed-up of the "
              "closed-form matrix exponential`);",
              "- in the optimizer, refinement that starts from the warm start's fine lattice when the warm "
              "start wins, so steady samples take one or two batched passes (NNPC p50 vs p99 above);",
              "- in the master, outputs read as Python floats from a reused ctypes buffer and one finiteness "
              "test per row instead of numpy calls, and outputs not re-read after a duty change the FMU "
              "declares no feedthrough for (`master overhead ratio`)."]
    md_path = atomic_write_text(out_dir / ("benchmarks-quick.md" if quick else "benchmarks.md"), "\n".join(lines) + "\n")
    return md_path, csv_path
