"""The polynomial of controllers/c/buckc_tanhf.h: 2**f on [-1/2, 1/2], minimax in relative error.

buckc_tanhf (the float32 build's tanh) computes tanh|x| = 1 - 2 / (e**(2|x|) + 1) with
e**(2|x|) = 2**n 2**f, n the integer nearest to 2|x| / ln 2 and |f| <= 1/2; 2**f is the polynomial
1 + c1 f + ... + cD f**D this script fits: the coefficients minimising max |p(f) / 2**f - 1| over
[-1/2, 1/2] with p(0) = 1 exactly, found as a linear programme (the error level bisected, feasibility
by scipy's HiGHS on 4 001 points, its tolerances tightened to 1e-10), then rounded to float. It prints
them as the C literals the header holds and the fitted relative error in exact arithmetic; what the
float evaluation adds is measured over the floats by tests/test_float32.py.

    ./.venv/bin/python scripts/fit_tanhf.py [DEGREE]      (the header uses degree 6)
"""

from __future__ import annotations

import sys

import numpy as np
from scipy.optimize import linprog


def fit(degree: int, points: int = 4001) -> tuple[np.ndarray, float]:
    """Coefficients c1..cD of the minimax-relative polynomial and its error level."""
    f = np.linspace(-0.5, 0.5, points)
    target = np.exp2(f)
    powers = np.stack([f ** k for k in range(1, degree + 1)], axis=1)  # p(f) - 1 = powers @ c

    def feasible(eps: float):
        # |1 + powers @ c - target| <= eps target
        upper = powers, target * (1 + eps) - 1
        lower = -powers, -(target * (1 - eps) - 1)
        result = linprog(np.zeros(degree), A_ub=np.vstack([upper[0], lower[0]]),
                         b_ub=np.concatenate([upper[1], lower[1]]), bounds=[(None, None)] * degree, method="highs",
                         options={"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10})
        return result.x if result.status == 0 else None

    low, high = 1e-16, 1e-2
    best = feasible(high)
    while high / low > 1.001:
        middle = np.sqrt(low * high)
        solution = feasible(middle)
        if solution is None:
            low = middle
        else:
            high, best = middle, solution
    return best, high


def main(argv: list[str]) -> int:
    degree = int(argv[1]) if len(argv) > 1 else 6
    coefficients, level = fit(degree)
    rounded = coefficients.astype(np.float32)
    f = np.linspace(-0.5, 0.5, 200_001)
    p = 1.0 + sum(float(c) * f ** (k + 1) for k, c in enumerate(rounded))
    print(f"degree {degree}: fitted relative error {level:.3g}, with float coefficients "
          f"{np.max(np.abs(p / np.exp2(f) - 1)):.3g} (exact arithmetic)")
    literals = [f"{np.format_float_scientific(c, unique=True)}f" for c in rounded]
    print(f"    p = {literals[-1]};       /* 2^f, Horner */")  # as controllers/c/buckc_tanhf.h writes them
    for literal in reversed(literals[:-1]):
        print(f"    p = p * f + {literal};")
    print("    p = p * f + 1.0f;")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
