"""What a step of the C controllers costs, counted rather than timed: operations per step from the
optimizer's candidate evaluations (exact for the code paths of ``controllers/c``), and cycles on a
microcontroller from a stated cost model. The cost model predates a measurement: the float32 builds of the
PI and the explicit NNPC are measured on an emulated Cortex-M4F (``make bench``, group ``embedded``:
``cosim.benchmark_harness.cortex_m4``), which reports the model's prediction against the measurement and
the cycles per MAC and per tanh the measurement implies.

Timing on this machine is the benchmark harness's job (``cosim.benchmark_harness``); the counts
here are deterministic, so the reproduction's report can carry them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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


def pi_operation_counts() -> dict[str, float]:
    """Operations per step of the PI (``controllers/c/pi.c``): Ki Ts e and Kp e (three multiplications, two
    additions: three MACs), the error, the clip and the anti-windup test as one candidate's bookkeeping."""
    return {"macs": 3.0, "tanh": 0.0, "sqrt": 0.0, "division": 0.0, "candidates": 1.0}


def cortex_m4f_cycles(counts: dict[str, np.ndarray], model: CostModel = CORTEX_M4F) -> np.ndarray:
    """Cycles per step of a float32 port on a Cortex-M4F under ``model`` (interrupt allowance included)."""
    return (counts["macs"] * model.mac + counts["tanh"] * model.tanh + counts["sqrt"] * model.sqrt
            + counts.get("division", 0.0) * model.division + counts["candidates"] * model.candidate + model.interrupt)
