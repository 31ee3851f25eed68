/* Twin of controllers/load_estimate.py: estimate_conductance. */
#include "load_estimate.h"

#include <math.h>

buckc_real buckc_estimate_conductance(buckc_real output_voltage, buckc_real load_current,
                                      buckc_real inductor_current, buckc_real previous)
{
    if (output_voltage > BUCKC_MIN_VOLTAGE) {
        buckc_real current = isfinite(load_current) ? load_current : inductor_current;
        if (current > BUCKC_MIN_CURRENT) /* false for NaN too */
            return current / output_voltage;
    }
    return previous;
}
