/* The controller object (buckc_controller.h): one instance of the controller the generated
 * headers select. controller_config.h (controllers/codegen.py) is data only; controller_entry.h
 * (cosim/benchmark_harness/cortex_m4.py, from its table of controllers) names the state type and
 * the init/reset/step calls of that controller's C twin as CONTROLLER_STATE, CONTROLLER_INIT,
 * CONTROLLER_RESET and CONTROLLER_STEP, written over the names `state`, `what`, `m`, `duty`. */
#include "buckc_controller.h"

#include "controller_config.h"
#include "controller_entry.h"

static CONTROLLER_STATE controller_state;

int buckc_controller_init(const char **what)
{
    CONTROLLER_STATE *state = &controller_state;
    return CONTROLLER_INIT;
}

void buckc_controller_reset(void)
{
    CONTROLLER_STATE *state = &controller_state;
    CONTROLLER_RESET;
}

int buckc_controller_step(const BuckcMeasurement *m, buckc_real *duty)
{
    CONTROLLER_STATE *state = &controller_state;
    return CONTROLLER_STEP;
}
