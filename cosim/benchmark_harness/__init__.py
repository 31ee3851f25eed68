"""What the C controllers cost: the step timed in C (Python out of the loop), operations counted,
and a cycle estimate for a 170 MHz Cortex-M4F.

* :func:`record_measurements` drives the plant FMU in closed loop with a controller and keeps
  what it measured at every sample;
* :func:`replay` compiles ``controller_step.c`` with the controller's generated header (the same
  sources as its FMU), replays the measurements through the C step and returns ns per step, the
  duty and the optimizer's candidate evaluations;
* :func:`operation_counts` turns candidate evaluations into multiply-accumulates, activations
  (tanh) and square roots per step -- exact for the code paths of ``controllers/c`` -- and
  :func:`cortex_m4f_cycles` into cycles with the cost model of :data:`CORTEX_M4F`.
"""

from __future__ import annotations

import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from controllers.base import Measurement
from controllers.codegen import config_header
from controllers.native import FLAGS, SOURCE_DIR, NativeBuildError, build_c

HARNESS = Path(__file__).parent / "controller_step.c"
CONTROLLER_FMU_DIR = Path(__file__).resolve().parents[1] / "fmi" / "controller_fmu"


@dataclass(frozen=True)
class CostModel:
    """Cycles per operation of a float32 port on a Cortex-M4F (single-precision FPU), and where the
    figures come from."""

    clock_hz: float = 170e6
    mac: float = 6.5  # a multiply-accumulate of a small MLP compiled to C, loads and loop included:
    # the 6-7 cycles published for MLPs on Cortex-M4 (the project's issue cites them)
    tanh: float = 60.0  # tanhf as one expf (a ~40-cycle range reduction + polynomial) and one
    # VDIV.F32 (14 cycles, ARM Cortex-M4 TRM), plus a few for sign handling: an assumption
    sqrt: float = 14.0  # VSQRT.F32 (ARM Cortex-M4 TRM)
    candidate: float = 30.0  # per candidate: lattice generation, clipping, compare (an assumption)
    interrupt: float = 200.0  # per control sample: ADC read, PWM update, ISR entry and exit (an allowance)
    division: float = 14.0  # VDIV.F32 (ARM Cortex-M4 TRM)


CORTEX_M4F = CostModel()


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


def harness(controller) -> Path:
    """The harness executable for a Python PI or predictive controller (cached by sources and data)."""
    sources = [HARNESS, *sorted(p for p in SOURCE_DIR.glob("*.c"))]
    headers = [*sorted(SOURCE_DIR.glob("*.h")), CONTROLLER_FMU_DIR / "controller_variables.h"]
    flags = tuple(f for f in FLAGS if f not in ("-fPIC", "-shared"))
    return build_c("controller-step", sources, headers, flags, "",
                   generated={"controller_config.h": config_header(controller)})


@dataclass
class Replay:
    ns: np.ndarray  # per step, every pass
    duty: np.ndarray  # of the last pass
    evaluations: np.ndarray  # candidate evaluations per step (0 for the PI), last pass
    passes: np.ndarray


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
                  passes=last[:, 3].astype(int))


def operation_counts(controller, evaluations: np.ndarray) -> dict[str, np.ndarray]:
    """Multiply-accumulates, activations and square roots per step of a predictive controller,
    exact for the code paths of ``controllers/c`` given the candidate evaluations per step.

    Per candidate and horizon step: the NN (``nn_model.c``): the shared fast path (1 delay, 1
    hidden layer of H) costs 3H MACs at the first step and 5H after it; the generic path
    n_in*H1 + sum H_l*H_l+1 + 2*H_last per step; one activation per hidden unit per step. The
    cost of eq. 23 (``predictive.c``): 3 MACs and one square root per step.
    """
    from controllers.predictors import NNPredictor

    horizon = controller.settings.horizon
    evaluations = np.asarray(evaluations, dtype=float)
    if not isinstance(controller.predictor, NNPredictor):
        raise ValueError("operation counts are defined for the NN predictor")
    config = controller.predictor.model.config
    hidden = list(config.hidden)
    if config.delays == 1 and len(hidden) == 1:
        macs_per_candidate = 3 * hidden[0] + 5 * hidden[0] * (horizon - 1)
    else:
        widths = [config.n_inputs, *hidden, 2]
        macs_per_candidate = horizon * sum(a * b for a, b in zip(widths[:-1], widths[1:]))
    macs_per_candidate += 3 * horizon
    return {"macs": evaluations * macs_per_candidate, "tanh": evaluations * horizon * sum(hidden),
            "sqrt": evaluations * horizon, "candidates": evaluations}


def policy_operation_counts(config) -> dict[str, float]:
    """Operations per step of the explicit NNPC (``controllers/c/explicit_policy.c``), the same at
    every step: the layers' multiply-accumulates plus the feature product G r and the integral
    term's (Ki Ts) e (:meth:`controllers.explicit_policy.PolicyConfig.macs`), one tanh per hidden
    unit, one division (the load estimate io / vo); the feature differences, the integral's
    condition and the clipping count as one candidate's bookkeeping."""
    return {"macs": float(config.macs()), "tanh": float(sum(config.hidden)), "sqrt": 0.0, "division": 1.0,
            "candidates": 1.0}


def cortex_m4f_cycles(counts: dict[str, np.ndarray], model: CostModel = CORTEX_M4F) -> np.ndarray:
    """Cycles per step of a float32 port on a Cortex-M4F under ``model`` (interrupt allowance included)."""
    return (counts["macs"] * model.mac + counts["tanh"] * model.tanh + counts["sqrt"] * model.sqrt
            + counts.get("division", 0.0) * model.division + counts["candidates"] * model.candidate + model.interrupt)
