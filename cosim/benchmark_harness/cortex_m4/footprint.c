/* The smallest program around the controller object, for its flash and RAM footprint: built once
 * with the controller's calls and once without (-DBUCKC_BASELINE); the difference in text, data
 * and bss is what the controller (its code, its configuration, the library functions it calls and
 * its state) adds to a firmware. Inputs and output are volatile so nothing is folded away. */
#include "buckc_controller.h"

volatile BuckcMeasurement footprint_input;
volatile buckc_real footprint_output;

int main(void)
{
#ifndef BUCKC_BASELINE
    const char *what = 0;
    BuckcMeasurement m;
    buckc_real duty = 0;
    if (buckc_controller_init(&what) != BUCKC_OK) return 1;
    m.time = footprint_input.time;
    m.reference = footprint_input.reference;
    m.output_voltage = footprint_input.output_voltage;
    m.inductor_current = footprint_input.inductor_current;
    m.load_current = footprint_input.load_current;
    m.input_voltage = footprint_input.input_voltage;
    if (buckc_controller_step(&m, &duty) != BUCKC_OK) return 1;
    footprint_output = duty;
#else
    footprint_output = footprint_input.reference;
#endif
    return 0;
}
