/*
 * box_qp.h -- C twin of controllers/box_qp.py: a small dense box-constrained QP,
 *
 *     minimise 0.5 x' H x + g' x   subject to   lower <= x <= upper,   H symmetric positive definite,
 *
 * by a primal active-set method with at most BUCKC_QP_MAX_VARIABLES unknowns (the real-time-iteration
 * optimizer's blocked duties). Hand-written because it is tiny and must run without allocation and
 * with a bounded amount of work: every array is on the stack at the fixed maximum size, and the
 * caller's iteration cap bounds the work (each iteration one Cholesky factorisation of at most 8 x 8).
 * Operation by operation the arithmetic of the Python twin. One source for the double and float32
 * builds (buckc_real, buckc.h).
 */
#ifndef BUCKC_BOX_QP_H
#define BUCKC_BOX_QP_H

#include "buckc.h"

#define BUCKC_QP_MAX_VARIABLES 8 /* box_qp.MAX_VARIABLES */

/* Solve for x[n] (n <= BUCKC_QP_MAX_VARIABLES); h is n x n, row-major with row stride `stride`.
 * Returns the iterations used (<= max_iterations), or BUCKC_ERR_LIMIT for n out of range;
 * *converged (may be NULL) is 1 at the optimum, 0 where the cap stopped the method (x is then the
 * feasible iterate reached, no worse than the start 0 clipped into the box). */
int buckc_box_qp(int n, const buckc_real *h, int stride, const buckc_real *g, const buckc_real *lower,
                 const buckc_real *upper, int max_iterations, buckc_real *x, int *converged);

#endif
