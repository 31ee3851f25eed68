/* FMI 2.0 glue for the buck converter: instantiation, modes, get/set, model exchange,
 * co-simulation and FMU state. The equations live in buck_model.c. The FMI headers
 * (fmi2Functions.h and friends) come from the importing tool, as the standard intends. */
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"

#include "buck_model.h"
#include "buck_variables.h"

/* Must equal the guid attribute of modelDescription.xml. */
#define MODEL_GUID "{4c1e9f2a-7d3b-4e58-9a61-2b8f0d5e7c42}"
#define NUMBER_OF_STATES BUCK_STATES
#define NUMBER_OF_EVENT_INDICATORS 2
#define SNAPSHOT_MAGIC 0x4255434bu /* "BUCK" */
#define SNAPSHOT_VERSION 3u

typedef enum {
    STATE_INSTANTIATED,
    STATE_INITIALIZATION,
    STATE_EVENT,
    STATE_CONTINUOUS_TIME,
    STATE_STEP_COMPLETE,
    STATE_TERMINATED,
    STATE_ERROR
} InstanceState;

typedef struct {
    BuckModel model;
    double requested_duty;  /* duty as set by the importer, before clamping */
    int duty_out_of_range;  /* warn once per excursion, not on every set */
} PlantState;

typedef struct {
    PlantState plant;
    fmi2Type type;
    InstanceState state;
    char *instance_name;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment environment;
    int logging_on;
} Instance;

typedef struct {
    uint32_t magic;
    uint32_t version;
    uint32_t size;
    PlantState plant;
} Snapshot;

/* ------------------------------------------------------------------------------------------ */
/* Logging and state checks                                                                   */

static void log_message(const Instance *inst, fmi2Status status, const char *category, const char *format, ...) {
    if (inst == NULL || inst->logger == NULL) return;
    if (status == fmi2OK && !inst->logging_on) return;
    char buffer[1024];
    va_list args;
    va_start(args, format);
    vsnprintf(buffer, sizeof buffer, format, args);
    va_end(args);
    inst->logger(inst->environment, inst->instance_name, status, category, "%s", buffer);
}

static fmi2Status fail(Instance *inst, const char *function, const char *message) {
    log_message(inst, fmi2Error, "logStatusError", "%s: %s", function, message);
    return fmi2Error;
}

static int allowed(Instance *inst, const char *function, unsigned mask) {
    if (inst == NULL) return 0;
    if (mask & (1u << inst->state)) return 1;
    log_message(inst, fmi2Error, "logStatusError", "%s must not be called in the current state", function);
    inst->state = STATE_ERROR;
    return 0;
}

#define IN(s) (1u << (s))
#define ANY_STATE 0xffffu
#define BEFORE_INIT_DONE (IN(STATE_INSTANTIATED) | IN(STATE_INITIALIZATION))
#define RUNNING (IN(STATE_EVENT) | IN(STATE_CONTINUOUS_TIME) | IN(STATE_STEP_COMPLETE))

/* ------------------------------------------------------------------------------------------ */
/* Variable access                                                                            */

