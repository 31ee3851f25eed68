"""Receding-horizon predictive control: one optimizer for the NNPC and every MPC baseline.

Cost (paper eq. 16 and 23): for a candidate duty sequence over the horizon N,

    J = sum_{j=1..N} gamma^(j-1) * sqrt((vo(k+j) - vref)^2 + (iL(k+j) - iref)^2)

with iref = vref / R the steady-state inductor current for vref at the load R, estimated from
the sensors by :func:`controllers.load_estimate.estimate_conductance` (io / vo, or iL / vo
without a load-current sensor).

Optimizer (:class:`HorizonOptimizer`): the duty is held over blocks of the horizon (move
blocking), so a candidate is a few block values. All candidates of a stage are evaluated in one
batched array pass of the predictor: a grid of constant sequences, a grid of first moves followed
by the steady-state duty, bang-bang openings (full or zero duty for the first blocks), and the
previous solution shifted by one sample (warm start); then a batched pattern search refines the
best candidate block by block with a shrinking step.

Real-time iteration (:class:`RealTimeIteration`, :class:`RtiSettings`; the study's default at both rates, its
settings per rate in ``cosim.design.experiments.rti_settings``): instead of searching, a fixed number of Gauss-Newton steps on the
blocked duties from the previous solution shifted by one sample, each a small box-constrained QP
(:mod:`controllers.box_qp`) built from the predictor's forward sensitivities
(:meth:`~controllers.predictors.Predictor.linearize`). Eq. 16 sums *non-squared* norms, which have
a kink at zero error; the RTI minimises the smoothed norm sqrt(|e|^2 + eps^2) (eps in volts,
:attr:`RtiSettings.smoothing`), while the cost it reports -- and the study's comparison -- is always
the paper's exact one. The search above stays as the reference and as the fallback at a cold start,
through the start-up's large error and a reference step's transient, at any sample far off the reference (a guard
where the model extrapolates), and when the measurements show a large change (a reference or load step, a prediction error far outside the model's), where one step from the last plan cannot
reach the new optimum or the model is poor (:meth:`PredictiveController.fallback_reason`).

Offset-free tracking: the model's one-step prediction made at k-1 for the applied duty is
compared with the measurement at k; the difference (a state-disturbance estimate, optionally
low-pass filtered) is added to every predicted state before it is fed back. The measured steady
state is then a fixed point of the corrected model over the whole horizon, so a model error does
not leave a steady-state error.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

from controllers.base import Measurement, check_duty_limits, check_sample_period
from controllers.box_qp import MAX_VARIABLES, solve_box_qp
from controllers.load_estimate import estimate_conductance
from controllers.predictors import PredictionContext, Predictor


def doubling_blocks(horizon: int) -> tuple[int, ...]:
    """Block lengths 1, 1, 2, 4, ... summing to ``horizon`` (fine early moves, coarse late ones)."""
    blocks, total, size = [], 0, 1
    while total < horizon:
        step = min(size, horizon - total)
        blocks.append(step)
        total += step
        if len(blocks) >= 2:
            size *= 2
    return tuple(blocks)


@dataclass(frozen=True)
class HorizonSettings:
    horizon: int = 3  # prediction steps N
    blocks: tuple[int, ...] | None = None  # move blocking; default doubling_blocks(horizon)
    discount: float = 0.95  # gamma of eq. 16
    levels: int = 21  # grid points per block in the first stage (full grid if few blocks)
    refine_iterations: int = 8  # at most this many refinement passes after the first stage
    duty_tolerance: float = 1e-4  # stop zooming once the lattice step is this fine
    bias_filter: float = 0.5  # weight of the newest disturbance estimate (1 = no filtering, 0 = no estimate:
    # the controller is then not offset-free, like the paper's MPC)

    def __post_init__(self):
        if self.horizon < 1:
            raise ValueError(f"horizon = {self.horizon} is invalid: expected >= 1")
        blocks = self.blocks or doubling_blocks(self.horizon)
        if sum(blocks) != self.horizon or min(blocks) < 1:
            raise ValueError(f"blocks {blocks} are invalid: expected positive lengths summing to the horizon {self.horizon}")
        object.__setattr__(self, "blocks", tuple(blocks))
        if not 0 < self.discount <= 1:
            raise ValueError(f"discount = {self.discount} is invalid: expected 0 < gamma <= 1")
        if self.levels < 2 or self.refine_iterations < 0:
            raise ValueError("levels must be >= 2 and refine_iterations >= 0")
        if not 0 <= self.bias_filter <= 1:
            raise ValueError(f"bias_filter = {self.bias_filter} is invalid: expected 0 <= alpha <= 1")


#: a full grid/lattice over the blocks is used while it has at most this many points
FULL_GRID_LIMIT = 128


class HorizonOptimizer:
    """Minimise a batched cost over block-held duty sequences within duty limits.

    Stage 1 (one batched evaluation): a fine lattice around the previous solution shifted by one
    sample (warm start) and a global search -- the full grid over all blocks when that is small,
    else constant sequences (coarse, and finely around the last move, so a warm start that merely
    reproduces itself cannot hold the output off its reference), a grid over the first move
    and a coarse one over the first two (then the steady-state duty), and bang-bang profiles
    (accelerate, brake, hold).
    Then refinement passes, each one batched evaluation around the best:
    * few blocks: a full lattice of offsets -h..h steps per block (33 points for one block, so two
      passes zoom from the grid to 1e-4; 11 per block for two, 5 for three), the step shrinking by
      2h per pass so each lattice spans the previous cell;
    * many blocks: a pattern search (moves of -4..4 steps along each block, one step along each
      pair of blocks in all four sign combinations, and 1, 2, 4 or 8 steps of all blocks together)
      from a step of 1/8 of the duty range, divided by three per pass.
    Refinement starts from the warm lattice's fine step when the warm start won stage 1, so steady
    operation needs few passes; passes stop at ``duty_tolerance`` or after ``refine_iterations``.
    """

    def __init__(self, settings: HorizonSettings, duty_limits: tuple[float, float]):
        self.settings = settings
        self.low, self.high = duty_limits
        self.blocks = np.array(settings.blocks)
        nb = self.n_blocks = len(settings.blocks)
        self.block_starts = np.concatenate([[0], np.cumsum(self.blocks)[:-1]])
        self._unblocked = bool(np.all(self.blocks == 1))
        self.passes = 0
        levels = settings.levels
        self.spacing = (self.high - self.low) / (levels - 1)
        grid = np.linspace(self.low, self.high, levels)
        self._grid = grid
        if levels ** nb <= FULL_GRID_LIMIT * 4:
            mesh = np.meshgrid(*[grid] * nb, indexing="ij")
            self._global = np.stack([g.ravel() for g in mesh], axis=1)
            self._global_is_full = True
        else:
            self._global = np.repeat(grid[:, None], nb, axis=1)  # constant sequences
            self._global_is_full = False
        # zoom lattice: the most points per block (odd, at most 33) a full lattice can afford;
        # offsets -h..h steps, and the step shrinks by 2h so each lattice spans the previous cell
        per_axis = max((p for p in range(3, 34, 2) if p ** nb <= FULL_GRID_LIMIT), default=0)
        if per_axis:
            half = (per_axis - 1) // 2
            offsets = np.arange(-half, half + 1, dtype=float)
            mesh = np.meshgrid(*[offsets] * nb, indexing="ij")
            self._lattice = np.stack([g.ravel() for g in mesh], axis=1)
            self._shrink = float(2 * half)
            self._full_lattice = True
        else:  # many blocks: a 9-point line along each block, pairs of blocks, all blocks together
            eye = np.eye(nb)
            moves = [np.zeros((1, nb))] + [v * eye for v in np.arange(-4.0, 5.0) if v]
            for i in range(nb):
                for j in range(i + 1, nb):
                    for a, b in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                        row = np.zeros((1, nb))
                        row[0, i], row[0, j] = a, b
                        moves.append(row)
            moves += [v * np.ones((1, nb)) for v in (-8.0, -4.0, -2.0, -1.0, 1.0, 2.0, 4.0, 8.0)]
            self._lattice = np.vstack(moves)
            self._shrink = 3.0
            self._full_lattice = False
        self.evaluations = 0
        self._near_offsets = self.spacing / 20 * np.arange(-10.0, 11.0)  # +-half a grid cell
        # the warm lattice spans about one tenth of a grid cell around the previous solution
        self.warm_step = self.spacing / (10 * self._shrink)
        self.warm_span = self.warm_step * float(np.max(np.abs(self._lattice)))
        self._warm_offsets = self.warm_step * self._lattice
        if self._global_is_full:
            self._stage_buffer = np.vstack([np.zeros_like(self._lattice), self._global])

    def _clip(self, duties: np.ndarray) -> np.ndarray:
        """Clip to the duty limits in place (two ufuncs: np.clip's dispatch costs more at this size)."""
        np.maximum(duties, self.low, out=duties)
        return np.minimum(duties, self.high, out=duties)

    def expand(self, moves: np.ndarray) -> np.ndarray:
        """Block values (K, blocks) -> per-step duties (K, horizon)."""
        return moves if self._unblocked else np.repeat(moves, self.blocks, axis=1)

    def first_stage(self, warm: np.ndarray | None, anchor: float) -> tuple[np.ndarray, int]:
        """Stage-1 candidates and how many of them (leading) form the warm-start lattice."""
        anchor = min(max(anchor, self.low), self.high)
        self._warm_center = None
        if self._global_is_full:  # a preallocated buffer: [warm lattice | global grid]
            if warm is None:
                return self._global, 0
            buffer = self._stage_buffer
            n_warm = len(self._lattice)
            center = np.concatenate([warm[1:], warm[-1:]])[self.block_starts]
            self._warm_center = center
            np.add(center, self._warm_offsets, out=buffer[:n_warm])
            self._clip(buffer[:n_warm])
            return buffer, n_warm
        candidates, n_warm = [], 0
        if warm is not None:  # first, so that ties go to the warm start
            shifted = np.concatenate([warm[1:], warm[-1:]])[self.block_starts]
            self._warm_center = shifted
            lattice = self._clip(shifted[None, :] + self._warm_offsets)
            candidates.append(lattice)
            n_warm = len(lattice)
            # constant sequences finely around the last move: when a model error shifts the
            # steady-state duty between grid points, a warm start that merely reproduces itself
            # must not keep the output off its reference
            near = self._clip(warm[0] + self._near_offsets)
            candidates.append(np.repeat(near[:, None], self.n_blocks, axis=1))
        candidates.append(self._global)
        candidates.append(self._openings(anchor))
        return np.vstack(candidates), n_warm


    def _openings(self, anchor: float) -> np.ndarray:
        """Structured sequences for long horizons, each ending at the steady-state duty ``anchor``:
        a grid over the first move, a coarse grid over the first two, and bang-bang profiles
        (full or zero duty for some blocks, then the opposite for some, then the anchor)."""
        nb, grid = self.n_blocks, self._grid
        rows = []
        first = np.full((len(grid), nb), anchor)
        first[:, 0] = grid
        rows.append(first)
        if nb >= 2:  # one block (a grid too fine for the full mesh) has no second move
            coarse = np.linspace(self.low, self.high, 5)
            pairs = np.full((25, nb), anchor)
            pairs[:, 0] = np.repeat(coarse, 5)
            pairs[:, 1] = np.tile(coarse, 5)
            rows.append(pairs)
        for a, b in ((self.high, self.low), (self.low, self.high)):
            for j in range(1, nb):
                for m in range(0, nb - j):
                    row = np.full(nb, anchor)
                    row[:j] = a
                    row[j:j + m] = b
                    rows.append(row[None, :])
        return np.vstack(rows)

    def solve(self, cost: Callable[[np.ndarray], np.ndarray], warm: np.ndarray | None = None,
              anchor: float = 0.5) -> tuple[np.ndarray, float]:
        """Return the best per-step duty sequence (horizon,) and its cost.

        :attr:`best_location` tells which call of ``cost`` (0-based) and which row produced it.
        """
        candidates, n_warm = self.first_stage(warm, anchor)
        costs = cost(self.expand(candidates))
        self.evaluations = len(candidates)
        self.passes = 1
        index = int(costs.argmin())
        best, best_cost = candidates[index].copy(), float(costs[index])
        self.best_location = (0, index)
        # strictly inside the warm lattice: on its edge the optimum may lie further out
        near_warm = n_warm and abs(best - self._warm_center).max() < self.warm_span - 0.5 * self.warm_step
        if near_warm:  # the best lies where the warm lattice already looked: refine from its fine step
            step = self.warm_step / self._shrink
        else:
            step = self.spacing / self._shrink if self._full_lattice else (self.high - self.low) / 8
        for _ in range(self.settings.refine_iterations):
            if step < self.settings.duty_tolerance:
                break
            trial = self._clip(best[None, :] + step * self._lattice)
            trial_costs = cost(self.expand(trial))
            self.evaluations += len(trial)
            self.passes += 1
            index = int(trial_costs.argmin())
            if trial_costs[index] < best_cost:
                best, best_cost = trial[index].copy(), float(trial_costs[index])
                self.best_location = (self.passes - 1, index)
            step /= self._shrink
        return self.expand(best[None, :])[0], best_cost


#: an RTI step is taken when its smoothed cost is at most this factor of the current plan's: "not higher"
#: up to rounding, so that the C twin, whose arithmetic differs from numpy's in the last bits, takes the same
#: decision on the ~1e-10 steps of a converged plan (with a strict comparison they flipped at random)
ACCEPT_TOLERANCE = 1.0 + 1e-12


#: the most box-QP iterations an RTI step may be given (RtiSettings.qp_iterations): far above the few per variable a
#: strictly convex box QP needs (at most 8 variables), and within the C twins' int
MAX_QP_ITERATIONS = 10_000


@dataclass(frozen=True)
class RtiSettings:
    """The real-time-iteration optimizer (:class:`RealTimeIteration`) and when the controller falls back
    to the search (:class:`HorizonOptimizer`) instead."""

    iterations: int = 1  # Gauss-Newton steps per sample, fixed (1..3): the step's cost is bounded and known. One step
    # is what fits a switching period in C; undamped, with the envelope-identified 8-10-2 networks, it missed the
    # quality targets at 13.33 us (2.8 x the search's IAE at worst): the study's one step is damped and hands the
    # start-up over late (cosim.design.experiments.SWITCHING_PERIOD_RTI)
    line_search: bool = False  # roll each trial out and take it only if its smoothed cost is not higher (else the
    # trust region shrinks); False takes every step, as acados' SQP-RTI does, and the plan's states are not rolled
    # out past the first (the step's cost: one linearisation). The reweighted model majorises the linearised cost,
    # and on the study's runs no trial was ever rejected (0 of every 13.33 us RTI step of the evaluation and of the
    # benchmark's mixed scenario), so the rollout bought nothing for a third of the step's time
    reuse_jacobian: bool = False  # the steps after the first keep the first step's sensitivities and re-evaluate
    # only the predicted trajectory at the new plan (a rollout: no sensitivities), as a simplified Newton method does
    reweightings: int = 0  # after each step's box QP, at most this many more on the same linearisation (0..3): the
    # weights w_j / s_j recomputed at the linear model's errors e_j + J_j delta, the QP solved again from there --
    # Weiszfeld's iteration carried on the linearised (convex) cost, which one QP only starts: the subproblem solved
    # closer to its optimum for a box QP and a Hessian each, no rollout and no new linearisation
    reweighting_tolerance: float = 0.0  # [duty] ... but none once the last QP moved no block by more than this (0: all
    # of them, always), as an active-set QP stops when no bound changes: near the reference the first QP's step is
    # tiny and the step costs what it did without; in a transient the subproblem is solved further
    smoothing: float = 0.05  # eps [V] of the smoothed norm sqrt(|e|^2 + eps^2) that stands in for |e| (eq. 16)
    step_limit: float = 0.25  # trust region: the most a block's duty moves in one step (/4 after a rejected step)
    regularization: float = 1e-6  # Levenberg-Marquardt: mu = this x mean(diag H) (+ 1e-12) added to H's diagonal
    move_damping: float = 0.0  # rho: each step's quadratic model adds (rho x mean(diag H) / 2) (u_0 - d_prev)^2, a
    # proximal term that pulls the first block (the duty applied next) toward the duty applied last sample (0: none).
    # Unlike the Levenberg-Marquardt term, which damps the step from the shifted plan and so lags every transient,
    # it only prices the applied move: it stops the sample-to-sample alternation of the first two 1-sample blocks
    # that a model identified from PI data invites at 13.33 us (a period-2 limit cycle, see
    # cosim.design.experiments.SWITCHING_PERIOD_RTI). It is not in eq. 16: the plan cost the ablation reports stays
    # eq. 16's
    qp_iterations: int = 24  # the box QP's active-set iterations, at most (controllers.box_qp)
    # fall back to the search (besides a cold start) when the reference moves more than reference_step [V], the
    # load-conductance estimate more than the fraction load_step, or the measured vo lands more than innovation [V]
    # from the one-step prediction (with its bias); 0 = never. Measured on the study's 13.33 us runs (seed 0):
    # without the reference-step fallback the reference step up ended at 1.04-1.06 x the search's IAE (the NNPC
    # and the mismatched MPC on the nominal averaged plant, the oracle MPC on the switched one), with it at
    # 0.93-1.00 x; the load-step one never fired (the period-mean load current splits a step over two samples
    # of about half the change each) and the prediction-error one fired at most samples of a poor model (the
    # paper's 3-7-2 network at 13.33 us), so both are off. A search step costs 0.1-3 ms in C: each reference
    # change costs one such step.
    reference_step: float = 0.5
    load_step: float = 0.0
    innovation: float = 0.0
    # [V] after a cold start, the search plans until the measured |vref - vo| first falls to this (0: the cold start's
    # sample only). Without it the start-up at 13.33 us overshot up to 23 points more than the search's (nominal
    # switched plant, seed 2; +1.4 averaged, +7.3 the mismatched MPC on the mismatch plant): the RTI's plan is
    # better on the model (its eq. 16 cost 15 against the search's 21 at the second sample there) but a model
    # identified from PI data is poor in the start-up's fast transient, and the search's coarse plan overshoots
    # less. With it, 4-10 samples of each start-up are planned by the search, and none of the rest. (Under an
    # error_region at most this wide the guard would plan those samples anyway: this then only names them, so the
    # fallback counts tell the start-up from the guard.) The study's one-step RTI at 13.33 us takes 0.1 V: handed
    # over at the 0.5 V guard, its one step lagged the last of the rise (+0.72 overshoot points over the search's on
    # the mismatch plant's seed-0 network), from 0.1 V on it overshoots as the search does
    startup_region: float = 1.0
    # [V] the search plans any sample whose measured |vref - vo| exceeds this (0: never) -- a guard, not a transient
    # rule: where the network extrapolates (light loads in DCM, far from its PI data) its tanh units saturate, its
    # Jacobian vanishes and a Gauss-Newton step stays where the shifted plan was, while the search's candidates still
    # tell duties apart. Without it, on the envelope map at 13.33 us, the RTI held the duty while the output rose from
    # 3 V to 12.9 V (3 V / 100 Ohm / 36 V; the search: 3.00 V), 12 of 150 runs above 4 x the search's IAE. It also
    # carries a reference step's transient, a start-up in small: with the step's sample alone (reference_step), the
    # two-step damped RTI at 13.33 us overshot the step up by 14-31 points more than the search (mismatch switched
    # plant, seed 4; 1.02-1.09 x its IAE); with the search through the transient until within 1 V, 0.98 x. The
    # guard does that for any step larger than itself, and any other large error alike
    error_region: float = 0.0
    # duty quantum: the plan's blocks are rounded to multiples of it (0: not rounded); at 1 ms the study sets the
    # search's finest step, so both optimizers command duties on the same lattice (a 13-bit DPWM). Without it the
    # RTI's exact optimum differs from the search's lattice point by < 1e-4 (< 5 mV of output), which decided the
    # IAE ratio where the IAE is that small (cosim.design.experiments.rti_settings)
    duty_resolution: float = 0.0

    def __post_init__(self):
        if not 1 <= self.iterations <= 3:
            raise ValueError(f"RTI iterations = {self.iterations} is invalid: expected 1, 2 or 3 (a fixed count per sample)")
        if not (self.smoothing > 0 and math.isfinite(self.smoothing)):
            raise ValueError(f"RTI smoothing = {self.smoothing} is invalid: expected eps > 0 [V]")
        if not 0 < self.step_limit <= 1:
            raise ValueError(f"RTI step_limit = {self.step_limit} is invalid: expected 0 < limit <= 1 (duty)")
        if not 0 <= self.regularization < 1:
            raise ValueError(f"RTI regularization = {self.regularization} is invalid: expected 0 <= mu < 1")
        if not (0 <= self.move_damping < 1):
            raise ValueError(f"RTI move_damping = {self.move_damping} is invalid: expected 0 <= rho < 1 (x mean(diag H))")
        if not 1 <= self.qp_iterations <= MAX_QP_ITERATIONS:
            raise ValueError(f"RTI qp_iterations = {self.qp_iterations} is invalid: expected 1 .. {MAX_QP_ITERATIONS} "
                             "(a bound on the box QP's active-set iterations; it needs a few per variable)")
        if not 0 <= self.reweightings <= 3:
            raise ValueError(f"RTI reweightings = {self.reweightings} is invalid: expected 0, 1, 2 or 3 (at most, per "
                             "step)")
        if self.reweightings and self.line_search:
            raise ValueError(f"RTI reweightings = {self.reweightings} with line_search is refused: expected 0 with the "
                             "line search (a rejected trial's step keeps its model, not the linearisation to reweight)")
        if not (0 <= self.reweighting_tolerance < 1):
            raise ValueError(f"RTI reweighting_tolerance = {self.reweighting_tolerance} is invalid: expected 0 <= "
                             "tolerance < 1 (duty; 0: every reweighting)")
        for name in ("reference_step", "load_step", "innovation", "startup_region", "error_region"):
            if not (getattr(self, name) >= 0 and math.isfinite(getattr(self, name))):
                raise ValueError(f"RTI {name} = {getattr(self, name)} is invalid: expected a finite value >= 0 "
                                 "(0: never)")
        if not (0 <= self.duty_resolution < 1):
            raise ValueError(f"RTI duty_resolution = {self.duty_resolution} is invalid: expected 0 <= quantum < 1 "
                             "(0: not rounded)")


class RealTimeIteration:
    """A fixed number of Gauss-Newton steps on the blocked duties (real-time iteration, as acados'
    SQP-RTI: one linearisation per step, no inner convergence loop).

    Per sample: u = the previous solution shifted by one sample, at the block starts (as the search's
    warm start). Each step linearises the predictor's rollout at u (states y_j and their Jacobian
    J_j to the blocks, :meth:`~controllers.predictors.Predictor.linearize`) and minimises a quadratic
    model of the smoothed cost sum_j w_j s_j, s_j = sqrt(|e_j|^2 + eps^2), e_j = y_j - target:

        gradient  g = sum_j (w_j / s_j) J_j' e_j             (exact, of the linearised cost)
        Hessian   H = sum_j (w_j / s_j) J_j' J_j + mu I     (iteratively reweighted least squares)

    plus, with :attr:`RtiSettings.move_damping` rho, the proximal term (rho m / 2) (u_0 + delta_0 - d_prev)^2
    on the first block (m: mean(diag H) before mu; d_prev: the duty applied at the previous sample),

    over the box max(low - u, -r) <= delta <= min(high - u, r) (duty limits and a trust region r,
    :mod:`controllers.box_qp`). The reweighted Hessian is the curvature of the quadratic that touches
    each norm from above at the current errors (majorise-minimise, Weiszfeld's iteration for sums of
    norms): a step never overshoots the linearised cost. The exact Hessian of the smoothed norm (the
    generalized Gauss-Newton one) has curvature only eps^2 / s^3 along an error much larger than eps,
    so its steps ran to the trust region and were rejected: on the study's nominal switched NNPC at
    13.33 us it gave 1.27-27.6 x the search's IAE where this gives 0.85-0.99 x.

    One such QP is one Weiszfeld iteration on the linearised cost, which is convex: with
    :attr:`RtiSettings.reweightings` k, each step's QP is followed by k more on the same linearisation,
    the weights and the gradient taken at the linear model's errors e_j + J_j delta (delta the step so far)
    and the box shifted by delta, each a majorise-minimise step that does not raise the linearised cost --
    the subproblem solved closer to its optimum (as an SQP-RTI solves its QP to convergence) for k more box
    QPs and Hessians, no rollout.

    Without a line search (:attr:`RtiSettings.line_search`, the default) every step is taken, and the
    last one is not rolled out: only the plan's first state is predicted (the disturbance estimate
    needs it), so ``iterations`` steps cost ``iterations`` linearisations, ``iterations`` x (1 +
    ``reweightings``) box QPs and one network evaluation, and the plan's exact cost is not known in the step (NaN;
    :meth:`PredictiveController.cost` evaluates it for the ablation). With the line search each trial
    u + delta is evaluated (rolled out) and replaces u only if its smoothed cost is not higher, else
    the trust region shrinks by 4 -- the plan applied is then never predicted worse than the shifted
    warm start, for one more rollout per step. Either way a step's work is bounded and known.

    With :attr:`RtiSettings.duty_resolution` the plan's blocks are finally rounded to its multiples
    (floor(u / q + 1/2) q), and the rounded plan is evaluated as above.
    """

    def __init__(self, settings: RtiSettings, horizon: HorizonSettings, duty_limits: tuple[float, float],
                 weights: np.ndarray):
        self.settings = settings
        self.low, self.high = duty_limits
        self.blocks = np.array(horizon.blocks)
        self.n_blocks = len(horizon.blocks)
        if self.n_blocks > MAX_VARIABLES:
            raise ValueError(f"the RTI optimizer takes at most {MAX_VARIABLES} move blocks (its box QP's fixed size); "
                             f"blocks {horizon.blocks} are {self.n_blocks}")
        self.block_of_step = np.repeat(np.arange(self.n_blocks), self.blocks)
        self.block_starts = np.concatenate([[0], np.cumsum(self.blocks)[:-1]]).astype(int)
        self.horizon = horizon.horizon
        self.weights = np.asarray(weights, dtype=float)
        # diagnostics of the last solve
        self.qp_iterations = 0
        self.accepted = 0
        self.reweighted = 0  # box QPs of the reweightings
        self.smoothed_cost = math.nan

    def shifted(self, warm: np.ndarray) -> np.ndarray:
        """The previous per-step solution shifted by one sample, at the block starts, within the limits."""
        center = np.concatenate([warm[1:], warm[-1:]])[self.block_starts]
        return np.minimum(np.maximum(center, self.low), self.high)

    def expand(self, moves: np.ndarray) -> np.ndarray:
        return moves[self.block_of_step]

    def costs(self, predicted: np.ndarray, target: np.ndarray) -> tuple[float, float]:
        """(smoothed, exact eq. 16) cost of one predicted trajectory (N, 2)."""
        e = predicted - target
        squared = e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1]
        eps = self.settings.smoothing
        return float(np.sqrt(squared + eps * eps) @ self.weights), float(np.sqrt(squared) @ self.weights)

    def model(self, predicted: np.ndarray, jacobian: np.ndarray, target: np.ndarray,
              first_move: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Gradient (nb,) and regularised (generalized) Gauss-Newton Hessian (nb, nb) of the smoothed cost;
        ``first_move``: u_0 - d_prev [duty], the current plan's first block less the duty applied last sample
        (priced with :attr:`RtiSettings.move_damping`)."""
        e = predicted - target
        eps = self.settings.smoothing
        s = np.sqrt(e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1] + eps * eps)
        c = self.weights / s
        q = jacobian[:, 0, :] * e[:, 0:1] + jacobian[:, 1, :] * e[:, 1:2]  # J_j' e_j, (N, nb)
        gradient = q.T @ c
        hessian = np.einsum("j,jca,jcb->ab", c, jacobian, jacobian)
        mean_diagonal = float(np.trace(hessian)) / self.n_blocks
        hessian[np.diag_indices(self.n_blocks)] += self.settings.regularization * mean_diagonal + 1e-12
        if self.settings.move_damping:
            rho = self.settings.move_damping * mean_diagonal
            hessian[0, 0] += rho
            gradient[0] += rho * first_move
        return gradient, hessian

    def solve(self, linearize: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
              evaluate: Callable[[np.ndarray], np.ndarray], target: np.ndarray,
              warm: np.ndarray, applied: float) -> tuple[np.ndarray, float, np.ndarray]:
        """Return the per-step plan (horizon,), its exact eq. 16 cost (NaN where it was not rolled out) and
        its predicted first state (2,); ``applied``: the duty applied at the previous sample.

        ``linearize(duties)`` -> (states (N, 2), Jacobian (N, 2, blocks)); ``evaluate(duties)`` -> the states
        (len(duties), 2) of a sequence (the plan, or its first step alone)."""
        st = self.settings
        u = self.shifted(warm)
        predicted, jacobian = linearize(self.expand(u))
        smoothed, exact = self.costs(predicted, target)
        gradient, hessian = self.model(predicted, jacobian, target, u[0] - applied)
        radius = st.step_limit
        self.qp_iterations = self.accepted = self.reweighted = 0
        rolled_out = True  # whether `predicted` is u's rollout
        for iteration in range(st.iterations):
            lower = np.maximum(self.low - u, -radius)
            upper = np.minimum(self.high - u, radius)
            delta, used, _ = solve_box_qp(hessian, gradient, lower, upper, st.qp_iterations)
            self.qp_iterations += used
            delta = last = np.array(delta)
            for _ in range(st.reweightings):  # the same linearisation, reweighted at its predicted errors
                if np.max(np.abs(last)) <= st.reweighting_tolerance:
                    break
                self.reweighted += 1
                linear = predicted.copy()
                for block in range(self.n_blocks):  # block by block, in the C twin's order (no BLAS kernel)
                    linear += jacobian[:, :, block] * delta[block]
                gradient, hessian = self.model(linear, jacobian, target, u[0] + delta[0] - applied)
                step, used, _ = solve_box_qp(hessian, gradient, lower - delta, upper - delta, st.qp_iterations)
                self.qp_iterations += used
                last = np.array(step)
                delta = delta + last
            trial = np.minimum(np.maximum(u + delta, self.low), self.high)
            final = iteration + 1 == st.iterations
            if final and not st.line_search:  # taken unevaluated
                u, rolled_out = trial, False
                self.accepted += 1
                break
            if final:
                trial_predicted, trial_jacobian = evaluate(self.expand(trial)), None
            elif st.reuse_jacobian:
                trial_predicted, trial_jacobian = evaluate(self.expand(trial)), jacobian
            else:
                trial_predicted, trial_jacobian = linearize(self.expand(trial))
            trial_smoothed, trial_exact = self.costs(trial_predicted, target)
            if not st.line_search or trial_smoothed <= smoothed * ACCEPT_TOLERANCE:
                u, predicted, smoothed, exact = trial, trial_predicted, trial_smoothed, trial_exact
                self.accepted += 1
                if not final:  # the next step's linearisation (the reweightings' too)
                    jacobian = trial_jacobian
                    gradient, hessian = self.model(predicted, jacobian, target, u[0] - applied)
            else:
                radius *= 0.25
        if st.duty_resolution:
            q = st.duty_resolution
            rounded = np.minimum(np.maximum(np.floor(u / q + 0.5) * q, self.low), self.high)
            if np.any(rounded != u):
                u, rolled_out = rounded, False
        if not rolled_out:
            if st.line_search:  # the plan's cost stays known, as the line search's plans' are
                predicted = evaluate(self.expand(u))
                smoothed, exact = self.costs(predicted, target)
            else:
                predicted = evaluate(self.expand(u)[:1])
                smoothed = exact = math.nan
        self.smoothed_cost = smoothed
        return self.expand(u), exact, predicted[0].copy()


class PredictiveController:
    """Receding-horizon controller on any :class:`Predictor` (NNPC, oracle MPC, mismatched MPC)."""

    def __init__(self, predictor: Predictor, sample_period: float, settings: HorizonSettings = HorizonSettings(),
                 duty_limits: tuple[float, float] = (0.0, 1.0), name: str = "NNPC", *,
                 nominal_load: float, nominal_input_voltage: float, rti: RtiSettings | None = None):
        """``nominal_load`` [Ohm] is the load assumed until the sensors give an estimate;
        ``nominal_input_voltage`` [V] stands in for a supply voltage the measurement lacks; ``rti``:
        the real-time-iteration optimizer's settings (None: the search at every sample)."""
        self.predictor = predictor
        self.sample_period = check_sample_period(sample_period, name)
        self.duty_limits = check_duty_limits(duty_limits, name)
        self.settings = settings
        self.name = name
        self.nominal_load = nominal_load
        self.nominal_input_voltage = nominal_input_voltage
        self.optimizer = HorizonOptimizer(settings, self.duty_limits)
        weights = settings.discount ** np.arange(settings.horizon)
        self._weights = weights
        self.rti = rti
        self.rti_optimizer = None if rti is None else RealTimeIteration(rti, settings, self.duty_limits, weights)
        self.reset()

    def reset(self) -> None:
        """Start over as a fresh controller: the predictor's cached matrices are forgotten too (an entry is
        made from the first load estimate rounding to its key, so a duty would depend on the run before)."""
        self.predictor.clear_cache()
        self._history = None  # (delays, 3)
        self._warm = None
        self._bias = np.zeros(2)
        self._predicted = None  # one-step prediction made at the previous sample (without bias)
        self._previous_duty = 0.0
        self._conductance = 1.0 / self.nominal_load  # [S] the load estimate
        self._previous_reference = math.nan
        self._starting = True  # in the start-up region (RtiSettings.startup_region) since the cold start
        self._problem = None  # (context, target, disturbance, anchor, warm start) of the last step
        self.last_solver = ""  # "search" or "rti": which optimizer planned the last step
        self.last_fallback = ""  # why the last step used the search with an RTI configured ("" if it did not)
        self.best_cost = math.nan  # eq. 16 cost of the last plan (exact, not smoothed; NaN where the RTI did not
        # roll its plan out: cost() evaluates it)

    def fallback_reason(self, reference: float, voltage: float, conductance: float, previous_conductance: float,
                        surprise: float) -> str:
        """Why this sample needs the search rather than an RTI step from the last plan ("" if it does not):
        no plan yet (a cold start: the search's global candidates find the start-up's bang-bang plan); the
        start-up, until the measured output ``voltage`` first comes within ``startup_region`` volts of the
        reference (the RTI would follow a model that is poor in that transient, see :class:`RtiSettings`); at any
        sample where it is more than ``error_region`` volts off (a guard where the model extrapolates); or,
        where :class:`RtiSettings` enables them, the measurements show a change one Gauss-Newton step might
        not follow -- the reference moved by more than ``reference_step`` volts, the load-conductance estimate
        by more than the fraction ``load_step``, or the output voltage landed more than ``innovation`` volts
        from the model's one-step prediction (``surprise``, its disturbance estimate included)."""
        st = self.rti
        if self._warm is None:
            return "cold start"
        if self._starting and st.startup_region and abs(reference - voltage) > st.startup_region:
            return "start-up"
        if st.error_region and abs(reference - voltage) > st.error_region:
            return "large error"
        if st.reference_step and abs(reference - self._previous_reference) > st.reference_step:
            return "reference step"
        if st.load_step and abs(conductance - previous_conductance) > st.load_step * previous_conductance:
            return "load step"
        if st.innovation and surprise > st.innovation:
            return "prediction error"
        return ""

    def step(self, m: Measurement) -> float:
        if not math.isfinite(m.inductor_current):
            raise ValueError(f"{self.name} needs the inductor current: the plant binding has no inductor_current role")
        current, voltage = m.inductor_current, m.output_voltage
        delays = self.predictor.delays
        row = (current, voltage, 0.0)
        if self._history is None:
            self._history = np.repeat(np.array([row]), delays, axis=0)
            self._history[:, 2] = self._previous_duty
        else:
            if delays > 1:
                self._history[1:] = self._history[:-1].copy()
                self._history[1, 2] = self._previous_duty  # the duty applied after that sample
            self._history[0] = row
        surprise = 0.0
        if self._predicted is not None:  # in floats: numpy's per-call cost dominates on 2-vectors
            alpha = self.settings.bias_filter
            (b_current, b_voltage), (p_current, p_voltage) = self._bias.tolist(), self._predicted.tolist()
            surprise = abs(voltage - (p_voltage + b_voltage))
            self._bias = np.array([(1 - alpha) * b_current + alpha * (current - p_current),
                                   (1 - alpha) * b_voltage + alpha * (voltage - p_voltage)])
        previous_conductance = self._conductance
        conductance = self._conductance = estimate_conductance(m.output_voltage, m.load_current, m.inductor_current,
                                                               self._conductance)
        reference = m.reference
        current_reference = reference * conductance
        context = PredictionContext(history=self._history, input_voltage=m.input_voltage if math.isfinite(m.input_voltage)
                                    else self.nominal_input_voltage, load_resistance=1.0 / conductance,
                                    load_conductance=conductance, load_current=m.load_current,
                                    previous_duty=self._previous_duty)
        target = np.array([current_reference, reference])
        disturbance = self._bias
        anchor = reference / context.input_voltage if context.input_voltage > 0 else self._previous_duty
        self._problem = (context, target, disturbance.copy(), anchor, self._warm)
        fallback = "" if self.rti is None else self.fallback_reason(reference, voltage, conductance,
                                                                     previous_conductance, surprise)
        if fallback not in ("cold start", "start-up"):
            self._starting = False
        self._previous_reference = reference
        sequence, self.best_cost, first, self.last_solver = self.plan(context, target, disturbance, anchor, fallback)
        self._predicted = first - disturbance  # the model's own one-step prediction (the disturbance is added after each step)
        self.last_fallback = fallback
        duty = float(sequence[0])
        self._warm = sequence
        self._previous_duty = duty
        return duty

    def plan(self, context: PredictionContext, target: np.ndarray, disturbance: np.ndarray, anchor: float,
             fallback: str) -> tuple[np.ndarray, float, np.ndarray, str]:
        """This sample's plan: (per-step duties (horizon,), its exact eq. 16 cost, its first predicted state
        with the disturbance, the solver's name) -- an RTI step, or the search where there is no RTI or
        ``fallback`` names a reason. (A peer solving the same problem otherwise overrides this.)"""
        weights, rollout = self._weights, self.predictor.rollout
        if self.rti is not None and not fallback:
            blocks, n_blocks = self.rti_optimizer.block_of_step, self.rti_optimizer.n_blocks
            linearize = self.predictor.linearize

            def linearized(duties: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                return linearize(context, duties, disturbance, blocks, n_blocks)

            def evaluate(duties: np.ndarray) -> np.ndarray:
                return rollout(context, duties[None, :], disturbance)[0]

            sequence, cost, first = self.rti_optimizer.solve(linearized, evaluate, target, self._warm,
                                                             self._previous_duty)
            return sequence, cost, first, "rti"
        predictions = []

        def costs(duties: np.ndarray) -> np.ndarray:
            predicted = rollout(context, duties, disturbance)
            predictions.append(predicted)
            error = predicted - target
            error *= error
            return np.sqrt(error.sum(axis=2)) @ weights

        sequence, cost = self.optimizer.solve(costs, self._warm, anchor)
        call, row = self.optimizer.best_location
        return sequence, cost, predictions[call][row, 0], "search"

    @property
    def plan_sequence(self) -> np.ndarray | None:
        """The last step's plan, per step (horizon,): what the next step shifts (None before the first)."""
        return self._warm

    def cost(self, duties: np.ndarray) -> tuple[float, np.ndarray]:
        """Eq. 16's exact cost of one per-step duty sequence for the problem of the last :meth:`step`, and its
        first predicted state (with the disturbance estimate): the plan's cost where the RTI did not roll it out."""
        context, target, disturbance, _, _ = self._problem
        predicted = self.predictor.rollout(context, np.asarray(duties, dtype=float)[None, :], disturbance)[0]
        error = predicted - target
        error *= error
        return float(np.sqrt(error.sum(axis=1)) @ self._weights), predicted[0].copy()

    def search_last_sample(self) -> tuple[np.ndarray, float]:
        """The search's plan and exact cost for the problem of the last :meth:`step` (its context, disturbance
        estimate and warm start), leaving the controller's state as it is: the reference an RTI step is
        judged against (:func:`cosim.study.optimizer_ablation`)."""
        context, target, disturbance, anchor, warm = self._problem
        weights, rollout = self._weights, self.predictor.rollout

        def cost(duties: np.ndarray) -> np.ndarray:
            error = rollout(context, duties, disturbance) - target
            error *= error
            return np.sqrt(error.sum(axis=2)) @ weights

        return HorizonOptimizer(self.settings, self.duty_limits).solve(cost, warm, anchor)

    def describe(self) -> dict:
        return {
            "type": "predictive (receding horizon, paper eq. 16 + 23)",
            "name": self.name,
            "sample_period_s": self.sample_period,
            "duty_limits": list(self.duty_limits),
            "horizon": asdict(self.settings),
            "predictor": self.predictor.describe(),
            "optimizer": "search (grid + pattern search)" if self.rti is None else
            {"type": "real-time iteration (Gauss-Newton + box QP), the search as fallback", **asdict(self.rti)},
            "offset_free": "state-disturbance estimate from the one-step prediction error, fed back over the horizon",
        }
