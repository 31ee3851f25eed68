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
 *
 * Written in buckc_real: the float32 build (buckc.h) is the NN predictor's controller alone (the circuit
 * predictors' members and cases are left out, BUCKC_HAVE_CIRCUIT_PREDICTORS), for the Cortex-M4F.
 */
#ifndef BUCKC_PREDICTIVE_H
#define BUCKC_PREDICTIVE_H

#include "box_qp.h"
#include "buckc.h"
#include "nn_model.h"
#if BUCKC_HAVE_CIRCUIT_PREDICTORS
#include "predictors.h"
#endif

/* The maxima below size the structs; a build may lower them to its controller (-D..., as the Cortex-M4F image
 * does: cosim/benchmark_harness/cortex_m4.py), init refuses a configuration above them (BUCKC_ERR_LIMIT). */
#ifndef BUCKC_MAX_HORIZON
#define BUCKC_MAX_HORIZON 32
#endif
#ifndef BUCKC_MAX_BLOCKS
#define BUCKC_MAX_BLOCKS 16
#endif
#ifndef BUCKC_MAX_LEVELS
#define BUCKC_MAX_LEVELS 129
#endif
#ifndef BUCKC_MAX_LATTICE
#define BUCKC_MAX_LATTICE 640     /* refinement moves: a full lattice (<= 128) or the pattern (<= 617) */
#endif
#define BUCKC_MAX_CANDIDATES 1536 /* stage-1 candidates: bounds the worst-case work of a step */
#define BUCKC_FULL_GRID_LIMIT 128 /* predictive.FULL_GRID_LIMIT */
#define BUCKC_NEAR_OFFSETS 21     /* constant sequences within half a grid cell of the last move */

/* predictive.HorizonSettings (blocks resolved: n_blocks = 0 means doubling_blocks(horizon)) */
typedef struct {
    int horizon;                  /* prediction steps N, 1..BUCKC_MAX_HORIZON */
    int n_blocks;
    int blocks[BUCKC_MAX_BLOCKS]; /* move blocking: positive lengths summing to the horizon */
    buckc_real discount;              /* gamma of eq. 16, 0 < gamma <= 1 */
    int levels;                   /* grid points per block in stage 1, 2..BUCKC_MAX_LEVELS */
    int refine_iterations;        /* at most this many refinement passes */
    buckc_real duty_tolerance;        /* stop zooming once the lattice step is this fine */
    buckc_real bias_filter;           /* weight of the newest disturbance estimate, 0 <= alpha <= 1 (0: none) */
} BuckcHorizonSettings;

/* The stage-1 and refinement structure HorizonOptimizer.__init__ derives from its settings,
 * plus the diagnostics of the last solve. */
typedef struct {
    BuckcHorizonSettings settings;
    buckc_real low, high;                     /* duty limits */
    int n_blocks;
    int block_of_step[BUCKC_MAX_HORIZON]; /* expand(): block index of each step */
    int block_starts[BUCKC_MAX_BLOCKS];
    buckc_real spacing;                       /* (high - low) / (levels - 1) */
    buckc_real grid[BUCKC_MAX_LEVELS];        /* np.linspace(low, high, levels) */
    buckc_real coarse[5];                     /* np.linspace(low, high, 5) */
    int global_is_full;                   /* levels ** n_blocks <= 4 * FULL_GRID_LIMIT */
    int n_global;
    int full_lattice;                     /* a full lattice of offsets, else the pattern moves */
    int n_lattice;
    signed char lattice[BUCKC_MAX_LATTICE][BUCKC_MAX_BLOCKS];
    buckc_real shrink;
    buckc_real warm_step, warm_span;
    buckc_real near_offsets[BUCKC_NEAR_OFFSETS];
    int stage_candidates_cold, stage_candidates_warm; /* stage-1 sizes without / with a warm start */
    /* diagnostics of the last buckc_optimizer_solve */
    int evaluations, passes, best_call, best_row;
    int warm_count, near_warm;
} BuckcOptimizer;

/* A candidate's cost: duties[horizon] per step; write its first predicted state (with the
 * disturbance, as Python's predictions[call][row, 0]) to first_prediction[2] (may be ignored). */
typedef buckc_real (*BuckcCostFunction)(void *user, const buckc_real *duties, int horizon, buckc_real *first_prediction);

