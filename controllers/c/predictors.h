/*
 * predictors.h -- C twin of the circuit-model predictors of controllers/predictors.py:
 * expm2 / expm2_many, circuit_matrix, measured_from_state, AveragedModelPredictor and
 * SwitchedModelPredictor (the NN predictor is nn_model.h plus the extras of NNPredictor,
 * assembled in predictive.c).
 *
 * Both circuit predictors keep Python's per-instance cache semantics exactly: Python keys its
 * cache by (round(load, 9), round(x, 9 or 12)), computes an entry from the *first* values that
 * map to a key, and clears the whole dict when a miss finds more than 256 keys. The C cache
 * remembers the same keys (BUCKC_PY_CACHE_KEYS of them, cleared by the same rule) with the
 * values that created them, so an entry is always computed from the same numbers as Python's.
 * Switched-model tables are large (BUCKC_SWITCHED_MAX_GRID x 24 doubles), so only
 * BUCKC_SWITCHED_TABLES of them are stored; an evicted table is recomputed from its key's
 * remembered values, which gives the same table. Keys are nearbyint(x * 10^digits): the same
 * classes as Python's round(x, digits) except within ~1e-16 relative of a rounding boundary.
 */
#ifndef BUCKC_PREDICTORS_H
#define BUCKC_PREDICTORS_H

#include "buckc.h"

#define BUCKC_PY_CACHE_KEYS 257      /* Python's dict holds at most 257 keys (cleared at > 256) */
#define BUCKC_SWITCHED_MAX_GRID 257  /* SwitchedModelPredictor grid_points */
#define BUCKC_SWITCHED_TABLES 2      /* switched-model tables kept at once */
#define BUCKC_SWITCHED_COLUMNS 24    /* K(4) kappa(2) H(4) h(2), then their slopes to the next row */
#define BUCKC_SENSITIVITY_DIRECTIONS 8 /* blocked moves the linearisations propagate (the RTI's box QP size) */

/* predictors.CARRIERS and SENSOR_MODELS */
enum { BUCKC_CARRIER_SAWTOOTH = 0, BUCKC_CARRIER_TRIANGLE = 1 };
enum { BUCKC_SENSOR_PERIOD_AVERAGE = 0, BUCKC_SENSOR_PERIOD_START = 1 };

/* predictors.CircuitParameters (SI units) */
typedef struct {
    double inductance;
    double capacitance;
    double inductor_resistance;
    double switch_on_resistance;
    double diode_forward_voltage;
    double capacitor_esr;
} BuckcCircuitParameters;

/* ---------------------------------------------------------------- closed forms */

/* expm2(a, t) (and each t of expm2_many): exp(A t) of a 2x2 matrix in closed form. */
void buckc_expm2(const double a[4], double t, double out[4]);
/* circuit_matrix(p, load, switch_resistance) */
void buckc_circuit_matrix(const BuckcCircuitParameters *p, double load, double switch_resistance, double a[4]);
/* measured_from_state(p, load) */
void buckc_measured_from_state(const BuckcCircuitParameters *p, double load, double t[4]);
/* np.linalg.solve / inv of a 2x2 matrix (LU with partial pivoting, as LAPACK's dgesv) */
void buckc_solve2(const double a[4], const double b[2], double x[2]);
void buckc_inverse2(const double a[4], double inverse[4]);

/* ---------------------------------------------------------------- averaged model */

typedef struct {
    BuckcCircuitParameters parameters;
    double sample_period; /* [s] the control period it is discretised at */
} BuckcAveragedConfig;

typedef struct {
    double key_load, key_switch; /* round(load, 9), round(switch_resistance, 12) */
    double phi[4];               /* x+ = Phi x + gamma * (switch-node voltage) */
    double gamma[2];
} BuckcAveragedEntry;

typedef struct {
    int count;
    BuckcAveragedEntry entries[BUCKC_PY_CACHE_KEYS];
} BuckcAveragedCache;

/* What AveragedModelPredictor.rollout computes before its loop over the horizon. */
typedef struct {
    double phi_y[4];      /* T Phi T^-1: y+ = phi_y y + gamma_y u, y = [iL, vo] */
    double gamma_y[2];
    double drive;         /* input_voltage + V_F */
    double forward;       /* V_F */
    double y0[2];         /* history[0, :2] */
    double disturbance[2];
} BuckcAveragedStep;

int buckc_averaged_check(const BuckcAveragedConfig *config, const char **what);
/* AveragedModelPredictor._discrete without its cache */
void buckc_averaged_discrete(const BuckcAveragedConfig *config, double load, double switch_resistance,
                             double phi[4], double gamma[2]);
