/*
 * nn_model.c -- twin of controllers/nn_model.py's numpy evaluation:
 *   buckc_nn_forward        NNPlantModel.predict (one row)
 *   buckc_nn_rollout        NNPlantModel.rollout (one candidate)
 *   buckc_nn_shared_*       NNPlantModel.rollout_shared: the fast path for one delay and one
 *                           hidden layer (the history's part of layer 0 computed once), else
 *                           rollout() on the broadcast history -- chosen by the same rule.
 *   buckc_nn_sensitivities  NNPlantModel.rollout_sensitivities (forward mode, analytic)
 * Weight layout and conventions: nn_model.h. Training and files stay in Python. One source for the
 * double and float32 builds (buckc_real, buckc.h).
 */
#include <math.h>
#include <string.h>

#include "buckc_pair.h"
#include "nn_model.h"

#define W BUCKC_NN_MAX_WIDTH

/* the sensitivity pass takes the directions two at a time (buckc_pair.h): an even number fits its arrays */
typedef char buckc_directions_even[(BUCKC_NN_MAX_DIRECTIONS % 2 == 0) ? 1 : -1];

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

/* nn_config.ACTIVATIONS' numpy functions */
static buckc_real activate(int activation, buckc_real z)
{
    const buckc_real zero = BUCKC_REAL_LITERAL(0.0), half = BUCKC_REAL_LITERAL(0.5);
    switch (activation) {
    case BUCKC_ACTIVATION_RELU:
        return z < zero ? zero : z; /* np.maximum(z, 0.0): NaN stays NaN */
    case BUCKC_ACTIVATION_SIGMOID:
        return half * (BUCKC_REAL_LITERAL(1.0) + BUCKC_NN_TANH(half * z));
    default:
        return BUCKC_NN_TANH(z);
    }
}

void buckc_nn_activate(int activation, const buckc_real *z, int n, buckc_real *out)
{
    int i;
    for (i = 0; i < n; ++i)
        out[i] = activate(activation, z[i]);
}

/* y = x @ W_l + b_l: each output's product summed over the inputs in order, then the bias.
 *
 * Eight (then four, two, one) outputs' sums run side by side, two per pair (buckc_pair.h): each is still one chain
 * of dependent additions in the same order -- the same bits as one output at a time -- but the processor overlaps
 * the chains where it waited out each addition's latency in one, and one instruction does two outputs' work (the
 * 13.33 us C RTI step: benchmarks.md, group c-controllers). Not reassociated: the Python twins' sums are in this
 * order. */
static void dense(const buckc_real (*weights)[W], const buckc_real *bias, const buckc_real *x, int n_in, int n_out, buckc_real *y)
{
    int i, j = 0;
    for (; j + 7 < n_out; j += 8) {
        buckc_pair x0 = buckc_pair_splat(x[0]);
        buckc_pair acc0 = buckc_pair_mul(x0, buckc_pair_load(&weights[0][j]));
        buckc_pair acc1 = buckc_pair_mul(x0, buckc_pair_load(&weights[0][j + 2]));
        buckc_pair acc2 = buckc_pair_mul(x0, buckc_pair_load(&weights[0][j + 4]));
        buckc_pair acc3 = buckc_pair_mul(x0, buckc_pair_load(&weights[0][j + 6]));
        for (i = 1; i < n_in; ++i) {
            buckc_pair xi = buckc_pair_splat(x[i]);
            acc0 = buckc_pair_add_mul(acc0, xi, buckc_pair_load(&weights[i][j]));
            acc1 = buckc_pair_add_mul(acc1, xi, buckc_pair_load(&weights[i][j + 2]));
            acc2 = buckc_pair_add_mul(acc2, xi, buckc_pair_load(&weights[i][j + 4]));
            acc3 = buckc_pair_add_mul(acc3, xi, buckc_pair_load(&weights[i][j + 6]));
        }
        buckc_pair_store(y + j, buckc_pair_add(acc0, buckc_pair_load(bias + j)));
        buckc_pair_store(y + j + 2, buckc_pair_add(acc1, buckc_pair_load(bias + j + 2)));
        buckc_pair_store(y + j + 4, buckc_pair_add(acc2, buckc_pair_load(bias + j + 4)));
        buckc_pair_store(y + j + 6, buckc_pair_add(acc3, buckc_pair_load(bias + j + 6)));
    }
    for (; j + 3 < n_out; j += 4) {
        buckc_pair x0 = buckc_pair_splat(x[0]);
        buckc_pair acc0 = buckc_pair_mul(x0, buckc_pair_load(&weights[0][j]));
        buckc_pair acc1 = buckc_pair_mul(x0, buckc_pair_load(&weights[0][j + 2]));
        for (i = 1; i < n_in; ++i) {
            buckc_pair xi = buckc_pair_splat(x[i]);
            acc0 = buckc_pair_add_mul(acc0, xi, buckc_pair_load(&weights[i][j]));
            acc1 = buckc_pair_add_mul(acc1, xi, buckc_pair_load(&weights[i][j + 2]));
        }
        buckc_pair_store(y + j, buckc_pair_add(acc0, buckc_pair_load(bias + j)));
        buckc_pair_store(y + j + 2, buckc_pair_add(acc1, buckc_pair_load(bias + j + 2)));
    }
    for (; j + 1 < n_out; j += 2) {
        buckc_pair acc = buckc_pair_mul(buckc_pair_splat(x[0]), buckc_pair_load(&weights[0][j]));
        for (i = 1; i < n_in; ++i)
            acc = buckc_pair_add_mul(acc, buckc_pair_splat(x[i]), buckc_pair_load(&weights[i][j]));
        buckc_pair_store(y + j, buckc_pair_add(acc, buckc_pair_load(bias + j)));
    }
    for (; j < n_out; ++j) {
        buckc_real acc = x[0] * weights[0][j];
        for (i = 1; i < n_in; ++i)
            acc += x[i] * weights[i][j];
        y[j] = acc + bias[j];
    }
}

