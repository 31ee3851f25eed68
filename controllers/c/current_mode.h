/*
 * current_mode.h -- C twin of controllers/current_mode.py (CurrentModeController): average-current-mode
 * control, an inner inductor-current PI inside an outer output-voltage PI.
 *
 *     e_v = r - vo;  I_v += ki_v Ts e_v (conditional);  i_ref = clip(kp_v e_v + I_v, 0, I_max)
 *     e_i = i_ref - iL;  I_i += ki_i Ts e_i (conditional);  u = kp_i e_i + I_i  [V]
 *     d = clip(u / Vs, duty_min, duty_max)     Vs measured if finite and > 0, else nominal
 *     with computation_delay = 1 the duty returned is the one computed at the previous sample
 *
 * Written in buckc_real and the BUCKC_* macros (double by default; -DBUCKC_FLOAT32 for a float build).
 */
#ifndef BUCKC_CURRENT_MODE_H
#define BUCKC_CURRENT_MODE_H

#include "buckc.h"
/* BuckcMeasurement: buckc.h */

typedef struct {
    buckc_real sample_period;         /* [s] */
    buckc_real duty_min;              /* duty limits, 0 <= min < max <= 1 */
    buckc_real duty_max;
    buckc_real nominal_input_voltage; /* [V] used when the measurement has no supply voltage */
    buckc_real kp_voltage;            /* [A/V] outer loop */
    buckc_real ki_voltage;            /* [A/(V s)] */
    buckc_real kp_current;            /* [V/A] inner loop */
    buckc_real ki_current;            /* [V/(A s)] */
    buckc_real current_limit;         /* [A] largest inductor-current reference */
    int computation_delay;            /* [samples] 0 or 1 */
} BuckcCurrentModeConfig;

typedef struct {
    BuckcCurrentModeConfig config;    /* a copy: ten numbers */
    buckc_real voltage_integral;      /* [A] */
    buckc_real current_integral;      /* [V] */
    buckc_real pending_duty;          /* computed at the last sample, applied at this one (delay 1) */
} BuckcCurrentMode;

/* Validate like CurrentModeController.__init__ and reset; *what (if not NULL) names a refused field. */
int buckc_current_mode_init(BuckcCurrentMode *controller, const BuckcCurrentModeConfig *config, const char **what);
void buckc_current_mode_reset(BuckcCurrentMode *controller);
/* CurrentModeController.step: *duty receives the duty to hold until the next sample. */
int buckc_current_mode_step(BuckcCurrentMode *controller, const BuckcMeasurement *measurement, buckc_real *duty);

#endif
