/* FMI 2.0 glue shared by every FMU the workbench builds: instantiation, the state machine, logging,
 * variable access, co-simulation steps, model exchange and FMU state -- all forwarded to the one
 * model compiled with it (fmu_model.h). Nothing here knows a model's variables or equations.
 * The FMI headers (fmi2Functions.h and friends) come from the importing tool, as the standard
 * intends. */
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "fmu_model.h"

typedef enum {
    STATE_INSTANTIATED,
    STATE_INITIALIZATION,
    STATE_EVENT,
    STATE_CONTINUOUS_TIME,
    STATE_STEP_COMPLETE,
    STATE_STEP_FAILED, /* fmi2DoStep returned fmi2Discard: fmi2Terminate, fmi2Reset, the getters and fmi2SetFMUstate */
    STATE_TERMINATED,
    STATE_ERROR
} InstanceState;

struct FmuInstance {
    void *data; /* the model's data block, FMU_MODEL.data_size bytes */
    fmi2Type type;
    InstanceState state;
    char *instance_name;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment environment;
    int logging_on;
};

typedef struct {
    uint32_t magic;
    uint32_t version;
    uint64_t size; /* of the model's data that follows */
} SnapshotHeader;

/* ------------------------------------------------------------------------------------------ */
/* Logging and state checks                                                                   */

static void vlog(const FmuInstance *inst, fmi2Status status, const char *category, const char *format, va_list args) {
    if (inst == NULL || inst->logger == NULL) return;
    if (status == fmi2OK && !inst->logging_on) return;
    char buffer[1024];
    vsnprintf(buffer, sizeof buffer, format, args);
    inst->logger(inst->environment, inst->instance_name, status, category, "%s", buffer);
}

void fmu_log(FmuInstance *fmu, fmi2Status status, const char *category, const char *format, ...) {
    va_list args;
    va_start(args, format);
    vlog(fmu, status, category, format, args);
    va_end(args);
}

int fmu_in_continuous_time(const FmuInstance *fmu) {
    return fmu->state == STATE_CONTINUOUS_TIME;
}

static fmi2Status fail(FmuInstance *inst, const char *function, const char *message) {
    fmu_log(inst, fmi2Error, "logStatusError", "%s: %s", function, message);
    return fmi2Error;
}

/* A call in a state where FMI 2.0 does not allow it is refused with fmi2Error and has no effect: the
 * instance keeps its state, so the importer can still terminate, reset or free it (and go on). */
static int allowed(FmuInstance *inst, const char *function, unsigned mask) {
    if (inst == NULL) return 0;
    if (mask & (1u << inst->state)) return 1;
    fmu_log(inst, fmi2Error, "logStatusError", "%s must not be called in the current state", function);
    return 0;
}

#define IN(s) (1u << (s))
#define ANY_STATE 0xffffu
#define BEFORE_INIT_DONE (IN(STATE_INSTANTIATED) | IN(STATE_INITIALIZATION))
#define RUNNING (IN(STATE_EVENT) | IN(STATE_CONTINUOUS_TIME) | IN(STATE_STEP_COMPLETE))
#define TERMINABLE (RUNNING | IN(STATE_STEP_FAILED))
#define READABLE (~IN(STATE_ERROR) & ANY_STATE)

static int has_model_exchange(void) { return FMU_MODEL.states > 0; }

