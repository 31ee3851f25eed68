"""What a step of the C controllers costs, counted rather than timed: operations per step from the
optimizer's candidate evaluations (exact for the code paths of ``controllers/c``), and cycles on a
microcontroller from a cost model -- cycles per operation.

Where a controller has a float32 build (the PI, the explicit NNPC, the current-mode controller, the
Type-III) its cycles are *measured* on an emulated Cortex-M4F (``make bench``, group ``embedded``:
``cosim.benchmark_harness.cortex_m4``), and the model is retired for it: the group still reports the
model's prediction against the measurement, per controller, as the record of how far the model is
off (the classical controllers' steps are half bookkeeping the model prices at one candidate's 30
cycles: the model predicts about half their cycles). The model stays for the controller without a
float32 build, the online NNPC, whose cost is its candidates' network rollouts: its multiply-accumulate
and tanh constants are calibrated on the emulated Cortex-M4F (:func:`calibrated`, the same group, which
checks that the constants below still agree with the measurement).

Timing on this machine is the benchmark harness's job (``cosim.benchmark_harness``); the counts
here are deterministic, so the reproduction's report can carry them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class CostModel:
    """Cycles per operation of the float32 build on a Cortex-M4F (single-precision FPU), and where the
    figures come from."""

    clock_hz: float = 170e6
    mac: float = 6.0  # a multiply-accumulate of a dense layer, its loads and loop share included: calibrated
    # (:func:`calibrated`) on the explicit NNPC's forward pass measured on the emulated Cortex-M4F (the
    # 6-7 cycles published for MLPs on Cortex-M4 were the assumption before the measurement)
    tanh: float = 63.3  # buckc_tanhf (controllers/c/buckc_tanhf.h) inlined in a loop, with the loop's load,
    # store and branch: measured on the emulated Cortex-M4F (cortex_m4/tanh_probe.c; libm's tanhf: ~210)
    sqrt: float = 14.0  # VSQRT.F32 (ARM Cortex-M4 TRM, FPU instruction table)
    candidate: float = 30.0  # per candidate: lattice generation, clipping, compare (an assumption; the online
    # NNPC's float32 build is measured on the emulated Cortex-M4F, group embedded, against this model's prediction)
    interrupt: float = 200.0  # per control sample: ADC read, PWM update, ISR entry and exit (an allowance)
    division: float = 14.0  # VDIV.F32 (ARM Cortex-M4 TRM, FPU instruction table)


CORTEX_M4F = CostModel()


def calibrated(model: CostModel, tanh_cycles: float, forward_cycles: float, layer_macs: float,
               tanh_calls: float) -> CostModel:
    """``model`` with its network constants from a measurement: ``tanh`` = the measured cycles of one tanh
    (inlined in a loop), ``mac`` = what a forward pass of ``layer_macs`` multiply-accumulates and
    ``tanh_calls`` tanh costs (``forward_cycles``, measured) less its tanh, per multiply-accumulate."""
    if not (layer_macs > 0 and forward_cycles > tanh_calls * tanh_cycles >= 0):
        raise ValueError(f"a forward pass of {forward_cycles} cycles with {tanh_calls} tanh of {tanh_cycles} "
                         f"cycles and {layer_macs} multiply-accumulates calibrates nothing")
    return replace(model, tanh=float(tanh_cycles), mac=float((forward_cycles - tanh_calls * tanh_cycles) / layer_macs))


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


def rti_operation_counts(controller, rti_steps: np.ndarray, qp_iterations: np.ndarray,
                         evaluations: np.ndarray, reweighted: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Operations per step of a predictive controller with the real-time iteration, from the C code paths
    (``controllers/c``): where ``rti_steps`` is False the search planned (:func:`operation_counts` of its
    ``evaluations``); an RTI step does a fixed amount of work, counted at the most the code can do except
    for the box QP, whose iterations are read off the step, and the reweightings, read off the step too
    (``reweighted``: the reweighted box QPs per step; None counts the most, ``iterations`` x
    :attr:`~controllers.predictive.RtiSettings.reweightings`):

    * ``iterations`` linearisations of the NN over the horizon (``nn_model.c``, buckc_nn_sensitivities), or with
      :attr:`~controllers.predictive.RtiSettings.reuse_jacobian` one, and a rollout of each further step's trial
      over the horizon (:func:`operation_counts`' candidate);
    * without the line search (:attr:`~controllers.predictive.RtiSettings.line_search`) the plan's first
      state (one network evaluation); with it one rollout of the last trial over the horizon, and one more
      where a duty quantum may round the plan;
    * with the line search the costs of each evaluated trajectory (4 MACs and two square roots per step; without
      it none: they would decide nothing), the Gauss-Newton model
      ``iterations`` times (c (c + 1) + 3 c MACs at a step with c = block + 1 blocks it depends on -- the Hessian's
      upper triangle, mirrored, and the gradient; causality leaves the later blocks' zeros out -- one square root
      and one division per step), once more per reweighting after the linear prediction y_j + J_j delta (2 c MACs
      per step), and the box QP
      (per iteration H x, a Cholesky of at most nb x nb, two triangular solves: 2 nb^2 + nb^3 / 6 MACs and nb
      square roots).

    Per linearisation step with c = block + 1 propagated directions (hidden widths H_0..H_L-1, n_in inputs,
    D delays): the forward pass (n_in H_0 + sum H_l H_l+1 + 2 H_L-1 MACs, sum H tanh) with the slopes (one
    MAC per hidden unit), the network's Jacobian to its 3 D window inputs backwards from the two outputs
    (2 H_L-1 for the output layer's slopes, 2 H_l-1 (H_l + 1) per further layer, 2 3D H_0 for the window),
    and the state's sensitivity 2 c 2D + 2 D."""
    from controllers.predictors import NNPredictor

    if controller.rti is None or not isinstance(controller.predictor, NNPredictor):
        raise ValueError("RTI operation counts are defined for the NN predictor with the real-time iteration")
    rti_steps = np.asarray(rti_steps, dtype=bool)
    search = operation_counts(controller, np.where(rti_steps, 0, np.asarray(evaluations, dtype=float)))
    config = controller.predictor.model.config
    settings, rti = controller.settings, controller.rti
    iterations, horizon = rti.iterations, settings.horizon
    blocks = np.repeat(np.arange(len(settings.blocks)), settings.blocks)
    nb, hidden, delays = len(settings.blocks), list(config.hidden), config.delays
    widths = [config.n_inputs, *hidden, 2]
    forward = sum(a * b for a, b in zip(widths[:-1], widths[1:]))  # one network evaluation
    backward = 2 * hidden[-1] + sum(2 * a * (b + 1) for a, b in zip(hidden[:-1], hidden[1:])) + 2 * 3 * delays * hidden[0]
    macs_linearize = sum(forward + sum(hidden) + backward + 2 * int(c) * 2 * delays + 2 * delays for c in blocks + 1)
    if rti.line_search:
        rollouts = 1 + (1 if rti.duty_resolution else 0)  # the last trial's, and the rounded plan's
        steps_evaluated, trajectories = rollouts * horizon, iterations + rollouts
    else:
        steps_evaluated, trajectories = 1, 0  # the plan's first state; no costs
    linearizations = 1 if rti.reuse_jacobian else iterations
    rollouts = iterations - linearizations  # the trials of the steps that reuse the first step's sensitivities
    macs_rollout = float(operation_counts(controller, np.ones(1))["macs"][0]) - 3 * horizon  # its cost counted below
    active = blocks + 1  # the blocks each step depends on
    macs_model = float(np.sum(active * (active + 1) + 3 * active))
    sweeps = (np.full(len(rti_steps), iterations * rti.reweightings, dtype=float) if reweighted is None
              else np.asarray(reweighted, dtype=float))
    models = iterations + sweeps  # the Gauss-Newton models, the reweighted ones included
    qp = np.asarray(qp_iterations, dtype=float) * (2 * nb * nb + nb ** 3 / 6.0)
    per_step = (linearizations * macs_linearize + rollouts * macs_rollout + steps_evaluated * forward
                + models * macs_model + sweeps * 2 * float(np.sum(active)) + trajectories * 4 * horizon)
    tanh = sum(hidden)
    return {"macs": np.where(rti_steps, per_step + qp, search["macs"]),
            "tanh": np.where(rti_steps, (iterations * horizon + steps_evaluated) * tanh, search["tanh"]),
            "sqrt": np.where(rti_steps, trajectories * 2 * horizon + models * horizon + qp_iterations * nb,
                             search["sqrt"]),
            "division": np.where(rti_steps, models * horizon, 0.0),
            "candidates": np.where(rti_steps, iterations + (1 if rti.line_search else 0), search["candidates"]),
            "qp_iterations": np.where(rti_steps, np.asarray(qp_iterations, dtype=float), 0.0)}


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


