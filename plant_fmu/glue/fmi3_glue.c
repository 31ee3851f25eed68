/* FMI 3.0 glue shared by every FMU the workbench builds as FMI 3.0: instantiation, the state machine,
 * logging, variable access, co-simulation steps, model exchange and FMU state -- all forwarded to the
 * one model compiled with it (fmu_model.h), the same model code the FMI 2.0 glue (fmi2_glue.c) serves.
 * Nothing here knows a model's variables or equations.
 *
 * The model interface (fmu_model.h) is written in FMI 2.0's scalar types (fmi2Real = double,
 * fmi2Integer = int, fmi2Status, fmi2ValueReference = unsigned int); this file maps them: fmi3Float64
 * to fmi2Real, fmi3Int32 to fmi2Integer, the statuses one to one (fmi3OK .. fmi3Fatal have the values of
 * fmi2OK .. fmi2Fatal). FMI 3.0 asks for variables FMI 2.0 does without -- the independent variable
 * (time) and one variable per event indicator -- which the glue serves itself, under the value
 * references of the generated fmi3_variables.h (cosim builds it with modelDescription.xml).
 *
 * What an FMU built on this glue offers: co-simulation without event mode, early return or
 * intermediate update (fmi3DoStep always completes the step: eventHandlingNeeded, terminateSimulation
 * and earlyReturn are false); model exchange when the model has continuous states; FMU state get, set
 * and serialisation; scalar Float64 and Int32 variables only (no arrays, clocks, Boolean, String or
 * Binary variables, no directional derivatives, no Scheduled Execution). */
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"
#include "fmi3_variables.h" /* generated: FMU3_TIME_VALUE_REFERENCE, FMU3_FIRST_EVENT_INDICATOR_VALUE_REFERENCE */
#include "fmu_model.h"

#define MAX_EVENT_INDICATORS 16

typedef enum {
    STATE_INSTANTIATED,
    STATE_INITIALIZATION,
    STATE_EVENT,
    STATE_CONTINUOUS_TIME,
    STATE_STEP,
    STATE_TERMINATED,
    STATE_ERROR
} InstanceState;

typedef enum { TYPE_MODEL_EXCHANGE, TYPE_CO_SIMULATION } InstanceType;

struct FmuInstance {
    void *data; /* the model's data block, FMU_MODEL.data_size bytes */
    InstanceType type;
    InstanceState state;
    char *instance_name;
    fmi3LogMessageCallback logger;
    fmi3InstanceEnvironment environment;
    int logging_on;
};

typedef struct {
    uint32_t magic;
    uint32_t version;
    uint64_t size; /* of the model's data that follows */
} SnapshotHeader;

/* ------------------------------------------------------------------------------------------ */
/* Logging and state checks                                                                   */

/* The model speaks the FMI 2.0 API (fmu_model.h) and names its functions so in its messages; this edition's
 * caller called their FMI 3.0 counterparts, so a message names those (pairs: FMI 2.0 name, FMI 3.0 name). */
static const char *const FUNCTION_NAMES[][2] = {
    {"fmi2SetReal", "fmi3SetFloat64"},       {"fmi2GetReal", "fmi3GetFloat64"},
    {"fmi2SetInteger", "fmi3SetInt32"},      {"fmi2GetInteger", "fmi3GetInt32"},
    {"fmi2DoStep", "fmi3DoStep"},            {"fmi2EnterEventMode", "fmi3EnterEventMode"},
    {"fmi2ExitInitializationMode", "fmi3ExitInitializationMode"},
};

/* `text` with every FMI 2.0 function name of FUNCTION_NAMES replaced by its FMI 3.0 name, into `out` (`size` bytes). */
static void fmi3_names(const char *text, char *out, size_t size) {
    size_t n = 0;
    while (*text != '\0' && n + 1 < size) {
        size_t k, count = sizeof FUNCTION_NAMES / sizeof FUNCTION_NAMES[0];
        for (k = 0; k < count; k++) {
            size_t length = strlen(FUNCTION_NAMES[k][0]);
            if (strncmp(text, FUNCTION_NAMES[k][0], length) == 0) break;
        }
        if (k < count) {
            const char *name = FUNCTION_NAMES[k][1];
            while (*name != '\0' && n + 1 < size) out[n++] = *name++;
            text += strlen(FUNCTION_NAMES[k][0]);
        } else {
            out[n++] = *text++;
        }
    }
    out[n] = '\0';
}

static void vlog(const FmuInstance *inst, fmi3Status status, const char *category, const char *format, va_list args) {
    if (inst == NULL || inst->logger == NULL) return;
    if (status == fmi3OK && !inst->logging_on) return;
    char buffer[1024], named[1100];
    vsnprintf(buffer, sizeof buffer, format, args);
    fmi3_names(buffer, named, sizeof named);
    inst->logger(inst->environment, status, category, named);
}

