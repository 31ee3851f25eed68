/* The load estimate: C twin of controllers/load_estimate.py (estimate_conductance).
 *
 * G = io / vo from the load-current and output-voltage sensors; iL / vo without a load-current
 * sensor (NaN); the previous estimate while vo <= BUCKC_MIN_VOLTAGE or the current is at most
 * BUCKC_MIN_CURRENT. The same constants as MIN_VOLTAGE / MIN_CURRENT there (a test checks); in
 * the float32 build they are the floats nearest to them. */
#ifndef BUCKC_LOAD_ESTIMATE_H
#define BUCKC_LOAD_ESTIMATE_H

#include "buckc.h"

#define BUCKC_MIN_VOLTAGE BUCKC_REAL_LITERAL(0.05) /* [V] */
#define BUCKC_MIN_CURRENT BUCKC_REAL_LITERAL(1e-6) /* [A] */

/* the load conductance 1/R [S] from one sample of the sensors */
buckc_real buckc_estimate_conductance(buckc_real output_voltage, buckc_real load_current,
                                      buckc_real inductor_current, buckc_real previous);

#endif
