/*
 * explicit_policy.c -- twin of controllers/explicit_policy.py: ExplicitPolicy.forward and
 * ExplicitPolicyController.reset() / step(). Layout and conventions: explicit_policy.h.
 * No allocation, libm only; buckc_real (buckc.h): one source for the double and float32 builds.
 */
#include <math.h>

#include "explicit_policy.h"
#include "load_estimate.h"

#define W BUCKC_POLICY_MAX_WIDTH

int buckc_policy_init(BuckcPolicy *policy, const BuckcPolicyConfig *config, const char **what)
{
    const buckc_real zero = BUCKC_REAL_LITERAL(0.0), one = BUCKC_REAL_LITERAL(1.0);
    int i;
    if (policy == NULL || config == NULL) {
        if (what) *what = "policy or config is NULL";
        return BUCKC_ERR_NULL;
    }
    if (!(config->sample_period > zero && isfinite(config->sample_period))) {
        if (what) *what = "sample_period: expected a finite value > 0";
        return BUCKC_ERR_INVALID;
    }
    if (!(zero <= config->duty_min && config->duty_min < config->duty_max && config->duty_max <= one)) {
        if (what) *what = "duty_min, duty_max: expected 0 <= min < max <= 1";
        return BUCKC_ERR_INVALID;
    }
    if (!(config->nominal_load > zero && isfinite(config->nominal_load))) {
        if (what) *what = "nominal_load: expected a finite value > 0";
        return BUCKC_ERR_INVALID;
    }
    if (!(config->integral_gain >= zero && isfinite(config->integral_gain) && config->integral_band >= zero &&
          isfinite(config->integral_band))) {
        if (what) *what = "integral_gain, integral_band: expected finite values >= 0";
        return BUCKC_ERR_INVALID;
    }
    if (config->n_hidden < 1) {
        if (what) *what = "policy n_hidden: expected one or more hidden layers";
        return BUCKC_ERR_INVALID;
    }
    if (config->n_hidden > BUCKC_POLICY_MAX_HIDDEN_LAYERS) {
        if (what) *what = "policy n_hidden: above BUCKC_POLICY_MAX_HIDDEN_LAYERS";
        return BUCKC_ERR_LIMIT;
    }
    for (i = 0; i < config->n_hidden; ++i) {
        if (config->hidden[i] < 1) {
            if (what) *what = "policy hidden: expected sizes >= 1";
            return BUCKC_ERR_INVALID;
        }
        if (config->hidden[i] > W) {
            if (what) *what = "policy hidden: a layer wider than BUCKC_POLICY_MAX_WIDTH";
            return BUCKC_ERR_LIMIT;
        }
    }
    policy->config = config;
    buckc_policy_reset(policy);
    return BUCKC_OK;
}

void buckc_policy_reset(BuckcPolicy *policy)
{
    const buckc_real zero = BUCKC_REAL_LITERAL(0.0);
    policy->have_history = 0;
    policy->previous_current = zero;
    policy->previous_voltage = zero;
    policy->previous_duty = zero;
    policy->conductance = BUCKC_REAL_LITERAL(1.0) / policy->config->nominal_load;
    policy->integral = zero;
    policy->last_output = (buckc_real)NAN;
}

buckc_real buckc_policy_forward(const BuckcPolicyConfig *config, const buckc_real *x)
{
    buckc_real a[W], b[W];
    const buckc_real *in = a;
    buckc_real *out = b;
    int width = config->hidden[0], layer, i, j;
    /* The sums run in the order of ExplicitPolicy.forward's (bias first, then input by input), as before;
     * written for the Cortex-M4F's sake (-O2 unrolls nothing by itself): layer 0 has BUCKC_POLICY_INPUTS
     * inputs, known when compiling, so its sums are unrolled (GCC's pragma) with the inputs held in
     * registers; the later layers' are unrolled by hand, four terms at a time. A taken loop branch costs
     * 2 to 4 cycles on that core, a multiply and an add 2 (the measurement: docs/guide/embedded.md). */
    for (j = 0; j < width; ++j) {
        buckc_real s = config->biases[0][j];
#if defined(__GNUC__) && !defined(__clang__) /* GCC 8 or later; other compilers go without the hint */
#pragma GCC unroll 16
#endif
        for (i = 0; i < BUCKC_POLICY_INPUTS; ++i)
            s += x[i] * config->weights[0][i][j];
        a[j] = BUCKC_TANH(s);
    }
    for (layer = 1; layer <= config->n_hidden; ++layer) {
        int last = layer == config->n_hidden;
        int units = last ? 1 : config->hidden[layer];
        for (j = 0; j < units; ++j) {
            const buckc_real *w = &config->weights[layer][0][j]; /* w[i * W] = W_l[i, j] */
            buckc_real s = config->biases[layer][j];
            for (i = 0; i + 4 <= width; i += 4) {
                s += in[i] * w[i * W];
                s += in[i + 1] * w[(i + 1) * W];
                s += in[i + 2] * w[(i + 2) * W];
                s += in[i + 3] * w[(i + 3) * W];
            }
            for (; i < width; ++i)
                s += in[i] * w[i * W];
            out[j] = last ? s : BUCKC_TANH(s);
        }
        in = out;
        out = out == a ? b : a;
        width = units;
    }
    return in[0];
}

int buckc_policy_step(BuckcPolicy *p, const BuckcMeasurement *m, buckc_real *duty)
{
    const BuckcPolicyConfig *c;
    const buckc_real zero = BUCKC_REAL_LITERAL(0.0);
    buckc_real x[BUCKC_POLICY_INPUTS], current, voltage, previous_current, previous_voltage, conductance, iref;
    buckc_real u, error, integral, unclamped, d;
    int pushing_high, pushing_low;
    if (p == NULL || m == NULL || duty == NULL)
        return BUCKC_ERR_NULL;
    if (!isfinite(m->inductor_current))
        return BUCKC_ERR_NO_INDUCTOR_CURRENT;
    c = p->config;
    current = m->inductor_current;
    voltage = m->output_voltage;
    conductance = buckc_estimate_conductance(voltage, m->load_current, current, p->conductance);
    previous_current = p->have_history ? p->previous_current : current;
    previous_voltage = p->have_history ? p->previous_voltage : voltage;
    iref = conductance * m->reference;
    x[0] = voltage - m->reference;
    x[1] = current - iref;
    x[2] = previous_voltage - m->reference;
    x[3] = previous_current - iref;
    x[4] = p->previous_duty;
    x[5] = m->reference;
    x[6] = conductance;
    p->conductance = conductance;
    u = buckc_policy_forward(c, x);
    error = m->reference - voltage;
    integral = p->integral;
    if (BUCKC_FABS(error) <= c->integral_band * BUCKC_FABS(m->reference))
        integral = integral + c->integral_gain * c->sample_period * error; /* (Ki Ts) e, as Python */
    unclamped = u + integral;
    d = unclamped;
    if (c->duty_min > d) d = c->duty_min; /* Python's clip order, NaN kept */
    if (c->duty_max < d) d = c->duty_max;
    pushing_high = unclamped > c->duty_max && error > zero;
    pushing_low = unclamped < c->duty_min && error < zero;
    if (!(pushing_high || pushing_low))
        p->integral = integral;
    p->previous_current = current;
    p->previous_voltage = voltage;
    p->have_history = 1;
    p->previous_duty = d;
    p->last_output = u;
    *duty = d;
    return BUCKC_OK;
}
