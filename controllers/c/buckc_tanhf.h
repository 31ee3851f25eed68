/*
 * buckc_tanhf.h -- tanh in single precision for the float32 build (BUCKC_TANH there, buckc.h).
 *
 * Why not libm's tanhf: newlib's (fdlibm's) costs an expm1f and a division, about 210 cycles a call on a
 * Cortex-M4F, 14 calls a step of the explicit NNPC; this one 63 (inlined in a loop: cortex_m4/tanh_probe.c).
 * A clamped exp-based form:
 *
 *     tanh|x| = 1 - 2 / (e^(2|x|) + 1),   e^(2|x|) = 2^n 2^f,   n = round(2|x| / ln 2),   |f| <= 1/2,
 *
 * 2^f by the degree-6 polynomial below (minimax in relative error on [-1/2, 1/2], fitted by
 * scripts/fit_tanhf.py, 1.6e-8 with its float coefficients), 2^n added to the exponent bits (exact),
 * +-1 from |x| = 9 on (tanh 9 is within 3.1e-8 of 1), the sign restored, NaN returned as it came.
 * Straight-line float arithmetic (no libm, no table): the same bits on every IEEE single-precision
 * target compiled with -ffp-contract=off, so the Cortex-M4F replays give the host float32 build's duties.
 *
 * Error: |buckc_tanhf(x) - tanh(x)| <= BUCKC_TANHF_ERROR for every float x -- an absolute bound (near 0
 * the result is not relatively accurate: up to 1.2e-7 off a tiny tanh). tests/test_float32.py checks every
 * float from 2^-7 to 9.5, every 32nd below 2^-7 and every 4096th above 9.5, both signs of the sampled
 * ones, infinities and NaN: at most 1.19e-7 (the bound takes 1.5e-7); controllers/float32.py's per-step
 * bound uses it (float32.TANH_ERROR). The double build keeps libm's tanh, equal to the Python references.
 */
#ifndef BUCKC_TANHF_H
#define BUCKC_TANHF_H

#include <math.h>
#include <stdint.h>
#include <string.h>

#define BUCKC_TANHF_ERROR 1.5e-7 /* [1] absolute (measured: 1.19e-7; tests/test_float32.py) */
#define BUCKC_TANHF_CLAMP 9.0f   /* from |x| = 9 on, +-1 */

static inline float buckc_tanhf(float x)
{
    float a = fabsf(x), y, f, p, e, t;
    int32_t n;
    uint32_t bits;
    if (!(a < BUCKC_TANHF_CLAMP)) /* |x| >= 9 (tanh within 3.1e-8 of +-1), or NaN */
        return a != a ? x : (x < 0.0f ? -1.0f : 1.0f);
    y = a * 2.88539008f;      /* 2|x| / ln 2, in [0, 26) */
    n = (int32_t)(y + 0.5f);  /* the nearest integer (y + 0.5 > 0: truncation is floor) */
    f = y - (float)n;         /* exact: |f| <= 1/2 */
    p = 1.5350802e-04f;       /* 2^f, Horner */
    p = p * f + 1.3398887e-03f;
    p = p * f + 9.618443e-03f;
    p = p * f + 5.5503324e-02f;
    p = p * f + 2.4022648e-01f;
    p = p * f + 6.931472e-01f;
    p = p * f + 1.0f;
    memcpy(&bits, &p, sizeof bits);
    bits += (uint32_t)n << 23; /* times 2^n: p in [0.7, 1.5), n <= 26, no overflow */
    memcpy(&e, &bits, sizeof e);
    t = 1.0f - 2.0f / (e + 1.0f);
    return x < 0.0f ? -t : t;
}

#endif