void fmu_log(FmuInstance *fmu, fmi2Status status, const char *category, const char *format, ...) {
    va_list args;
    va_start(args, format);
    vlog(fmu, (fmi3Status)status, category, format, args);
    va_end(args);
}

int fmu_in_continuous_time(const FmuInstance *fmu) {
    return fmu->state == STATE_CONTINUOUS_TIME;
}

static fmi3Status fail(FmuInstance *inst, const char *function, const char *message) {
    fmu_log(inst, fmi2Error, "logStatusError", "%s: %s", function, message);
    return fmi3Error;
}

static const char *STATE_NAMES[] = {"Instantiated", "Initialization Mode", "Event Mode", "Continuous-Time Mode",
                                    "Step Mode", "Terminated", "an error state"};

static int allowed(FmuInstance *inst, const char *function, unsigned mask) {
    if (inst == NULL) return 0;
    if (mask & (1u << inst->state)) return 1;
    fmu_log(inst, fmi2Error, "logStatusError", "%s must not be called in %s", function, STATE_NAMES[inst->state]);
    return 0; /* refused (fmi3Error) without effect: the instance keeps its state */
}

#define IN(s) (1u << (s))
#define ANY_STATE 0xffffu
#define BEFORE_INIT_DONE (IN(STATE_INSTANTIATED) | IN(STATE_INITIALIZATION))
#define RUNNING (IN(STATE_EVENT) | IN(STATE_CONTINUOUS_TIME) | IN(STATE_STEP))
#define READABLE (~IN(STATE_ERROR) & ANY_STATE)

static int has_model_exchange(void) { return FMU_MODEL.states > 0; }

static fmi3Status status3(fmi2Status status) { return (fmi3Status)status; }

/* ------------------------------------------------------------------------------------------ */
/* Inquire version numbers and set debug logging                                               */

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[]) {
    FmuInstance *inst = (FmuInstance *)instance;
    (void)nCategories;
    (void)categories;
    if (!allowed(inst, "fmi3SetDebugLogging", ANY_STATE)) return fmi3Error;
    inst->logging_on = loggingOn;
    return fmi3OK;
}

/* ------------------------------------------------------------------------------------------ */
/* Creation and destruction of instances                                                       */

static FmuInstance *instantiate(fmi3String instanceName, InstanceType type, fmi3String instantiationToken,
                                fmi3Boolean loggingOn, fmi3InstanceEnvironment environment,
                                fmi3LogMessageCallback logMessage, const char *refusal) {
    if (instanceName == NULL) return NULL;
    FmuInstance probe;
    memset(&probe, 0, sizeof probe);
    probe.logger = logMessage;
    probe.environment = environment;
    probe.instance_name = (char *)instanceName;
    if (refusal != NULL) {
        fmu_log(&probe, fmi2Error, "logStatusError", "%s: %s", FMU_MODEL.name, refusal);
        return NULL;
    }
    if (instantiationToken == NULL || strcmp(instantiationToken, FMU_MODEL.guid) != 0) {
        fmu_log(&probe, fmi2Error, "logStatusError", "instantiation token %s does not match %s of %s",
                instantiationToken ? instantiationToken : "(null)", FMU_MODEL.guid, FMU_MODEL.name);
        return NULL;
    }
    if (FMU_MODEL.event_indicators > MAX_EVENT_INDICATORS) {
        fmu_log(&probe, fmi2Error, "logStatusError", "%s has more than %d event indicators", FMU_MODEL.name,
                MAX_EVENT_INDICATORS);
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
    inst->logger = logMessage;
    inst->environment = environment;
    inst->logging_on = loggingOn;
    inst->type = type;
    inst->state = STATE_INSTANTIATED;
    model_set_defaults(inst->data);
    return inst;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken,
                                          fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                          fmi3InstanceEnvironment instanceEnvironment,
                                          fmi3LogMessageCallback logMessage) {
    (void)resourcePath;
    (void)visible;
    return instantiate(instanceName, TYPE_MODEL_EXCHANGE, instantiationToken, loggingOn, instanceEnvironment,
                       logMessage, has_model_exchange() ? NULL : "offers co-simulation only");
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String instanceName, fmi3String instantiationToken,
                                         fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                         fmi3Boolean eventModeUsed, fmi3Boolean earlyReturnAllowed,
                                         const fmi3ValueReference requiredIntermediateVariables[],
                                         size_t nRequiredIntermediateVariables,
                                         fmi3InstanceEnvironment instanceEnvironment,
                                         fmi3LogMessageCallback logMessage,
                                         fmi3IntermediateUpdateCallback intermediateUpdate) {
    (void)resourcePath;
    (void)visible;
    (void)earlyReturnAllowed; /* the FMU never returns early, allowed or not */
    (void)requiredIntermediateVariables;
    (void)intermediateUpdate;
    const char *refusal = NULL;
    if (eventModeUsed) refusal = "has no event mode in co-simulation (hasEventMode=\"false\"): eventModeUsed must "
                                 "be false";
    else if (nRequiredIntermediateVariables > 0) refusal = "provides no intermediate update";
    return instantiate(instanceName, TYPE_CO_SIMULATION, instantiationToken, loggingOn, instanceEnvironment,
                       logMessage, refusal);
}

fmi3Instance fmi3InstantiateScheduledExecution(fmi3String instanceName, fmi3String instantiationToken,
                                               fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                               fmi3InstanceEnvironment instanceEnvironment,
                                               fmi3LogMessageCallback logMessage, fmi3ClockUpdateCallback clockUpdate,
                                               fmi3LockPreemptionCallback lockPreemption,
                                               fmi3UnlockPreemptionCallback unlockPreemption) {
    (void)resourcePath;
    (void)visible;
    (void)clockUpdate;
    (void)lockPreemption;
    (void)unlockPreemption;
    return instantiate(instanceName, TYPE_CO_SIMULATION, instantiationToken, loggingOn, instanceEnvironment,
                       logMessage, "offers no Scheduled Execution");
}

void fmi3FreeInstance(fmi3Instance instance) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (inst == NULL) return;
    free(inst->data);
    free(inst->instance_name);
    free(inst);
}

