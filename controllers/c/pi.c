/*
 * pi.c -- twin of controllers/pi.py: PIController.__init__ (validation), reset() and step().
 *
 *   e(k) = v_ref(k) - v_o(k)
 *   I(k) = I(k-1) + K_i T_s e(k)   -- kept only if it does not push a saturated duty further
 *   d(k) = clip(K_p e(k) + I(k), d_min, d_max)
 */
#include <math.h>

#include "pi.h"

int buckc_pi_init(BuckcPi *pi, const BuckcPiConfig *config, const char **what)
{
    const buckc_real zero = BUCKC_REAL_LITERAL(0.0), one = BUCKC_REAL_LITERAL(1.0);
    if (pi == NULL || config == NULL) {
        if (what) *what = "pi or config is NULL";
        return BUCKC_ERR_NULL;
    }
    if (!(isfinite(config->kp) && isfinite(config->ki) && config->kp >= zero && config->ki >= zero)) {
        if (what) *what = "kp, ki: expected finite values >= 0";
        return BUCKC_ERR_INVALID;
    }
    if (!(config->sample_period > zero && isfinite(config->sample_period))) {
        if (what) *what = "sample_period: expected a finite value > 0";
        return BUCKC_ERR_INVALID;
    }
    if (!(zero <= config->duty_min && config->duty_min < config->duty_max && config->duty_max <= one)) {
        if (what) *what = "duty_min, duty_max: expected 0 <= min < max <= 1";
        return BUCKC_ERR_INVALID;
    }
    pi->config = *config;
    pi->integral = zero;
    return BUCKC_OK;
}

void buckc_pi_reset(BuckcPi *pi)
{
    pi->integral = BUCKC_REAL_LITERAL(0.0);
}

buckc_real buckc_pi_step(BuckcPi *pi, buckc_real reference, buckc_real output_voltage)
{
    const BuckcPiConfig *c = &pi->config;
    const buckc_real zero = BUCKC_REAL_LITERAL(0.0);
    buckc_real error = reference - output_voltage;
    buckc_real low = c->duty_min, high = c->duty_max;
    buckc_real integral = pi->integral + c->ki * c->sample_period * error; /* (ki Ts) e, as Python */
    buckc_real unclamped = c->kp * error + integral;
    buckc_real duty = unclamped;
    int pushing_high, pushing_low;
    if (low > duty) duty = low;   /* Python's min(max(unclamped, low), high), NaN kept */
    if (high < duty) duty = high;
    pushing_high = unclamped > high && error > zero;
    pushing_low = unclamped < low && error < zero;
    if (!(pushing_high || pushing_low))
        pi->integral = integral;
    return duty;
}