/* out[i] = (sum_h g[h][0] W_l[i][h], sum_h g[h][1] W_l[i][h]) for the layer's inputs i < n_rows: g W_l' for the two
 * outputs at once (g and out hold them side by side: one pair), each sum over h in order; four (then two, then
 * one) rows' sums side by side, for the reason dense() gives */
static void backward_rows(const buckc_real g[][2], const buckc_real (*weights)[W], int n_rows, int n_h,
                          buckc_real out[][2])
{
    int i = 0, h;
    for (; i + 3 < n_rows; i += 4) {
        const buckc_real *w0 = weights[i], *w1 = weights[i + 1], *w2 = weights[i + 2], *w3 = weights[i + 3];
        buckc_pair g0 = buckc_pair_load(g[0]);
        buckc_pair acc0 = buckc_pair_mul(g0, buckc_pair_splat(w0[0])), acc1 = buckc_pair_mul(g0, buckc_pair_splat(w1[0]));
        buckc_pair acc2 = buckc_pair_mul(g0, buckc_pair_splat(w2[0])), acc3 = buckc_pair_mul(g0, buckc_pair_splat(w3[0]));
        for (h = 1; h < n_h; ++h) {
            buckc_pair gh = buckc_pair_load(g[h]);
            acc0 = buckc_pair_add_mul(acc0, gh, buckc_pair_splat(w0[h]));
            acc1 = buckc_pair_add_mul(acc1, gh, buckc_pair_splat(w1[h]));
            acc2 = buckc_pair_add_mul(acc2, gh, buckc_pair_splat(w2[h]));
            acc3 = buckc_pair_add_mul(acc3, gh, buckc_pair_splat(w3[h]));
        }
        buckc_pair_store(out[i], acc0);
        buckc_pair_store(out[i + 1], acc1);
        buckc_pair_store(out[i + 2], acc2);
        buckc_pair_store(out[i + 3], acc3);
    }
    for (; i + 1 < n_rows; i += 2) {
        const buckc_real *w0 = weights[i], *w1 = weights[i + 1];
        buckc_pair g0 = buckc_pair_load(g[0]);
        buckc_pair acc0 = buckc_pair_mul(g0, buckc_pair_splat(w0[0])), acc1 = buckc_pair_mul(g0, buckc_pair_splat(w1[0]));
        for (h = 1; h < n_h; ++h) {
            buckc_pair gh = buckc_pair_load(g[h]);
            acc0 = buckc_pair_add_mul(acc0, gh, buckc_pair_splat(w0[h]));
            acc1 = buckc_pair_add_mul(acc1, gh, buckc_pair_splat(w1[h]));
        }
        buckc_pair_store(out[i], acc0);
        buckc_pair_store(out[i + 1], acc1);
    }
    for (; i < n_rows; ++i) {
        const buckc_real *w = weights[i];
        buckc_pair acc = buckc_pair_mul(buckc_pair_load(g[0]), buckc_pair_splat(w[0]));
        for (h = 1; h < n_h; ++h)
            acc = buckc_pair_add_mul(acc, buckc_pair_load(g[h]), buckc_pair_splat(w[h]));
        buckc_pair_store(out[i], acc);
    }
}