/* ------------------------------------------------------------------------------------------ */
/* Initialization, termination, reset                                                         */

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined, fmi3Float64 tolerance,
                                       fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    FmuInstance *inst = (FmuInstance *)instance;
    (void)toleranceDefined;
    (void)tolerance;
    (void)stopTimeDefined;
    (void)stopTime;
    if (!allowed(inst, "fmi3EnterInitializationMode", IN(STATE_INSTANTIATED))) return fmi3Error;
    if (!isfinite(startTime)) return fail(inst, "fmi3EnterInitializationMode", "startTime is not finite");
    model_set_time(inst->data, startTime);
    inst->state = STATE_INITIALIZATION;
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (!allowed(inst, "fmi3ExitInitializationMode", IN(STATE_INITIALIZATION))) return fmi3Error;
    char message[512];
    const char *problem = model_start(inst, inst->data, model_time(inst->data), message, sizeof message);
    if (problem != NULL) /* refused: still in Initialization Mode, where the values may be set again */
        return fail(inst, "fmi3ExitInitializationMode", problem);
    inst->state = inst->type == TYPE_MODEL_EXCHANGE ? STATE_EVENT : STATE_STEP;
    return fmi3OK;
}

fmi3Status fmi3EnterEventMode(fmi3Instance instance) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (inst != NULL && inst->type == TYPE_CO_SIMULATION)
        return fail(inst, "fmi3EnterEventMode", "this co-simulation FMU has no event mode");
    if (!allowed(inst, "fmi3EnterEventMode", IN(STATE_EVENT) | IN(STATE_CONTINUOUS_TIME))) return fmi3Error;
    inst->state = STATE_EVENT;
    return fmi3OK;
}

fmi3Status fmi3Terminate(fmi3Instance instance) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (!allowed(inst, "fmi3Terminate", RUNNING)) return fmi3Error;
    inst->state = STATE_TERMINATED;
    return fmi3OK;
}

fmi3Status fmi3Reset(fmi3Instance instance) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (inst == NULL) return fmi3Error;
    memset(inst->data, 0, FMU_MODEL.data_size);
    model_set_defaults(inst->data);
    inst->state = STATE_INSTANTIATED;
    return fmi3OK;
}

/* ------------------------------------------------------------------------------------------ */
/* Variable access: Float64 and Int32 scalars                                                  */

static int scalars(FmuInstance *inst, const char *function, size_t nValueReferences, size_t nValues) {
    if (nValues == nValueReferences) return 1;
    char message[160];
    snprintf(message, sizeof message, "%zu values for %zu value references: the FMU has no array variables", nValues,
             nValueReferences);
    fail(inst, function, message);
    return 0;
}

static int event_indicator_index(fmi3ValueReference vr) {
    if (vr < FMU3_FIRST_EVENT_INDICATOR_VALUE_REFERENCE) return -1;
    fmi3ValueReference i = vr - FMU3_FIRST_EVENT_INDICATOR_VALUE_REFERENCE;
    return i < (fmi3ValueReference)FMU_MODEL.event_indicators ? (int)i : -1;
}

