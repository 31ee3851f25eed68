/*
 * box_qp.c -- twin of controllers/box_qp.py (solve_box_qp, cholesky_solve); see box_qp.h.
 */
#include <math.h>

#include "box_qp.h"

#define N BUCKC_QP_MAX_VARIABLES

/* H[F, F] p = rhs[F] over the free indices (Cholesky on a copy); 0 if not positive definite. */
static int cholesky_solve(const buckc_real *h, int stride, const buckc_real *rhs, const int *free, int n,
                          buckc_real *p)
{
    buckc_real a[N][N], y[N];
    int i, j, k;
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j)
            a[i][j] = h[free[i] * stride + free[j]];
    for (j = 0; j < n; ++j) {
        buckc_real s = a[j][j], d;
        for (k = 0; k < j; ++k)
            s -= a[j][k] * a[j][k];
        if (!(s > BUCKC_REAL_LITERAL(0.0)))
            return 0;
        d = BUCKC_SQRT(s);
        a[j][j] = d;
        for (i = j + 1; i < n; ++i) {
            buckc_real t = a[i][j];
            for (k = 0; k < j; ++k)
                t -= a[i][k] * a[j][k];
            a[i][j] = t / d;
        }
    }
    for (i = 0; i < n; ++i) { /* L y = rhs */
        buckc_real t = rhs[free[i]];
        for (k = 0; k < i; ++k)
            t -= a[i][k] * y[k];
        y[i] = t / a[i][i];
    }
    for (i = n - 1; i >= 0; --i) { /* L' p = y */
        buckc_real t = y[i];
        for (k = i + 1; k < n; ++k)
            t -= a[k][i] * p[k];
        p[i] = t / a[i][i];
    }
    return 1;
}

/* g[i] + sum_k H[i][k] x[k], summed in the Python twin's order */
static buckc_real gradient_at(const buckc_real *h, int stride, const buckc_real *g, const buckc_real *x, int n, int i)
{
    buckc_real sum = BUCKC_REAL_LITERAL(0.0);
    int k;
    for (k = 0; k < n; ++k)
        sum += h[i * stride + k] * x[k];
    return g[i] + sum;
}

int buckc_box_qp(int n, const buckc_real *h, int stride, const buckc_real *g, const buckc_real *lower,
                 const buckc_real *upper, int max_iterations, buckc_real *x, int *converged)
{
    int state[N], free[N], i, iteration;
    buckc_real rhs[N], p[N], step[N];
    const buckc_real zero = BUCKC_REAL_LITERAL(0.0);
    if (converged != NULL)
        *converged = 0;
    if (n < 1 || n > N)
        return BUCKC_ERR_LIMIT;
    for (i = 0; i < n; ++i) {
        buckc_real v = zero < lower[i] ? lower[i] : zero; /* min(max(0, lower), upper) */
        x[i] = v < upper[i] ? v : upper[i];
        state[i] = 0; /* -1: fixed at its lower bound, +1: at its upper bound, 0: free */
    }
    for (iteration = 1; iteration <= max_iterations; ++iteration) {
        int n_free = 0, k, blocking = -1, side = 0, release = -1;
        buckc_real alpha = BUCKC_REAL_LITERAL(1.0), worst = zero;
        for (i = 0; i < n; ++i) {
            rhs[i] = -gradient_at(h, stride, g, x, n, i);
            step[i] = zero;
            if (state[i] == 0)
                free[n_free++] = i;
        }
        if (n_free > 0) {
            if (!cholesky_solve(h, stride, rhs, free, n_free, p))
                return iteration; /* not positive definite: the caller regularises */
            for (k = 0; k < n_free; ++k)
                step[free[k]] = p[k];
        }
        for (k = 0; k < n_free; ++k) { /* ratio test: the first bound the step meets */
            buckc_real reach;
            i = free[k];
            if (step[i] < zero) {
                reach = (lower[i] - x[i]) / step[i];
                if (reach < alpha) {
                    alpha = reach;
                    blocking = i;
                    side = -1;
                }
            } else if (step[i] > zero) {
                reach = (upper[i] - x[i]) / step[i];
                if (reach < alpha) {
                    alpha = reach;
                    blocking = i;
                    side = 1;
                }
            }
        }
        if (alpha < zero)
            alpha = zero;
        for (k = 0; k < n_free; ++k)
            x[free[k]] = x[free[k]] + alpha * step[free[k]];
        if (blocking >= 0) { /* fix it exactly on its bound */
            x[blocking] = side < 0 ? lower[blocking] : upper[blocking];
            state[blocking] = side;
            continue;
        }
        for (i = 0; i < n; ++i) { /* a full step: the multipliers of the fixed variables decide */
            buckc_real slope, pull;
            if (state[i] == 0)
                continue;
            slope = gradient_at(h, stride, g, x, n, i);
            pull = state[i] < 0 ? -slope : slope;
            if (pull > worst) {
                worst = pull;
                release = i;
            }
        }
        if (release < 0) {
            if (converged != NULL)
                *converged = 1;
            return iteration;
        }
        state[release] = 0;
    }
    return max_iterations;
}
