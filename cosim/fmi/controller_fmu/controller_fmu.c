/* A workbench controller as an FMU model (fmu_model.h): the PI, the predictive controller, the
 * explicit NNPC (explicit policy), the average-current-mode controller or the discrete compensator
 * (Type-III) of controllers/c/, sampled on the FMU's own clock.
 *
 * The algorithm and its settings come from the generated controller_config.h (data only: the
 * kind, the PI gains, the predictive configuration with the network's weights, or the explicit
 * policy's weights) -- the
 * algorithms themselves are the hand-written C twins in controllers/c/. The FMI 2.0 glue is the
 * one the plant FMU uses (fmi2_glue.c).
 *
 * Sampling. The FMU samples at t_k = t0 + k Ts (t0: the start time). At a sample instant the duty
 * computed from the inputs of that instant is in effect at that instant: reading duty_cycle
 * there computes it (direct feedthrough, declared in modelDescription.xml) without committing
 * it, so a master may set inputs and read the duty as often as it likes; fmi2DoStep from a sample
 * instant commits that computation (the controller's state advances) and moves to the next one.
 * A communication step may end anywhere: one that spans several sample instants takes each of them
 * with the inputs held over the step (model_do_step), so the FMU runs in any master at any step
 * size (modelDescription.xml's DefaultExperiment proposes stepSize = Ts). Between sample instants
 * the duty is held (zero-order hold).
 *
 * Precision. The FMU's variables are doubles (fmi2Real); the controller computes in buckc_real
 * (controllers/c/buckc.h). A float32 FMU (export-controller --precision float32) compiles every
 * file with BUCKC_FLOAT32 defined (by the generated f32_*.c wrappers): the inputs are rounded to
 * float at each sample, the duty is a float widened to fmi2Real; the predictive controller is left
 * out there (BUCKC_HAVE_PREDICTIVE: its float32 build, the online NNPC's, runs in the Cortex-M4F image). */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "compensator.h"
#include "controller_variables.h"
#include "current_mode.h"
#include "explicit_policy.h"
#include "fmu_model.h"
#include "pi.h"
#if BUCKC_HAVE_PREDICTIVE
#include "predictive.h"
#endif

#include "controller_config.h" /* generated: CONTROLLER_KIND, CONTROLLER_NAME, CONTROLLER_GUID, PI_CONFIG,
                                  PREDICTIVE_CONFIG, POLICY_CONFIG, CURRENT_MODE_CONFIG,
                                  COMPENSATOR_CONFIG */

typedef struct {
    double time;          /* the FMU's clock [s] */
    double start_time;    /* t0 [s] */
    long long next;       /* index k of the next sample instant not yet committed */
    double inputs[CONTROLLER_INPUTS];
    int computed;         /* a duty has been computed for sample `next` from the inputs now set */
    double pending_duty;  /* that duty */
    double duty;          /* the duty in effect between samples */
    int started;          /* initialisation has ended: the controller is configured and may compute */
    double period;        /* the sample clock's Ts [s] (double in every build; the PI's may be set) */
    BuckcPiConfig pi_config; /* PI: its parameters may be set before initialisation */
    BuckcPi pi, pi_pending;
    BuckcPolicy policy, policy_pending;
    BuckcCurrentMode current_mode, current_mode_pending;
    BuckcCompensator compensator, compensator_pending;
#if BUCKC_HAVE_PREDICTIVE
    BuckcPredictiveState predictive_pending;
    BuckcPredictive predictive; /* last: the big one (the predictors' caches) */
#endif
} ControllerData;

const FmuModelInfo FMU_MODEL = {
    CONTROLLER_GUID,
    CONTROLLER_NAME,
    sizeof(ControllerData),
    0, /* co-simulation only */
    0,
    0x42434354u, /* "BCCT" */
    2u,
};