fmi3Status fmi3GetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                          fmi3Float64 values[], size_t nValues) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (!allowed(inst, "fmi3GetFloat64", READABLE)) return fmi3Error;
    if (!scalars(inst, "fmi3GetFloat64", nValueReferences, nValues)) return fmi3Error;
    for (size_t i = 0; i < nValueReferences; ++i) {
        fmi3ValueReference vr = valueReferences[i];
        int indicator = event_indicator_index(vr);
        if (vr == FMU3_TIME_VALUE_REFERENCE) {
            values[i] = model_time(inst->data);
        } else if (indicator >= 0) {
            double z[MAX_EVENT_INDICATORS];
            model_event_indicators(inst->data, z);
            values[i] = z[indicator];
        } else {
            fmi2Real value = 0.0;
            fmi2Status status = model_get_real(inst, inst->data, vr, &value);
            if (status >= fmi2Error) return status3(status);
            values[i] = value;
        }
    }
    return fmi3OK;
}

fmi3Status fmi3SetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                          const fmi3Float64 values[], size_t nValues) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (!allowed(inst, "fmi3SetFloat64", BEFORE_INIT_DONE | RUNNING)) return fmi3Error;
    if (!scalars(inst, "fmi3SetFloat64", nValueReferences, nValues)) return fmi3Error;
    int initializing = (BEFORE_INIT_DONE & IN(inst->state)) != 0;
    fmi2Status worst = fmi2OK;
    for (size_t i = 0; i < nValueReferences; ++i) {
        if (valueReferences[i] == FMU3_TIME_VALUE_REFERENCE || event_indicator_index(valueReferences[i]) >= 0)
            return fail(inst, "fmi3SetFloat64", "time and the event indicators cannot be set");
        fmi2Status status = model_set_real(inst, inst->data, valueReferences[i], values[i], initializing);
        if (status > worst) worst = status;
        if (status >= fmi2Error) return status3(status);
    }
    return status3(worst);
}

fmi3Status fmi3GetInt32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                        fmi3Int32 values[], size_t nValues) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (!allowed(inst, "fmi3GetInt32", READABLE)) return fmi3Error;
    if (!scalars(inst, "fmi3GetInt32", nValueReferences, nValues)) return fmi3Error;
    for (size_t i = 0; i < nValueReferences; ++i) {
        fmi2Integer value = 0;
        fmi2Status status = model_get_integer(inst, inst->data, valueReferences[i], &value);
        if (status >= fmi2Error) return status3(status);
        values[i] = (fmi3Int32)value;
    }
    return fmi3OK;
}

fmi3Status fmi3SetInt32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                        const fmi3Int32 values[], size_t nValues) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (!allowed(inst, "fmi3SetInt32", BEFORE_INIT_DONE | RUNNING)) return fmi3Error;
    if (!scalars(inst, "fmi3SetInt32", nValueReferences, nValues)) return fmi3Error;
    int initializing = (BEFORE_INIT_DONE & IN(inst->state)) != 0;
    for (size_t i = 0; i < nValueReferences; ++i) {
        fmi2Status status = model_set_integer(inst, inst->data, valueReferences[i], (fmi2Integer)values[i],
                                              initializing);
        if (status >= fmi2Error) return status3(status);
    }
    return fmi3OK;
}

/* The types the workbench's models have no variables of: any value reference is refused. */
#define NO_VARIABLES_OF(TYPE, GETTER, SETTER)                                                                    \
    fmi3Status GETTER(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, \
                      TYPE values[], size_t nValues) {                                                           \
        (void)valueReferences;                                                                                   \
        (void)values;                                                                                            \
        (void)nValues;                                                                                           \
        return nValueReferences == 0 ? fmi3OK                                                                    \
                                     : fail((FmuInstance *)instance, #GETTER, "the FMU has no " #TYPE " variables"); \
    }                                                                                                            \
    fmi3Status SETTER(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, \
                      const TYPE values[], size_t nValues) {                                                     \
        (void)valueReferences;                                                                                   \
        (void)values;                                                                                            \
        (void)nValues;                                                                                           \
        return nValueReferences == 0 ? fmi3OK                                                                    \
                                     : fail((FmuInstance *)instance, #SETTER, "the FMU has no " #TYPE " variables"); \
    }

NO_VARIABLES_OF(fmi3Float32, fmi3GetFloat32, fmi3SetFloat32)
NO_VARIABLES_OF(fmi3Int8, fmi3GetInt8, fmi3SetInt8)
NO_VARIABLES_OF(fmi3UInt8, fmi3GetUInt8, fmi3SetUInt8)
NO_VARIABLES_OF(fmi3Int16, fmi3GetInt16, fmi3SetInt16)
NO_VARIABLES_OF(fmi3UInt16, fmi3GetUInt16, fmi3SetUInt16)
NO_VARIABLES_OF(fmi3UInt32, fmi3GetUInt32, fmi3SetUInt32)
NO_VARIABLES_OF(fmi3Int64, fmi3GetInt64, fmi3SetInt64)
NO_VARIABLES_OF(fmi3UInt64, fmi3GetUInt64, fmi3SetUInt64)
NO_VARIABLES_OF(fmi3Boolean, fmi3GetBoolean, fmi3SetBoolean)
NO_VARIABLES_OF(fmi3String, fmi3GetString, fmi3SetString)

fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                         size_t valueSizes[], fmi3Binary values[], size_t nValues) {
    (void)valueReferences;
    (void)valueSizes;
    (void)values;
    (void)nValues;
    return nValueReferences == 0 ? fmi3OK
                                 : fail((FmuInstance *)instance, "fmi3GetBinary", "the FMU has no Binary variables");
}

fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                         const size_t valueSizes[], const fmi3Binary values[], size_t nValues) {
    (void)valueReferences;
    (void)valueSizes;
    (void)values;
    (void)nValues;
    return nValueReferences == 0 ? fmi3OK
                                 : fail((FmuInstance *)instance, "fmi3SetBinary", "the FMU has no Binary variables");
}

