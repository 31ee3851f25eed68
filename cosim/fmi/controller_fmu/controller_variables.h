/* Value references of the workbench's controller FMUs: the single place where they are numbered.
 * cosim/fmi/controller_export.py writes modelDescription.xml from the same table (VARIABLES)
 * and tests/test_controller_fmu.py checks that both agree. */
#ifndef CONTROLLER_VARIABLES_H
#define CONTROLLER_VARIABLES_H

typedef enum {
    /* inputs: what the controller reads at a sample instant */
    VR_REFERENCE = 0,                 /* [V] output-voltage reference */
    VR_MEASURED_OUTPUT_VOLTAGE = 1,   /* [V] */
    VR_MEASURED_INDUCTOR_CURRENT = 2, /* [A] */
    VR_MEASURED_LOAD_CURRENT = 3,     /* [A] NaN: no load-current sensor */
    VR_INPUT_VOLTAGE = 4,             /* [V] supply voltage */
    /* output */
    VR_DUTY_CYCLE = 5,                /* [1] the duty in effect */
    /* parameters */
    VR_SAMPLE_PERIOD = 6,             /* [s] */
    VR_DUTY_MIN = 7,                  /* [1] */
    VR_DUTY_MAX = 8,                  /* [1] */
    VR_KP = 9,                        /* [1/V] PI only */
    VR_KI = 10                        /* [1/(V s)] PI only */
} ControllerValueReference;

#define CONTROLLER_INPUTS 5

/* what kind of algorithm a generated configuration holds (controller_config.h: CONTROLLER_KIND) */
enum { CONTROLLER_PI = 0, CONTROLLER_PREDICTIVE = 1, CONTROLLER_EXPLICIT = 2, CONTROLLER_CURRENT_MODE = 3,
       CONTROLLER_COMPENSATOR = 4, CONTROLLER_ADAPTIVE = 5 /* the bench harness only: no controller FMU */ };

#endif