/* a configuration value of the controller this FMU was generated for (the PI's may be set) */
#if BUCKC_HAVE_PREDICTIVE
#define PREDICTIVE_OR(explicit_value, predictive_value) \
    (CONTROLLER_KIND == CONTROLLER_EXPLICIT ? (double)(explicit_value) : (double)(predictive_value))
#else
#define PREDICTIVE_OR(explicit_value, predictive_value) ((double)(explicit_value))
#endif
#ifdef CONTROLLER_SAMPLE_PERIOD /* float32 data: the exact sample period as a double, for the clock */
static double fixed_sample_period(void) { return CONTROLLER_SAMPLE_PERIOD; }
#define DEFAULT_PERIOD CONTROLLER_SAMPLE_PERIOD
#else
static double fixed_sample_period(void) {
    if (CONTROLLER_KIND == CONTROLLER_CURRENT_MODE) return (double)CURRENT_MODE_CONFIG.sample_period;
    if (CONTROLLER_KIND == CONTROLLER_COMPENSATOR) return (double)COMPENSATOR_CONFIG.sample_period;
    return PREDICTIVE_OR(POLICY_CONFIG.sample_period, PREDICTIVE_CONFIG.sample_period);
}
#define DEFAULT_PERIOD ((double)PI_CONFIG.sample_period)
#endif
#ifdef BUCKC_FLOAT32
#define FIXED_TOLERANCE 1e-7 /* a float's rounding of the generated value */
#else
#define FIXED_TOLERANCE 1e-12
#endif
static double fixed_duty_min(void) {
    if (CONTROLLER_KIND == CONTROLLER_CURRENT_MODE) return (double)CURRENT_MODE_CONFIG.duty_min;
    if (CONTROLLER_KIND == CONTROLLER_COMPENSATOR) return (double)COMPENSATOR_CONFIG.duty_min;
    return PREDICTIVE_OR(POLICY_CONFIG.duty_min, PREDICTIVE_CONFIG.duty_min);
}
static double fixed_duty_max(void) {
    if (CONTROLLER_KIND == CONTROLLER_CURRENT_MODE) return (double)CURRENT_MODE_CONFIG.duty_max;
    if (CONTROLLER_KIND == CONTROLLER_COMPENSATOR) return (double)COMPENSATOR_CONFIG.duty_max;
    return PREDICTIVE_OR(POLICY_CONFIG.duty_max, PREDICTIVE_CONFIG.duty_max);
}
static double nominal_input_voltage(void) {
    if (CONTROLLER_KIND == CONTROLLER_CURRENT_MODE) return (double)CURRENT_MODE_CONFIG.nominal_input_voltage;
    if (CONTROLLER_KIND == CONTROLLER_COMPENSATOR) return (double)COMPENSATOR_CONFIG.nominal_input_voltage;
    return PREDICTIVE_OR(48.0, PREDICTIVE_CONFIG.nominal_input_voltage);
}

static double sample_period(const ControllerData *d) {
    return CONTROLLER_KIND == CONTROLLER_PI ? d->period : fixed_sample_period();
}

static double sample_time(const ControllerData *d, long long k) {
    return d->start_time + (double)k * sample_period(d);
}

static double tolerance(const ControllerData *d) { return 1e-9 * sample_period(d); }

static int at_sample(const ControllerData *d) {
    return fabs(d->time - sample_time(d, d->next)) <= tolerance(d);
}

void model_set_defaults(void *data) {
    ControllerData *d = (ControllerData *)data;
    memset(d, 0, sizeof *d);
    d->pi_config = PI_CONFIG;
    d->period = DEFAULT_PERIOD;
    d->inputs[VR_INPUT_VOLTAGE] = nominal_input_voltage();
    d->inputs[VR_MEASURED_LOAD_CURRENT] = NAN;
}