/* the hidden layers of one row, into a or b (alternating); returns the last hidden layer's activations */
static const buckc_real *hidden_layers(const BuckcNnConfig *config, const buckc_real *x, buckc_real *a, buckc_real *b)
{
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
    return h;
}

void buckc_nn_features(const BuckcNnConfig *config, const buckc_real *x, buckc_real *features)
{
    buckc_real a[W], b[W];
    const buckc_real *h = hidden_layers(config, x, a, b);
    memcpy(features, h, sizeof(buckc_real) * (size_t)config->hidden[config->n_hidden - 1]);
}

void buckc_nn_forward(const BuckcNnConfig *config, const buckc_real *x, buckc_real *y)
{
    buckc_real a[W], b[W];
    const buckc_real *h = hidden_layers(config, x, a, b);
    int width = config->hidden[config->n_hidden - 1];
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
    int hidden, j, h;
    if (!shared->fast) {
        buckc_nn_rollout(config, &shared->history[0][0], shared->extras, duties, n, shared->disturbance, out);
        return;
    }
    w1 = config->weights[0];
    w2 = config->weights[1];
    hidden = config->hidden[0];
    if (hidden < 1) /* refused by buckc_nn_check; said here for the compiler, which reads z[0] below */
        return;
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
        { /* the two outputs' sums side by side (dense() says why), each over h in order */
            buckc_real acc0 = z[0] * w2[0][0], acc1 = z[0] * w2[0][1];
            for (h = 1; h < hidden; ++h) {
                acc0 += z[h] * w2[h][0];
                acc1 += z[h] * w2[h][1];
            }
            acc0 += shared->b2[0];
            acc1 += shared->b2[1];
            if (config->residual) {
                acc0 += previous[0];
                acc1 += previous[1];
            }
            out[2 * j] = acc0;
            out[2 * j + 1] = acc1;
        }
    }
}

/* z[i] = activation(z[i]) and slope[i] its slope there, i < n (the slope from the activation itself where that is
 * exact); the activation chosen once per layer, not per unit */
static void activate_with_slopes(int activation, buckc_real *z, int n, buckc_real *slope)
{
    const buckc_real zero = BUCKC_REAL_LITERAL(0.0), one = BUCKC_REAL_LITERAL(1.0), half = BUCKC_REAL_LITERAL(0.5);
    int i;
    switch (activation) {
    case BUCKC_ACTIVATION_RELU:
        for (i = 0; i < n; ++i) {
            slope[i] = z[i] > zero ? one : zero;
            z[i] = z[i] < zero ? zero : z[i];
        }
        return;
    case BUCKC_ACTIVATION_SIGMOID:
        for (i = 0; i < n; ++i) {
            buckc_real a = half * (one + BUCKC_NN_TANH(half * z[i]));
            slope[i] = a * (one - a);
            z[i] = a;
        }
        return;
    default:
        for (i = 0; i < n; ++i) {
            buckc_real a = BUCKC_NN_TANH(z[i]);
            slope[i] = one - a * a;
            z[i] = a;
        }
        return;
    }
}