/* ------------------------------------------------------------------------------------------ */
/* Common functions                                                                           */

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    FmuInstance *inst = (FmuInstance *)c;
    (void)nCategories;
    (void)categories;
    if (!allowed(inst, "fmi2SetDebugLogging", ANY_STATE)) return fmi2Error;
    inst->logging_on = loggingOn != fmi2False;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn) {
    (void)fmuResourceLocation;
    (void)visible;
    if (functions == NULL || instanceName == NULL) return NULL;
    FmuInstance probe;
    memset(&probe, 0, sizeof probe);
    probe.logger = functions->logger;
    probe.environment = functions->componentEnvironment;
    probe.instance_name = (char *)instanceName;
    if (fmuGUID == NULL || strcmp(fmuGUID, FMU_MODEL.guid) != 0) {
        fmu_log(&probe, fmi2Error, "logStatusError", "fmi2Instantiate: GUID %s does not match %s of %s",
                fmuGUID ? fmuGUID : "(null)", FMU_MODEL.guid, FMU_MODEL.name);
        return NULL;
    }
    if (fmuType != fmi2CoSimulation && !(fmuType == fmi2ModelExchange && has_model_exchange())) {
        fmu_log(&probe, fmi2Error, "logStatusError", "fmi2Instantiate: %s does not offer FMU type %d",
                FMU_MODEL.name, (int)fmuType);
        return NULL;
    }
    FmuInstance *inst = (FmuInstance *)calloc(1, sizeof *inst);
    void *data = calloc(1, FMU_MODEL.data_size);
    char *name = (char *)malloc(strlen(instanceName) + 1);
    if (inst == NULL || data == NULL || name == NULL) {
        free(inst);
        free(data);
        free(name);
        return NULL;
    }
    strcpy(name, instanceName);
    inst->data = data;
    inst->instance_name = name;
    inst->logger = functions->logger;
    inst->environment = functions->componentEnvironment;
    inst->logging_on = loggingOn != fmi2False;
    inst->type = fmuType;
    inst->state = STATE_INSTANTIATED;
    model_set_defaults(inst->data);
    return inst;
}

void fmi2FreeInstance(fmi2Component c) {
    FmuInstance *inst = (FmuInstance *)c;
    if (inst == NULL) return;
    free(inst->data);
    free(inst->instance_name);
    free(inst);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    FmuInstance *inst = (FmuInstance *)c;
    (void)toleranceDefined;
    (void)tolerance;
    (void)stopTimeDefined;
    (void)stopTime;
    if (!allowed(inst, "fmi2SetupExperiment", IN(STATE_INSTANTIATED))) return fmi2Error;
    if (!isfinite(startTime)) return fail(inst, "fmi2SetupExperiment", "startTime is not finite");
    model_set_time(inst->data, startTime);
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    FmuInstance *inst = (FmuInstance *)c;
    if (!allowed(inst, "fmi2EnterInitializationMode", IN(STATE_INSTANTIATED))) return fmi2Error;
    inst->state = STATE_INITIALIZATION;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    FmuInstance *inst = (FmuInstance *)c;
    if (!allowed(inst, "fmi2ExitInitializationMode", IN(STATE_INITIALIZATION))) return fmi2Error;
    char message[512];
    const char *problem = model_start(inst, inst->data, model_time(inst->data), message, sizeof message);
    if (problem != NULL) /* refused: still in Initialization Mode, where the values may be set again */
        return fail(inst, "fmi2ExitInitializationMode", problem);
    inst->state = inst->type == fmi2ModelExchange ? STATE_EVENT : STATE_STEP_COMPLETE;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    FmuInstance *inst = (FmuInstance *)c;
    if (!allowed(inst, "fmi2Terminate", TERMINABLE)) return fmi2Error;
    inst->state = STATE_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    FmuInstance *inst = (FmuInstance *)c;
    if (inst == NULL) return fmi2Error;
    memset(inst->data, 0, FMU_MODEL.data_size);
    model_set_defaults(inst->data);
    inst->state = STATE_INSTANTIATED;
    return fmi2OK;
}