int buckc_doubling_blocks(int horizon, int *blocks, int max_blocks); /* doubling_blocks(); returns the count */
int buckc_optimizer_init(BuckcOptimizer *optimizer, const BuckcHorizonSettings *settings, buckc_real low,
                         buckc_real high, const char **what);
/* HorizonOptimizer.solve: writes the best per-step sequence[horizon] and its first prediction
 * (first_prediction may be NULL); warm = the previous solution (horizon values) or NULL;
 * returns the best cost. */
buckc_real buckc_optimizer_solve(BuckcOptimizer *optimizer, BuckcCostFunction cost, void *user, const buckc_real *warm,
                             buckc_real anchor, buckc_real *sequence, buckc_real *first_prediction);

#define BUCKC_RTI_ACCEPT_TOLERANCE ((buckc_real)(1.0 + 1e-12)) /* predictive.ACCEPT_TOLERANCE (1 in float32) */

/* predictive.RtiSettings; enabled = 0: the search at every sample (rti=None in Python) */
typedef struct {
    int enabled;
    int iterations;            /* Gauss-Newton steps per sample, 1..3 */
    int line_search;           /* 1: roll each trial out, take it if not worse; 0: take every step, the last unevaluated */
    int reuse_jacobian;        /* 1: the steps after the first keep the first step's sensitivities (a rollout each) */
    int reweightings;          /* at most this many more box QPs on each step's linearisation, reweighted, 0..3 */
    buckc_real smoothing;          /* eps [V] of BUCKC_SQRT(|e|^2 + eps^2) */
    buckc_real step_limit;         /* trust region [duty], 0 < r <= 1 */
    buckc_real regularization;     /* mu = this x mean(diag H) + 1e-12 */
    buckc_real move_damping;       /* rho: + (rho mean(diag H) / 2)(u_0 - d_prev)^2 in each step's model, 0 <= rho < 1 */
    buckc_real reweighting_tolerance; /* [duty] no reweighting once the last QP moved no block by more (0: all) */
    int qp_iterations;         /* the box QP's active-set iterations, at most */
    buckc_real reference_step;     /* [V] fallback when the reference moves more than this, */
    buckc_real load_step;          /* the load-conductance estimate more than this fraction, */
    buckc_real innovation;         /* or vo lands more than this [V] from the one-step prediction (each 0: never) */
    buckc_real startup_region;     /* [V] after a cold start, the search until |vref - vo| first falls to this (0: none) */
    buckc_real error_region;       /* [V] the search at any sample with |vref - vo| above this (0: never) */
    buckc_real duty_resolution;    /* round the plan's blocks to multiples of this (0: not rounded), 0 <= q < 1 */
} BuckcRtiSettings;

/* PredictiveController.last_solver and last_fallback */
enum { BUCKC_SOLVER_SEARCH = 0, BUCKC_SOLVER_RTI = 1 };
enum {
    BUCKC_FALLBACK_NONE = 0,
    BUCKC_FALLBACK_COLD_START = 1,
    BUCKC_FALLBACK_REFERENCE_STEP = 2,
    BUCKC_FALLBACK_LOAD_STEP = 3,
    BUCKC_FALLBACK_PREDICTION_ERROR = 4,
    BUCKC_FALLBACK_STARTUP = 5,
    BUCKC_FALLBACK_LARGE_ERROR = 6
};

/* ------------------------------------------------------------------ the controller */

enum { BUCKC_PREDICTOR_NN = 0, BUCKC_PREDICTOR_AVERAGED = 1, BUCKC_PREDICTOR_SWITCHED = 2 };

typedef struct {
    int kind;                       /* BUCKC_PREDICTOR_...: which of the three below is used */
    BuckcNnConfig nn;
#if BUCKC_HAVE_CIRCUIT_PREDICTORS
    BuckcAveragedConfig averaged;
    BuckcSwitchedConfig switched;
#endif
} BuckcPredictorConfig;

typedef struct {
    buckc_real sample_period;           /* [s] */
    buckc_real duty_min, duty_max;
    buckc_real nominal_load;            /* [Ohm] the load assumed until one is measured */
    buckc_real nominal_input_voltage;   /* [V] stands in for a supply voltage the measurement lacks */
    BuckcHorizonSettings horizon;
    BuckcPredictorConfig predictor;
    BuckcRtiSettings rti;
} BuckcPredictiveConfig;

