/*
 * adaptation.h -- C twin of controllers/adaptation.py: AdaptiveNNPC, the online NNPC whose network's
 * output layer follows the plant by recursive least squares with forgetting, guarded (saturated,
 * non-informative and load-step samples skipped; each update and the total deviation bounded; the
 * covariance trace capped; a fall back to the last good model when the running one-step error grows).
 *
 * The adaptive controller owns a copy of its NNPC's configuration (predictive.h) and rewrites that
 * copy's output layer after each update, as the Python controller rewrites its NNPC's; the NNPC it
 * wraps (BuckcPredictive) plans with it from the next sample on. Same order of operations as the
 * Python reference (its numpy products as plain loops in index order); no allocation.
 */
#ifndef BUCKC_ADAPTATION_H
#define BUCKC_ADAPTATION_H

#include "buckc.h"
#include "nn_model.h"
#include "predictive.h"

#define BUCKC_ADAPT_MAX_FEATURES (BUCKC_NN_MAX_WIDTH + 1) /* the last hidden layer's units and the bias */

/* adaptation.AdaptationSettings */
typedef struct {
    buckc_real forgetting;         /* RLS forgetting factor lambda, 0 < lambda <= 1 */
    buckc_real initial_covariance; /* P0 = p0 I */
    buckc_real duty_margin;        /* a duty this close to a limit counts as saturated */
    buckc_real min_change_current; /* [A] */
    buckc_real min_change_voltage; /* [V] */
    buckc_real min_change_duty;
    buckc_real load_change;        /* relative change of the load estimate that marks a load step */
    buckc_real max_step;           /* per update, per output: |delta theta| <= max_step |theta_offline| */
    buckc_real max_deviation;      /* in total: |theta - theta_offline| <= max_deviation |theta_offline| */
    buckc_real error_memory;       /* weight of the running one-step error */
    buckc_real fallback_ratio;     /* fall back when the running error exceeds this x the last good one */
    int checkpoint_every;          /* samples between promotions of the current model to the last good one */
    int warmup;                    /* samples of error history before a fallback or a promotion */
} BuckcAdaptationSettings;

typedef struct {
    BuckcAdaptationSettings settings;
    buckc_real nominal_load;          /* [Ohm] the load assumed until the sensors tell */
    buckc_real nominal_input_voltage; /* [V] the supply for samples without a supply reading (NaN: none) */
    buckc_real output_scale[2];       /* 1 / output_std^2 of the network: the error weights per output */
} BuckcAdaptationConfig;

/* AdaptiveNNPC.counters, in this order */
enum {
    BUCKC_ADAPT_SAMPLES = 0, BUCKC_ADAPT_UPDATES, BUCKC_ADAPT_SATURATED, BUCKC_ADAPT_STEADY, BUCKC_ADAPT_LOAD_STEP,
    BUCKC_ADAPT_BOUNDED, BUCKC_ADAPT_FALLBACKS, BUCKC_ADAPT_CHECKPOINTS, BUCKC_ADAPT_COUNTERS
};

typedef struct {
    BuckcPredictiveConfig predictive; /* the NNPC's configuration, its own copy: the output layer is rewritten */
    BuckcAdaptationConfig config;
    int features;                     /* last hidden layer's units + 1 */
    buckc_real offline[BUCKC_ADAPT_MAX_FEATURES][2]; /* theta offline: [weights; bias] of the output layer */
    buckc_real offline_norm[2];
    buckc_real theta[BUCKC_ADAPT_MAX_FEATURES][2];
    buckc_real covariance[BUCKC_ADAPT_MAX_FEATURES][BUCKC_ADAPT_MAX_FEATURES];
    buckc_real good_theta[BUCKC_ADAPT_MAX_FEATURES][2]; /* the last good model */
    buckc_real good_covariance[BUCKC_ADAPT_MAX_FEATURES][BUCKC_ADAPT_MAX_FEATURES];
    buckc_real error, good_error;     /* running one-step errors of the adapted and the last good model */
    int errors_seen, since_checkpoint;
    int have_input;                   /* the network input of the previous sample is known */
    buckc_real input[BUCKC_NN_MAX_INPUTS];
    buckc_real input_conductance;     /* [S] the load estimate that input was formed with */
    int history_count;
    buckc_real history[BUCKC_NN_MAX_DELAYS][3]; /* rows [iL, vo, d], most recent first */
    buckc_real conductance;           /* [S] the load estimate (the network's load input) */
    int counters[BUCKC_ADAPT_COUNTERS];
    BuckcPredictive inner;            /* the NNPC, on `predictive` (last: the big one) */
} BuckcAdaptive;

size_t buckc_adaptive_size(void);
/* AdaptiveNNPC.__init__ + reset: the NN predictor's NNPC of `predictive` (copied), adapted by `config`
 * (copied); *what names a refused field. The struct must not move after init (the NNPC points into it). */
int buckc_adaptive_init(BuckcAdaptive *adaptive, const BuckcPredictiveConfig *predictive,
                        const BuckcAdaptationConfig *config, const char **what);
/* AdaptiveNNPC.reset: the offline output layer, P0, no history (the NNPC reset too). */
void buckc_adaptive_reset(BuckcAdaptive *adaptive);
/* AdaptiveNNPC.step: learn from the sample (if it may), then the NNPC's step; *duty as buckc_predictive_step. */
int buckc_adaptive_step(BuckcAdaptive *adaptive, const BuckcMeasurement *measurement, buckc_real *duty);
/* AdaptiveNNPC.counters (BUCKC_ADAPT_COUNTERS of them, in the enum's order) */
const int *buckc_adaptive_counters(const BuckcAdaptive *adaptive);
/* AdaptiveNNPC.output_weights: theta[features][2], row-major */
void buckc_adaptive_output_layer(const BuckcAdaptive *adaptive, buckc_real *theta);
/* the NNPC it wraps (its state: buckc_predictive_state) */
BuckcPredictive *buckc_adaptive_inner(BuckcAdaptive *adaptive);

#endif