fmi3Status fmi3GetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                        fmi3Clock values[]) {
    (void)valueReferences;
    (void)values;
    return nValueReferences == 0 ? fmi3OK : fail((FmuInstance *)instance, "fmi3GetClock", "the FMU has no clocks");
}

fmi3Status fmi3SetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                        const fmi3Clock values[]) {
    (void)valueReferences;
    (void)values;
    return nValueReferences == 0 ? fmi3OK : fail((FmuInstance *)instance, "fmi3SetClock", "the FMU has no clocks");
}

/* ------------------------------------------------------------------------------------------ */
/* Dependencies, partial derivatives, configuration and clocks: not provided                   */

fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance, fmi3ValueReference valueReference,
                                               size_t *nDependencies) {
    (void)valueReference;
    (void)nDependencies;
    return fail((FmuInstance *)instance, "fmi3GetNumberOfVariableDependencies",
                "not provided (the dependencies are in modelDescription.xml)");
}

fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent,
                                       size_t elementIndicesOfDependent[], fmi3ValueReference independents[],
                                       size_t elementIndicesOfIndependents[], fmi3DependencyKind dependencyKinds[],
                                       size_t nDependencies) {
    (void)dependent;
    (void)elementIndicesOfDependent;
    (void)independents;
    (void)elementIndicesOfIndependents;
    (void)dependencyKinds;
    (void)nDependencies;
    return fail((FmuInstance *)instance, "fmi3GetVariableDependencies",
                "not provided (the dependencies are in modelDescription.xml)");
}

fmi3Status fmi3GetDirectionalDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,
                                        const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[],
                                        size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    (void)unknowns;
    (void)nUnknowns;
    (void)knowns;
    (void)nKnowns;
    (void)seed;
    (void)nSeed;
    (void)sensitivity;
    (void)nSensitivity;
    return fail((FmuInstance *)instance, "fmi3GetDirectionalDerivative", "not provided by this FMU");
}

fmi3Status fmi3GetAdjointDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,
                                    const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[],
                                    size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    (void)unknowns;
    (void)nUnknowns;
    (void)knowns;
    (void)nKnowns;
    (void)seed;
    (void)nSeed;
    (void)sensitivity;
    (void)nSensitivity;
    return fail((FmuInstance *)instance, "fmi3GetAdjointDerivative", "not provided by this FMU");
}

fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance) {
    return fail((FmuInstance *)instance, "fmi3EnterConfigurationMode", "the FMU has no structural parameters");
}

fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance) {
    return fail((FmuInstance *)instance, "fmi3ExitConfigurationMode", "the FMU has no structural parameters");
}

fmi3Status fmi3GetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                  size_t nValueReferences, fmi3Float64 intervals[],
                                  fmi3IntervalQualifier qualifiers[]) {
    (void)valueReferences;
    (void)nValueReferences;
    (void)intervals;
    (void)qualifiers;
    return fail((FmuInstance *)instance, "fmi3GetIntervalDecimal", "the FMU has no clocks");
}

fmi3Status fmi3GetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                   size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[],
                                   fmi3IntervalQualifier qualifiers[]) {
    (void)valueReferences;
    (void)nValueReferences;
    (void)counters;
    (void)resolutions;
    (void)qualifiers;
    return fail((FmuInstance *)instance, "fmi3GetIntervalFraction", "the FMU has no clocks");
}

fmi3Status fmi3GetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                               size_t nValueReferences, fmi3Float64 shifts[]) {
    (void)valueReferences;
    (void)nValueReferences;
    (void)shifts;
    return fail((FmuInstance *)instance, "fmi3GetShiftDecimal", "the FMU has no clocks");
}

fmi3Status fmi3GetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[]) {
    (void)valueReferences;
    (void)nValueReferences;
    (void)counters;
    (void)resolutions;
    return fail((FmuInstance *)instance, "fmi3GetShiftFraction", "the FMU has no clocks");
}

fmi3Status fmi3SetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                  size_t nValueReferences, const fmi3Float64 intervals[]) {
    (void)valueReferences;
    (void)nValueReferences;
    (void)intervals;
    return fail((FmuInstance *)instance, "fmi3SetIntervalDecimal", "the FMU has no clocks");
}

