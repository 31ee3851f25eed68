/*
 * compensator.c -- twin of controllers/compensator.py: CompensatorController.__init__ (validation),
 * reset() and step(), operation by operation (see compensator.h).
 */
#include <math.h>

#include "compensator.h"

int buckc_compensator_init(BuckcCompensator *c, const BuckcCompensatorConfig *config, const char **what)
{
    int i;
    if (c == NULL || config == NULL) {
        if (what) *what = "controller or config is NULL";
        return BUCKC_ERR_NULL;
    }
    if (config->order < 1 || config->order > BUCKC_COMPENSATOR_MAX_ORDER) {
        if (what) *what = "order: expected 1 .. BUCKC_COMPENSATOR_MAX_ORDER";
        return config->order < 1 ? BUCKC_ERR_INVALID : BUCKC_ERR_LIMIT;
    }
    if (config->denominator[0] != BUCKC_REAL_LITERAL(1.0)) {
        if (what) *what = "denominator[0]: expected 1";
        return BUCKC_ERR_INVALID;
    }
    for (i = 0; i <= config->order; i++) {
        if (!(isfinite(config->numerator[i]) && isfinite(config->denominator[i]))) {
            if (what) *what = "numerator, denominator: expected finite values";
            return BUCKC_ERR_INVALID;
        }
    }
    if (config->computation_delay != 0 && config->computation_delay != 1) {
        if (what) *what = "computation_delay: expected 0 or 1";
        return BUCKC_ERR_INVALID;
    }
    if (!(config->sample_period > BUCKC_REAL_LITERAL(0.0) && isfinite(config->sample_period))) {
        if (what) *what = "sample_period: expected a finite value > 0";
        return BUCKC_ERR_INVALID;
    }
    if (!(BUCKC_REAL_LITERAL(0.0) <= config->duty_min && config->duty_min < config->duty_max
          && config->duty_max <= BUCKC_REAL_LITERAL(1.0))) {
        if (what) *what = "duty_min, duty_max: expected 0 <= min < max <= 1";
        return BUCKC_ERR_INVALID;
    }
    if (!(isfinite(config->nominal_input_voltage) && config->nominal_input_voltage > BUCKC_REAL_LITERAL(0.0))) {
        if (what) *what = "nominal_input_voltage: expected a finite value > 0";
        return BUCKC_ERR_INVALID;
    }
    c->config = *config;
    buckc_compensator_reset(c);
    return BUCKC_OK;
}

void buckc_compensator_reset(BuckcCompensator *c)
{
    int i;
    for (i = 0; i < BUCKC_COMPENSATOR_MAX_ORDER; i++)
        c->state[i] = BUCKC_REAL_LITERAL(0.0);
    c->pending_duty = BUCKC_REAL_LITERAL(0.0);
}

int buckc_compensator_step(BuckcCompensator *c, const BuckcMeasurement *m, buckc_real *duty)
{
    const BuckcCompensatorConfig *g;
    const buckc_real *b, *a;
    buckc_real *s;
    buckc_real zero = BUCKC_REAL_LITERAL(0.0);
    buckc_real error, y, supply, unclamped, d, low, high, vin;
    int i, n;
    if (c == NULL || m == NULL || duty == NULL)
        return BUCKC_ERR_NULL;
    g = &c->config;
    b = g->numerator;
    a = g->denominator;
    s = c->state;
    n = g->order;
    error = (buckc_real)m->reference - (buckc_real)m->output_voltage;
    y = b[0] * error + s[0];
    vin = (buckc_real)m->input_voltage;
    supply = (isfinite(vin) && vin > zero) ? vin : g->nominal_input_voltage;
    unclamped = y / supply;
    low = g->duty_min;
    high = g->duty_max;
    d = unclamped;
    if (low > d) d = low;
    if (high < d) d = high;
    if (!((unclamped > high && error > zero) || (unclamped < low && error < zero))) {
        for (i = 0; i < n - 1; i++)
            s[i] = b[i + 1] * error - a[i + 1] * y + s[i + 1];
        s[n - 1] = b[n] * error - a[n] * y;
    }
    if (g->computation_delay) {
        buckc_real applied = c->pending_duty;
        c->pending_duty = d;
        d = applied;
    }
    *duty = d;
    return BUCKC_OK;
}
