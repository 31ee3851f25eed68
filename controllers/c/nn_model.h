/*
 * nn_model.h -- C twin of the numpy forward pass and rollouts of controllers/nn_model.py
 * (NNPlantModel.predict, NNPlantModel.rollout, NNPlantModel.rollout_shared).
 *
 * Weight layout (BuckcNnConfig). The weights are the *folded* ones of the numpy path,
 * NNPlantModel._weights / _biases: the input standardisation is folded into layer 0 and the
 * output de-standardisation into the last layer, so the network maps physical inputs to
 * physical outputs [iL(k), vc(k)] (minus x(k-1) if residual). Row-vector convention,
 *
 *     h_{l+1} = act(h_l @ W_l + b_l),   y = h_L @ W_L + b_L   (no activation on the last layer)
 *
 * with weights[l][i][j] = W_l[i, j] (input i, output unit j) and biases[l][j] = b_l[j];
 * layer l = 0 .. n_hidden, layer n_hidden being the output layer (2 units). Unused entries
 * are ignored (zero them). Inputs of layer 0, in order (NNConfig.input_names):
 *
 *     [iL, vc, d](k-1), [iL, vc, d](k-2), ..., [iL, vc, d](k-delays), extras...(k-1)
 *
 * Numbers are buckc_real (buckc.h: buckc_real, or float in the float32 build). History arrays are
 * buckc_real[delays][3], rows [iL, vc, d], most recent first; the duty of row 0
 * is replaced by the candidate's first duty, as in Python.
 */
#ifndef BUCKC_NN_MODEL_H
#define BUCKC_NN_MODEL_H

#include "buckc.h"

/* The maxima size the configuration struct; a build for one known network may set the first two
 * to its own sizes (-DBUCKC_NN_MAX_WIDTH=..., as the Cortex-M4F image does); the host keeps these. */
#ifndef BUCKC_NN_MAX_HIDDEN_LAYERS
#define BUCKC_NN_MAX_HIDDEN_LAYERS 4
#endif
#ifndef BUCKC_NN_MAX_WIDTH
#define BUCKC_NN_MAX_WIDTH 32       /* units per hidden layer; also bounds the inputs (<= 15) */
#endif
#define BUCKC_NN_MAX_DELAYS 4
#define BUCKC_NN_MAX_EXTRAS 3
#define BUCKC_NN_OUTPUTS 2
#define BUCKC_NN_MAX_LAYERS (BUCKC_NN_MAX_HIDDEN_LAYERS + 1)
#define BUCKC_NN_MAX_INPUTS (3 * BUCKC_NN_MAX_DELAYS + BUCKC_NN_MAX_EXTRAS)
#define BUCKC_NN_MAX_DIRECTIONS 8 /* blocked moves a sensitivity pass propagates (the RTI's box QP size) */

/* NNConfig.activation */
enum { BUCKC_ACTIVATION_TANH = 0, BUCKC_ACTIVATION_RELU = 1, BUCKC_ACTIVATION_SIGMOID = 2 };
/* nn_config.EXTRA_SIGNALS, as the NNPredictor computes them from its PredictionContext */
enum {
    BUCKC_EXTRA_LOAD_CONDUCTANCE = 0, /* 1 / load_resistance */
    BUCKC_EXTRA_LOAD_CURRENT = 1,     /* load_current (NaN without a load-current sensor) */
    BUCKC_EXTRA_INPUT_VOLTAGE = 2     /* input_voltage */
};

typedef struct {
    int delays;                           /* NNConfig.delays, 1..BUCKC_NN_MAX_DELAYS */
    int n_extras;                         /* len(NNConfig.extra_signals) */
    int extras[BUCKC_NN_MAX_EXTRAS];      /* BUCKC_EXTRA_..., in input order */
    int n_hidden;                         /* len(NNConfig.hidden), 1..BUCKC_NN_MAX_HIDDEN_LAYERS */
    int hidden[BUCKC_NN_MAX_HIDDEN_LAYERS]; /* units per hidden layer */
    int activation;                       /* BUCKC_ACTIVATION_... */
    int residual;                         /* NNConfig.residual: the network learns x(k) - x(k-1) */
    buckc_real weights[BUCKC_NN_MAX_LAYERS][BUCKC_NN_MAX_WIDTH][BUCKC_NN_MAX_WIDTH];
    buckc_real biases[BUCKC_NN_MAX_LAYERS][BUCKC_NN_MAX_WIDTH];
} BuckcNnConfig;

