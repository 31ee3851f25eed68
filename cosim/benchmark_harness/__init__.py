"""What the C controllers cost: the step timed in C (Python out of the loop), operations counted,
and a cycle estimate for a 170 MHz Cortex-M4F.

* :func:`record_measurements` drives the plant FMU in closed loop with a controller and keeps
  what it measured at every sample;
* :func:`replay` compiles ``controller_step.c`` with the controller's generated header (the same
  sources as its FMU), replays the measurements through the C step and returns ns per step, the
  duty and the optimizer's candidate evaluations; :func:`replay_interleaved` times several controllers
  pass by pass in turn, so that a machine whose speed drifts slows each of them alike;
* :func:`~controllers.cost_model.operation_counts` (re-exported here) turns candidate evaluations
  into multiply-accumulates, activations (tanh) and square roots per step -- exact for the code
  paths of ``controllers/c`` -- and :func:`~controllers.cost_model.cortex_m4f_cycles` into cycles
  with the cost model of :data:`~controllers.cost_model.CORTEX_M4F` (calibrated on the float32 builds
  measured on an emulated Cortex-M4F: :mod:`cosim.benchmark_harness.cortex_m4`).
"""

from __future__ import annotations

import subprocess
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from controllers.base import Measurement
from controllers.codegen import config_header
from controllers.cost_model import (  # noqa: F401  (re-exported)
    CORTEX_M4F,
    CostModel,
    cortex_m4f_cycles,
    operation_counts,
    policy_operation_counts,
    rti_operation_counts,
)
from controllers.native import FLAGS, SOURCE_DIR, NativeBuildError, build_c

HARNESS = Path(__file__).parent / "controller_step.c"
CONTROLLER_FMU_DIR = Path(__file__).resolve().parents[1] / "fmi" / "controller_fmu"




class Recorder:
    """Wraps a controller and keeps the measurements it is given (time, ref, vo, iL, io, vin)."""

    def __init__(self, inner):
        self.inner = inner
        self.name, self.sample_period, self.duty_limits = inner.name, inner.sample_period, inner.duty_limits
        self.rows: list[tuple] = []

    def reset(self):
        self.inner.reset()

    def step(self, m: Measurement) -> float:
        self.rows.append((m.time, m.reference, m.output_voltage, m.inductor_current, m.load_current,
                          m.input_voltage))
        return self.inner.step(m)

    def describe(self):
        return self.inner.describe()


def record_measurements(binding, controller, scenario) -> np.ndarray:
    """The measurements a controller receives driving ``binding``'s plant through ``scenario``."""
    from cosim.master import simulate

    recorder = Recorder(controller)
    simulate(binding, recorder, scenario, record_period=controller.sample_period)
    return np.array(recorder.rows, dtype=float)


def harness(controller, count_instructions: bool = False) -> Path:
    """The harness executable for a Python PI or predictive controller (cached by sources and data);
    ``count_instructions``: the build that callgrind counts step by step (:mod:`.instruction_count`)."""
    sources = [HARNESS, *sorted(p for p in SOURCE_DIR.glob("*.c"))]
    headers = [*sorted(SOURCE_DIR.glob("*.h")), CONTROLLER_FMU_DIR / "controller_variables.h"]
    flags = tuple(f for f in FLAGS if f not in ("-fPIC", "-shared"))
    flags += ("-DHARNESS_COUNT_INSTRUCTIONS",) if count_instructions else ()
    return build_c("controller-step-counted" if count_instructions else "controller-step", sources, headers, flags,
                   "", generated={"controller_config.h": config_header(controller)})


@dataclass
class Replay:
    ns: np.ndarray  # per step, every pass
    duty: np.ndarray  # of the last pass
    evaluations: np.ndarray  # candidate evaluations per step (0 for the PI and RTI steps), last pass
    passes: np.ndarray
    rti: np.ndarray  # True where the real-time iteration planned the step, last pass
    qp_iterations: np.ndarray  # the RTI's box-QP iterations per step, last pass
    updated: np.ndarray  # True where the adaptive NNPC's RLS updated its output layer in the step, last pass
    reweighted: np.ndarray  # the RTI's reweighted box QPs per step (RtiSettings.reweightings), last pass


def replay_interleaved(jobs, passes: int) -> list[Replay]:
    """Time the C steps of several ``(controller, measurements)`` jobs in turn, one pass of each, ``passes``
    times -- job 1's pass, job 2's, ..., then the next round -- each pass in its own harness process after an
    untimed warm-up pass over the same measurements. One controller's passes then span the same stretch of time
    as the others': a shared VM whose speed steps between two levels (measured here: the same step 5 us or
    10 us by the minute on some days, from one ~10 ms pass to the next on others) slows each job alike in the
    share of passes, and a ratio between jobs is one of the same
    conditions, which replaying one controller's passes after another's does not give. Each result has ns of all
    ``passes`` (pass-major, as :func:`replay`'s) and the last pass's diagnostics."""
    timed: list[list[np.ndarray]] = [[] for _ in jobs]
    last: list[Replay | None] = [None] * len(jobs)
    for _ in range(passes):
        for index, (controller, measurements) in enumerate(jobs):
            last[index] = replay_warm(controller, measurements, 1)
            timed[index].append(last[index].ns)
    return [replace(result, ns=np.concatenate(ns)) for result, ns in zip(last, timed)]


def replay_warm(controller, measurements: np.ndarray, passes: int, warm_up: bool = True) -> Replay:
    """:func:`replay` of ``passes`` timed passes after an untimed warm-up pass over the same measurements (in
    the same harness process; ``warm_up=False``: none); ns holds the timed passes only."""
    result = replay(controller, measurements, repeats=passes + (1 if warm_up else 0))
    return replace(result, ns=result.ns[len(measurements) if warm_up else 0:])


def replay(controller, measurements: np.ndarray, repeats: int = 3) -> Replay:
    """Time the C step of ``controller`` over ``measurements`` (``repeats`` passes)."""
    executable = harness(controller)
    with tempfile.TemporaryDirectory(prefix="buck-cosim-harness-") as tmp:
        data = Path(tmp) / "measurements.bin"
        np.ascontiguousarray(measurements, dtype="<f8").tofile(data)
        done = subprocess.run([str(executable), str(data), str(repeats)], capture_output=True, text=True,
                              timeout=3600)
    if done.returncode != 0:
        raise NativeBuildError(f"the C benchmark harness failed (exit {done.returncode}): {done.stderr.strip()}")
    table = np.loadtxt(done.stdout.splitlines(), ndmin=2)
    last = table[-len(measurements):]
    return Replay(ns=table[:, 0], duty=last[:, 1], evaluations=last[:, 2].astype(int),
                  passes=last[:, 3].astype(int), rti=last[:, 4] == 1, qp_iterations=last[:, 5].astype(int),
                  updated=last[:, 6] == 1, reweighted=last[:, 7].astype(int))
