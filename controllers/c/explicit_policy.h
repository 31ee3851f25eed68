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
#include "predictive.h" /* BuckcMeasurement */

#define BUCKC_POLICY_MAX_HIDDEN_LAYERS 3
#define BUCKC_POLICY_MAX_WIDTH 32
#define BUCKC_POLICY_INPUTS 7
#define BUCKC_POLICY_MAX_LAYERS (BUCKC_POLICY_MAX_HIDDEN_LAYERS + 1)

typedef struct {
    double sample_period;   /* [s] */
    double duty_min;        /* duty limits, 0 <= min < max <= 1 */
    double duty_max;
    double nominal_load;    /* [Ohm] the load assumed until the sensors give an estimate */
    double integral_gain;   /* Ki [1/(V s)] */
    double integral_band;   /* integrate while |r - vo| <= band |r| [1] */
    int n_hidden;           /* 1 .. BUCKC_POLICY_MAX_HIDDEN_LAYERS */
    int hidden[BUCKC_POLICY_MAX_HIDDEN_LAYERS];
    double weights[BUCKC_POLICY_MAX_LAYERS][BUCKC_POLICY_MAX_WIDTH][BUCKC_POLICY_MAX_WIDTH];
    double biases[BUCKC_POLICY_MAX_LAYERS][BUCKC_POLICY_MAX_WIDTH];
} BuckcPolicyConfig;

typedef struct {
    const BuckcPolicyConfig *config; /* not copied: keep it alive (it may be static const data) */
    int have_history;
    double previous_current;  /* [A] iL at the last sample */
    double previous_voltage;  /* [V] vo at the last sample */
    double previous_duty;     /* the duty applied since the last sample */
    double conductance;       /* [S] the load estimate (load_estimate.h) */
    double integral;          /* the integral term [1] */
    double last_output;       /* u of the last step (diagnostics) */
} BuckcPolicy;

/* Validate like ExplicitPolicy / ExplicitPolicyController and reset; *what names a refused field. */
int buckc_policy_init(BuckcPolicy *policy, const BuckcPolicyConfig *config, const char **what);
void buckc_policy_reset(BuckcPolicy *policy);
/* The network output u for features x[BUCKC_POLICY_INPUTS] (ExplicitPolicy.forward). */
double buckc_policy_forward(const BuckcPolicyConfig *config, const double *x);
/* ExplicitPolicyController.step: *duty receives the duty to hold until the next sample. */
int buckc_policy_step(BuckcPolicy *policy, const BuckcMeasurement *measurement, double *duty);

#endif
