/* A controller of controllers/c as one object for a microcontroller's control interrupt.
 *
 * controller_instance.c holds the controller's state (static, in .bss) and its generated
 * configuration (static const, in flash) and offers three calls; a firmware calls
 * buckc_controller_step() from its ADC/PWM interrupt with the sampled sensors in SI units and
 * writes the duty to the PWM compare register. Which controller it is (PI, explicit NNPC, ...)
 * is decided when the object is built (cosim/benchmark_harness/cortex_m4.py: EMBEDDED_CONTROLLERS). */
#ifndef BUCKC_CONTROLLER_H
#define BUCKC_CONTROLLER_H

#include "buckc.h"

/* Check the configuration and reset; BUCKC_OK, else a status and *what naming the refused field. */
int buckc_controller_init(const char **what);
/* Forget the controller's history (as at start-up). */
void buckc_controller_reset(void);
/* One control sample: the measurement in, *duty (0..1) out; BUCKC_OK or a status. */
int buckc_controller_step(const BuckcMeasurement *measurement, buckc_real *duty);

#endif
