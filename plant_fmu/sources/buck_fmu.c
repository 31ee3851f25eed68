/* The buck converter as an FMU model (fmu_model.h): its variables, their checks and its steps.
 * The equations are in buck_model.c; the FMI 2.0 glue, shared with the workbench's other FMUs,
 * in fmi2_glue.c. */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "buck_model.h"
#include "buck_variables.h"
#include "fmu_model.h"

typedef struct {
    BuckModel model;
    double requested_duty; /* duty as set by the importer, before clamping */
    int duty_out_of_range; /* warn once per excursion, not on every set */
} PlantData;

const FmuModelInfo FMU_MODEL = {
    "{4c1e9f2a-7d3b-4e58-9a61-2b8f0d5e7c42}", /* must equal modelDescription.xml */
    "BuckConverter",
    sizeof(PlantData),
    BUCK_STATES,
    2,
    0x4255434bu, /* "BUCK" */
    5u,          /* snapshot version: the data block of the shared glue (5: pwm_latched) */
};

void model_set_defaults(void *data) {
    PlantData *d = (PlantData *)data;
    memset(d, 0, sizeof *d);
    buck_set_defaults(&d->model);
}

const char *model_start(FmuInstance *fmu, void *data, double time, char *buffer, size_t size) {
    PlantData *d = (PlantData *)data;
    (void)fmu;
    const char *problem = buck_check(&d->model, true, buffer, size);
    if (problem != NULL) return problem;
    buck_start(&d->model, time);
    return NULL;
}

double model_time(const void *data) { return ((const PlantData *)data)->model.time; }
void model_set_time(void *data, double time) { ((PlantData *)data)->model.time = time; }

/* ------------------------------------------------------------------------------------------ */
/* Variables                                                                                  */

