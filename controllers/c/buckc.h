/*
 * buckc.h -- what every C twin shares: status codes and the struct-size query.
 *
 * Not an algorithm file. The twins themselves are pi.c (controllers/pi.py), nn_model.c
 * (controllers/nn_model.py), predictors.c (controllers/predictors.py), predictive.c
 * (controllers/predictive.py) and explicit_policy.c (controllers/explicit_policy.py).
 *
 * Conventions of all twins:
 *  - C99, libm only, no allocation, no mutable globals: every instance lives in a caller-owned
 *    struct, so any number of them can coexist.
 *  - Configuration structs hold only numbers and fixed-size arrays (a code generator can emit
 *    them as `static const` data); sizes above the compile-time maxima are refused at
 *    configuration time with BUCKC_ERR_LIMIT and a short text naming the field.
 *  - Arithmetic follows the Python reference operation by operation (same operand order, one
 *    rounding per operation). Compile with -ffp-contract=off (as controllers/native.py does):
 *    a compiler that fuses a*b+c into one FMA would round differently from numpy's separate
 *    ufunc calls. Remaining differences are ulp-level: numpy evaluates matrix products with
 *    BLAS kernels (their own summation order, FMA) and tanh/exp/sin/cos/pow with its own SIMD
 *    routines, the twins with plain loops and libm.
 *  - 2x2 matrices are double[4], row-major: {a00, a01, a10, a11}.
 */
#ifndef BUCKC_H
#define BUCKC_H

#include <stddef.h>

enum {
    BUCKC_OK = 0,
    BUCKC_ERR_NULL = -1,             /* a required pointer is NULL */
    BUCKC_ERR_LIMIT = -2,            /* a size above a compile-time maximum (BUCKC_MAX_...) */
    BUCKC_ERR_INVALID = -3,          /* a value the Python reference refuses too */
    BUCKC_ERR_NO_INDUCTOR_CURRENT = -4 /* the predictive step needs a finite inductor current */
};

/* A one-line description of a status code (a string literal). */
const char *buckc_status_text(int status);

/* sizeof() of a public struct by its type name ("BuckcNnConfig", ...), 0 if unknown: lets a
 * binding (controllers/native.py) check that its mirrors have the C layout. */
size_t buckc_struct_size(const char *type_name);

#endif
