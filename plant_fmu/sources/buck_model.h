/* Buck converter equations (paper eq. 1-3) and their exact piecewise solution.
 *
 * Circuit: source Vs -> switch (R_on) -> node -> inductor (L, DCR) -> output node;
 * freewheeling diode (forward drop V_F) from ground to the switch node; capacitor C with ESR
 * in parallel with the load R at the output node. States: inductor current i_L >= 0 (the
 * diode blocks reverse current) and capacitor voltage v_C.
 *
 * Between switch and diode transitions the circuit is linear, x' = A x + b, so every
 * interval has a closed-form solution (2x2 matrix exponential). The only non-linear piece
 * is the averaged model in discontinuous conduction (DCM): its inductor current is algebraic
 * there (the reduced-order model; buck_model.c derives why), and v_C alone is integrated by an
 * embedded Runge-Kutta 5(4) method with tight tolerances.
 *
 * This file knows nothing about FMI: fmi2_functions.c is the glue. */
#ifndef BUCK_MODEL_H
#define BUCK_MODEL_H

#include <stdbool.h>
#include <stddef.h>

enum { MODE_AVERAGED = 0, MODE_SWITCHED = 1 };
enum { CARRIER_SAWTOOTH = 0, CARRIER_TRIANGLE = 1 };

typedef enum {
    CONDUCTION_CONTINUOUS = 0,    /* current flows (switched: through switch or diode; averaged: CCM) */
    CONDUCTION_DISCONTINUOUS = 1, /* averaged mode only: each PWM period has an idle interval (DCM);
                                   * i_L is then the algebraic period mean i_q(v_C) */
    CONDUCTION_BLOCKED = 2        /* i_L held at 0 by the diode */
} Conduction;

typedef struct {
    double inductance;            /* L [H] */
    double capacitance;           /* C [F] */
    double switching_frequency;   /* f_sw [Hz] */
    double inductor_resistance;   /* inductor DCR [Ohm] */
    double switch_on_resistance;  /* R_on [Ohm] */
    double diode_forward_voltage; /* V_F [V] */
    double capacitor_esr;         /* ESR [Ohm] */
    int plant_mode;               /* MODE_AVERAGED or MODE_SWITCHED */
    int pwm_carrier;              /* CARRIER_SAWTOOTH (trailing edge) or CARRIER_TRIANGLE (centred) */
} BuckParameters;

typedef struct {
    double duty_cycle;      /* [1], already clamped to [0, 1] */
    double input_voltage;   /* V_s [V] */
    double load_resistance; /* R [Ohm] */
} BuckInputs;

typedef struct {
    BuckParameters p;
    BuckInputs u;
    double time;              /* [s] */
    double inductor_current;  /* state i_L [A] */
    double capacitor_voltage; /* state v_C [V] */
    Conduction conduction;
    /* switched mode: PWM bookkeeping. The duty is latched at the start of each carrier period,
     * like the shadow register of a microcontroller PWM unit. */
    long long pwm_period;     /* index of the period whose duty is latched (any sign: a run may start before 0) */
    bool pwm_latched;         /* a duty has been latched since the start (pwm_period is valid) */
    double pwm_duty;          /* duty latched for pwm_period */
    bool switch_on;           /* model exchange: switch state of the current interval */
    double dcm_step;          /* last accepted step of the DCM (v_C) integrator [s] */
    /* switched mode: exact means over each PWM period, as an averaging ADC measures them */
    double period_charge;     /* integral of i_L since period_start [A s] (a model-exchange state) */
    double period_flux;       /* integral of v_o since period_start [V s] (a model-exchange state) */
    double period_start;      /* [s] */
    double average_current;   /* mean i_L over the last completed period [A] */
    double average_voltage;   /* mean v_o over the last completed period [V] */
    /* the load current i_o = v_o / R is integrated from period_flux: R is constant between load
     * changes, so each change closes a piece (flux_at_load_change marks where it began). Exact when
     * R is set at communication points (co-simulation; model exchange between accepted steps, as
     * fmpy does); an importer setting R inside its solver's trial evaluations would need a state. */
    double load_charge_before_change; /* integral of i_o from period_start to the last load change [A s] */
    double flux_at_load_change;       /* period_flux at the last load change in this period [V s] */
    double average_load_current;      /* mean i_o over the last completed period [A] */
    bool have_average;
} BuckModel;

#define BUCK_STATES 4 /* i_L, v_C, and the two period integrals */

void buck_set_defaults(BuckModel *m);

/* NULL if parameters and inputs (and, with check_states, the states) are physically valid, else a
 * message naming the culprit. During a model-exchange run the solver's trial states may dip below
 * zero between events; setting an input then must not fail on them, so only a start value or a
 * state set by name is checked. */
const char *buck_check(const BuckModel *m, bool check_states, char *buffer, size_t size);

/* Classify the conduction state and latch the PWM at time t (after initialization). */
void buck_start(BuckModel *m, double t);

/* Co-simulation: advance exactly from m->time to t_end with the current inputs. Returns false
 * (with m->time where it got stuck) if the conduction regimes alternated without progress. */
bool buck_advance(BuckModel *m, double t_end);

/* Model exchange: dx has BUCK_STATES entries. */
void buck_derivatives(const BuckModel *m, double dx[BUCK_STATES]);
void buck_event_indicators(const BuckModel *m, double z[2]);
/* Event update at m->time; returns true if the continuous states were changed. */
bool buck_update_discrete(BuckModel *m, double *next_event_time, bool *next_event_defined);

/* Set the load resistance (an input), keeping the period's load-current integral exact. */
void buck_set_load_resistance(BuckModel *m, double resistance);

/* Outputs. */
double buck_output_voltage(const BuckModel *m);
double buck_applied_duty(const BuckModel *m);
/* Mean over the last completed PWM period (switched mode); the averaged model's own state otherwise. */
double buck_average_output_voltage(const BuckModel *m);
double buck_average_inductor_current(const BuckModel *m);
double buck_average_load_current(const BuckModel *m);

#endif