fmi2Status model_get_real(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Real *value) {
    PlantData *d = (PlantData *)data;
    BuckModel *m = &d->model;
    double dx[BUCK_STATES];
    switch (vr) {
    case VR_DUTY_CYCLE: *value = d->requested_duty; break;
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
        fmu_log(fmu, fmi2Error, "logStatusError", "fmi2GetReal: unknown value reference %u", vr);
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
fmi2Status model_set_real(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Real value, int initializing) {
    PlantData *d = (PlantData *)data;
    PlantData trial = *d;
    BuckModel *m = &trial.model;
    fmi2Status status = fmi2OK;
    const char *fixed = fixed_parameter_name(vr);
    if (fixed != NULL && !initializing) {
        fmu_log(fmu, fmi2Error, "logStatusError",
                "fmi2SetReal: %s can only be set before fmi2ExitInitializationMode", fixed);
        return fmi2Error;
    }
    const char *tunable = tunable_parameter_name(vr);
    if (tunable != NULL && fmu_in_continuous_time(fmu)) {
        fmu_log(fmu, fmi2Error, "logStatusError",
                "fmi2SetReal: %s is tunable in event mode only (call fmi2EnterEventMode first)", tunable);
        return fmi2Error;
    }
    switch (vr) {
    case VR_DUTY_CYCLE: {
        if (!isfinite(value)) {
            fmu_log(fmu, fmi2Error, "logStatusError",
                    "fmi2SetReal: duty_cycle = %g is invalid: expected a finite value in [0, 1]", value);
            return fmi2Error;
        }
        double clamped = value < 0.0 ? 0.0 : (value > 1.0 ? 1.0 : value);
        trial.requested_duty = value;
        m->u.duty_cycle = clamped;
        if (clamped != value) {
            if (!trial.duty_out_of_range) {
                fmu_log(fmu, fmi2Warning, "logStatusWarning",
                        "duty_cycle = %g at t = %g s is outside [0, 1]: clamped to %g", value, m->time, clamped);
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
        fmu_log(fmu, fmi2Error, "logStatusError", "fmi2SetReal: value reference %u is not an input or parameter", vr);
        return fmi2Error;
    }
    char message[256];
    const char *problem = buck_check(m, initializing || vr == VR_INDUCTOR_CURRENT || vr == VR_CAPACITOR_VOLTAGE,
                                     message, sizeof message);
    if (problem != NULL) {
        fmu_log(fmu, fmi2Error, "logStatusError", "fmi2SetReal: %s", problem);
        return fmi2Error;
    }
    *d = trial;
    return status;
}

fmi2Status model_get_integer(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Integer *value) {
    const BuckModel *m = &((PlantData *)data)->model;
    if (vr == VR_PLANT_MODE) *value = m->p.plant_mode;
    else if (vr == VR_PWM_CARRIER) *value = m->p.pwm_carrier;
    else {
        fmu_log(fmu, fmi2Error, "logStatusError", "fmi2GetInteger: unknown value reference %u", vr);
        return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status model_set_integer(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Integer value,
                             int initializing) {
    PlantData *d = (PlantData *)data;
    if (vr != VR_PLANT_MODE && vr != VR_PWM_CARRIER) {
        fmu_log(fmu, fmi2Error, "logStatusError", "fmi2SetInteger: unknown value reference %u", vr);
        return fmi2Error;
    }
    if (!initializing) {
        fmu_log(fmu, fmi2Error, "logStatusError", "fmi2SetInteger: %s can only be set before "
                "fmi2ExitInitializationMode", fixed_parameter_name(vr));
        return fmi2Error;
    }
    BuckModel trial = d->model;
    if (vr == VR_PLANT_MODE) trial.p.plant_mode = value;
    else trial.p.pwm_carrier = value;
    char message[256];
    const char *problem = buck_check(&trial, true, message, sizeof message);
    if (problem != NULL) {
        fmu_log(fmu, fmi2Error, "logStatusError", "fmi2SetInteger: %s", problem);
        return fmi2Error;
    }
    d->model = trial;
    return fmi2OK;
}

/* ------------------------------------------------------------------------------------------ */
/* Co-simulation                                                                              */

fmi2Status model_do_step(FmuInstance *fmu, void *data, double time, double step) {
    BuckModel *m = &((PlantData *)data)->model;
    if (!buck_advance(m, time + step)) {
        fmu_log(fmu, fmi2Error, "logStatusError",
                "fmi2DoStep: no progress at t = %.17g s (conduction regimes kept alternating)", m->time);
        return fmi2Error;
    }
    if (!isfinite(m->inductor_current) || !isfinite(m->capacitor_voltage)) {
        fmu_log(fmu, fmi2Error, "logStatusError", "fmi2DoStep: the state became non-finite at t = %g s", m->time);
        return fmi2Error;
    }
    return fmi2OK;
}

/* ------------------------------------------------------------------------------------------ */
/* Model exchange: states i_L, v_C and the two period integrals                                */

void model_get_states(const void *data, double x[]) {
    const BuckModel *m = &((const PlantData *)data)->model;
    x[0] = m->inductor_current;
    x[1] = m->capacitor_voltage;
    x[2] = m->period_charge;
    x[3] = m->period_flux;
}

void model_set_states(void *data, const double x[]) {
    BuckModel *m = &((PlantData *)data)->model;
    m->inductor_current = m->conduction == CONDUCTION_BLOCKED ? 0.0 : x[0];
    m->capacitor_voltage = x[1];
    m->period_charge = x[2];
    m->period_flux = x[3];
}

void model_nominal_states(double x[]) {
    x[0] = 1.0;  /* [A] */
    x[1] = 10.0; /* [V] */
    x[2] = 1e-5; /* [A s]: about 1 A over one period */
    x[3] = 1e-4; /* [V s] */
}

void model_derivatives(const void *data, double dx[]) { buck_derivatives(&((const PlantData *)data)->model, dx); }

void model_event_indicators(const void *data, double z[]) {
    buck_event_indicators(&((const PlantData *)data)->model, z);
}

int model_update_discrete(FmuInstance *fmu, void *data, double *next_event_time, int *next_event_defined) {
    bool defined = false;
    (void)fmu;
    int changed = buck_update_discrete(&((PlantData *)data)->model, next_event_time, &defined) ? 1 : 0;
    *next_event_defined = defined ? 1 : 0;
    return changed;
}
