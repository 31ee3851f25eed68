/*
 * current_mode.c -- twin of controllers/current_mode.py: CurrentModeController.__init__ (validation),
 * reset() and step(), operation by operation (see current_mode.h).
 */
#include <math.h>

#include "current_mode.h"

static int finite_nonnegative(buckc_real x) { return isfinite(x) && x >= BUCKC_REAL_LITERAL(0.0); }

int buckc_current_mode_init(BuckcCurrentMode *c, const BuckcCurrentModeConfig *config, const char **what)
{
    if (c == NULL || config == NULL) {
        if (what) *what = "controller or config is NULL";
        return BUCKC_ERR_NULL;
    }
    if (!(finite_nonnegative(config->kp_voltage) && finite_nonnegative(config->ki_voltage)
          && finite_nonnegative(config->kp_current) && finite_nonnegative(config->ki_current))) {
        if (what) *what = "kp_voltage, ki_voltage, kp_current, ki_current: expected finite values >= 0";
        return BUCKC_ERR_INVALID;
    }
    if (!(isfinite(config->current_limit) && config->current_limit > BUCKC_REAL_LITERAL(0.0))) {
        if (what) *what = "current_limit: expected a finite value > 0";
        return BUCKC_ERR_INVALID;
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
    buckc_current_mode_reset(c);
    return BUCKC_OK;
}

void buckc_current_mode_reset(BuckcCurrentMode *c)
{
    c->voltage_integral = BUCKC_REAL_LITERAL(0.0);
    c->current_integral = BUCKC_REAL_LITERAL(0.0);
    c->pending_duty = BUCKC_REAL_LITERAL(0.0);
}

int buckc_current_mode_step(BuckcCurrentMode *c, const BuckcMeasurement *m, buckc_real *duty)
{
    const BuckcCurrentModeConfig *g;
    buckc_real zero = BUCKC_REAL_LITERAL(0.0);
    buckc_real error_v, integral_v, reference_unclamped, reference, error_i, integral_i, node, supply;
    buckc_real unclamped, d, low, high, vin;
    if (c == NULL || m == NULL || duty == NULL)
        return BUCKC_ERR_NULL;
    if (!isfinite(m->inductor_current))
        return BUCKC_ERR_NO_INDUCTOR_CURRENT;
    g = &c->config;
    error_v = (buckc_real)m->reference - (buckc_real)m->output_voltage;
    integral_v = c->voltage_integral + g->ki_voltage * g->sample_period * error_v; /* (ki Ts) e, as Python */
    reference_unclamped = g->kp_voltage * error_v + integral_v;
    reference = reference_unclamped;
    if (zero > reference) reference = zero;   /* min(max(x, 0), I_max), NaN kept */
    if (g->current_limit < reference) reference = g->current_limit;
    if (!((reference_unclamped > g->current_limit && error_v > zero) || (reference_unclamped < zero && error_v < zero)))
        c->voltage_integral = integral_v;
    error_i = reference - (buckc_real)m->inductor_current;
    integral_i = c->current_integral + g->ki_current * g->sample_period * error_i;
    node = g->kp_current * error_i + integral_i;
    vin = (buckc_real)m->input_voltage;
    supply = (isfinite(vin) && vin > zero) ? vin : g->nominal_input_voltage;
    unclamped = node / supply;
    low = g->duty_min;
    high = g->duty_max;
    d = unclamped;
    if (low > d) d = low;
    if (high < d) d = high;
    if (!((unclamped > high && error_i > zero) || (unclamped < low && error_i < zero)))
        c->current_integral = integral_i;
    if (g->computation_delay) {
        buckc_real applied = c->pending_duty;
        c->pending_duty = d;
        d = applied;
    }
    *duty = d;
    return BUCKC_OK;
}
