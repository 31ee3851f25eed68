/*
 * predictive.h -- C twin of controllers/predictive.py: HorizonOptimizer (move-blocked duty
 * sequences, stage-1 candidates + batched refinement) and PredictiveController.step (history,
 * offset-free disturbance estimate, load estimate, eq. 23 cost), on any of the three predictors
 * (NNPredictor, AveragedModelPredictor, SwitchedModelPredictor).
 *
 * The optimizer streams its candidates (generated in Python's order, each costed as it is
 * made), so no candidate array is stored; numpy's argmin (the first minimum, or the first NaN)
 * is reproduced by strict '<' scanning.
 *
 * The real-time-iteration optimizer (RealTimeIteration, predictive.py; settings BuckcRtiSettings):
 * a fixed number of Gauss-Newton steps from the shifted plan, each a linearisation of the predictor
 * (nn_model.c, predictors.c) and a box QP (box_qp.c), the search above as the fallback the
 * controller's rule (PredictiveController.fallback_reason) picks. No allocation, fixed work.
 */
#ifndef BUCKC_PREDICTIVE_H
#define BUCKC_PREDICTIVE_H

#include "box_qp.h"
#include "buckc.h"
#include "nn_model.h"
#include "predictors.h"

#define BUCKC_MAX_HORIZON 32
#define BUCKC_MAX_BLOCKS 16
#define BUCKC_MAX_LEVELS 129
#define BUCKC_MAX_LATTICE 640     /* refinement moves: a full lattice (<= 128) or the pattern (<= 617) */
#define BUCKC_MAX_CANDIDATES 1536 /* stage-1 candidates: bounds the worst-case work of a step */
#define BUCKC_FULL_GRID_LIMIT 128 /* predictive.FULL_GRID_LIMIT */
#define BUCKC_NEAR_OFFSETS 21     /* constant sequences within half a grid cell of the last move */

/* predictive.HorizonSettings (blocks resolved: n_blocks = 0 means doubling_blocks(horizon)) */
typedef struct {
    int horizon;                  /* prediction steps N, 1..BUCKC_MAX_HORIZON */
    int n_blocks;
    int blocks[BUCKC_MAX_BLOCKS]; /* move blocking: positive lengths summing to the horizon */
    double discount;              /* gamma of eq. 16, 0 < gamma <= 1 */
    int levels;                   /* grid points per block in stage 1, 2..BUCKC_MAX_LEVELS */
    int refine_iterations;        /* at most this many refinement passes */
    double duty_tolerance;        /* stop zooming once the lattice step is this fine */
    double bias_filter;           /* weight of the newest disturbance estimate, 0 <= alpha <= 1 (0: none) */
} BuckcHorizonSettings;

/* The stage-1 and refinement structure HorizonOptimizer.__init__ derives from its settings,
 * plus the diagnostics of the last solve. */
typedef struct {
    BuckcHorizonSettings settings;
    double low, high;                     /* duty limits */
    int n_blocks;
    int block_of_step[BUCKC_MAX_HORIZON]; /* expand(): block index of each step */
    int block_starts[BUCKC_MAX_BLOCKS];
    double spacing;                       /* (high - low) / (levels - 1) */
    double grid[BUCKC_MAX_LEVELS];        /* np.linspace(low, high, levels) */
    double coarse[5];                     /* np.linspace(low, high, 5) */
    int global_is_full;                   /* levels ** n_blocks <= 4 * FULL_GRID_LIMIT */
    int n_global;
    int full_lattice;                     /* a full lattice of offsets, else the pattern moves */
    int n_lattice;
    signed char lattice[BUCKC_MAX_LATTICE][BUCKC_MAX_BLOCKS];
    double shrink;
    double warm_step, warm_span;
    double near_offsets[BUCKC_NEAR_OFFSETS];
    int stage_candidates_cold, stage_candidates_warm; /* stage-1 sizes without / with a warm start */
    /* diagnostics of the last buckc_optimizer_solve */
    int evaluations, passes, best_call, best_row;
    int warm_count, near_warm;
} BuckcOptimizer;

/* A candidate's cost: duties[horizon] per step; write its first predicted state (with the
 * disturbance, as Python's predictions[call][row, 0]) to first_prediction[2] (may be ignored). */
typedef double (*BuckcCostFunction)(void *user, const double *duties, int horizon, double *first_prediction);

int buckc_doubling_blocks(int horizon, int *blocks, int max_blocks); /* doubling_blocks(); returns the count */
int buckc_optimizer_init(BuckcOptimizer *optimizer, const BuckcHorizonSettings *settings, double low,
                         double high, const char **what);
/* HorizonOptimizer.solve: writes the best per-step sequence[horizon] and its first prediction
 * (first_prediction may be NULL); warm = the previous solution (horizon values) or NULL;
 * returns the best cost. */
double buckc_optimizer_solve(BuckcOptimizer *optimizer, BuckcCostFunction cost, void *user, const double *warm,
                             double anchor, double *sequence, double *first_prediction);

#define BUCKC_RTI_ACCEPT_TOLERANCE (1.0 + 1e-12) /* predictive.ACCEPT_TOLERANCE */

/* predictive.RtiSettings; enabled = 0: the search at every sample (rti=None in Python) */
typedef struct {
    int enabled;
    int iterations;            /* Gauss-Newton steps per sample, 1..3 */
    double smoothing;          /* eps [V] of sqrt(|e|^2 + eps^2) */
    double step_limit;         /* trust region [duty], 0 < r <= 1 */
    double regularization;     /* mu = this x mean(diag H) + 1e-12 */
    int qp_iterations;         /* the box QP's active-set iterations, at most */
    double reference_step;     /* [V] fallback when the reference moves more than this, */
    double load_step;          /* the load-conductance estimate more than this fraction, */
    double innovation;         /* or vo lands more than this [V] from the one-step prediction (each 0: never) */
} BuckcRtiSettings;

