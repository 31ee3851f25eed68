/* A scenario as an FMU model (fmu_model.h): a signal source with no inputs whose outputs follow a
 * workbench scenario's events, so a system of FMUs (an SSP) needs no tool-specific input files.
 *
 * The events come from the generated scenario_config.h (data only: the three piecewise-constant
 * schedules in the FMU's time, i.e. plant time, with the settle interval already added). Each
 * output is the value of the last change at or before the FMU's time, within SCENARIO_TOLERANCE
 * (the workbench master's MERGE_TOLERANCE, 1e-12 s): read at a communication point that is an
 * event instant, an output already holds the new value, as the master applies a load or supply
 * event right after stepping the plant to it and a reference change at the control sample at or
 * after it. Before the first change the initial value holds. The FMI 2.0 glue is the plant's
 * (fmi2_glue.c); co-simulation only. */
#include <string.h>

#include "fmu_model.h"
#include "scenario_schedule.h"

#include "scenario_config.h" /* generated: SCENARIO_NAME, SCENARIO_GUID, SCENARIO_TOLERANCE, the schedules */

enum { VR_REFERENCE = 0, VR_LOAD_RESISTANCE = 1, VR_INPUT_VOLTAGE = 2, SIGNALS = 3 };

typedef struct {
    double time; /* the FMU's clock [s] */
} ScenarioData;

const FmuModelInfo FMU_MODEL = {
    SCENARIO_GUID,
    SCENARIO_NAME,
    sizeof(ScenarioData),
    0, /* co-simulation only */
    0,
    0x42435343u, /* "BCSC" */
    1u,
};

static const ScenarioSchedule *const SCHEDULES[SIGNALS] = {&REFERENCE_SCHEDULE, &LOAD_RESISTANCE_SCHEDULE,
                                                           &INPUT_VOLTAGE_SCHEDULE};

/* The value of a schedule at time t: its last change at or before t (+ tolerance), else its first value. */
static double value_at(const ScenarioSchedule *s, double t) {
    int i, last = 0;
    for (i = 1; i < s->count; i++) {
        if (s->times[i] <= t + SCENARIO_TOLERANCE) last = i;
        else break;
    }
    return s->values[last];
}

void model_set_defaults(void *data) { memset(data, 0, sizeof(ScenarioData)); }

const char *model_start(FmuInstance *fmu, void *data, double time, char *buffer, size_t size) {
    (void)fmu;
    (void)buffer;
    (void)size;
    ((ScenarioData *)data)->time = time;
    return NULL;
}

double model_time(const void *data) { return ((const ScenarioData *)data)->time; }
void model_set_time(void *data, double time) { ((ScenarioData *)data)->time = time; }

fmi2Status model_get_real(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Real *value) {
    const ScenarioData *d = (const ScenarioData *)data;
    if (vr >= SIGNALS) {
        fmu_log(fmu, fmi2Error, "logStatusError", "fmi2GetReal: unknown value reference %u", vr);
        return fmi2Error;
    }
    *value = value_at(SCHEDULES[vr], d->time);
    return fmi2OK;
}

fmi2Status model_set_real(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Real value, int initializing) {
    (void)data;
    (void)value;
    (void)initializing;
    fmu_log(fmu, fmi2Error, "logStatusError",
            "fmi2SetReal: value reference %u is an output of scenario %s (it has no inputs or parameters)", vr,
            SCENARIO_NAME);
    return fmi2Error;
}

fmi2Status model_do_step(FmuInstance *fmu, void *data, double time, double step) {
    (void)fmu;
    ((ScenarioData *)data)->time = time + step;
    return fmi2OK;
}

/* No Integer variables and no model exchange (a piecewise-constant source has no continuous states):
 * those functions of fmu_model.h are the shared ones of real_co_simulation_only.c. */