/* ------------------------------------------------------------------------------------------ */
/* Variable access                                                                            */

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    FmuInstance *inst = (FmuInstance *)c;
    if (!allowed(inst, "fmi2GetReal", READABLE)) return fmi2Error;
    for (size_t i = 0; i < nvr; ++i) {
        fmi2Status status = model_get_real(inst, inst->data, vr[i], &value[i]);
        if (status >= fmi2Error) return status;
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[]) {
    FmuInstance *inst = (FmuInstance *)c;
    if (!allowed(inst, "fmi2GetInteger", READABLE)) return fmi2Error;
    for (size_t i = 0; i < nvr; ++i) {
        fmi2Status status = model_get_integer(inst, inst->data, vr[i], &value[i]);
        if (status >= fmi2Error) return status;
    }
    return fmi2OK;
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[]) {
    (void)vr;
    (void)value;
    return nvr == 0 ? fmi2OK : fail((FmuInstance *)c, "fmi2GetBoolean", "the FMU has no Boolean variables");
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[]) {
    (void)vr;
    (void)value;
    return nvr == 0 ? fmi2OK : fail((FmuInstance *)c, "fmi2GetString", "the FMU has no String variables");
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    FmuInstance *inst = (FmuInstance *)c;
    if (!allowed(inst, "fmi2SetReal", BEFORE_INIT_DONE | RUNNING)) return fmi2Error;
    int initializing = (BEFORE_INIT_DONE & IN(inst->state)) != 0;
    fmi2Status worst = fmi2OK;
    for (size_t i = 0; i < nvr; ++i) {
        fmi2Status status = model_set_real(inst, inst->data, vr[i], value[i], initializing);
        if (status > worst) worst = status;
        if (status >= fmi2Error) return status;
    }
    return worst;
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[]) {
    FmuInstance *inst = (FmuInstance *)c;
    if (!allowed(inst, "fmi2SetInteger", BEFORE_INIT_DONE | RUNNING)) return fmi2Error;
    int initializing = (BEFORE_INIT_DONE & IN(inst->state)) != 0;
    for (size_t i = 0; i < nvr; ++i) {
        fmi2Status status = model_set_integer(inst, inst->data, vr[i], value[i], initializing);
        if (status >= fmi2Error) return status;
    }
    return fmi2OK;
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[]) {
    (void)vr;
    (void)value;
    return nvr == 0 ? fmi2OK : fail((FmuInstance *)c, "fmi2SetBoolean", "the FMU has no Boolean variables");
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[]) {
    (void)vr;
    (void)value;
    return nvr == 0 ? fmi2OK : fail((FmuInstance *)c, "fmi2SetString", "the FMU has no String variables");
}

/* ------------------------------------------------------------------------------------------ */
/* FMU state: a header and a copy of the model's data block                                   */

static size_t snapshot_size(void) { return sizeof(SnapshotHeader) + FMU_MODEL.data_size; }

static int valid_snapshot(const void *s) {
    const SnapshotHeader *h = (const SnapshotHeader *)s;
    return h != NULL && h->magic == FMU_MODEL.snapshot_magic && h->version == FMU_MODEL.snapshot_version &&
           h->size == FMU_MODEL.data_size;
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    FmuInstance *inst = (FmuInstance *)c;
    if (!allowed(inst, "fmi2GetFMUstate", READABLE)) return fmi2Error;
    unsigned char *snapshot = (unsigned char *)*FMUstate;
    if (snapshot == NULL) {
        snapshot = (unsigned char *)calloc(1, snapshot_size());
        if (snapshot == NULL) return fail(inst, "fmi2GetFMUstate", "out of memory");
        *FMUstate = snapshot;
    }
    SnapshotHeader header = {FMU_MODEL.snapshot_magic, FMU_MODEL.snapshot_version, FMU_MODEL.data_size};
    memcpy(snapshot, &header, sizeof header);
    memcpy(snapshot + sizeof header, inst->data, FMU_MODEL.data_size);
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    FmuInstance *inst = (FmuInstance *)c;
    if (!allowed(inst, "fmi2SetFMUstate", READABLE)) return fmi2Error;
    if (!valid_snapshot(FMUstate)) return fail(inst, "fmi2SetFMUstate", "not a state of this FMU");
    memcpy(inst->data, (const unsigned char *)FMUstate + sizeof(SnapshotHeader), FMU_MODEL.data_size);
    if (inst->state == STATE_STEP_FAILED) inst->state = STATE_STEP_COMPLETE; /* restarted from a stored state */
    return fmi2OK;
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    (void)c;
    if (FMUstate != NULL) {
        free(*FMUstate);
        *FMUstate = NULL;
    }
    return fmi2OK;
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size) {
    (void)c;
    (void)FMUstate;
    *size = snapshot_size();
    return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[], size_t size) {
    FmuInstance *inst = (FmuInstance *)c;
    if (!valid_snapshot(FMUstate)) return fail(inst, "fmi2SerializeFMUstate", "not a state of this FMU");
    if (size < snapshot_size()) return fail(inst, "fmi2SerializeFMUstate", "buffer too small");
    memcpy(serializedState, FMUstate, snapshot_size());
    return fmi2OK;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate) {
    FmuInstance *inst = (FmuInstance *)c;
    if (size != snapshot_size()) return fail(inst, "fmi2DeSerializeFMUstate", "serialized state has the wrong size");
    if (!valid_snapshot(serializedState)) return fail(inst, "fmi2DeSerializeFMUstate", "not a state of this FMU");
    if (*FMUstate == NULL) {
        *FMUstate = calloc(1, snapshot_size());
        if (*FMUstate == NULL) return fail(inst, "fmi2DeSerializeFMUstate", "out of memory");
    }
    memcpy(*FMUstate, serializedState, snapshot_size());
    return fmi2OK;
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[], size_t nUnknown,
                                        const fmi2ValueReference vKnown_ref[], size_t nKnown,
                                        const fmi2Real dvKnown[], fmi2Real dvUnknown[]) {
    (void)vUnknown_ref;
    (void)nUnknown;
    (void)vKnown_ref;
    (void)nKnown;
    (void)dvKnown;
    (void)dvUnknown;
    return fail((FmuInstance *)c, "fmi2GetDirectionalDerivative", "not provided by this FMU");
}