/* PredictiveController.last_solver and last_fallback */
enum { BUCKC_SOLVER_SEARCH = 0, BUCKC_SOLVER_RTI = 1 };
enum {
    BUCKC_FALLBACK_NONE = 0,
    BUCKC_FALLBACK_COLD_START = 1,
    BUCKC_FALLBACK_REFERENCE_STEP = 2,
    BUCKC_FALLBACK_LOAD_STEP = 3,
    BUCKC_FALLBACK_PREDICTION_ERROR = 4
};

/* ------------------------------------------------------------------ the controller */

enum { BUCKC_PREDICTOR_NN = 0, BUCKC_PREDICTOR_AVERAGED = 1, BUCKC_PREDICTOR_SWITCHED = 2 };

typedef struct {
    int kind;                       /* BUCKC_PREDICTOR_...: which of the three below is used */
    BuckcNnConfig nn;
    BuckcAveragedConfig averaged;
    BuckcSwitchedConfig switched;
} BuckcPredictorConfig;

typedef struct {
    double sample_period;           /* [s] */
    double duty_min, duty_max;
    double nominal_load;            /* [Ohm] the load assumed until one is measured */
    double nominal_input_voltage;   /* [V] stands in for a supply voltage the measurement lacks */
    BuckcHorizonSettings horizon;
    BuckcPredictorConfig predictor;
    BuckcRtiSettings rti;
} BuckcPredictiveConfig;

/* BuckcMeasurement (controllers.base.Measurement) is defined in buckc.h. */

/* PredictiveController's state between samples, plus diagnostics of the last step. */
typedef struct {
    int delays;
    int have_history;
    double history[BUCKC_NN_MAX_DELAYS][3]; /* rows [iL, vo, d], most recent first */
    int have_warm;
    double warm[BUCKC_MAX_HORIZON];         /* the previous solution */
    double bias[2];                         /* the state-disturbance estimate */
    int have_predicted;
    double predicted[2];                    /* the model's one-step prediction made at the last sample */
    double previous_duty;
    double conductance;                     /* [S] the last load estimate (load_estimate.h) */
    double previous_reference;              /* [V] the reference of the last sample (NaN before the first) */
    /* diagnostics of the last step */
    double best_cost;                       /* eq. 16 cost of the plan (exact, not smoothed) */
    int evaluations, passes, best_call, best_row; /* the search's, when it planned */
    int last_solver;                        /* BUCKC_SOLVER_... */
    int last_fallback;                      /* BUCKC_FALLBACK_... (with the RTI enabled) */
    int qp_iterations, accepted;            /* the RTI's box-QP iterations and accepted steps */
    /* the last step's problem, for buckc_predictive_search_last (the context stays in BuckcPredictive) */
    int warm_before_valid;
    double warm_before[BUCKC_MAX_HORIZON];
    double anchor;
} BuckcPredictiveState;

typedef struct {
    const BuckcPredictiveConfig *config; /* not copied: keep it alive (it may be static const data) */
    BuckcOptimizer optimizer;
    double weights[BUCKC_MAX_HORIZON];   /* discount ** j */
    BuckcPredictiveState state;
    /* the sample being solved (the predictor's PredictionContext) */
    double target[2];                    /* [iref, vref] */
    double context_previous_duty;
    double context_disturbance[2];
    BuckcNnShared nn;
    BuckcAveragedStep averaged;
    const BuckcSwitchedTable *table;
    /* the predictors' caches (cleared by reset(), as the Python predictor's are) */
    BuckcAveragedCache averaged_cache;
    BuckcSwitchedCache switched_cache;
} BuckcPredictive;

size_t buckc_predictive_size(void);
/* Validate the whole configuration (what Python refuses, and the C maxima) and reset. */
int buckc_predictive_init(BuckcPredictive *controller, const BuckcPredictiveConfig *config, const char **what);
/* PredictiveController.reset (the predictor caches are cleared too, as in Python) */
void buckc_predictive_reset(BuckcPredictive *controller);
/* PredictiveController.step: *duty receives the duty to hold until the next sample. */
int buckc_predictive_step(BuckcPredictive *controller, const BuckcMeasurement *measurement, double *duty);
/* Forget the predictors' cached matrices and tables (Predictor.clear_cache; reset calls it). */
void buckc_predictive_clear_caches(BuckcPredictive *controller);
const BuckcPredictiveState *buckc_predictive_state(const BuckcPredictive *controller);
/* The eq. 23 cost of one duty sequence at the last step's context (for tests and tools). */
double buckc_predictive_cost(BuckcPredictive *controller, const double *duties, double *first_prediction);
/* PredictiveController.search_last_sample: the search's plan (sequence[horizon]) and exact cost for the last
 * step's problem, the controller's state left as it is. */
double buckc_predictive_search_last(BuckcPredictive *controller, double *sequence);
/* The RTI's linearisation at the last step's context (for tests): states out[horizon][2] and their
 * Jacobian jacobian[horizon][2][n_blocks] for one per-step sequence (the blocks of the horizon settings). */
int buckc_predictive_linearize(BuckcPredictive *controller, const double *duties, double *out, double *jacobian);

#endif