fmi3Status fmi3SetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                   size_t nValueReferences, const fmi3UInt64 counters[],
                                   const fmi3UInt64 resolutions[]) {
    (void)valueReferences;
    (void)nValueReferences;
    (void)counters;
    (void)resolutions;
    return fail((FmuInstance *)instance, "fmi3SetIntervalFraction", "the FMU has no clocks");
}

fmi3Status fmi3SetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                               size_t nValueReferences, const fmi3Float64 shifts[]) {
    (void)valueReferences;
    (void)nValueReferences;
    (void)shifts;
    return fail((FmuInstance *)instance, "fmi3SetShiftDecimal", "the FMU has no clocks");
}

fmi3Status fmi3SetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                size_t nValueReferences, const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) {
    (void)valueReferences;
    (void)nValueReferences;
    (void)counters;
    (void)resolutions;
    return fail((FmuInstance *)instance, "fmi3SetShiftFraction", "the FMU has no clocks");
}

fmi3Status fmi3ActivateModelPartition(fmi3Instance instance, fmi3ValueReference clockReference,
                                      fmi3Float64 activationTime) {
    (void)clockReference;
    (void)activationTime;
    return fail((FmuInstance *)instance, "fmi3ActivateModelPartition", "the FMU offers no Scheduled Execution");
}

/* ------------------------------------------------------------------------------------------ */
/* FMU state: a header and a copy of the model's data block                                   */

static size_t snapshot_size(void) { return sizeof(SnapshotHeader) + FMU_MODEL.data_size; }

static int valid_snapshot(const void *s) {
    const SnapshotHeader *h = (const SnapshotHeader *)s;
    return h != NULL && h->magic == FMU_MODEL.snapshot_magic && h->version == FMU_MODEL.snapshot_version &&
           h->size == FMU_MODEL.data_size;
}

fmi3Status fmi3GetFMUState(fmi3Instance instance, fmi3FMUState *FMUState) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (!allowed(inst, "fmi3GetFMUState", READABLE)) return fmi3Error;
    unsigned char *snapshot = (unsigned char *)*FMUState;
    if (snapshot == NULL) {
        snapshot = (unsigned char *)calloc(1, snapshot_size());
        if (snapshot == NULL) return fail(inst, "fmi3GetFMUState", "out of memory");
        *FMUState = snapshot;
    }
    SnapshotHeader header = {FMU_MODEL.snapshot_magic, FMU_MODEL.snapshot_version, FMU_MODEL.data_size};
    memcpy(snapshot, &header, sizeof header);
    memcpy(snapshot + sizeof header, inst->data, FMU_MODEL.data_size);
    return fmi3OK;
}

fmi3Status fmi3SetFMUState(fmi3Instance instance, fmi3FMUState FMUState) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (!allowed(inst, "fmi3SetFMUState", READABLE)) return fmi3Error;
    if (!valid_snapshot(FMUState)) return fail(inst, "fmi3SetFMUState", "not a state of this FMU");
    memcpy(inst->data, (const unsigned char *)FMUState + sizeof(SnapshotHeader), FMU_MODEL.data_size);
    return fmi3OK;
}

fmi3Status fmi3FreeFMUState(fmi3Instance instance, fmi3FMUState *FMUState) {
    (void)instance;
    if (FMUState != NULL) {
        free(*FMUState);
        *FMUState = NULL;
    }
    return fmi3OK;
}

fmi3Status fmi3SerializedFMUStateSize(fmi3Instance instance, fmi3FMUState FMUState, size_t *size) {
    (void)instance;
    (void)FMUState;
    *size = snapshot_size();
    return fmi3OK;
}

fmi3Status fmi3SerializeFMUState(fmi3Instance instance, fmi3FMUState FMUState, fmi3Byte serializedState[],
                                 size_t size) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (!valid_snapshot(FMUState)) return fail(inst, "fmi3SerializeFMUState", "not a state of this FMU");
    if (size < snapshot_size()) return fail(inst, "fmi3SerializeFMUState", "buffer too small");
    memcpy(serializedState, FMUState, snapshot_size());
    return fmi3OK;
}

fmi3Status fmi3DeserializeFMUState(fmi3Instance instance, const fmi3Byte serializedState[], size_t size,
                                   fmi3FMUState *FMUState) {
    FmuInstance *inst = (FmuInstance *)instance;
    if (size != snapshot_size()) return fail(inst, "fmi3DeserializeFMUState", "serialized state has the wrong size");
    if (!valid_snapshot(serializedState)) return fail(inst, "fmi3DeserializeFMUState", "not a state of this FMU");
    if (*FMUState == NULL) {
        *FMUState = calloc(1, snapshot_size());
        if (*FMUState == NULL) return fail(inst, "fmi3DeserializeFMUState", "out of memory");
    }
    memcpy(*FMUState, serializedState, snapshot_size());
    return fmi3OK;
}