const char *model_start(FmuInstance *fmu, void *data, double time, char *buffer, size_t size) {
    ControllerData *d = (ControllerData *)data;
    const char *what = NULL;
    int status;
    (void)fmu;
    if (CONTROLLER_KIND == CONTROLLER_PI) status = buckc_pi_init(&d->pi, &d->pi_config, &what);
    else if (CONTROLLER_KIND == CONTROLLER_EXPLICIT) status = buckc_policy_init(&d->policy, &POLICY_CONFIG, &what);
    else if (CONTROLLER_KIND == CONTROLLER_CURRENT_MODE)
        status = buckc_current_mode_init(&d->current_mode, &CURRENT_MODE_CONFIG, &what);
    else if (CONTROLLER_KIND == CONTROLLER_COMPENSATOR)
        status = buckc_compensator_init(&d->compensator, &COMPENSATOR_CONFIG, &what);
#if BUCKC_HAVE_PREDICTIVE
    else status = buckc_predictive_init(&d->predictive, &PREDICTIVE_CONFIG, &what);
#else
    else status = BUCKC_ERR_INVALID, what = "the predictive controller has no " BUCKC_REAL_NAME " build";
#endif
    if (status != BUCKC_OK) {
        snprintf(buffer, size, "%s refuses its configuration: %s (%s)", CONTROLLER_NAME, what ? what : "",
                 buckc_status_text(status));
        return buffer;
    }
    d->start_time = d->time = time;
    d->next = 0;
    d->computed = 0;
    d->duty = d->pending_duty = 0.0;
    d->started = 1;
    return NULL;
}

double model_time(const void *data) { return ((const ControllerData *)data)->time; }
void model_set_time(void *data, double time) { ((ControllerData *)data)->time = time; }

/* The duty of the sample instant from the inputs now set, without committing the state; a failure is
 * logged with status `failure` (fmi2Error for a read of the duty, fmi2Discard for a step) and returned. */
static fmi2Status compute(FmuInstance *fmu, ControllerData *d, fmi2Status failure) {
    buckc_real duty = 0;
    if (CONTROLLER_KIND == CONTROLLER_PI) {
        d->pi_pending = d->pi;
        duty = buckc_pi_step(&d->pi_pending, (buckc_real)d->inputs[VR_REFERENCE],
                             (buckc_real)d->inputs[VR_MEASURED_OUTPUT_VOLTAGE]);
    } else {
        BuckcMeasurement m;
        int status = BUCKC_ERR_INVALID;
        m.time = (buckc_real)d->time;
        m.reference = (buckc_real)d->inputs[VR_REFERENCE];
        m.output_voltage = (buckc_real)d->inputs[VR_MEASURED_OUTPUT_VOLTAGE];
        m.inductor_current = (buckc_real)d->inputs[VR_MEASURED_INDUCTOR_CURRENT];
        m.load_current = (buckc_real)d->inputs[VR_MEASURED_LOAD_CURRENT];
        m.input_voltage = (buckc_real)d->inputs[VR_INPUT_VOLTAGE];
        if (CONTROLLER_KIND == CONTROLLER_EXPLICIT) {
            d->policy.config = &POLICY_CONFIG; /* again: a deserialized FMU state may come from another process */
            d->policy_pending = d->policy; /* committed by fmi2DoStep, not by reading the duty */
            status = buckc_policy_step(&d->policy_pending, &m, &duty);
        } else if (CONTROLLER_KIND == CONTROLLER_CURRENT_MODE) {
            d->current_mode_pending = d->current_mode; /* committed by fmi2DoStep, not by reading the duty */
            status = buckc_current_mode_step(&d->current_mode_pending, &m, &duty);
        } else if (CONTROLLER_KIND == CONTROLLER_COMPENSATOR) {
            d->compensator_pending = d->compensator;
            status = buckc_compensator_step(&d->compensator_pending, &m, &duty);
        } else {
#if BUCKC_HAVE_PREDICTIVE
            BuckcPredictiveState committed = d->predictive.state;
            status = buckc_predictive_step(&d->predictive, &m, &duty);
            d->predictive_pending = d->predictive.state;
            d->predictive.state = committed; /* committed by fmi2DoStep, not by reading the duty */
#endif
        }
        if (status != BUCKC_OK) {
            fmu_log(fmu, failure, "logStatusError", "%s at t = %.9g s: %s%s", CONTROLLER_NAME, d->time,
                    buckc_status_text(status),
                    status == BUCKC_ERR_NO_INDUCTOR_CURRENT ? " (measured_inductor_current is not finite)" : "");
            return failure;
        }
    }
    if (!isfinite((double)duty)) {
        fmu_log(fmu, failure, "logStatusError", "%s computed a non-finite duty at t = %.9g s", CONTROLLER_NAME,
                d->time);
        return failure;
    }
    d->pending_duty = (double)duty;
    d->computed = 1;
    return fmi2OK;
}

