/* The part of the model interface (fmu_model.h) that a co-simulation-only model whose variables are
 * all Real has nothing to put in: fmi2GetInteger and fmi2SetInteger refuse every value reference,
 * and the model-exchange functions do nothing (the glue never calls them for a model with
 * FmuModelInfo.states == 0; they exist to satisfy the linker).
 *
 * Compiled beside fmi2_glue.c and the model by the controller FMUs (controller_fmu.c) and the
 * scenario FMUs (scenario_fmu.c); the buck plant, which has Integer parameters and model exchange,
 * implements these functions itself. */
#include "fmu_model.h"

fmi2Status model_get_integer(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Integer *value) {
    (void)data;
    (void)value;
    fmu_log(fmu, fmi2Error, "logStatusError", "fmi2GetInteger: unknown value reference %u", vr);
    return fmi2Error;
}

fmi2Status model_set_integer(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Integer value,
                             int initializing) {
    (void)data;
    (void)value;
    (void)initializing;
    fmu_log(fmu, fmi2Error, "logStatusError", "fmi2SetInteger: unknown value reference %u", vr);
    return fmi2Error;
}

void model_get_states(const void *data, double x[]) { (void)data; (void)x; }
void model_set_states(void *data, const double x[]) { (void)data; (void)x; }
void model_nominal_states(double x[]) { (void)x; }
void model_derivatives(const void *data, double dx[]) { (void)data; (void)dx; }
void model_event_indicators(const void *data, double z[]) { (void)data; (void)z; }

int model_update_discrete(FmuInstance *fmu, void *data, double *next_event_time, int *next_event_defined) {
    (void)fmu;
    (void)data;
    *next_event_time = 0.0;
    *next_event_defined = 0;
    return 0;
}