static fmi2Status get_real(Instance *inst, fmi2ValueReference vr, fmi2Real *value) {
    BuckModel *m = &inst->plant.model;
    double dx[NUMBER_OF_STATES];
    switch (vr) {
    case VR_DUTY_CYCLE: *value = inst->plant.requested_duty; break;
    case VR_INPUT_VOLTAGE: *value = m->u.input_voltage; break;
    case VR_LOAD_RESISTANCE: *value = m->u.load_resistance; break;
    case VR_OUTPUT_VOLTAGE: *value = buck_output_voltage(m); break;
    case VR_INDUCTOR_CURRENT: *value = m->inductor_current; break;
    case VR_LOAD_CURRENT: *value = buck_output_voltage(m) / m->u.load_resistance; break;
    case VR_APPLIED_DUTY_CYCLE: *value = buck_applied_duty(m); break;
    case VR_CAPACITOR_VOLTAGE: *value = m->capacitor_voltage; break;
    case VR_DER_INDUCTOR_CURRENT: buck_derivatives(m, dx); *value = dx[0]; break;
    case VR_DER_CAPACITOR_VOLTAGE: buck_derivatives(m, dx); *value = dx[1]; break;
    case VR_INDUCTANCE: *value = m->p.inductance; break;
    case VR_CAPACITANCE: *value = m->p.capacitance; break;
    case VR_SWITCHING_FREQUENCY: *value = m->p.switching_frequency; break;
    case VR_INDUCTOR_RESISTANCE: *value = m->p.inductor_resistance; break;
    case VR_SWITCH_ON_RESISTANCE: *value = m->p.switch_on_resistance; break;
    case VR_DIODE_FORWARD_VOLTAGE: *value = m->p.diode_forward_voltage; break;
    case VR_CAPACITOR_ESR: *value = m->p.capacitor_esr; break;
    case VR_AVERAGE_OUTPUT_VOLTAGE: *value = buck_average_output_voltage(m); break;
    case VR_AVERAGE_INDUCTOR_CURRENT: *value = buck_average_inductor_current(m); break;
    case VR_AVERAGE_LOAD_CURRENT: *value = buck_average_load_current(m); break;
    case VR_PERIOD_CHARGE: *value = m->period_charge; break;
    case VR_PERIOD_FLUX: *value = m->period_flux; break;
    case VR_DER_PERIOD_CHARGE: buck_derivatives(m, dx); *value = dx[2]; break;
    case VR_DER_PERIOD_FLUX: buck_derivatives(m, dx); *value = dx[3]; break;
    default:
        log_message(inst, fmi2Error, "logStatusError", "fmi2GetReal: unknown value reference %u", vr);
        return fmi2Error;
    }
    return fmi2OK;
}

static const char *fixed_parameter_name(fmi2ValueReference vr) {
    switch (vr) {
    case VR_SWITCHING_FREQUENCY: return "switching_frequency";
    case VR_INDUCTOR_CURRENT: return "inductor_current";
    case VR_CAPACITOR_VOLTAGE: return "capacitor_voltage";
    case VR_PLANT_MODE: return "plant_mode";
    case VR_PWM_CARRIER: return "pwm_carrier";
    default: return NULL;
    }
}

/* Circuit parameters with variability="tunable": settable during a run -- co-simulation between
 * steps, model exchange in event mode (FMI 2.0 forbids it in continuous-time mode). The states
 * i_L and v_C carry over, so a change at a communication point is exact: every interval after it
 * is solved with the new values and the period means integrate across it. */
static const char *tunable_parameter_name(fmi2ValueReference vr) {
    switch (vr) {
    case VR_INDUCTANCE: return "inductance";
    case VR_CAPACITANCE: return "capacitance";
    case VR_INDUCTOR_RESISTANCE: return "inductor_resistance";
    case VR_SWITCH_ON_RESISTANCE: return "switch_on_resistance";
    case VR_DIODE_FORWARD_VOLTAGE: return "diode_forward_voltage";
    case VR_CAPACITOR_ESR: return "capacitor_esr";
    default: return NULL;
    }
}