/* ------------------------------------------------------------------------------------------ */
/* Variables                                                                                  */

fmi2Status model_get_real(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Real *value) {
    ControllerData *d = (ControllerData *)data;
    if (vr < CONTROLLER_INPUTS) {
        *value = d->inputs[vr];
        return fmi2OK;
    }
    switch (vr) {
    case VR_DUTY_CYCLE:
        /* In Initialization Mode the controller is not configured yet (that happens when
         * initialisation ends, after the last parameter change): the duty reads 0, the value held
         * before the first sample. A master that iterates initial values (libcosim) reads it. */
        if (!d->started) {
            *value = 0.0;
            return fmi2OK;
        }
        if (at_sample(d) && !d->computed) {
            fmi2Status status = compute(fmu, d, fmi2Error);
            if (status != fmi2OK) return status;
        }
        *value = at_sample(d) ? d->pending_duty : d->duty;
        return fmi2OK;
    case VR_SAMPLE_PERIOD: *value = sample_period(d); return fmi2OK;
    case VR_DUTY_MIN:
        *value = CONTROLLER_KIND == CONTROLLER_PI ? (double)d->pi_config.duty_min : fixed_duty_min();
        return fmi2OK;
    case VR_DUTY_MAX:
        *value = CONTROLLER_KIND == CONTROLLER_PI ? (double)d->pi_config.duty_max : fixed_duty_max();
        return fmi2OK;
    case VR_KP:
        if (CONTROLLER_KIND != CONTROLLER_PI) break;
        *value = (double)d->pi_config.kp;
        return fmi2OK;
    case VR_KI:
        if (CONTROLLER_KIND != CONTROLLER_PI) break;
        *value = (double)d->pi_config.ki;
        return fmi2OK;
    default: break;
    }
    fmu_log(fmu, fmi2Error, "logStatusError", "fmi2GetReal: unknown value reference %u", vr);
    return fmi2Error;
}