/* What rollout_shared computes once per measured history (one sample of the controller). */
typedef struct {
    int fast; /* 1: rollout_shared's fast path (1 delay, 1 hidden layer); 0: rollout() on the history */
    buckc_real history[BUCKC_NN_MAX_DELAYS][3];
    buckc_real extras[BUCKC_NN_MAX_EXTRAS];
    buckc_real disturbance[2];
    buckc_real constant[BUCKC_NN_MAX_WIDTH]; /* fast: b1 (+ extras @ w_extra) */
    buckc_real z0[BUCKC_NN_MAX_WIDTH];       /* fast: state @ w_state + constant */
    buckc_real b2[BUCKC_NN_OUTPUTS];         /* fast: b2 + disturbance */
} BuckcNnShared;

/* Validate sizes and codes; *what names the refused field. */
int buckc_nn_check(const BuckcNnConfig *config, const char **what);
/* 3 * delays + n_extras */
int buckc_nn_inputs(const BuckcNnConfig *config);

/* The hidden layers' activation as the forward passes compute it (BUCKC_NN_TANH for tanh and the
 * sigmoid, buckc.h), elementwise: out[i] = act(z[i]) for i < n (for tests and tools). */
void buckc_nn_activate(int activation, const buckc_real *z, int n, buckc_real *out);

/* The last hidden layer's activations of one row, x[buckc_nn_inputs()] -> features[hidden[n_hidden - 1]]:
 * what the output layer sees (AdaptiveNNPC._features, without its appended 1). */
void buckc_nn_features(const BuckcNnConfig *config, const buckc_real *x, buckc_real *features);

/* NNPlantModel.predict for one row: x[buckc_nn_inputs()] -> y[2]. */
void buckc_nn_forward(const BuckcNnConfig *config, const buckc_real *x, buckc_real *y);

/* NNPlantModel.rollout for one candidate: history[delays][3] (row-major), extras[n_extras]
 * (may be NULL when n_extras == 0), duties[n], disturbance[2] (NULL = none) -> out[n][2]. */
void buckc_nn_rollout(const BuckcNnConfig *config, const buckc_real *history, const buckc_real *extras,
                      const buckc_real *duties, int n, const buckc_real *disturbance, buckc_real *out);

/* NNPlantModel.rollout_shared, split into its per-history part and its per-candidate part. */
void buckc_nn_shared_prepare(const BuckcNnConfig *config, const buckc_real *history, const buckc_real *extras,
                             const buckc_real *disturbance, BuckcNnShared *shared);
void buckc_nn_shared_rollout(const BuckcNnConfig *config, const BuckcNnShared *shared,
                             const buckc_real *duties, int n, buckc_real *out);

/* NNPlantModel.rollout_sensitivities: one duty sequence duties[n] rolled out from history[delays][3]
 * (extras[n_extras], may be NULL without extras; disturbance[2], NULL = none) with the forward
 * sensitivities of the states to the blocked moves -- step j's duty being block block_of_step[j]'s
 * value, blocks numbered in time order, n_blocks <= BUCKC_NN_MAX_DIRECTIONS: out[n][2] and
 * jacobian[n][2][n_blocks] (row-major). Only a block's columns from its first step on are
 * propagated (before it they are zero); a duty of the window is a unit direction, not a dense
 * product. Returns BUCKC_OK or BUCKC_ERR_LIMIT (n_blocks out of range). */
int buckc_nn_sensitivities(const BuckcNnConfig *config, const buckc_real *history, const buckc_real *extras,
                           const buckc_real *disturbance, const buckc_real *duties, int n, const int *block_of_step,
                           int n_blocks, buckc_real *out, buckc_real *jacobian);

#endif