/* ------------------------------------------------------------------------------------------ */
/* Model exchange (and the event mode it shares with co-simulation)                            */

#define ME_ONLY(inst, function)                                                                              \
    if ((inst) == NULL) return fmi3Error;                                                                    \
    if ((inst)->type != TYPE_MODEL_EXCHANGE) return fail((inst), (function), "not a model-exchange instance")

fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance) {
    return fail((FmuInstance *)instance, "fmi3EvaluateDiscreteStates", "not provided (providesEvaluateDiscreteStates "
                "is false)");
}

fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean *discreteStatesNeedUpdate,
                                    fmi3Boolean *terminateSimulation, fmi3Boolean *nominalsOfContinuousStatesChanged,
                                    fmi3Boolean *valuesOfContinuousStatesChanged, fmi3Boolean *nextEventTimeDefined,
                                    fmi3Float64 *nextEventTime) {
    FmuInstance *inst = (FmuInstance *)instance;
    ME_ONLY(inst, "fmi3UpdateDiscreteStates");
    if (!allowed(inst, "fmi3UpdateDiscreteStates", IN(STATE_EVENT))) return fmi3Error;
    double next_event_time = 0.0;
    int next_event_defined = 0;
    int changed = model_update_discrete(inst, inst->data, &next_event_time, &next_event_defined);
    *discreteStatesNeedUpdate = false;
    *terminateSimulation = false;
    *nominalsOfContinuousStatesChanged = false;
    *valuesOfContinuousStatesChanged = changed != 0;
    *nextEventTimeDefined = next_event_defined != 0;
    *nextEventTime = next_event_time;
    return fmi3OK;
}

fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance) {
    FmuInstance *inst = (FmuInstance *)instance;
    ME_ONLY(inst, "fmi3EnterContinuousTimeMode");
    if (!allowed(inst, "fmi3EnterContinuousTimeMode", IN(STATE_EVENT))) return fmi3Error;
    inst->state = STATE_CONTINUOUS_TIME;
    return fmi3OK;
}

fmi3Status fmi3CompletedIntegratorStep(fmi3Instance instance, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi3Boolean *enterEventMode, fmi3Boolean *terminateSimulation) {
    FmuInstance *inst = (FmuInstance *)instance;
    (void)noSetFMUStatePriorToCurrentPoint;
    ME_ONLY(inst, "fmi3CompletedIntegratorStep");
    if (!allowed(inst, "fmi3CompletedIntegratorStep", IN(STATE_CONTINUOUS_TIME))) return fmi3Error;
    *enterEventMode = false;
    *terminateSimulation = false;
    return fmi3OK;
}

fmi3Status fmi3SetTime(fmi3Instance instance, fmi3Float64 time) {
    FmuInstance *inst = (FmuInstance *)instance;
    ME_ONLY(inst, "fmi3SetTime");
    if (!allowed(inst, "fmi3SetTime", IN(STATE_EVENT) | IN(STATE_CONTINUOUS_TIME))) return fmi3Error;
    model_set_time(inst->data, time);
    return fmi3OK;
}

static int count_ok(FmuInstance *inst, const char *function, size_t n, int expected) {
    if (n == (size_t)expected) return 1;
    char message[128];
    snprintf(message, sizeof message, "expected %d values, got %zu", expected, n);
    fail(inst, function, message);
    return 0;
}

fmi3Status fmi3SetContinuousStates(fmi3Instance instance, const fmi3Float64 continuousStates[],
                                   size_t nContinuousStates) {
    FmuInstance *inst = (FmuInstance *)instance;
    ME_ONLY(inst, "fmi3SetContinuousStates");
    if (!allowed(inst, "fmi3SetContinuousStates", IN(STATE_EVENT) | IN(STATE_CONTINUOUS_TIME))) return fmi3Error;
    if (!count_ok(inst, "fmi3SetContinuousStates", nContinuousStates, FMU_MODEL.states)) return fmi3Error;
    model_set_states(inst->data, continuousStates);
    return fmi3OK;
}

fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance instance, fmi3Float64 derivatives[],
                                             size_t nContinuousStates) {
    FmuInstance *inst = (FmuInstance *)instance;
    ME_ONLY(inst, "fmi3GetContinuousStateDerivatives");
    if (!allowed(inst, "fmi3GetContinuousStateDerivatives", READABLE)) return fmi3Error;
    if (!count_ok(inst, "fmi3GetContinuousStateDerivatives", nContinuousStates, FMU_MODEL.states)) return fmi3Error;
    model_derivatives(inst->data, derivatives);
    return fmi3OK;
}