/* ------------------------------------------------------------------------------------------ */
/* Model exchange                                                                             */

#define ME_ONLY(inst, function)                                                                 \
    if (!has_model_exchange()) return fail((inst), (function), "this FMU offers co-simulation only")

fmi2Status fmi2EnterEventMode(fmi2Component c) {
    FmuInstance *inst = (FmuInstance *)c;
    ME_ONLY(inst, "fmi2EnterEventMode");
    if (!allowed(inst, "fmi2EnterEventMode", IN(STATE_EVENT) | IN(STATE_CONTINUOUS_TIME))) return fmi2Error;
    inst->state = STATE_EVENT;
    return fmi2OK;
}

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *info) {
    FmuInstance *inst = (FmuInstance *)c;
    ME_ONLY(inst, "fmi2NewDiscreteStates");
    if (!allowed(inst, "fmi2NewDiscreteStates", IN(STATE_EVENT))) return fmi2Error;
    double next_event_time = 0.0;
    int next_event_defined = 0;
    int changed = model_update_discrete(inst, inst->data, &next_event_time, &next_event_defined);
    info->newDiscreteStatesNeeded = fmi2False;
    info->terminateSimulation = fmi2False;
    info->nominalsOfContinuousStatesChanged = fmi2False;
    info->valuesOfContinuousStatesChanged = changed ? fmi2True : fmi2False;
    info->nextEventTimeDefined = next_event_defined ? fmi2True : fmi2False;
    info->nextEventTime = next_event_time;
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) {
    FmuInstance *inst = (FmuInstance *)c;
    ME_ONLY(inst, "fmi2EnterContinuousTimeMode");
    if (!allowed(inst, "fmi2EnterContinuousTimeMode", IN(STATE_EVENT))) return fmi2Error;
    inst->state = STATE_CONTINUOUS_TIME;
    return fmi2OK;
}

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi2Boolean *enterEventMode, fmi2Boolean *terminateSimulation) {
    FmuInstance *inst = (FmuInstance *)c;
    (void)noSetFMUStatePriorToCurrentPoint;
    ME_ONLY(inst, "fmi2CompletedIntegratorStep");
    if (!allowed(inst, "fmi2CompletedIntegratorStep", IN(STATE_CONTINUOUS_TIME))) return fmi2Error;
    *enterEventMode = fmi2False;
    *terminateSimulation = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time) {
    FmuInstance *inst = (FmuInstance *)c;
    ME_ONLY(inst, "fmi2SetTime");
    if (!allowed(inst, "fmi2SetTime", IN(STATE_EVENT) | IN(STATE_CONTINUOUS_TIME))) return fmi2Error;
    model_set_time(inst->data, time);
    return fmi2OK;
}

