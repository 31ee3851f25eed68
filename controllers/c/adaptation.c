/*
 * adaptation.c -- twin of controllers/adaptation.py (AdaptiveNNPC: __init__, reset, step, _learn, _write);
 * see adaptation.h.
 */
#include <math.h>
#include <string.h>

#include "adaptation.h"
#include "load_estimate.h"

#define FAIL(code, text) do { if (what) *what = (text); return (code); } while (0)
#define F BUCKC_ADAPT_MAX_FEATURES

size_t buckc_adaptive_size(void)
{
    return sizeof(BuckcAdaptive);
}

/* the output layer of the NNPC's network: rows of the last hidden layer's units, then the bias */
static void write_output_layer(BuckcAdaptive *a, const buckc_real (*theta)[2])
{
    BuckcNnConfig *nn = &a->predictive.predictor.nn;
    int layer = nn->n_hidden, i, j, h = a->features - 1;
    for (i = 0; i < h; ++i)
        for (j = 0; j < 2; ++j)
            nn->weights[layer][i][j] = theta[i][j];
    for (j = 0; j < 2; ++j)
        nn->biases[layer][j] = theta[h][j];
}

/* np.linalg.norm(x, axis=0) of an (n, 2) array */
static void column_norms(const buckc_real (*x)[2], int n, buckc_real norms[2])
{
    int i, j;
    for (j = 0; j < 2; ++j) {
        buckc_real sum = x[0][j] * x[0][j];
        for (i = 1; i < n; ++i)
            sum += x[i][j] * x[i][j];
        norms[j] = BUCKC_SQRT(sum);
    }
}

/* np.minimum(1.0, limit / np.maximum(norm, 1e-300)) */
static buckc_real shrink(buckc_real limit, buckc_real norm)
{
    buckc_real floor_ = BUCKC_REAL_LITERAL(1e-300), factor = limit / (norm > floor_ ? norm : floor_);
    return factor < BUCKC_REAL_LITERAL(1.0) ? factor : BUCKC_REAL_LITERAL(1.0);
}

int buckc_adaptive_init(BuckcAdaptive *a, const BuckcPredictiveConfig *predictive, const BuckcAdaptationConfig *config,
                        const char **what)
{
    const BuckcAdaptationSettings *s;
    const BuckcNnConfig *nn;
    int status, i, j;
    if (a == NULL || predictive == NULL || config == NULL)
        FAIL(BUCKC_ERR_NULL, "adaptive controller, predictive config or adaptation config is NULL");
    s = &config->settings;
    if (!(s->forgetting > 0 && s->forgetting <= 1))
        FAIL(BUCKC_ERR_INVALID, "forgetting: expected 0 < lambda <= 1");
    if (!(s->initial_covariance > 0 && s->max_step > 0 && s->max_deviation > 0))
        FAIL(BUCKC_ERR_INVALID, "initial_covariance, max_step and max_deviation: expected > 0");
    if (!(s->error_memory > 0 && s->error_memory < 1) || !(s->fallback_ratio > 1) || s->checkpoint_every < 1)
        FAIL(BUCKC_ERR_INVALID, "error_memory: expected in (0, 1), fallback_ratio > 1 and checkpoint_every >= 1");
    if (!(config->nominal_load > 0))
        FAIL(BUCKC_ERR_INVALID, "nominal_load: expected > 0");
    if (predictive->predictor.kind != BUCKC_PREDICTOR_NN)
        FAIL(BUCKC_ERR_INVALID, "predictor kind: the adaptation adapts the NN predictor's network");
    nn = &predictive->predictor.nn;
    status = buckc_nn_check(nn, what);
    if (status != BUCKC_OK)
        return status;
    if (nn->residual)
        FAIL(BUCKC_ERR_INVALID, "residual: the adaptation adapts networks that predict the state itself");
    for (i = 0; i < nn->n_extras; ++i)
        if (nn->extras[i] == BUCKC_EXTRA_INPUT_VOLTAGE && !isfinite(config->nominal_input_voltage))
            FAIL(BUCKC_ERR_INVALID, "nominal_input_voltage: the network takes the supply voltage as an input");
    memset(a, 0, sizeof(*a));
    a->predictive = *predictive;
    a->config = *config;
    nn = &a->predictive.predictor.nn;
    a->features = nn->hidden[nn->n_hidden - 1] + 1;
    for (i = 0; i < a->features - 1; ++i) /* np.vstack([weights, bias]) of the offline network */
        for (j = 0; j < 2; ++j)
            a->offline[i][j] = nn->weights[nn->n_hidden][i][j];
    for (j = 0; j < 2; ++j)
        a->offline[a->features - 1][j] = nn->biases[nn->n_hidden][j];
    column_norms((const buckc_real (*)[2])a->offline, a->features, a->offline_norm);
    status = buckc_predictive_init(&a->inner, &a->predictive, what);
    if (status != BUCKC_OK)
        return status;
    buckc_adaptive_reset(a);
    return BUCKC_OK;
}

