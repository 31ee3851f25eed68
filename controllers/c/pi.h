/*
 * pi.h -- C twin of controllers/pi.py (PIController): discrete PI with duty limits and
 * anti-windup by conditional integration.
 */
#ifndef BUCKC_PI_H
#define BUCKC_PI_H

#include "buckc.h"

typedef struct {
    buckc_real kp;            /* [1/V] duty per volt of error */
    buckc_real ki;            /* [1/(V s)] */
    buckc_real sample_period; /* [s] */
    buckc_real duty_min;      /* duty limits, 0 <= min < max <= 1 */
    buckc_real duty_max;
} BuckcPiConfig;

typedef struct {
    BuckcPiConfig config; /* a copy: the PI's configuration is five numbers */
    buckc_real integral;
} BuckcPi;

/* Validate like PIController.__init__ and reset; *what (if not NULL) names a refused field. */
int buckc_pi_init(BuckcPi *pi, const BuckcPiConfig *config, const char **what);
void buckc_pi_reset(BuckcPi *pi);
/* PIController.step: the duty to hold until the next sample. */
buckc_real buckc_pi_step(BuckcPi *pi, buckc_real reference, buckc_real output_voltage);

#endif