/* ... and with it (cache may be NULL: no caching) */
void buckc_averaged_cached(const BuckcAveragedConfig *config, BuckcAveragedCache *cache, double load,
                           double switch_resistance, double phi[4], double gamma[2]);
void buckc_averaged_cache_clear(BuckcAveragedCache *cache);
/* AveragedModelPredictor.rollout, split into its per-sample part and its per-candidate loop */
void buckc_averaged_prepare(const BuckcAveragedConfig *config, BuckcAveragedCache *cache, double load,
                            double previous_duty, double input_voltage, const double y0[2],
                            const double disturbance[2], BuckcAveragedStep *step);
void buckc_averaged_rollout(const BuckcAveragedStep *step, const double *duties, int n, double *out);
/* AveragedModelPredictor.linearize: one sequence with the Jacobian of its states to the blocked moves,
 * out[n][2] and jacobian[n][2][n_blocks] (step j's duty is block block_of_step[j]'s value). */
void buckc_averaged_linearize(const BuckcAveragedStep *step, const double *duties, int n, const int *block_of_step,
                              int n_blocks, double *out, double *jacobian);

/* ---------------------------------------------------------------- switched model */

typedef struct {
    BuckcCircuitParameters parameters;
    double sample_period;       /* [s] a whole number of switching periods */
    double switching_frequency; /* [Hz] */
    int carrier;                /* BUCKC_CARRIER_... */
    int sensor;                 /* BUCKC_SENSOR_... */
    int grid_points;            /* duty grid linspace(0, 1, grid_points), 2..BUCKC_SWITCHED_MAX_GRID */
} BuckcSwitchedConfig;

/* predictors.MAX_SENSOR_CONDITION: a table whose sensor map H is worse conditioned is refused */
#define BUCKC_SWITCHED_MAX_CONDITION 1e8
/* predictors.NODE_TOLERANCE [grid steps]: a duty this close to an interior node of the table takes the mean of the
 * two intervals' slopes (buckc_switched_lookup_slope) */
#define BUCKC_SWITCHED_NODE_TOLERANCE 1e-6

typedef struct {
    double load, input_voltage; /* the values it was computed from */
    int points;
    double condition;           /* the largest 2-norm condition number of H over the grid (inf: singular) */
    double rows[BUCKC_SWITCHED_MAX_GRID][BUCKC_SWITCHED_COLUMNS];
} BuckcSwitchedTable;

typedef struct {
    double key_load, key_input; /* round(load, 9), round(input_voltage, 9) */
    double load, input_voltage; /* the first values seen for the key */
} BuckcSwitchedKey;

typedef struct {
    int n_keys;
    BuckcSwitchedKey keys[BUCKC_PY_CACHE_KEYS];
    int n_tables, next_table;
    BuckcSwitchedTable tables[BUCKC_SWITCHED_TABLES];
} BuckcSwitchedCache;

/* Validate; *periods (if not NULL) receives the PWM periods per control period. */
int buckc_switched_check(const BuckcSwitchedConfig *config, int *periods, const char **what);
/* SwitchedModelPredictor._table without its cache (config must pass buckc_switched_check) */
void buckc_switched_table(const BuckcSwitchedConfig *config, double load, double input_voltage,
                          BuckcSwitchedTable *table);
/* ... and with it: the table Python would use for (load, input_voltage) */
const BuckcSwitchedTable *buckc_switched_cached(const BuckcSwitchedConfig *config, BuckcSwitchedCache *cache,
                                                double load, double input_voltage);
void buckc_switched_cache_clear(BuckcSwitchedCache *cache);
/* SwitchedModelPredictor._lookup at one duty: the 12 interpolated map entries */
void buckc_switched_lookup(const BuckcSwitchedTable *table, double duty, double values[12]);
/* ... and its slope in the duty on the interval the lookup uses (the duty clamped to 0..1, as the lookup does; at
 * an interior node the mean of its two intervals' slopes) */
void buckc_switched_lookup_slope(const BuckcSwitchedTable *table, double duty, double values[12], double slopes[12]);
/* SwitchedModelPredictor.rollout for one candidate, from y0 = history[0, :2] */
void buckc_switched_rollout(const BuckcSwitchedTable *table, const double y0[2], double previous_duty,
                            const double *duties, int n, const double disturbance[2], double *out);
/* SwitchedModelPredictor.linearize: as buckc_averaged_linearize */
void buckc_switched_linearize(const BuckcSwitchedTable *table, const double y0[2], double previous_duty,
                              const double *duties, int n, const double disturbance[2], const int *block_of_step,
                              int n_blocks, double *out, double *jacobian);

#endif