/* Apply one value to a copy, validate the copy, and commit only if it is physically valid. */
static fmi2Status set_real(Instance *inst, fmi2ValueReference vr, fmi2Real value) {
    PlantState trial = inst->plant;
    BuckModel *m = &trial.model;
    fmi2Status status = fmi2OK;
    const char *fixed = fixed_parameter_name(vr);
    if (fixed != NULL && !(BEFORE_INIT_DONE & IN(inst->state))) {
        log_message(inst, fmi2Error, "logStatusError",
                    "fmi2SetReal: %s can only be set before fmi2ExitInitializationMode", fixed);
        return fmi2Error;
    }
    const char *tunable = tunable_parameter_name(vr);
    if (tunable != NULL && inst->state == STATE_CONTINUOUS_TIME) {
        log_message(inst, fmi2Error, "logStatusError",
                    "fmi2SetReal: %s is tunable in event mode only (call fmi2EnterEventMode first)", tunable);
        return fmi2Error;
    }
    switch (vr) {
    case VR_DUTY_CYCLE: {
        if (!isfinite(value)) {
            log_message(inst, fmi2Error, "logStatusError",
                        "fmi2SetReal: duty_cycle = %g is invalid: expected a finite value in [0, 1]", value);
            return fmi2Error;
        }
        double clamped = value < 0.0 ? 0.0 : (value > 1.0 ? 1.0 : value);
        trial.requested_duty = value;
        m->u.duty_cycle = clamped;
        if (clamped != value) {
            if (!trial.duty_out_of_range) {
                log_message(inst, fmi2Warning, "logStatusWarning",
                            "duty_cycle = %g at t = %g s is outside [0, 1]: clamped to %g", value, m->time,
                            clamped);
                status = fmi2Warning;
            }
            trial.duty_out_of_range = 1;
        } else {
            trial.duty_out_of_range = 0;
        }
        break;
    }
    case VR_INPUT_VOLTAGE: m->u.input_voltage = value; break;
    case VR_LOAD_RESISTANCE: buck_set_load_resistance(m, value); break;
    case VR_INDUCTANCE: m->p.inductance = value; break;
    case VR_CAPACITANCE: m->p.capacitance = value; break;
    case VR_SWITCHING_FREQUENCY: m->p.switching_frequency = value; break;
    case VR_INDUCTOR_RESISTANCE: m->p.inductor_resistance = value; break;
    case VR_SWITCH_ON_RESISTANCE: m->p.switch_on_resistance = value; break;
    case VR_DIODE_FORWARD_VOLTAGE: m->p.diode_forward_voltage = value; break;
    case VR_CAPACITOR_ESR: m->p.capacitor_esr = value; break;
    case VR_INDUCTOR_CURRENT: m->inductor_current = value; break;
    case VR_CAPACITOR_VOLTAGE: m->capacitor_voltage = value; break;
    default:
        log_message(inst, fmi2Error, "logStatusError",
                    "fmi2SetReal: value reference %u is not an input or parameter", vr);
        return fmi2Error;
    }
    char message[256];
    const char *problem = buck_check(m, message, sizeof message);
    if (problem != NULL) {
        log_message(inst, fmi2Error, "logStatusError", "fmi2SetReal: %s", problem);
        return fmi2Error;
    }
    inst->plant = trial;
    return status;
}

/* ------------------------------------------------------------------------------------------ */
/* Common functions                                                                           */

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    Instance *inst = (Instance *)c;
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
    Instance probe;
    memset(&probe, 0, sizeof probe);
    probe.logger = functions->logger;
    probe.environment = functions->componentEnvironment;
    probe.instance_name = (char *)instanceName;
    if (fmuGUID == NULL || strcmp(fmuGUID, MODEL_GUID) != 0) {
        log_message(&probe, fmi2Error, "logStatusError", "fmi2Instantiate: GUID %s does not match %s",
                    fmuGUID ? fmuGUID : "(null)", MODEL_GUID);
        return NULL;
    }
    if (fmuType != fmi2ModelExchange && fmuType != fmi2CoSimulation) {
        log_message(&probe, fmi2Error, "logStatusError", "fmi2Instantiate: unknown FMU type %d", (int)fmuType);
        return NULL;
    }
    Instance *inst = (Instance *)calloc(1, sizeof *inst);
    char *name = (char *)malloc(strlen(instanceName) + 1);
    if (inst == NULL || name == NULL) {
        free(inst);
        free(name);
        return NULL;
    }
    strcpy(name, instanceName);
    inst->instance_name = name;
    inst->logger = functions->logger;
    inst->environment = functions->componentEnvironment;
    inst->logging_on = loggingOn != fmi2False;
    inst->type = fmuType;
    inst->state = STATE_INSTANTIATED;
    buck_set_defaults(&inst->plant.model);
    return inst;
}

