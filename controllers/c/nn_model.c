/*
 * nn_model.c -- twin of controllers/nn_model.py's numpy evaluation:
 *   buckc_nn_forward        NNPlantModel.predict (one row)
 *   buckc_nn_rollout        NNPlantModel.rollout (one candidate)
 *   buckc_nn_shared_*       NNPlantModel.rollout_shared: the fast path for one delay and one
 *                           hidden layer (the history's part of layer 0 computed once), else
 *                           rollout() on the broadcast history -- chosen by the same rule.
 * Weight layout and conventions: nn_model.h. Training and files stay in Python. One source for the
 * double and float32 builds (buckc_real, buckc.h).
 */
#include <math.h>
#include <string.h>

#include "nn_model.h"

#define W BUCKC_NN_MAX_WIDTH

int buckc_nn_inputs(const BuckcNnConfig *config)
{
    return 3 * config->delays + config->n_extras;
}

int buckc_nn_check(const BuckcNnConfig *config, const char **what)
{
    int i;
    if (config == NULL) {
        if (what) *what = "nn config is NULL";
        return BUCKC_ERR_NULL;
    }
    if (config->delays < 1) {
        if (what) *what = "nn delays: expected >= 1";
        return BUCKC_ERR_INVALID;
    }
    if (config->delays > BUCKC_NN_MAX_DELAYS) {
        if (what) *what = "nn delays: above BUCKC_NN_MAX_DELAYS";
        return BUCKC_ERR_LIMIT;
    }
    if (config->n_extras < 0 || config->n_extras > BUCKC_NN_MAX_EXTRAS) {
        if (what) *what = "nn n_extras: expected 0..BUCKC_NN_MAX_EXTRAS";
        return BUCKC_ERR_LIMIT;
    }
    for (i = 0; i < config->n_extras; ++i) {
        if (config->extras[i] < BUCKC_EXTRA_LOAD_CONDUCTANCE || config->extras[i] > BUCKC_EXTRA_INPUT_VOLTAGE) {
            if (what) *what = "nn extras: unknown extra-signal code";
            return BUCKC_ERR_INVALID;
        }
    }
    if (config->n_hidden < 1) {
        if (what) *what = "nn n_hidden: expected one or more hidden layers";
        return BUCKC_ERR_INVALID;
    }
    if (config->n_hidden > BUCKC_NN_MAX_HIDDEN_LAYERS) {
        if (what) *what = "nn n_hidden: above BUCKC_NN_MAX_HIDDEN_LAYERS";
        return BUCKC_ERR_LIMIT;
    }
    for (i = 0; i < config->n_hidden; ++i) {
        if (config->hidden[i] < 1) {
            if (what) *what = "nn hidden: expected sizes >= 1";
            return BUCKC_ERR_INVALID;
        }
        if (config->hidden[i] > BUCKC_NN_MAX_WIDTH) {
            if (what) *what = "nn hidden: a layer wider than BUCKC_NN_MAX_WIDTH";
            return BUCKC_ERR_LIMIT;
        }
    }
    if (buckc_nn_inputs(config) > BUCKC_NN_MAX_WIDTH) {
        if (what) *what = "nn inputs: more than BUCKC_NN_MAX_WIDTH";
        return BUCKC_ERR_LIMIT;
    }
    if (config->activation < BUCKC_ACTIVATION_TANH || config->activation > BUCKC_ACTIVATION_SIGMOID) {
        if (what) *what = "nn activation: unknown code";
        return BUCKC_ERR_INVALID;
    }
    return BUCKC_OK;
}

/* nn_model.ACTIVATIONS' numpy functions */
static buckc_real activate(int activation, buckc_real z)
{
    const buckc_real zero = BUCKC_REAL_LITERAL(0.0), half = BUCKC_REAL_LITERAL(0.5);
    switch (activation) {
    case BUCKC_ACTIVATION_RELU:
        return z < zero ? zero : z; /* np.maximum(z, 0.0): NaN stays NaN */
    case BUCKC_ACTIVATION_SIGMOID:
        return half * (BUCKC_REAL_LITERAL(1.0) + BUCKC_TANH(half * z));
    default:
        return BUCKC_TANH(z);
    }
}

/* y = x @ W_l + b_l: the product summed over the inputs in order, then the bias */
static void dense(const buckc_real (*weights)[W], const buckc_real *bias, const buckc_real *x, int n_in, int n_out, buckc_real *y)
{
    int i, j;
    for (j = 0; j < n_out; ++j) {
        buckc_real acc = x[0] * weights[0][j];
        for (i = 1; i < n_in; ++i)
            acc += x[i] * weights[i][j];
        y[j] = acc + bias[j];
    }
}

