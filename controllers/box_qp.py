"""A small dense box-constrained QP: the step of the real-time-iteration optimizer.

    minimise 0.5 x' H x + g' x   subject to   lower <= x <= upper,   H symmetric positive definite

with at most :data:`MAX_VARIABLES` unknowns (the horizon's blocked duties: 1 at 1 ms, 6 at one
switching period). Written by hand rather than taken from a QP library because it is tiny and
must have a C twin (``controllers/c/box_qp.c``) that allocates nothing and does a bounded amount
of work: a primal active-set method (Nocedal & Wright, *Numerical Optimization*, algorithm 16.3,
specialised to bounds), each iteration one Cholesky factorisation of the free variables' block of
H (at most 8 x 8: ~100 flops).

Start: x = 0 clipped into the box (feasible; the RTI's box always contains 0, the current plan).
Each iteration solves for the free variables with the fixed ones at their bounds; a step that would
leave the box is cut at the first bound it meets (ratio test) and that variable is fixed there; a
full step is followed by the multiplier test, which frees the fixed variable whose gradient points
most strongly into the box. Each iteration lowers the objective, so the iterate is feasible and no
worse than the start when the iteration cap (``max_iterations``) stops it; strictly convex problems
end in at most a few iterations per variable (none of the RTI's needed more than 2 n + 1 in the
study). Arithmetic follows the C twin operation by operation (plain loops, no BLAS), so both give
the same numbers.
"""

from __future__ import annotations

import math

MAX_VARIABLES = 8


def cholesky_solve(h: list[list[float]], rhs: list[float], free: list[int]) -> list[float] | None:
    """Solve H[F, F] p = rhs[F] for the free indices F (Cholesky, in place on a copy); None if the
    block is not positive definite. Returns p over the free indices, in their order."""
    n = len(free)
    a = [[h[free[i]][free[j]] for j in range(n)] for i in range(n)]
    for j in range(n):
        s = a[j][j]
        for k in range(j):
            s -= a[j][k] * a[j][k]
        if not s > 0.0:
            return None
        d = math.sqrt(s)
        a[j][j] = d
        for i in range(j + 1, n):
            t = a[i][j]
            for k in range(j):
                t -= a[i][k] * a[j][k]
            a[i][j] = t / d
    y = [0.0] * n
    for i in range(n):  # L y = rhs
        t = rhs[free[i]]
        for k in range(i):
            t -= a[i][k] * y[k]
        y[i] = t / a[i][i]
    x = [0.0] * n
    for i in range(n - 1, -1, -1):  # L' x = y
        t = y[i]
        for k in range(i + 1, n):
            t -= a[k][i] * x[k]
        x[i] = t / a[i][i]
    return x


def solve_box_qp(h, g, lower, upper, max_iterations: int) -> tuple[list[float], int, bool]:
    """Minimise 0.5 x'Hx + g'x on lower <= x <= upper (``lower <= 0 <= upper`` need not hold: the start
    is 0 clipped into the box). Returns (x, iterations used, converged); a non-converged x is the
    feasible iterate where ``max_iterations`` stopped the method (no worse than the start)."""
    n = len(g)
    if n > MAX_VARIABLES:
        raise ValueError(f"box QP with {n} variables: at most {MAX_VARIABLES} (the C twin's fixed size)")
    h = [[float(h[i][j]) for j in range(n)] for i in range(n)]
    g = [float(v) for v in g]
    lower = [float(v) for v in lower]
    upper = [float(v) for v in upper]
    x = [min(max(0.0, lower[i]), upper[i]) for i in range(n)]
    # -1: fixed at its lower bound, +1: at its upper bound, 0: free
    state = [0] * n
    for iteration in range(1, max_iterations + 1):
        free = [i for i in range(n) if state[i] == 0]
        gradient = [g[i] + sum(h[i][k] * x[k] for k in range(n)) for i in range(n)]
        step = [0.0] * n
        if free:
            p = cholesky_solve(h, [-v for v in gradient], free)
            if p is None:  # not positive definite: the caller regularises; keep the feasible iterate
                return x, iteration, False
            for k, i in enumerate(free):
                step[i] = p[k]
        # ratio test: the longest fraction of the step that stays in the box, the first blocking bound
        alpha, blocking, side = 1.0, -1, 0
        for i in free:
            if step[i] < 0.0:
                reach = (lower[i] - x[i]) / step[i]
                if reach < alpha:
                    alpha, blocking, side = reach, i, -1
            elif step[i] > 0.0:
                reach = (upper[i] - x[i]) / step[i]
                if reach < alpha:
                    alpha, blocking, side = reach, i, 1
        if alpha < 0.0:
            alpha = 0.0
        for i in free:
            x[i] = x[i] + alpha * step[i]
        if blocking >= 0:  # fix it exactly on its bound
            x[blocking] = lower[blocking] if side < 0 else upper[blocking]
            state[blocking] = side
            continue
        # a full step: x minimises over the free variables; the multipliers of the fixed ones decide
        worst, release = 0.0, -1
        for i in range(n):
            if state[i] == 0:
                continue
            slope = g[i] + sum(h[i][k] * x[k] for k in range(n))
            pull = -slope if state[i] < 0 else slope  # > 0: the objective falls going into the box
            if pull > worst:
                worst, release = pull, i
        if release < 0:
            return x, iteration, True
        state[release] = 0
    return x, max_iterations, False