void fmi2FreeInstance(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return;
    free(inst->instance_name);
    free(inst);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    Instance *inst = (Instance *)c;
    (void)toleranceDefined;
    (void)tolerance;
    (void)stopTimeDefined;
    (void)stopTime;
    if (!allowed(inst, "fmi2SetupExperiment", IN(STATE_INSTANTIATED))) return fmi2Error;
    inst->plant.model.time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2EnterInitializationMode", IN(STATE_INSTANTIATED))) return fmi2Error;
    inst->state = STATE_INITIALIZATION;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2ExitInitializationMode", IN(STATE_INITIALIZATION))) return fmi2Error;
    char message[256];
    const char *problem = buck_check(&inst->plant.model, message, sizeof message);
    if (problem != NULL) {
        inst->state = STATE_ERROR;
        return fail(inst, "fmi2ExitInitializationMode", problem);
    }
    buck_start(&inst->plant.model, inst->plant.model.time);
    inst->state = inst->type == fmi2ModelExchange ? STATE_EVENT : STATE_STEP_COMPLETE;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2Terminate", RUNNING)) return fmi2Error;
    inst->state = STATE_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    memset(&inst->plant, 0, sizeof inst->plant);
    buck_set_defaults(&inst->plant.model);
    inst->state = STATE_INSTANTIATED;
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2GetReal", ~IN(STATE_ERROR) & ANY_STATE)) return fmi2Error;
    for (size_t i = 0; i < nvr; ++i)
        if (get_real(inst, vr[i], &value[i]) != fmi2OK) return fmi2Error;
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[]) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2GetInteger", ~IN(STATE_ERROR) & ANY_STATE)) return fmi2Error;
    for (size_t i = 0; i < nvr; ++i) {
        if (vr[i] == VR_PLANT_MODE) value[i] = inst->plant.model.p.plant_mode;
        else if (vr[i] == VR_PWM_CARRIER) value[i] = inst->plant.model.p.pwm_carrier;
        else return fail(inst, "fmi2GetInteger", "unknown value reference");
    }
    return fmi2OK;
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[]) {
    (void)vr;
    (void)value;
    return nvr == 0 ? fmi2OK : fail((Instance *)c, "fmi2GetBoolean", "the FMU has no Boolean variables");
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[]) {
    (void)vr;
    (void)value;
    return nvr == 0 ? fmi2OK : fail((Instance *)c, "fmi2GetString", "the FMU has no String variables");
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2SetReal", BEFORE_INIT_DONE | RUNNING)) return fmi2Error;
    fmi2Status worst = fmi2OK;
    for (size_t i = 0; i < nvr; ++i) {
        fmi2Status status = set_real(inst, vr[i], value[i]);
        if (status > worst) worst = status;
        if (status >= fmi2Error) return status;
    }
    return worst;
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[]) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2SetInteger", BEFORE_INIT_DONE | RUNNING)) return fmi2Error;
    for (size_t i = 0; i < nvr; ++i) {
        const char *name = fixed_parameter_name(vr[i]);
        if (vr[i] != VR_PLANT_MODE && vr[i] != VR_PWM_CARRIER)
            return fail(inst, "fmi2SetInteger", "unknown value reference");
        if (!(BEFORE_INIT_DONE & IN(inst->state))) {
            log_message(inst, fmi2Error, "logStatusError",
                        "fmi2SetInteger: %s can only be set before fmi2ExitInitializationMode", name);
            return fmi2Error;
        }
        BuckModel trial = inst->plant.model;
        if (vr[i] == VR_PLANT_MODE) trial.p.plant_mode = value[i];
        else trial.p.pwm_carrier = value[i];
        char message[256];
        const char *problem = buck_check(&trial, message, sizeof message);
        if (problem != NULL) return fail(inst, "fmi2SetInteger", problem);
        inst->plant.model = trial;
    }
    return fmi2OK;
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[]) {
    (void)vr;
    (void)value;
    return nvr == 0 ? fmi2OK : fail((Instance *)c, "fmi2SetBoolean", "the FMU has no Boolean variables");
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[]) {
    (void)vr;
    (void)value;
    return nvr == 0 ? fmi2OK : fail((Instance *)c, "fmi2SetString", "the FMU has no String variables");
}

/* ------------------------------------------------------------------------------------------ */
/* FMU state                                                                                  */

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2GetFMUstate", ~IN(STATE_ERROR) & ANY_STATE)) return fmi2Error;
    Snapshot *snapshot = (Snapshot *)*FMUstate;
    if (snapshot == NULL) {
        snapshot = (Snapshot *)calloc(1, sizeof *snapshot);
        if (snapshot == NULL) return fail(inst, "fmi2GetFMUstate", "out of memory");
        *FMUstate = snapshot;
    }
    snapshot->magic = SNAPSHOT_MAGIC;
    snapshot->version = SNAPSHOT_VERSION;
    snapshot->size = (uint32_t)sizeof(Snapshot);
    snapshot->plant = inst->plant;
    return fmi2OK;
}

