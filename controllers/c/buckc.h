/*
 * buckc.h -- what every C twin shares: status codes and the struct-size query.
 *
 * Not an algorithm file. The twins themselves are pi.c (controllers/pi.py), nn_model.c
 * (controllers/nn_model.py), predictors.c (controllers/predictors.py), predictive.c
 * (controllers/predictive.py), box_qp.c (controllers/box_qp.py), explicit_policy.c
 * (controllers/explicit_policy.py), current_mode.c (controllers/current_mode.py), compensator.c
 * (controllers/compensator.py) and adaptation.c (controllers/adaptation.py, double only).
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
#include <math.h>

/*
 * The twins' arithmetic type. double by default (the twins' equivalence with the Python
 * references, 1e-9 per step, is stated for it); a build with -DBUCKC_FLOAT32 computes in float
 * (a Cortex-M4F's single-precision FPU), calling the float functions of the target's libm, but
 * for tanh: buckc_tanhf (buckc_tanhf.h), a clamped exp-based form within 1.5e-7 of tanh, 63
 * cycles a call on a Cortex-M4F where newlib's tanhf takes 210. The NN predictor (nn_model.c) calls
 * BUCKC_NN_TANH: buckc_tanhf there too, and in double buckc_tanh (buckc_tanh.h: exp-based, within
 * 2.5e-16 of tanh, 2.5 x faster than glibc's); the other double twins keep libm's tanh.
 * New algorithm code is written in buckc_real and the BUCKC_* math macros, never in a bare
 * double or a bare tanh/exp/sqrt, and every constant as BUCKC_REAL_LITERAL(x), so one source
 * serves both builds: the float32 builds compile with -Wdouble-promotion -Werror, which refuses
 * an expression that silently computes in double (software floating point on a Cortex-M4F).
 * BUCKC_REAL_NAME names the build ("float64" / "float32") for bindings and generated headers.
 *
 * Which files have a float32 build: pi.c, load_estimate.c, nn_model.c (with the NN sensitivities of
 * the real-time iteration), box_qp.c, explicit_policy.c, current_mode.c, compensator.c, predictive.c
 * (and buckc.c). predictive.c's float32 build is the online NNPC alone -- the NN predictor with both
 * optimizers, the real-time iteration and the search it falls back to -- for the Cortex-M4F
 * (cosim/benchmark_harness/cortex_m4.py); predictors.c (the circuit predictors of the MPC baselines:
 * matrix exponentials, switched-model tables of thousands of doubles, a host's tool) computes in double
 * only, so BUCKC_HAVE_CIRCUIT_PREDICTORS is 0 in a float32 build and predictive.c leaves them out there.
 * BUCKC_HAVE_PREDICTIVE (1 in double only) says whether the host bindings (controllers/native.py's ctypes
 * mirrors, buckc_struct_size) and the controller FMU (controller_fmu.c) have the predictive controller:
 * its float32 build is linked into the Cortex-M4F image (and the host's build of that image), not there.
 */
#ifdef BUCKC_FLOAT32
#include "buckc_tanhf.h"
typedef float buckc_real;
#define BUCKC_TANH buckc_tanhf /* not libm's tanhf: buckc_tanhf.h says why and how accurate */
#define BUCKC_NN_TANH buckc_tanhf
#define BUCKC_EXP expf
#define BUCKC_SQRT sqrtf
#define BUCKC_FABS fabsf
#define BUCKC_FLOOR floorf
#define BUCKC_REAL_LITERAL(x) x##f
#define BUCKC_REAL_NAME "float32"
#define BUCKC_HAVE_PREDICTIVE 0
#define BUCKC_HAVE_CIRCUIT_PREDICTORS 0
#else
#include "buckc_tanh.h"
typedef double buckc_real;
#define BUCKC_TANH tanh
#define BUCKC_NN_TANH buckc_tanh /* the NN predictor's (nn_model.c): not libm's, buckc_tanh.h says why */
#define BUCKC_EXP exp
#define BUCKC_SQRT sqrt
#define BUCKC_FABS fabs
#define BUCKC_FLOOR floor
#define BUCKC_REAL_LITERAL(x) x
#define BUCKC_REAL_NAME "float64"
#define BUCKC_HAVE_PREDICTIVE 1
#define BUCKC_HAVE_CIRCUIT_PREDICTORS 1
#endif

/* controllers.base.Measurement (SI units, NaN where the plant has no such output): what every
 * controller's step reads (here, not in predictive.h, so the float32 controllers have it too). */
typedef struct {
    buckc_real time;             /* [s] */
    buckc_real reference;        /* [V] */
    buckc_real output_voltage;   /* [V] */
    buckc_real inductor_current; /* [A] */
    buckc_real load_current;     /* [A] */
    buckc_real input_voltage;    /* [V] */
} BuckcMeasurement;

enum {
    BUCKC_OK = 0,
    BUCKC_ERR_NULL = -1,             /* a required pointer is NULL */
    BUCKC_ERR_LIMIT = -2,            /* a size above a compile-time maximum (BUCKC_MAX_...) */
    BUCKC_ERR_INVALID = -3,          /* a value the Python reference refuses too */
    BUCKC_ERR_NO_INDUCTOR_CURRENT = -4, /* the predictive step needs a finite inductor current */
    BUCKC_ERR_ILL_CONDITIONED = -5      /* the switched model cannot rebuild the state at this load */
};

/* A one-line description of a status code (a string literal). */
const char *buckc_status_text(int status);

/* BUCKC_REAL_NAME of the build ("float64" or "float32"), for bindings to check what they loaded. */
const char *buckc_real_name(void);
/* how buckc_pair.h computes its pairs in this build: "sse2" or "scalar" (the same bits either way) */
const char *buckc_pair_backend(void);

/* sizeof() of a public struct by its type name ("BuckcNnConfig", ...), 0 if unknown: lets a
 * binding (controllers/native.py) check that its mirrors have the C layout. */
size_t buckc_struct_size(const char *type_name);

#endif