void buckc_nn_forward(const BuckcNnConfig *config, const buckc_real *x, buckc_real *y)
{
    buckc_real a[W], b[W];
    const buckc_real *h = x;
    int width = buckc_nn_inputs(config);
    int l, j;
    for (l = 0; l < config->n_hidden; ++l) {
        buckc_real *next = (l % 2 == 0) ? a : b;
        dense(config->weights[l], config->biases[l], h, width, config->hidden[l], next);
        for (j = 0; j < config->hidden[l]; ++j)
            next[j] = activate(config->activation, next[j]);
        h = next;
        width = config->hidden[l];
    }
    dense(config->weights[config->n_hidden], config->biases[config->n_hidden], h, width, BUCKC_NN_OUTPUTS, y);
    if (config->residual) { /* h + x[:, :2] */
        y[0] = y[0] + x[0];
        y[1] = y[1] + x[1];
    }
}

void buckc_nn_rollout(const BuckcNnConfig *config, const buckc_real *history, const buckc_real *extras,
                      const buckc_real *duties, int n, const buckc_real *disturbance, buckc_real *out)
{
    buckc_real x[W]; /* the window [iL, vc, d] x delays, row-major, then the extras */
    int delays = config->delays, e = config->n_extras, j, r;
    memcpy(x, history, sizeof(buckc_real) * 3 * (size_t)delays);
    for (r = 0; r < e; ++r)
        x[3 * delays + r] = extras != NULL ? extras[r] : (buckc_real)NAN;
    for (j = 0; j < n; ++j) {
        buckc_real state[2];
        x[2] = duties[j];
        buckc_nn_forward(config, x, state);
        if (disturbance != NULL) {
            state[0] += disturbance[0];
            state[1] += disturbance[1];
        }
        out[2 * j] = state[0];
        out[2 * j + 1] = state[1];
        if (delays > 1) /* window[:, 1:] = window[:, :-1] */
            memmove(x + 3, x, sizeof(buckc_real) * 3 * (size_t)(delays - 1));
        x[0] = state[0];
        x[1] = state[1];
    }
}

void buckc_nn_shared_prepare(const BuckcNnConfig *config, const buckc_real *history, const buckc_real *extras,
                             const buckc_real *disturbance, BuckcNnShared *shared)
{
    int delays = config->delays, r, h;
    memset(shared, 0, sizeof(*shared));
    memcpy(shared->history, history, sizeof(buckc_real) * 3 * (size_t)delays);
    for (r = 0; r < config->n_extras; ++r)
        shared->extras[r] = extras != NULL ? extras[r] : (buckc_real)NAN;
    shared->disturbance[0] = disturbance != NULL ? disturbance[0] : BUCKC_REAL_LITERAL(0.0);
    shared->disturbance[1] = disturbance != NULL ? disturbance[1] : BUCKC_REAL_LITERAL(0.0);
    shared->fast = delays == 1 && config->n_hidden == 1;
    if (shared->fast) {
        const buckc_real (*w1)[W] = config->weights[0];
        const buckc_real *b1 = config->biases[0];
        int hidden = config->hidden[0];
        for (h = 0; h < hidden; ++h) {
            buckc_real c = b1[h];
            if (extras != NULL && config->n_extras > 0) { /* b1 + extras @ w_extra */
                buckc_real acc = extras[0] * w1[3][h];
                for (r = 1; r < config->n_extras; ++r)
                    acc += extras[r] * w1[3 + r][h];
                c = b1[h] + acc;
            }
            shared->constant[h] = c;
            /* (state @ w_state + constant), the history's part of layer 0 */
            shared->z0[h] = (history[0] * w1[0][h] + history[1] * w1[1][h]) + c;
        }
        for (r = 0; r < BUCKC_NN_OUTPUTS; ++r) /* b2 + disturbance (only if one is given, as Python) */
            shared->b2[r] = disturbance != NULL ? config->biases[1][r] + disturbance[r] : config->biases[1][r];
    }
}

void buckc_nn_shared_rollout(const BuckcNnConfig *config, const BuckcNnShared *shared,
                             const buckc_real *duties, int n, buckc_real *out)
{
    const buckc_real (*w1)[W], (*w2)[W];
    int hidden, j, h, i;
    if (!shared->fast) {
        buckc_nn_rollout(config, &shared->history[0][0], shared->extras, duties, n, shared->disturbance, out);
        return;
    }
    w1 = config->weights[0];
    w2 = config->weights[1];
    hidden = config->hidden[0];
    for (j = 0; j < n; ++j) {
        buckc_real z[W];
        const buckc_real *previous = j ? out + 2 * (j - 1) : &shared->history[0][0];
        for (h = 0; h < hidden; ++h) {
            buckc_real v;
            if (j == 0) {
                v = shared->z0[h] + duties[0] * w1[2][h];
            } else { /* z = out[j-1] @ w_state; z += d * w_duty; z += constant */
                v = previous[0] * w1[0][h] + previous[1] * w1[1][h];
                v += duties[j] * w1[2][h];
                v += shared->constant[h];
            }
            z[h] = activate(config->activation, v);
        }
        for (i = 0; i < BUCKC_NN_OUTPUTS; ++i) {
            buckc_real acc = z[0] * w2[0][i];
            for (h = 1; h < hidden; ++h)
                acc += z[h] * w2[h][i];
            acc += shared->b2[i];
            if (config->residual)
                acc += previous[i];
            out[2 * j + i] = acc;
        }
    }
}
