/*
 * compensator.h -- C twin of controllers/compensator.py (CompensatorController): a discrete voltage-mode
 * compensator (the Type-III) u/e = (b0 + b1 z^-1 + ... + bn z^-n) / (1 + a1 z^-1 + ... + an z^-n) in
 * direct form II transposed, with input-voltage feed-forward and anti-windup:
 *
 *     e = r - vo;  y = b0 e + s[0];  d = clip(y / Vs, duty_min, duty_max)
 *     unless d is saturated and e pushes it further:
 *         s[i] = b[i+1] e - a[i+1] y + s[i+1]  (i < n-1),   s[n-1] = b[n] e - a[n] y
 *     with computation_delay = 1 the duty returned is the one computed at the previous sample
 *
 * Written in buckc_real and the BUCKC_* macros (double by default; -DBUCKC_FLOAT32 for a float build).
 */
#ifndef BUCKC_COMPENSATOR_H
#define BUCKC_COMPENSATOR_H

#include "buckc.h"
/* BuckcMeasurement: buckc.h */

#define BUCKC_COMPENSATOR_MAX_ORDER 4

typedef struct {
    buckc_real sample_period;         /* [s] */
    buckc_real duty_min;              /* duty limits, 0 <= min < max <= 1 */
    buckc_real duty_max;
    buckc_real nominal_input_voltage; /* [V] used when the measurement has no supply voltage */
    int order;                        /* n, 1 .. BUCKC_COMPENSATOR_MAX_ORDER */
    buckc_real numerator[BUCKC_COMPENSATOR_MAX_ORDER + 1];   /* b0 .. bn [V/V] */
    buckc_real denominator[BUCKC_COMPENSATOR_MAX_ORDER + 1]; /* 1, a1 .. an */
    int computation_delay;            /* [samples] 0 or 1 */
} BuckcCompensatorConfig;

typedef struct {
    BuckcCompensatorConfig config;
    buckc_real state[BUCKC_COMPENSATOR_MAX_ORDER];
    buckc_real pending_duty;
} BuckcCompensator;

/* Validate like CompensatorController.__init__ and reset; *what (if not NULL) names a refused field. */
int buckc_compensator_init(BuckcCompensator *controller, const BuckcCompensatorConfig *config, const char **what);
void buckc_compensator_reset(BuckcCompensator *controller);
/* CompensatorController.step: *duty receives the duty to hold until the next sample. */
int buckc_compensator_step(BuckcCompensator *controller, const BuckcMeasurement *measurement, buckc_real *duty);

#endif