def current_mode_operation_counts() -> dict[str, float]:
    """Operations per step of the current-mode controller (``controllers/c/current_mode.c``): (ki Ts) e and
    kp e in each of its two loops (six multiplications: six MACs), the feed-forward division by the supply;
    the errors, clips and anti-windup tests as one candidate's bookkeeping."""
    return {"macs": 6.0, "tanh": 0.0, "sqrt": 0.0, "division": 1.0, "candidates": 1.0}


def compensator_operation_counts(order: int) -> dict[str, float]:
    """Operations per step of a compensator of ``order`` (``controllers/c/compensator.c``): b0 e, and
    b_i e and a_i y for each of its ``order`` states (1 + 2 order MACs), the feed-forward division; the
    error, clip and anti-windup test as one candidate's bookkeeping."""
    return {"macs": 1.0 + 2.0 * order, "tanh": 0.0, "sqrt": 0.0, "division": 1.0, "candidates": 1.0}


def cortex_m4f_cycles(counts: dict[str, np.ndarray], model: CostModel = CORTEX_M4F) -> np.ndarray:
    """Cycles per step of a float32 port on a Cortex-M4F under ``model`` (interrupt allowance included)."""
    return (counts["macs"] * model.mac + counts["tanh"] * model.tanh + counts["sqrt"] * model.sqrt
            + counts.get("division", 0.0) * model.division + counts["candidates"] * model.candidate + model.interrupt)
