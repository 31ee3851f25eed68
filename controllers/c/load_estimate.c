/* Twin of controllers/load_estimate.py: estimate_conductance. */
#include "load_estimate.h"

#include <math.h>

double buckc_estimate_conductance(double output_voltage, double load_current, double inductor_current,
                                  double previous)
{
    if (output_voltage > BUCKC_MIN_VOLTAGE) {
        double current = isfinite(load_current) ? load_current : inductor_current;
        if (current > BUCKC_MIN_CURRENT) /* false for NaN too */
            return current / output_voltage;
    }
    return previous;
}