fmi2Status model_set_real(FmuInstance *fmu, void *data, fmi2ValueReference vr, fmi2Real value, int initializing) {
    ControllerData *d = (ControllerData *)data;
    if (vr < CONTROLLER_INPUTS) {
        if (d->inputs[vr] != value) d->computed = 0; /* NaN for the load current: "no such sensor" */
        d->inputs[vr] = value;
        return fmi2OK;
    }
    buckc_real *target = NULL;
    if (CONTROLLER_KIND == CONTROLLER_PI) {
        switch (vr) {
        case VR_SAMPLE_PERIOD: target = &d->pi_config.sample_period; break; /* and d->period, below */
        case VR_DUTY_MIN: target = &d->pi_config.duty_min; break;
        case VR_DUTY_MAX: target = &d->pi_config.duty_max; break;
        case VR_KP: target = &d->pi_config.kp; break;
        case VR_KI: target = &d->pi_config.ki; break;
        default: break;
        }
    } else if (vr == VR_SAMPLE_PERIOD || vr == VR_DUTY_MIN || vr == VR_DUTY_MAX) {
        double fixed = vr == VR_SAMPLE_PERIOD ? fixed_sample_period()
                       : vr == VR_DUTY_MIN   ? fixed_duty_min()
                                             : fixed_duty_max();
        if (value == fixed || fabs(value - fixed) <= FIXED_TOLERANCE * fabs(fixed)) return fmi2OK;
        fmu_log(fmu, fmi2Error, "logStatusError",
                "fmi2SetReal: %s was generated for %s = %.17g; its network and optimizer hold only for that value "
                "(export it again for another)", CONTROLLER_NAME,
                vr == VR_SAMPLE_PERIOD ? "sample_period" : vr == VR_DUTY_MIN ? "duty_min" : "duty_max", fixed);
        return fmi2Error;
    }
    if (target == NULL) {
        fmu_log(fmu, fmi2Error, "logStatusError", "fmi2SetReal: value reference %u is not an input or parameter", vr);
        return fmi2Error;
    }
    if (!initializing) {
        fmu_log(fmu, fmi2Error, "logStatusError",
                "fmi2SetReal: the parameters of %s can only be set before fmi2ExitInitializationMode", CONTROLLER_NAME);
        return fmi2Error;
    }
    if (!isfinite(value)) {
        fmu_log(fmu, fmi2Error, "logStatusError", "fmi2SetReal: %g is invalid: expected a finite value", value);
        return fmi2Error;
    }
    *target = (buckc_real)value; /* the whole configuration is checked when initialisation ends */
    if (vr == VR_SAMPLE_PERIOD) d->period = value;
    return fmi2OK;
}

/* ------------------------------------------------------------------------------------------ */
/* Co-simulation                                                                              */

/* Commit the sample instant `next` at the FMU's time: its duty (computed now from the inputs held, unless
 * a read computed it already) takes effect and the controller's state advances. */
static fmi2Status commit_sample(FmuInstance *fmu, ControllerData *d) {
    if (!d->computed) {
        fmi2Status status = compute(fmu, d, fmi2Discard);
        if (status != fmi2OK) return status;
    }
    if (CONTROLLER_KIND == CONTROLLER_PI) d->pi = d->pi_pending;
    else if (CONTROLLER_KIND == CONTROLLER_EXPLICIT) d->policy = d->policy_pending;
    else if (CONTROLLER_KIND == CONTROLLER_CURRENT_MODE) d->current_mode = d->current_mode_pending;
    else if (CONTROLLER_KIND == CONTROLLER_COMPENSATOR) d->compensator = d->compensator_pending;
#if BUCKC_HAVE_PREDICTIVE
    else d->predictive.state = d->predictive_pending;
#endif
    d->duty = d->pending_duty;
    d->next += 1;
    d->computed = 0;
    return fmi2OK;
}

/* A communication step of any length: the sample instant the step starts on (if it does) and every
 * sample instant strictly inside the step are taken in turn, each with the inputs set before the step
 * (held over it), as a master stepping from instant to instant would with those inputs. A step that ends
 * on a sample instant lands exactly on it; that instant is taken by the next step (its duty reads from
 * the inputs set there). A sample that cannot be computed ends the step there with fmi2Discard: the
 * FMU stays at that instant (fmi2GetRealStatus(fmi2LastSuccessfulTime)), nothing of it committed. */
fmi2Status model_do_step(FmuInstance *fmu, void *data, double time, double step) {
    ControllerData *d = (ControllerData *)data;
    double end = d->time + step, next;
    (void)time;
    if (at_sample(d) && commit_sample(fmu, d) != fmi2OK) return fmi2Discard;
    for (;;) {
        next = sample_time(d, d->next);
        if (next >= end - tolerance(d)) break;
        d->time = next; /* a sample instant inside the step */
        if (commit_sample(fmu, d) != fmi2OK) return fmi2Discard;
    }
    d->time = fabs(end - next) <= tolerance(d) ? next : end; /* land exactly on a sample instant */
    return fmi2OK;
}

/* No Integer variables and no model exchange (a sampled controller has no continuous states): those
 * functions of fmu_model.h are the shared ones of real_co_simulation_only.c. */