static int state_count_ok(FmuInstance *inst, const char *function, size_t n, int expected) {
    if (n == (size_t)expected) return 1;
    char message[128];
    snprintf(message, sizeof message, "expected %d values, got %zu", expected, n);
    fail(inst, function, message);
    return 0;
}

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx) {
    FmuInstance *inst = (FmuInstance *)c;
    ME_ONLY(inst, "fmi2SetContinuousStates");
    if (!allowed(inst, "fmi2SetContinuousStates", IN(STATE_EVENT) | IN(STATE_CONTINUOUS_TIME))) return fmi2Error;
    if (!state_count_ok(inst, "fmi2SetContinuousStates", nx, FMU_MODEL.states)) return fmi2Error;
    model_set_states(inst->data, x);
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real derivatives[], size_t nx) {
    FmuInstance *inst = (FmuInstance *)c;
    ME_ONLY(inst, "fmi2GetDerivatives");
    if (!allowed(inst, "fmi2GetDerivatives", READABLE)) return fmi2Error;
    if (!state_count_ok(inst, "fmi2GetDerivatives", nx, FMU_MODEL.states)) return fmi2Error;
    model_derivatives(inst->data, derivatives);
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real eventIndicators[], size_t ni) {
    FmuInstance *inst = (FmuInstance *)c;
    ME_ONLY(inst, "fmi2GetEventIndicators");
    if (!allowed(inst, "fmi2GetEventIndicators", READABLE)) return fmi2Error;
    if (!state_count_ok(inst, "fmi2GetEventIndicators", ni, FMU_MODEL.event_indicators)) return fmi2Error;
    model_event_indicators(inst->data, eventIndicators);
    return fmi2OK;
}

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    FmuInstance *inst = (FmuInstance *)c;
    ME_ONLY(inst, "fmi2GetContinuousStates");
    if (!allowed(inst, "fmi2GetContinuousStates", READABLE)) return fmi2Error;
    if (!state_count_ok(inst, "fmi2GetContinuousStates", nx, FMU_MODEL.states)) return fmi2Error;
    model_get_states(inst->data, x);
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x_nominal[], size_t nx) {
    FmuInstance *inst = (FmuInstance *)c;
    ME_ONLY(inst, "fmi2GetNominalsOfContinuousStates");
    if (!state_count_ok(inst, "fmi2GetNominalsOfContinuousStates", nx, FMU_MODEL.states)) return fmi2Error;
    model_nominal_states(x_nominal);
    return fmi2OK;
}

/* ------------------------------------------------------------------------------------------ */
/* Co-simulation                                                                              */

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    (void)vr;
    (void)nvr;
    (void)order;
    (void)value;
    return fail((FmuInstance *)c, "fmi2SetRealInputDerivatives", "inputs are held constant over a step");
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    (void)vr;
    (void)nvr;
    (void)order;
    (void)value;
    return fail((FmuInstance *)c, "fmi2GetRealOutputDerivatives", "output derivatives are not provided");
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentCommunicationPoint) {
    FmuInstance *inst = (FmuInstance *)c;
    (void)noSetFMUStatePriorToCurrentCommunicationPoint;
    if (!allowed(inst, "fmi2DoStep", IN(STATE_STEP_COMPLETE))) return fmi2Error;
    if (!(communicationStepSize >= 0.0) || !isfinite(communicationStepSize)) {
        fmu_log(inst, fmi2Error, "logStatusError",
                "fmi2DoStep: communicationStepSize = %g s is invalid: expected a finite value >= 0",
                communicationStepSize);
        return fmi2Error;
    }
    double now = model_time(inst->data);
    if (fabs(currentCommunicationPoint - now) > 1e-9 * fmax(1.0, fabs(now))) {
        fmu_log(inst, fmi2Error, "logStatusError",
                "fmi2DoStep: currentCommunicationPoint = %.17g s but the FMU is at t = %.17g s",
                currentCommunicationPoint, now);
        return fmi2Error;
    }
    model_set_time(inst->data, currentCommunicationPoint); /* the importer's clock is the reference */
    fmi2Status status = model_do_step(inst, inst->data, currentCommunicationPoint, communicationStepSize);
    /* fmi2Discard: only part of the step was computed (up to fmi2LastSuccessfulTime); FMI 2.0's stepFailed */
    if (status == fmi2Discard) inst->state = STATE_STEP_FAILED;
    else if (status >= fmi2Error) inst->state = STATE_ERROR;
    return status;
}

fmi2Status fmi2CancelStep(fmi2Component c) {
    return fail((FmuInstance *)c, "fmi2CancelStep", "steps complete synchronously");
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    (void)s;
    (void)c;
    *value = fmi2OK;
    return fmi2OK;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    FmuInstance *inst = (FmuInstance *)c;
    if (s != fmi2LastSuccessfulTime) return fmi2Discard;
    *value = model_time(inst->data);
    return fmi2OK;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    (void)c;
    (void)s;
    (void)value;
    return fmi2Discard;
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    (void)c;
    if (s != fmi2Terminated) return fmi2Discard;
    *value = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)c;
    (void)s;
    (void)value;
    return fmi2Discard;
}
