/*
 * buckc_pair.h -- two buckc_real lanes computed together, for the NN predictor's sums (nn_model.c) and the
 * real-time iteration's Gauss-Newton model (predictive.c).
 *
 * Each lane does exactly what a scalar variable would, in the same order: a lane's sum is the same chain of
 * IEEE additions as before and gives the same bits (no reassociation, and no fused multiply-add because the builds
 * pass -ffp-contract=off: a build with -march=native and contraction on would fuse these products as it would the
 * scalar code's). What the pairs change is how many instructions the processor
 * decodes and how many chains it keeps in flight: two outputs', two directions' or two rows' sums per
 * instruction -- the 13.33 us C RTI step's sensitivity pass is most of the step (benchmarks.md, group
 * c-controllers), and its sums are 2 to 10 terms long, too short for the compiler's own vectoriser.
 *
 * Two back ends, one algorithm:
 *   - SSE2 (every x86-64 processor: the ISA's baseline, no -m flag) in the double build on x86-64 -- not on
 *     32-bit x86, whose scalar doubles may be x87's extended precision (lanes and tails would then differ);
 *   - a struct of two scalars everywhere else: the float32 build, the Cortex-M4F image, any other compiler or
 *     processor, and -DBUCKC_SCALAR_PAIRS (the tests build it on the host to check that both give the same bits,
 *     and check the sums' order against a one-operation-at-a-time Python computation: tests/test_c_twins.py).
 * Hand-written rather than GCC's vector extensions: those are not ISO C (the sources build with -std=c99
 * -Wpedantic for any compiler an FMU user has) and their loads would need the aliasing rules bent.
 */
#ifndef BUCKC_PAIR_H
#define BUCKC_PAIR_H

#include "buckc.h"

#if defined(__SSE2__) && (defined(__x86_64__) || defined(_M_X64)) && !defined(BUCKC_FLOAT32) && \
    !defined(BUCKC_SCALAR_PAIRS)
#include <emmintrin.h>

#define BUCKC_PAIRS_SSE2 1
typedef __m128d buckc_pair;

static inline buckc_pair buckc_pair_load(const buckc_real *p) { return _mm_loadu_pd(p); } /* (p[0], p[1]) */
static inline void buckc_pair_store(buckc_real *p, buckc_pair a) { _mm_storeu_pd(p, a); }
static inline buckc_pair buckc_pair_splat(buckc_real v) { return _mm_set1_pd(v); }        /* (v, v) */
static inline buckc_pair buckc_pair_add(buckc_pair a, buckc_pair b) { return _mm_add_pd(a, b); }
static inline buckc_pair buckc_pair_mul(buckc_pair a, buckc_pair b) { return _mm_mul_pd(a, b); }

#else

#define BUCKC_PAIRS_SSE2 0
typedef struct {
    buckc_real lane[2];
} buckc_pair;

static inline buckc_pair buckc_pair_load(const buckc_real *p)
{
    buckc_pair r;
    r.lane[0] = p[0];
    r.lane[1] = p[1];
    return r;
}
static inline void buckc_pair_store(buckc_real *p, buckc_pair a)
{
    p[0] = a.lane[0];
    p[1] = a.lane[1];
}
static inline buckc_pair buckc_pair_splat(buckc_real v)
{
    buckc_pair r;
    r.lane[0] = v;
    r.lane[1] = v;
    return r;
}
static inline buckc_pair buckc_pair_add(buckc_pair a, buckc_pair b)
{
    a.lane[0] = a.lane[0] + b.lane[0];
    a.lane[1] = a.lane[1] + b.lane[1];
    return a;
}
static inline buckc_pair buckc_pair_mul(buckc_pair a, buckc_pair b)
{
    a.lane[0] = a.lane[0] * b.lane[0];
    a.lane[1] = a.lane[1] * b.lane[1];
    return a;
}

#endif

/* a + b * c, lane by lane: the multiplication rounded, then the addition (never fused) */
static inline buckc_pair buckc_pair_add_mul(buckc_pair a, buckc_pair b, buckc_pair c)
{
    return buckc_pair_add(a, buckc_pair_mul(b, c));
}

#endif