/* BuckcMeasurement (controllers.base.Measurement) is defined in buckc.h. */

/* PredictiveController's state between samples, plus diagnostics of the last step. */
typedef struct {
    int delays;
    int have_history;
    buckc_real history[BUCKC_NN_MAX_DELAYS][3]; /* rows [iL, vo, d], most recent first */
    int have_warm;
    buckc_real warm[BUCKC_MAX_HORIZON];         /* the previous solution */
    buckc_real bias[2];                         /* the state-disturbance estimate */
    int have_predicted;
    buckc_real predicted[2];                    /* the model's one-step prediction made at the last sample */
    buckc_real previous_duty;
    buckc_real conductance;                     /* [S] the last load estimate (load_estimate.h) */
    buckc_real previous_reference;              /* [V] the reference of the last sample (NaN before the first) */
    int starting;                           /* in the start-up region since the cold start (RtiSettings.startup_region) */
    /* diagnostics of the last step */
    buckc_real best_cost;                       /* eq. 16 cost of the plan (exact, not smoothed; NaN where not rolled out) */
    int evaluations, passes, best_call, best_row; /* the search's, when it planned */
    int last_solver;                        /* BUCKC_SOLVER_... */
    int last_fallback;                      /* BUCKC_FALLBACK_... (with the RTI enabled) */
    int qp_iterations, accepted;            /* the RTI's box-QP iterations and accepted steps */
    int reweighted;                         /* the RTI's reweighted box QPs (RtiSettings.reweightings) */
    /* the last step's problem, for buckc_predictive_search_last (the context stays in BuckcPredictive) */
    int warm_before_valid;
    buckc_real warm_before[BUCKC_MAX_HORIZON];
    buckc_real anchor;
} BuckcPredictiveState;

typedef struct {
    const BuckcPredictiveConfig *config; /* not copied: keep it alive (it may be static const data) */
    BuckcOptimizer optimizer;
    buckc_real weights[BUCKC_MAX_HORIZON];   /* discount ** j */
    BuckcPredictiveState state;
    /* the sample being solved (the predictor's PredictionContext) */
    buckc_real target[2];                    /* [iref, vref] */
    buckc_real context_previous_duty;
    buckc_real context_disturbance[2];
    BuckcNnShared nn;
#if BUCKC_HAVE_CIRCUIT_PREDICTORS
    BuckcAveragedStep averaged;
    const BuckcSwitchedTable *table;
    /* the predictors' caches (cleared by reset(), as the Python predictor's are) */
    BuckcAveragedCache averaged_cache;
    BuckcSwitchedCache switched_cache;
#endif
} BuckcPredictive;

size_t buckc_predictive_size(void);
/* Validate the whole configuration (what Python refuses, and the C maxima) and reset. */
int buckc_predictive_init(BuckcPredictive *controller, const BuckcPredictiveConfig *config, const char **what);
/* PredictiveController.reset (the predictor caches are cleared too, as in Python) */
void buckc_predictive_reset(BuckcPredictive *controller);
/* PredictiveController.step: *duty receives the duty to hold until the next sample. */
int buckc_predictive_step(BuckcPredictive *controller, const BuckcMeasurement *measurement, buckc_real *duty);
/* Forget the predictors' cached matrices and tables (Predictor.clear_cache; reset calls it). */
void buckc_predictive_clear_caches(BuckcPredictive *controller);
const BuckcPredictiveState *buckc_predictive_state(const BuckcPredictive *controller);
/* The eq. 23 cost of one duty sequence at the last step's context (for tests and tools). */
buckc_real buckc_predictive_cost(BuckcPredictive *controller, const buckc_real *duties, buckc_real *first_prediction);
/* PredictiveController.search_last_sample: the search's plan (sequence[horizon]) and exact cost for the last
 * step's problem, the controller's state left as it is. */
buckc_real buckc_predictive_search_last(BuckcPredictive *controller, buckc_real *sequence);
/* The RTI's linearisation at the last step's context (for tests): states out[horizon][2] and their
 * Jacobian jacobian[horizon][2][n_blocks] for one per-step sequence (the blocks of the horizon settings). */
int buckc_predictive_linearize(BuckcPredictive *controller, const buckc_real *duties, buckc_real *out, buckc_real *jacobian);

#endif