void buckc_adaptive_reset(BuckcAdaptive *a)
{
    int n = a->features, i;
    buckc_predictive_reset(&a->inner);
    memcpy(a->theta, a->offline, sizeof(a->theta));
    write_output_layer(a, (const buckc_real (*)[2])a->theta);
    memset(a->covariance, 0, sizeof(a->covariance));
    for (i = 0; i < n; ++i)
        a->covariance[i][i] = a->config.settings.initial_covariance;
    memcpy(a->good_theta, a->theta, sizeof(a->theta));
    memcpy(a->good_covariance, a->covariance, sizeof(a->covariance));
    a->error = a->good_error = 0;
    a->errors_seen = a->since_checkpoint = 0;
    a->have_input = 0;
    a->history_count = 0;
    a->conductance = BUCKC_REAL_LITERAL(1.0) / a->config.nominal_load;
    memset(a->counters, 0, sizeof(a->counters));
}

/* AdaptiveNNPC._learn: x the network input of the previous sample, measured = [iL, vo] now */
static void learn(BuckcAdaptive *a, const buckc_real *x, const buckc_real measured[2], buckc_real conductance)
{
    const BuckcAdaptationSettings *s = &a->config.settings;
    const BuckcNnConfig *nn = &a->predictive.predictor.nn;
    const buckc_real one = BUCKC_REAL_LITERAL(1.0);
    int n = a->features, delays = nn->delays, i, k, j, bounded;
    buckc_real phi[F], error[2], good_error[2], p_phi[F], gain[F], step[F][2], theta[F][2], norms[2], limit[2];
    buckc_real memory = s->error_memory, denominator, previous, trace, cap, low, high;
    int *counters = a->counters;
    counters[BUCKC_ADAPT_SAMPLES] += 1;
    buckc_nn_features(nn, x, phi);
    phi[n - 1] = one;
    for (j = 0; j < 2; ++j) { /* measured - phi @ theta, and with the last good theta */
        buckc_real fit = phi[0] * a->theta[0][j], good = phi[0] * a->good_theta[0][j];
        for (i = 1; i < n; ++i) {
            fit += phi[i] * a->theta[i][j];
            good += phi[i] * a->good_theta[i][j];
        }
        error[j] = measured[j] - fit;
        good_error[j] = measured[j] - good;
    }
    a->error = memory * a->error + (one - memory) * (error[0] * error[0] * a->config.output_scale[0]
                                                     + error[1] * error[1] * a->config.output_scale[1]);
    a->good_error = memory * a->good_error + (one - memory) * (good_error[0] * good_error[0] * a->config.output_scale[0]
                                                               + good_error[1] * good_error[1] * a->config.output_scale[1]);
    a->errors_seen += 1;
    a->since_checkpoint += 1;
    if (a->errors_seen >= s->warmup) {
        if (a->error > s->fallback_ratio * a->good_error) { /* the adapted model got worse: back to the last good */
            memcpy(a->theta, a->good_theta, sizeof(a->theta));
            memcpy(a->covariance, a->good_covariance, sizeof(a->covariance));
            write_output_layer(a, (const buckc_real (*)[2])a->theta);
            a->error = a->good_error;
            counters[BUCKC_ADAPT_FALLBACKS] += 1;
            a->since_checkpoint = 0;
            return;
        }
        if (a->since_checkpoint >= s->checkpoint_every) {
            if (a->error <= a->good_error) {
                memcpy(a->good_theta, a->theta, sizeof(a->theta));
                memcpy(a->good_covariance, a->covariance, sizeof(a->covariance));
                a->good_error = a->error;
                counters[BUCKC_ADAPT_CHECKPOINTS] += 1;
            }
            a->since_checkpoint = 0;
        }
    }
    low = a->predictive.duty_min;
    high = a->predictive.duty_max;
    for (k = 2; k < 3 * delays; k += 3) /* the duties of the window: x[2::3] */
        if (x[k] <= low + s->duty_margin || x[k] >= high - s->duty_margin) {
            counters[BUCKC_ADAPT_SATURATED] += 1;
            return;
        }
    previous = a->input_conductance;
    if (previous > 0 && BUCKC_FABS(conductance - previous) > s->load_change * previous) {
        counters[BUCKC_ADAPT_LOAD_STEP] += 1;
        return;
    }
    if (!(BUCKC_FABS(measured[0] - x[0]) > s->min_change_current || BUCKC_FABS(measured[1] - x[1]) > s->min_change_voltage
          || (delays > 1 && BUCKC_FABS(x[2] - x[5]) > s->min_change_duty))) {
        counters[BUCKC_ADAPT_STEADY] += 1;
        return;
    }
    for (i = 0; i < n; ++i) { /* P phi, lambda + phi P phi */
        buckc_real sum = a->covariance[i][0] * phi[0];
        for (k = 1; k < n; ++k)
            sum += a->covariance[i][k] * phi[k];
        p_phi[i] = sum;
    }
    denominator = phi[0] * p_phi[0];
    for (i = 1; i < n; ++i)
        denominator += phi[i] * p_phi[i];
    denominator = s->forgetting + denominator;
    for (i = 0; i < n; ++i) {
        gain[i] = p_phi[i] / denominator;
        for (j = 0; j < 2; ++j)
            step[i][j] = gain[i] * error[j];
    }
    column_norms((const buckc_real (*)[2])step, n, norms);
    bounded = 0;
    for (j = 0; j < 2; ++j) {
        limit[j] = s->max_step * a->offline_norm[j];
        bounded |= norms[j] > limit[j];
    }
    if (bounded) { /* each output's step shortened to its limit */
        for (j = 0; j < 2; ++j) {
            buckc_real factor = shrink(limit[j], norms[j]);
            for (i = 0; i < n; ++i)
                step[i][j] *= factor;
        }
        counters[BUCKC_ADAPT_BOUNDED] += 1;
    }
    for (i = 0; i < n; ++i)
        for (j = 0; j < 2; ++j) {
            theta[i][j] = a->theta[i][j] + step[i][j];
            step[i][j] = theta[i][j] - a->offline[i][j]; /* now the deviation from the offline weights */
        }
    column_norms((const buckc_real (*)[2])step, n, norms);
    bounded = 0;
    for (j = 0; j < 2; ++j) {
        limit[j] = s->max_deviation * a->offline_norm[j];
        bounded |= norms[j] > limit[j];
    }
    if (bounded) { /* pulled back towards the offline weights */
        for (j = 0; j < 2; ++j) {
            buckc_real factor = shrink(limit[j], norms[j]);
            for (i = 0; i < n; ++i)
                theta[i][j] = a->offline[i][j] + step[i][j] * factor;
        }
        counters[BUCKC_ADAPT_BOUNDED] += 1;
    }
    memcpy(a->theta, theta, sizeof(theta));
    trace = 0;
    for (i = 0; i < n; ++i) { /* (P - gain p_phi^T) / lambda, its trace capped, symmetrised */
        for (k = 0; k < n; ++k)
            a->covariance[i][k] = (a->covariance[i][k] - gain[i] * p_phi[k]) / s->forgetting;
    }
    for (i = 0; i < n; ++i)
        trace += a->covariance[i][i];
    cap = s->initial_covariance * (buckc_real)n;
    if (trace > cap) {
        buckc_real factor = cap / trace;
        for (i = 0; i < n; ++i)
            for (k = 0; k < n; ++k)
                a->covariance[i][k] *= factor;
    }
    for (i = 0; i < n; ++i)
        for (k = i; k < n; ++k) {
            buckc_real mean = BUCKC_REAL_LITERAL(0.5) * (a->covariance[i][k] + a->covariance[k][i]);
            a->covariance[i][k] = a->covariance[k][i] = mean;
        }
    write_output_layer(a, (const buckc_real (*)[2])a->theta);
    counters[BUCKC_ADAPT_UPDATES] += 1;
}