fmi3Status fmi3GetEventIndicators(fmi3Instance instance, fmi3Float64 eventIndicators[], size_t nEventIndicators) {
    FmuInstance *inst = (FmuInstance *)instance;
    ME_ONLY(inst, "fmi3GetEventIndicators");
    if (!allowed(inst, "fmi3GetEventIndicators", READABLE)) return fmi3Error;
    if (!count_ok(inst, "fmi3GetEventIndicators", nEventIndicators, FMU_MODEL.event_indicators)) return fmi3Error;
    model_event_indicators(inst->data, eventIndicators);
    return fmi3OK;
}

fmi3Status fmi3GetContinuousStates(fmi3Instance instance, fmi3Float64 continuousStates[], size_t nContinuousStates) {
    FmuInstance *inst = (FmuInstance *)instance;
    ME_ONLY(inst, "fmi3GetContinuousStates");
    if (!allowed(inst, "fmi3GetContinuousStates", READABLE)) return fmi3Error;
    if (!count_ok(inst, "fmi3GetContinuousStates", nContinuousStates, FMU_MODEL.states)) return fmi3Error;
    model_get_states(inst->data, continuousStates);
    return fmi3OK;
}

fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance instance, fmi3Float64 nominals[], size_t nContinuousStates) {
    FmuInstance *inst = (FmuInstance *)instance;
    ME_ONLY(inst, "fmi3GetNominalsOfContinuousStates");
    if (!count_ok(inst, "fmi3GetNominalsOfContinuousStates", nContinuousStates, FMU_MODEL.states)) return fmi3Error;
    model_nominal_states(nominals);
    return fmi3OK;
}

fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance instance, size_t *nEventIndicators) {
    FmuInstance *inst = (FmuInstance *)instance;
    ME_ONLY(inst, "fmi3GetNumberOfEventIndicators");
    *nEventIndicators = (size_t)FMU_MODEL.event_indicators;
    return fmi3OK;
}

fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance instance, size_t *nContinuousStates) {
    FmuInstance *inst = (FmuInstance *)instance;
    ME_ONLY(inst, "fmi3GetNumberOfContinuousStates");
    *nContinuousStates = (size_t)FMU_MODEL.states;
    return fmi3OK;
}

/* ------------------------------------------------------------------------------------------ */
/* Co-simulation                                                                              */

fmi3Status fmi3EnterStepMode(fmi3Instance instance) {
    return fail((FmuInstance *)instance, "fmi3EnterStepMode",
                "this co-simulation FMU has no event mode (it is in Step Mode after initialisation)");
}

fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                    size_t nValueReferences, const fmi3Int32 orders[], fmi3Float64 values[],
                                    size_t nValues) {
    (void)valueReferences;
    (void)nValueReferences;
    (void)orders;
    (void)values;
    (void)nValues;
    return fail((FmuInstance *)instance, "fmi3GetOutputDerivatives", "output derivatives are not provided");
}

fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint, fmi3Float64 communicationStepSize,
                      fmi3Boolean noSetFMUStatePriorToCurrentPoint, fmi3Boolean *eventHandlingNeeded,
                      fmi3Boolean *terminateSimulation, fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime) {
    FmuInstance *inst = (FmuInstance *)instance;
    (void)noSetFMUStatePriorToCurrentPoint;
    if (inst != NULL && inst->type != TYPE_CO_SIMULATION)
        return fail(inst, "fmi3DoStep", "not a co-simulation instance");
    if (!allowed(inst, "fmi3DoStep", IN(STATE_STEP))) return fmi3Error;
    *eventHandlingNeeded = false;
    *terminateSimulation = false;
    *earlyReturn = false;
    *lastSuccessfulTime = model_time(inst->data);
    if (!(communicationStepSize >= 0.0) || !isfinite(communicationStepSize)) {
        fmu_log(inst, fmi2Error, "logStatusError",
                "fmi3DoStep: communicationStepSize = %g s is invalid: expected a finite value >= 0",
                communicationStepSize);
        return fmi3Error;
    }
    double now = model_time(inst->data);
    if (fabs(currentCommunicationPoint - now) > 1e-9 * fmax(1.0, fabs(now))) {
        fmu_log(inst, fmi2Error, "logStatusError",
                "fmi3DoStep: currentCommunicationPoint = %.17g s but the FMU is at t = %.17g s",
                currentCommunicationPoint, now);
        return fmi3Error;
    }
    model_set_time(inst->data, currentCommunicationPoint); /* the importer's clock is the reference */
    fmi2Status status = model_do_step(inst, inst->data, currentCommunicationPoint, communicationStepSize);
    /* fmi3Discard: computed up to *lastSuccessfulTime only; the instance stays in Step Mode (it may be
     * terminated, reset, or set to a stored state) */
    if (status >= fmi2Error) inst->state = STATE_ERROR;
    *lastSuccessfulTime = model_time(inst->data);
    return status3(status);
}
