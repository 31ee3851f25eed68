/* The load estimate: C twin of controllers/load_estimate.py (estimate_conductance).
 *
 * G = io / vo from the load-current and output-voltage sensors; iL / vo without a load-current
 * sensor (NaN); the previous estimate while vo <= BUCKC_MIN_VOLTAGE or the current is at most
 * BUCKC_MIN_CURRENT. The same constants as MIN_VOLTAGE / MIN_CURRENT there (a test checks). */
#ifndef BUCKC_LOAD_ESTIMATE_H
#define BUCKC_LOAD_ESTIMATE_H

#define BUCKC_MIN_VOLTAGE 0.05 /* [V] */
#define BUCKC_MIN_CURRENT 1e-6 /* [A] */

/* the load conductance 1/R [S] from one sample of the sensors */
double buckc_estimate_conductance(double output_voltage, double load_current, double inductor_current,
                                  double previous);

#endif