static int valid_snapshot(const Snapshot *s) {
    return s != NULL && s->magic == SNAPSHOT_MAGIC && s->version == SNAPSHOT_VERSION && s->size == sizeof(Snapshot);
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2SetFMUstate", ~IN(STATE_ERROR) & ANY_STATE)) return fmi2Error;
    const Snapshot *snapshot = (const Snapshot *)FMUstate;
    if (!valid_snapshot(snapshot)) return fail(inst, "fmi2SetFMUstate", "not a BuckConverter FMU state");
    inst->plant = snapshot->plant;
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
    *size = sizeof(Snapshot);
    return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[], size_t size) {
    Instance *inst = (Instance *)c;
    if (!valid_snapshot((const Snapshot *)FMUstate)) return fail(inst, "fmi2SerializeFMUstate", "not a BuckConverter FMU state");
    if (size < sizeof(Snapshot)) return fail(inst, "fmi2SerializeFMUstate", "buffer too small");
    memcpy(serializedState, FMUstate, sizeof(Snapshot));
    return fmi2OK;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate) {
    Instance *inst = (Instance *)c;
    Snapshot copy;
    if (size != sizeof(Snapshot)) return fail(inst, "fmi2DeSerializeFMUstate", "serialized state has the wrong size");
    memcpy(&copy, serializedState, sizeof copy);
    if (!valid_snapshot(&copy)) return fail(inst, "fmi2DeSerializeFMUstate", "not a BuckConverter FMU state");
    if (*FMUstate == NULL) {
        *FMUstate = calloc(1, sizeof(Snapshot));
        if (*FMUstate == NULL) return fail(inst, "fmi2DeSerializeFMUstate", "out of memory");
    }
    memcpy(*FMUstate, &copy, sizeof copy);
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
    return fail((Instance *)c, "fmi2GetDirectionalDerivative", "not provided by this FMU");
}

/* ------------------------------------------------------------------------------------------ */
/* Model exchange                                                                             */