int buckc_nn_sensitivities(const BuckcNnConfig *config, const buckc_real *history, const buckc_real *extras,
                           const buckc_real *disturbance, const buckc_real *duties, int n, const int *block_of_step,
                           int n_blocks, buckc_real *out, buckc_real *jacobian)
{
    enum { D = BUCKC_NN_MAX_DIRECTIONS };
    const buckc_real zero = BUCKC_REAL_LITERAL(0.0);
    buckc_real x[W];                            /* the window [iL, vc, d] x delays, then the extras */
    buckc_real state_sens[BUCKC_NN_MAX_DELAYS][2][D]; /* d [iL, vc] of each window row / d block values */
    buckc_real slopes[BUCKC_NN_MAX_HIDDEN_LAYERS][W]; /* each hidden layer's activation slopes */
    int duty_block[BUCKC_NN_MAX_DELAYS];        /* the block whose value a window row's duty is (-1: none) */
    int delays = config->delays, e = config->n_extras, n_in = buckc_nn_inputs(config), last = config->n_hidden;
    int window = 3 * delays, j, r, c, h, l, o, i;
    if (n_blocks < 1 || n_blocks > D)
        return BUCKC_ERR_LIMIT;
    memcpy(x, history, sizeof(buckc_real) * (size_t)window);
    for (r = 0; r < e; ++r)
        x[window + r] = extras != NULL ? extras[r] : (buckc_real)NAN;
    memset(state_sens, 0, sizeof(state_sens));
    for (r = 0; r < delays; ++r)
        duty_block[r] = -1;
    for (j = 0; j < n; ++j) {
        /* g, gn, jin: per unit or input, the two outputs' values side by side (backward_rows) */
        buckc_real a[W], b[W], y[2], g[W][2], gn[W][2], jin[W][2], y_sens[2][D];
        const buckc_real *hv = x;
        int active = block_of_step[j] + 1, width = n_in;
        x[2] = duties[j];
        duty_block[0] = block_of_step[j];
        /* the forward pass, keeping each hidden layer's slopes */
        for (l = 0; l < last; ++l) {
            buckc_real *next = (l % 2 == 0) ? a : b;
            dense(config->weights[l], config->biases[l], hv, width, config->hidden[l], next);
            activate_with_slopes(config->activation, next, config->hidden[l], slopes[l]);
            hv = next;
            width = config->hidden[l];
        }
        dense(config->weights[last], config->biases[last], hv, width, BUCKC_NN_OUTPUTS, y);
        /* the network's Jacobian to its window inputs, backwards from the two outputs:
         * g = W_last' diag(slope), then g W_l' diag(slope) per further layer, jin = g W_0' (window rows) */
        for (h = 0; h < width; ++h) /* W_last[h][0], W_last[h][1]: both outputs' weights of unit h */
            buckc_pair_store(g[h], buckc_pair_mul(buckc_pair_load(config->weights[last][h]),
                                                  buckc_pair_splat(slopes[last - 1][h])));
        for (l = last - 1; l > 0; --l) {
            int below = config->hidden[l - 1];
            backward_rows((const buckc_real (*)[2])g, config->weights[l], below, config->hidden[l], gn);
            for (i = 0; i < below; ++i)
                buckc_pair_store(g[i], buckc_pair_mul(buckc_pair_load(gn[i]), buckc_pair_splat(slopes[l - 1][i])));
        }
        backward_rows((const buckc_real (*)[2])g, config->weights[0], window, config->hidden[0], jin);
        /* the state's sensitivity: jin times the window's (its states dense, its duties unit directions), two
         * directions per pair; where `active` is odd the last pair's second lane is the next direction, whose
         * sensitivities are zeros so far (no step has moved it yet): computed, never read */
        for (o = 0; o < 2; ++o) {
            for (c = 0; c < active; c += 2) {
                buckc_pair acc = buckc_pair_splat(zero);
                for (r = 0; r < delays; ++r)
                    acc = buckc_pair_add(acc, buckc_pair_add(
                        buckc_pair_mul(buckc_pair_splat(jin[3 * r][o]), buckc_pair_load(&state_sens[r][0][c])),
                        buckc_pair_mul(buckc_pair_splat(jin[3 * r + 1][o]), buckc_pair_load(&state_sens[r][1][c]))));
                buckc_pair_store(&y_sens[o][c], acc);
            }
            for (r = 0; r < delays; ++r)
                if (duty_block[r] >= 0)
                    y_sens[o][duty_block[r]] += jin[3 * r + 2][o];
        }
        if (config->residual) { /* + x[:2] and its sensitivity */
            for (o = 0; o < 2; ++o) {
                y[o] = y[o] + x[o];
                for (c = 0; c < active; ++c)
                    y_sens[o][c] = y_sens[o][c] + state_sens[0][o][c];
            }
        }
        if (disturbance != NULL) {
            y[0] = y[0] + disturbance[0];
            y[1] = y[1] + disturbance[1];
        }
        out[2 * j] = y[0];
        out[2 * j + 1] = y[1];
        for (o = 0; o < 2; ++o)
            for (c = 0; c < n_blocks; ++c)
                jacobian[(2 * j + o) * n_blocks + c] = c < active ? y_sens[o][c] : zero;
        if (delays > 1) { /* window[1:] = window[:-1] */
            memmove(x + 3, x, sizeof(buckc_real) * 3 * (size_t)(delays - 1));
            memmove(state_sens[1], state_sens[0], sizeof(state_sens[0]) * (size_t)(delays - 1));
            memmove(duty_block + 1, duty_block, sizeof(int) * (size_t)(delays - 1));
        }
        x[0] = y[0];
        x[1] = y[1];
        for (o = 0; o < 2; ++o)
            for (c = 0; c < D; ++c)
                state_sens[0][o][c] = c < active ? y_sens[o][c] : zero;
    }
    return BUCKC_OK;
}
