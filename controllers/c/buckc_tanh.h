/*
 * buckc_tanh.h -- tanh in double precision for the NN predictor's forward passes and sensitivities
 * (nn_model.c: BUCKC_NN_TANH in the double build, buckc.h).
 *
 * Why not libm's tanh: glibc's computes it through expm1, about 17 ns a call with the arguments of a
 * hidden layer (x in [-3, 3]) on the benchmark machine, where this one takes 7 ns -- and the online
 * NNPC's real-time iteration evaluates ~240 of them per sample: with libm's they were 44 % of the C step
 * (perf, the 13.33 us replay). The exp-based form
 *
 *     tanh|x| = 1 - 2 / (e^(2|x|) + 1),   the sign restored by copysign,
 *
 * with libm's exp (correctly rounded to within 1 ulp). NaN comes back NaN, +-inf +-1, -0 -0; from
 * |x| = 19.1 on the result is exactly +-1, as tanh's rounded value is.
 *
 * Error: |buckc_tanh(x) - tanh(x)| <= BUCKC_TANH_ERROR for every double x -- an absolute bound, the
 * rounding of 2 / (e + 1) near 1 (it is what an activation's error does to a network's output: a
 * weight times it); relative, within 4.2 ulp for |x| >= 0.3, but near 0 not relatively accurate (up to
 * 2.2e-16 off a tiny tanh). tests/test_c_twins.py checks 4.2 million arguments from 1e-300 to 25 of both
 * signs against a long-double tanh (measured 2.18e-16) and the specials. numpy's np.tanh, the Python
 * references', is itself within 1e-16 of tanh: the NN twins stay within their 1e-12 (per rollout).
 * The explicit NNPC keeps libm's tanh: its Python reference's scalar step calls math.tanh, bit for bit.
 */
#ifndef BUCKC_TANH_H
#define BUCKC_TANH_H

#include <math.h>

#define BUCKC_TANH_ERROR 2.5e-16 /* [1] absolute (measured: 2.18e-16; tests/test_c_twins.py) */

static inline double buckc_tanh(double x)
{
    double a = fabs(x);
    return copysign(1.0 - 2.0 / (exp(a + a) + 1.0), x);
}

#endif
