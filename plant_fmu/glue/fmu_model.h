/* The interface between the workbench's one FMI 2.0 glue layer (fmi2_glue.c) and a model.
 *
 * Every FMU the workbench builds -- the buck plant, the controllers, the scenario sources -- is
 * fmi2_glue.c plus one model that implements the functions below, the way modelica/Reference-FMUs
 * pairs its shared fmi2Functions.c with a model.c per FMU. The glue owns the FMI state machine,
 * instances, logging, FMU-state snapshots and argument checks; the model owns its variables and
 * its mathematics, kept in one plain data block (FmuModelInfo.data_size bytes) that the glue
 * allocates once per instance and copies for fmi2GetFMUstate.
 *
 * A model with states > 0 offers model exchange as well (the glue then forwards the ME calls);
 * one with states == 0 is co-simulation only. */
#ifndef FMU_MODEL_H
#define FMU_MODEL_H

#include <stddef.h>

#include "fmi2Functions.h"

typedef struct FmuInstance FmuInstance; /* the glue's instance: models log through it */

typedef struct {
    const char *guid;           /* must equal modelDescription.xml's guid */
    const char *name;           /* how messages name the model */
    size_t data_size;           /* bytes of the model's data block */
    int states;                 /* continuous states for model exchange (0: co-simulation only) */
    int event_indicators;
    unsigned snapshot_magic;    /* identifies this model's FMU states */
    unsigned snapshot_version;  /* bumped whenever the data layout changes */
} FmuModelInfo;

extern const FmuModelInfo FMU_MODEL;

/* ------------------------------------------------------------------ every model */

/* Start values into a zeroed data block (after fmi2Instantiate and fmi2Reset). */
void model_set_defaults(void *data);
/* Leave initialization mode at `time`: NULL if the values are valid, else a message naming the
 * culprit (written to buffer); the glue reports it as fmi2Error. */
const char *model_start(FmuInstance *fmu, void *data, double time, char *buffer, size_t size);
/* Variables by value reference. `initializing` is nonzero before fmi2ExitInitializationMode, when
 * fixed parameters may still change. A model logs its own errors (fmu_log) and returns the status. */
fmi2Status model_get_real(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Real *value);
fmi2Status model_set_real(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Real value, int initializing);
fmi2Status model_get_integer(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Integer *value);
fmi2Status model_set_integer(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Integer value,
                             int initializing);
/* Co-simulation: advance from `time` (the model's own time, checked by the glue) by `step` >= 0. */
fmi2Status model_do_step(FmuInstance *fmu, void *data, double time, double step);
double model_time(const void *data);
void model_set_time(void *data, double time);

/* ------------------------------------------------------------------ model exchange (states > 0) */

void model_get_states(const void *data, double x[]);
void model_set_states(void *data, const double x[]);
void model_nominal_states(double x[]);
void model_derivatives(const void *data, double dx[]);
void model_event_indicators(const void *data, double z[]);
/* Event update at the model's time: returns nonzero if the continuous states changed. */
int model_update_discrete(FmuInstance *fmu, void *data, double *next_event_time, int *next_event_defined);

/* ------------------------------------------------------------------ for models */

/* Log through the importer's logger: fmi2OK messages only when logging is on. */
void fmu_log(FmuInstance *fmu, fmi2Status status, const char *category, const char *format, ...);

/* 1 in model exchange's continuous-time mode, where FMI 2.0 forbids changing tunable parameters
 * (a model refuses them there; event mode and co-simulation between steps accept them). */
int fmu_in_continuous_time(const FmuInstance *fmu);

#endif