const int *buckc_adaptive_counters(const BuckcAdaptive *a)
{
    return a->counters;
}

void buckc_adaptive_output_layer(const BuckcAdaptive *a, buckc_real *theta)
{
    memcpy(theta, a->theta, sizeof(buckc_real) * 2 * (size_t)a->features);
}

BuckcPredictive *buckc_adaptive_inner(BuckcAdaptive *a)
{
    return &a->inner;
}

int buckc_adaptive_step(BuckcAdaptive *a, const BuckcMeasurement *m, buckc_real *duty)
{
    const BuckcNnConfig *nn = &a->predictive.predictor.nn;
    buckc_real state[2], conductance, supply;
    int status, d, e, delays = nn->delays;
    if (m == NULL || duty == NULL)
        return BUCKC_ERR_NULL;
    state[0] = m->inductor_current;
    state[1] = m->output_voltage;
    conductance = a->conductance = buckc_estimate_conductance(m->output_voltage, m->load_current, m->inductor_current,
                                                              a->conductance);
    if (a->have_input && isfinite(state[0]))
        learn(a, a->input, state, conductance);
    status = buckc_predictive_step(&a->inner, m, duty);
    if (status != BUCKC_OK)
        return status;
    for (d = (a->history_count < delays ? a->history_count : delays - 1); d >= 1; --d) /* insert at the front */
        memcpy(a->history[d], a->history[d - 1], sizeof(a->history[d]));
    a->history[0][0] = state[0];
    a->history[0][1] = state[1];
    a->history[0][2] = *duty;
    if (a->history_count < delays)
        a->history_count += 1;
    if (a->history_count == delays) {
        /* a plant without a supply reading: the nominal supply, as the controller's predictor assumes it */
        supply = isfinite(m->input_voltage) ? m->input_voltage : a->config.nominal_input_voltage;
        for (d = 0; d < delays; ++d)
            for (e = 0; e < 3; ++e)
                a->input[3 * d + e] = a->history[d][e];
        for (e = 0; e < nn->n_extras; ++e) {
            switch (nn->extras[e]) {
            case BUCKC_EXTRA_LOAD_CURRENT: a->input[3 * delays + e] = m->load_current; break;
            case BUCKC_EXTRA_INPUT_VOLTAGE: a->input[3 * delays + e] = supply; break;
            default: a->input[3 * delays + e] = conductance; break;
            }
        }
        a->input_conductance = conductance;
        a->have_input = 1;
    }
    return BUCKC_OK;
}