fmi2Status fmi2EnterEventMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2EnterEventMode", IN(STATE_EVENT) | IN(STATE_CONTINUOUS_TIME))) return fmi2Error;
    inst->state = STATE_EVENT;
    return fmi2OK;
}

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *info) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2NewDiscreteStates", IN(STATE_EVENT))) return fmi2Error;
    double next_event_time = 0.0;
    bool next_event_defined = false;
    bool changed = buck_update_discrete(&inst->plant.model, &next_event_time, &next_event_defined);
    info->newDiscreteStatesNeeded = fmi2False;
    info->terminateSimulation = fmi2False;
    info->nominalsOfContinuousStatesChanged = fmi2False;
    info->valuesOfContinuousStatesChanged = changed ? fmi2True : fmi2False;
    info->nextEventTimeDefined = next_event_defined ? fmi2True : fmi2False;
    info->nextEventTime = next_event_time;
    if (changed)
        log_message(inst, fmi2OK, "logEvents", "t = %.9g s: continuous states reinitialised (diode or period mean)",
                    inst->plant.model.time);
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2EnterContinuousTimeMode", IN(STATE_EVENT))) return fmi2Error;
    inst->state = STATE_CONTINUOUS_TIME;
    return fmi2OK;
}

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi2Boolean *enterEventMode, fmi2Boolean *terminateSimulation) {
    Instance *inst = (Instance *)c;
    (void)noSetFMUStatePriorToCurrentPoint;
    if (!allowed(inst, "fmi2CompletedIntegratorStep", IN(STATE_CONTINUOUS_TIME))) return fmi2Error;
    *enterEventMode = fmi2False;
    *terminateSimulation = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2SetTime", IN(STATE_EVENT) | IN(STATE_CONTINUOUS_TIME))) return fmi2Error;
    inst->plant.model.time = time;
    return fmi2OK;
}

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2SetContinuousStates", IN(STATE_EVENT) | IN(STATE_CONTINUOUS_TIME))) return fmi2Error;
    if (nx != NUMBER_OF_STATES) return fail(inst, "fmi2SetContinuousStates", "expected 4 states");
    BuckModel *m = &inst->plant.model;
    m->inductor_current = m->conduction == CONDUCTION_BLOCKED ? 0.0 : x[0];
    m->capacitor_voltage = x[1];
    m->period_charge = x[2];
    m->period_flux = x[3];
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real derivatives[], size_t nx) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2GetDerivatives", ~IN(STATE_ERROR) & ANY_STATE)) return fmi2Error;
    if (nx != NUMBER_OF_STATES) return fail(inst, "fmi2GetDerivatives", "expected 4 states");
    buck_derivatives(&inst->plant.model, derivatives);
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real eventIndicators[], size_t ni) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2GetEventIndicators", ~IN(STATE_ERROR) & ANY_STATE)) return fmi2Error;
    if (ni != NUMBER_OF_EVENT_INDICATORS) return fail(inst, "fmi2GetEventIndicators", "expected 2 indicators");
    buck_event_indicators(&inst->plant.model, eventIndicators);
    return fmi2OK;
}

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    Instance *inst = (Instance *)c;
    if (!allowed(inst, "fmi2GetContinuousStates", ~IN(STATE_ERROR) & ANY_STATE)) return fmi2Error;
    if (nx != NUMBER_OF_STATES) return fail(inst, "fmi2GetContinuousStates", "expected 4 states");
    x[0] = inst->plant.model.inductor_current;
    x[1] = inst->plant.model.capacitor_voltage;
    x[2] = inst->plant.model.period_charge;
    x[3] = inst->plant.model.period_flux;
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x_nominal[], size_t nx) {
    Instance *inst = (Instance *)c;
    if (nx != NUMBER_OF_STATES) return fail(inst, "fmi2GetNominalsOfContinuousStates", "expected 4 states");
    x_nominal[0] = 1.0;  /* [A] */
    x_nominal[1] = 10.0; /* [V] */
    x_nominal[2] = 1e-5; /* [A s]: about 1 A over one period */
    x_nominal[3] = 1e-4; /* [V s] */
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
    return fail((Instance *)c, "fmi2SetRealInputDerivatives", "inputs are held constant over a step");
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    (void)vr;
    (void)nvr;
    (void)order;
    (void)value;
    return fail((Instance *)c, "fmi2GetRealOutputDerivatives", "output derivatives are not provided");
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentCommunicationPoint) {
    Instance *inst = (Instance *)c;
    (void)noSetFMUStatePriorToCurrentCommunicationPoint;
    if (!allowed(inst, "fmi2DoStep", IN(STATE_STEP_COMPLETE))) return fmi2Error;
    BuckModel *m = &inst->plant.model;
    if (!(communicationStepSize >= 0.0) || !isfinite(communicationStepSize)) {
        log_message(inst, fmi2Error, "logStatusError",
                    "fmi2DoStep: communicationStepSize = %g s is invalid: expected a finite value >= 0",
                    communicationStepSize);
        return fmi2Error;
    }
    double drift = fabs(currentCommunicationPoint - m->time);
    if (drift > 1e-9 * fmax(1.0, fabs(m->time))) {
        log_message(inst, fmi2Error, "logStatusError",
                    "fmi2DoStep: currentCommunicationPoint = %.17g s but the FMU is at t = %.17g s",
                    currentCommunicationPoint, m->time);
        return fmi2Error;
    }
    m->time = currentCommunicationPoint; /* the importer's clock is the reference */
    if (!buck_advance(m, currentCommunicationPoint + communicationStepSize)) {
        inst->state = STATE_ERROR;
        log_message(inst, fmi2Error, "logStatusError",
                    "fmi2DoStep: no progress at t = %.17g s (conduction regimes kept alternating)", m->time);
        return fmi2Error;
    }
    if (!isfinite(m->inductor_current) || !isfinite(m->capacitor_voltage)) {
        inst->state = STATE_ERROR;
        log_message(inst, fmi2Error, "logStatusError", "fmi2DoStep: the state became non-finite at t = %g s",
                    m->time);
        return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) {
    return fail((Instance *)c, "fmi2CancelStep", "steps complete synchronously");
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    (void)s;
    (void)c;
    *value = fmi2OK;
    return fmi2OK;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    Instance *inst = (Instance *)c;
    if (s != fmi2LastSuccessfulTime) return fmi2Discard;
    *value = inst->plant.model.time;
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
