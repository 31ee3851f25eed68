/* Value references of the BuckConverter FMU: the single place where they are numbered.
 * modelDescription.xml must agree; tests/test_plant_fmu.py checks it does. */
#ifndef BUCK_VARIABLES_H
#define BUCK_VARIABLES_H

typedef enum {
    /* inputs */
    VR_DUTY_CYCLE = 0,
    VR_INPUT_VOLTAGE = 1,
    VR_LOAD_RESISTANCE = 2,
    /* outputs */
    VR_OUTPUT_VOLTAGE = 3,
    VR_INDUCTOR_CURRENT = 4,
    VR_LOAD_CURRENT = 5,
    VR_APPLIED_DUTY_CYCLE = 6,
    /* local: second state and the state derivatives */
    VR_CAPACITOR_VOLTAGE = 7,
    VR_DER_INDUCTOR_CURRENT = 8,
    VR_DER_CAPACITOR_VOLTAGE = 9,
    /* parameters */
    VR_INDUCTANCE = 10,
    VR_CAPACITANCE = 11,
    VR_SWITCHING_FREQUENCY = 12,
    VR_INDUCTOR_RESISTANCE = 13,
    VR_SWITCH_ON_RESISTANCE = 14,
    VR_DIODE_FORWARD_VOLTAGE = 15,
    VR_CAPACITOR_ESR = 16,
    /* Integer parameters */
    VR_PLANT_MODE = 20,
    VR_PWM_CARRIER = 21,
    /* period means (averaging sensor) and the model-exchange states that integrate them */
    VR_AVERAGE_OUTPUT_VOLTAGE = 22,
    VR_AVERAGE_INDUCTOR_CURRENT = 23,
    VR_PERIOD_CHARGE = 24,
    VR_PERIOD_FLUX = 25,
    VR_DER_PERIOD_CHARGE = 26,
    VR_DER_PERIOD_FLUX = 27,
    VR_AVERAGE_LOAD_CURRENT = 28
} ValueReference;

#endif
