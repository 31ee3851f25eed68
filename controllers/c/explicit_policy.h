/*
 * explicit_policy.h -- C twin of controllers/explicit_policy.py (ExplicitPolicyController): the
 * explicit NNPC, a small network imitating the online NNPC's first move, plus an offset-free
 * integral term near the reference.
 *
 * At sample k (features in the order of explicit_policy.FEATURES, G r = conductance * reference):
 *
 *     x = [vo - r, iL - G r, vo(k-1) - r, iL(k-1) - G r, d(k-1), r, G]
 *     u = net(x)                     tanh hidden layers, linear output (normalisation folded in)
 *     I = I + (Ki Ts) (r - vo)       only while |r - vo| <= band |r|; kept unless it pushes a
 *                                    saturated duty further (conditional integration, as pi.c)
 *     d = clip(u + I, duty_min, duty_max)
 *
 * Weight layout: weights[l][i][j] = W_l[i, j] (input i, output unit j), biases[l][j]; layer l =
 * 0 .. n_hidden, the last one the single output. Sums start from the bias and add the inputs in
 * order, as the Python reference's scalar step does, so the twins agree bit for bit (with
 * -ffp-contract=off and the same libm tanh).
 */
#ifndef BUCKC_EXPLICIT_POLICY_H
#define BUCKC_EXPLICIT_POLICY_H

#include "buckc.h"

/* The maxima size the configuration struct. A build for one known policy may set them to its own
 * sizes (-DBUCKC_POLICY_MAX_WIDTH=14 -DBUCKC_POLICY_MAX_HIDDEN_LAYERS=1: the Cortex-M4F image does,
 * so the weights take 1.5 KiB of flash, not 16); the host library keeps these. */
#ifndef BUCKC_POLICY_MAX_HIDDEN_LAYERS
#define BUCKC_POLICY_MAX_HIDDEN_LAYERS 3
#endif
#ifndef BUCKC_POLICY_MAX_WIDTH
#define BUCKC_POLICY_MAX_WIDTH 32
#endif
#define BUCKC_POLICY_INPUTS 7
#define BUCKC_POLICY_MAX_LAYERS (BUCKC_POLICY_MAX_HIDDEN_LAYERS + 1)
#if BUCKC_POLICY_MAX_WIDTH < BUCKC_POLICY_INPUTS
#error "BUCKC_POLICY_MAX_WIDTH must be at least BUCKC_POLICY_INPUTS: layer 0's weights are indexed by input"
#endif

typedef struct {
    buckc_real sample_period;   /* [s] */
    buckc_real duty_min;        /* duty limits, 0 <= min < max <= 1 */
    buckc_real duty_max;
    buckc_real nominal_load;    /* [Ohm] the load assumed until the sensors give an estimate */
    buckc_real integral_gain;   /* Ki [1/(V s)] */
    buckc_real integral_band;   /* integrate while |r - vo| <= band |r| [1] */
    int n_hidden;           /* 1 .. BUCKC_POLICY_MAX_HIDDEN_LAYERS */
    int hidden[BUCKC_POLICY_MAX_HIDDEN_LAYERS];
    buckc_real weights[BUCKC_POLICY_MAX_LAYERS][BUCKC_POLICY_MAX_WIDTH][BUCKC_POLICY_MAX_WIDTH];
    buckc_real biases[BUCKC_POLICY_MAX_LAYERS][BUCKC_POLICY_MAX_WIDTH];
} BuckcPolicyConfig;

typedef struct {
    const BuckcPolicyConfig *config; /* not copied: keep it alive (it may be static const data) */
    int have_history;
    buckc_real previous_current;  /* [A] iL at the last sample */
    buckc_real previous_voltage;  /* [V] vo at the last sample */
    buckc_real previous_duty;     /* the duty applied since the last sample */
    buckc_real conductance;       /* [S] the load estimate (load_estimate.h) */
    buckc_real integral;          /* the integral term [1] */
    buckc_real last_output;       /* u of the last step (diagnostics) */
} BuckcPolicy;

/* Validate like ExplicitPolicy / ExplicitPolicyController and reset; *what names a refused field. */
int buckc_policy_init(BuckcPolicy *policy, const BuckcPolicyConfig *config, const char **what);
void buckc_policy_reset(BuckcPolicy *policy);
/* The network output u for features x[BUCKC_POLICY_INPUTS] (ExplicitPolicy.forward). */
buckc_real buckc_policy_forward(const BuckcPolicyConfig *config, const buckc_real *x);
/* ExplicitPolicyController.step: *duty receives the duty to hold until the next sample. */
int buckc_policy_step(BuckcPolicy *policy, const BuckcMeasurement *measurement, buckc_real *duty);

#endif
