/*
 * predictive.c -- twin of controllers/predictive.py:
 *   buckc_doubling_blocks    doubling_blocks
 *   buckc_optimizer_init     HorizonSettings.__post_init__ (validation) + HorizonOptimizer.__init__
 *   buckc_optimizer_solve    HorizonOptimizer.solve with first_stage and _openings
 *   buckc_predictive_*       PredictiveController.__init__ / reset / step / fallback_reason / search_last_sample
 *                            (the load estimate: load_estimate.c), and the NNPredictor.rollout / linearize glue
 *                            (its extra signals from the context)
 *   rti_solve                RealTimeIteration.solve (shifted, costs, model; the box QP: box_qp.c)
 * Candidates are generated and costed one at a time in Python's stage order (so ties go where
 * numpy's argmin sends them); see predictive.h.
 */
#include <math.h>
#include <string.h>

#include "buckc_pair.h"
#include "predictive.h"
#include "load_estimate.h"

#define FAIL(code, text) do { if (what) *what = (text); return (code); } while (0)

#define ZERO BUCKC_REAL_LITERAL(0.0)
#define ONE BUCKC_REAL_LITERAL(1.0)

/* the linearisations propagate at least as many directions as the box QP has variables */
#if BUCKC_HAVE_CIRCUIT_PREDICTORS
typedef char buckc_directions_fit[(BUCKC_QP_MAX_VARIABLES <= BUCKC_NN_MAX_DIRECTIONS &&
                                   BUCKC_QP_MAX_VARIABLES <= BUCKC_SENSITIVITY_DIRECTIONS) ? 1 : -1];
#else
typedef char buckc_directions_fit[(BUCKC_QP_MAX_VARIABLES <= BUCKC_NN_MAX_DIRECTIONS) ? 1 : -1];
#endif
/* a full lattice (at most BUCKC_FULL_GRID_LIMIT rows) always fits */
typedef char buckc_lattice_fits[(BUCKC_MAX_LATTICE >= BUCKC_FULL_GRID_LIMIT) ? 1 : -1];

/* ------------------------------------------------------------------ settings */

int buckc_doubling_blocks(int horizon, int *blocks, int max_blocks)
{
    int n = 0, total = 0, size = 1;
    while (total < horizon) {
        int step = size < horizon - total ? size : horizon - total;
        if (n >= max_blocks)
            return -1;
        blocks[n++] = step;
        total += step;
        if (n >= 2)
            size *= 2;
    }
    return n;
}

/* levels ** n capped just above limit (no overflow) */
static long capped_power(long base, int n, long limit)
{
    long r = 1;
    int i;
    for (i = 0; i < n; ++i) {
        r *= base;
        if (r > limit)
            return limit + 1;
    }
    return r;
}

/* np.linspace(low, high, num) for num >= 2: i * ((high - low) / (num - 1)) + low, the last = high */
static void linspace(buckc_real low, buckc_real high, int num, buckc_real *out)
{
    buckc_real step = (high - low) / (buckc_real)(num - 1);
    int i;
    for (i = 0; i < num; ++i)
        out[i] = (buckc_real)i * step + low;
    out[num - 1] = high;
}

int buckc_optimizer_init(BuckcOptimizer *o, const BuckcHorizonSettings *settings, buckc_real low, buckc_real high,
                         const char **what)
{
    BuckcHorizonSettings s;
    int nb, i, j, b, t, per_axis, openings;
    if (o == NULL || settings == NULL)
        FAIL(BUCKC_ERR_NULL, "optimizer or settings is NULL");
    s = *settings;
    if (s.horizon < 1)
        FAIL(BUCKC_ERR_INVALID, "horizon: expected >= 1");
    if (s.horizon > BUCKC_MAX_HORIZON)
        FAIL(BUCKC_ERR_LIMIT, "horizon: above BUCKC_MAX_HORIZON");
    if (s.n_blocks == 0) {
        s.n_blocks = buckc_doubling_blocks(s.horizon, s.blocks, BUCKC_MAX_BLOCKS);
        if (s.n_blocks < 0)
            FAIL(BUCKC_ERR_LIMIT, "blocks: doubling_blocks(horizon) has more than BUCKC_MAX_BLOCKS");
    }
    if (s.n_blocks < 0)
        FAIL(BUCKC_ERR_INVALID, "blocks: a negative count");
    if (s.n_blocks > BUCKC_MAX_BLOCKS)
        FAIL(BUCKC_ERR_LIMIT, "blocks: more than BUCKC_MAX_BLOCKS");
    for (i = 0, t = 0; i < s.n_blocks; ++i) {
        if (s.blocks[i] < 1)
            FAIL(BUCKC_ERR_INVALID, "blocks: expected positive lengths");
        t += s.blocks[i];
    }
    if (t != s.horizon)
        FAIL(BUCKC_ERR_INVALID, "blocks: expected lengths summing to the horizon");
    if (!(s.discount > ZERO && s.discount <= ONE))
        FAIL(BUCKC_ERR_INVALID, "discount: expected 0 < gamma <= 1");
    if (s.levels < 2 || s.refine_iterations < 0)
        FAIL(BUCKC_ERR_INVALID, "levels must be >= 2 and refine_iterations >= 0");
    if (s.levels > BUCKC_MAX_LEVELS)
        FAIL(BUCKC_ERR_LIMIT, "levels: above BUCKC_MAX_LEVELS");
    if (!(s.bias_filter >= ZERO && s.bias_filter <= ONE))
        FAIL(BUCKC_ERR_INVALID, "bias_filter: expected 0 <= alpha <= 1");
    if (!(ZERO <= low && low < high && high <= ONE))
        FAIL(BUCKC_ERR_INVALID, "duty limits: expected 0 <= min < max <= 1");

    memset(o, 0, sizeof(*o));
    o->settings = s;
    o->low = low;
    o->high = high;
    nb = o->n_blocks = s.n_blocks;
    for (b = 0, t = 0; b < nb; ++b) {
        o->block_starts[b] = t;
        for (j = 0; j < s.blocks[b]; ++j)
            o->block_of_step[t++] = b;
    }
    o->spacing = (high - low) / (s.levels - 1);
    linspace(low, high, s.levels, o->grid);
    linspace(low, high, 5, o->coarse);
    if (capped_power(s.levels, nb, 4 * BUCKC_FULL_GRID_LIMIT) <= 4 * BUCKC_FULL_GRID_LIMIT) {
        o->global_is_full = 1;
        o->n_global = (int)capped_power(s.levels, nb, 4 * BUCKC_FULL_GRID_LIMIT);
    } else {
        o->global_is_full = 0;
        o->n_global = s.levels; /* constant sequences */
    }
    per_axis = 0;
    for (i = 3; i < 34; i += 2)
        if (capped_power(i, nb, BUCKC_FULL_GRID_LIMIT) <= BUCKC_FULL_GRID_LIMIT)
            per_axis = i;
    if (per_axis) { /* meshgrid(offsets, ..., indexing="ij").ravel(): the last block fastest */
        int half = (per_axis - 1) / 2, rows = (int)capped_power(per_axis, nb, BUCKC_FULL_GRID_LIMIT);
        for (i = 0; i < rows; ++i) {
            int rest = i;
            for (b = nb - 1; b >= 0; --b) {
                o->lattice[i][b] = (signed char)(rest % per_axis - half);
                rest /= per_axis;
            }
        }
        o->n_lattice = rows;
        o->shrink = (buckc_real)(2 * half);
        o->full_lattice = 1;
        o->warm_step = o->spacing / (10 * o->shrink);
        o->warm_span = o->warm_step * (buckc_real)half;
    } else { /* many blocks: lines along each block, pairs of blocks, all blocks together */
        static const int line[8] = {-4, -3, -2, -1, 1, 2, 3, 4};
        static const int pair[4][2] = {{1, 1}, {1, -1}, {-1, 1}, {-1, -1}};
        static const int all[8] = {-8, -4, -2, -1, 1, 2, 4, 8};
        int r = 1, v, q; /* row 0: no move */
        if (1 + 8 * nb + 2 * nb * (nb - 1) + 8 > BUCKC_MAX_LATTICE)
            FAIL(BUCKC_ERR_LIMIT, "blocks: the pattern-search moves exceed BUCKC_MAX_LATTICE");
        for (v = 0; v < 8; ++v)
            for (b = 0; b < nb; ++b, ++r)
                o->lattice[r][b] = (signed char)line[v];
        for (i = 0; i < nb; ++i)
            for (j = i + 1; j < nb; ++j)
                for (q = 0; q < 4; ++q, ++r) {
                    o->lattice[r][i] = (signed char)pair[q][0];
                    o->lattice[r][j] = (signed char)pair[q][1];
                }
        for (v = 0; v < 8; ++v, ++r)
            for (b = 0; b < nb; ++b)
                o->lattice[r][b] = (signed char)all[v];
        o->n_lattice = r;
        o->shrink = BUCKC_REAL_LITERAL(3.0);
        o->full_lattice = 0;
        o->warm_step = o->spacing / (10 * o->shrink);
        o->warm_span = o->warm_step * BUCKC_REAL_LITERAL(8.0);
    }
    for (i = 0; i < BUCKC_NEAR_OFFSETS; ++i) /* spacing / 20 * np.arange(-10.0, 11.0) */
        o->near_offsets[i] = o->spacing / 20 * (buckc_real)(i - 10);
    if (o->global_is_full) {
        o->stage_candidates_cold = o->n_global;
        o->stage_candidates_warm = o->n_lattice + o->n_global;
    } else {
        openings = s.levels + (nb >= 2 ? 25 : 0) + nb * (nb - 1); /* one block: no pairs (as _openings) */
        o->stage_candidates_cold = o->n_global + openings;
        o->stage_candidates_warm = o->n_lattice + BUCKC_NEAR_OFFSETS + o->n_global + openings;
    }
    if (o->stage_candidates_warm > BUCKC_MAX_CANDIDATES)
        FAIL(BUCKC_ERR_LIMIT, "stage-1 candidates: more than BUCKC_MAX_CANDIDATES");
    return BUCKC_OK;
}

/* ------------------------------------------------------------------ solve */

/* numpy's argmin over the candidates seen so far: the first minimum, or the first NaN */
typedef struct {
    int count, index, is_nan;
    buckc_real cost;
    buckc_real values[BUCKC_MAX_BLOCKS];
    buckc_real prediction[2];
} Scan;

typedef struct {
    BuckcOptimizer *o;
    BuckcCostFunction cost;
    void *user;
} Problem;

static buckc_real clip(const BuckcOptimizer *o, buckc_real d)
{
    if (d < o->low) d = o->low; /* np.maximum then np.minimum: NaN stays NaN */
    if (d > o->high) d = o->high;
    return d;
}

static void consider(const Problem *p, Scan *scan, const buckc_real *values)
{
    const BuckcOptimizer *o = p->o;
    buckc_real duties[BUCKC_MAX_HORIZON], prediction[2] = {NAN, NAN}, c;
    int t, take;
    for (t = 0; t < o->settings.horizon; ++t) /* expand() */
        duties[t] = values[o->block_of_step[t]];
    c = p->cost(p->user, duties, o->settings.horizon, prediction);
    if (scan->count == 0)
        take = 1;
    else if (scan->is_nan)
        take = 0;
    else
        take = isnan(c) || c < scan->cost;
    if (take) {
        scan->cost = c;
        scan->index = scan->count;
        scan->is_nan = isnan(c) != 0;
        memcpy(scan->values, values, sizeof(buckc_real) * (size_t)o->n_blocks);
        scan->prediction[0] = prediction[0];
        scan->prediction[1] = prediction[1];
    }
    scan->count++;
}

/* _openings(anchor): each row ends at the steady-state duty */
static void openings(const Problem *p, Scan *scan, buckc_real anchor)
{
    const BuckcOptimizer *o = p->o;
    int nb = o->n_blocks, i, b, j, m, q;
    buckc_real row[BUCKC_MAX_BLOCKS];
    for (i = 0; i < o->settings.levels; ++i) { /* a grid over the first move */
        for (b = 0; b < nb; ++b)
            row[b] = anchor;
        row[0] = o->grid[i];
        consider(p, scan, row);
    }
    for (i = 0; nb >= 2 && i < 25; ++i) { /* a coarse grid over the first two */
        for (b = 0; b < nb; ++b)
            row[b] = anchor;
        row[0] = o->coarse[i / 5];
        row[1] = o->coarse[i % 5];
        consider(p, scan, row);
    }
    for (q = 0; q < 2; ++q) { /* bang-bang: (high, low) then (low, high) */
        buckc_real a = q == 0 ? o->high : o->low, bb = q == 0 ? o->low : o->high;
        for (j = 1; j < nb; ++j)
            for (m = 0; m < nb - j; ++m) {
                for (b = 0; b < nb; ++b)
                    row[b] = b < j ? a : (b < j + m ? bb : anchor);
                consider(p, scan, row);
            }
    }
}

buckc_real buckc_optimizer_solve(BuckcOptimizer *o, BuckcCostFunction cost, void *user, const buckc_real *warm,
                             buckc_real anchor, buckc_real *sequence, buckc_real *first_prediction)
{
    Problem p;
    Scan scan;
    buckc_real center[BUCKC_MAX_BLOCKS], row[BUCKC_MAX_BLOCKS], best[BUCKC_MAX_BLOCKS], best_prediction[2];
    buckc_real best_cost, step;
    int nb = o->n_blocks, horizon = o->settings.horizon, n_warm = 0, i, b, t, it, near_warm = 0;
    p.o = o;
    p.cost = cost;
    p.user = user;
    memset(&scan, 0, sizeof(scan));

    /* ---- first_stage */
    if (o->low > anchor) anchor = o->low; /* min(max(anchor, low), high) */
    if (o->high < anchor) anchor = o->high;
    if (warm != NULL) { /* the previous solution shifted by one sample, per block */
        for (b = 0; b < nb; ++b) {
            int s = o->block_starts[b] + 1;
            center[b] = warm[s < horizon ? s : horizon - 1];
        }
        for (i = 0; i < o->n_lattice; ++i) { /* first, so that ties go to the warm start */
            for (b = 0; b < nb; ++b)
                row[b] = clip(o, center[b] + o->warm_step * (buckc_real)o->lattice[i][b]);
            consider(&p, &scan, row);
        }
        n_warm = o->n_lattice;
    }
    if (o->global_is_full) { /* the full grid, the last block fastest */
        for (i = 0; i < o->n_global; ++i) {
            int rest = i;
            for (b = nb - 1; b >= 0; --b) {
                row[b] = o->grid[rest % o->settings.levels];
                rest /= o->settings.levels;
            }
            consider(&p, &scan, row);
        }
    } else {
        if (warm != NULL) /* constant sequences finely around the last move */
            for (i = 0; i < BUCKC_NEAR_OFFSETS; ++i) {
                buckc_real d = clip(o, warm[0] + o->near_offsets[i]);
                for (b = 0; b < nb; ++b)
                    row[b] = d;
                consider(&p, &scan, row);
            }
        for (i = 0; i < o->settings.levels; ++i) { /* constant sequences */
            for (b = 0; b < nb; ++b)
                row[b] = o->grid[i];
            consider(&p, &scan, row);
        }
        openings(&p, &scan, anchor);
    }
    o->evaluations = scan.count;
    o->passes = 1;
    o->warm_count = n_warm;
    memcpy(best, scan.values, sizeof(buckc_real) * (size_t)nb);
    best_cost = scan.cost;
    best_prediction[0] = scan.prediction[0];
    best_prediction[1] = scan.prediction[1];
    o->best_call = 0;
    o->best_row = scan.index;

    /* ---- refinement */
    if (n_warm) { /* strictly inside the warm lattice: on its edge the optimum may lie further out */
        buckc_real deviation = ZERO;
        for (b = 0; b < nb; ++b) {
            buckc_real d = BUCKC_FABS(best[b] - center[b]);
            if (d > deviation || b == 0)
                deviation = d;
        }
        near_warm = deviation < o->warm_span - BUCKC_REAL_LITERAL(0.5) * o->warm_step;
    }
    o->near_warm = near_warm;
    if (near_warm)
        step = o->warm_step / o->shrink;
    else
        step = o->full_lattice ? o->spacing / o->shrink : (o->high - o->low) / 8;
    for (it = 0; it < o->settings.refine_iterations; ++it) {
        buckc_real start[BUCKC_MAX_BLOCKS];
        if (step < o->settings.duty_tolerance)
            break;
        memcpy(start, best, sizeof(start));
        memset(&scan, 0, sizeof(scan));
        for (i = 0; i < o->n_lattice; ++i) {
            for (b = 0; b < nb; ++b)
                row[b] = clip(o, start[b] + step * (buckc_real)o->lattice[i][b]);
            consider(&p, &scan, row);
        }
        o->evaluations += scan.count;
        o->passes += 1;
        if (scan.cost < best_cost) {
            memcpy(best, scan.values, sizeof(buckc_real) * (size_t)nb);
            best_cost = scan.cost;
            best_prediction[0] = scan.prediction[0];
            best_prediction[1] = scan.prediction[1];
            o->best_call = o->passes - 1;
            o->best_row = scan.index;
        }
        step /= o->shrink;
    }
    for (t = 0; t < horizon; ++t)
        sequence[t] = best[o->block_of_step[t]];
    if (first_prediction != NULL) {
        first_prediction[0] = best_prediction[0];
        first_prediction[1] = best_prediction[1];
    }
    return best_cost;
}

/* ------------------------------------------------------------------ the controller */

size_t buckc_predictive_size(void)
{
    return sizeof(BuckcPredictive);
}

static int predictor_delays(const BuckcPredictiveConfig *config)
{
    return config->predictor.kind == BUCKC_PREDICTOR_NN ? config->predictor.nn.delays : 1;
}

int buckc_predictive_init(BuckcPredictive *c, const BuckcPredictiveConfig *config, const char **what)
{
    int status, j;
    if (c == NULL || config == NULL)
        FAIL(BUCKC_ERR_NULL, "controller or config is NULL");
    if (!(config->sample_period > ZERO && isfinite(config->sample_period)))
        FAIL(BUCKC_ERR_INVALID, "sample_period: expected a finite value > 0");
    if (!(ZERO <= config->duty_min && config->duty_min < config->duty_max && config->duty_max <= ONE))
        FAIL(BUCKC_ERR_INVALID, "duty limits: expected 0 <= min < max <= 1");
    switch (config->predictor.kind) {
    case BUCKC_PREDICTOR_NN:
        status = buckc_nn_check(&config->predictor.nn, what);
        break;
#if BUCKC_HAVE_CIRCUIT_PREDICTORS
    case BUCKC_PREDICTOR_AVERAGED:
        status = buckc_averaged_check(&config->predictor.averaged, what);
        break;
    case BUCKC_PREDICTOR_SWITCHED:
        status = buckc_switched_check(&config->predictor.switched, NULL, what);
        break;
#else
    case BUCKC_PREDICTOR_AVERAGED:
    case BUCKC_PREDICTOR_SWITCHED:
        FAIL(BUCKC_ERR_INVALID, "predictor kind: the circuit predictors have no float32 build (the NN predictor's has)");
#endif
    default:
        FAIL(BUCKC_ERR_INVALID, "predictor kind: unknown code");
    }
    if (status != BUCKC_OK)
        return status;
    if (config->rti.enabled) { /* RtiSettings.__post_init__ */
        const BuckcRtiSettings *r = &config->rti;
        if (r->iterations < 1 || r->iterations > 3)
            FAIL(BUCKC_ERR_INVALID, "rti iterations: expected 1, 2 or 3");
        if (!(r->smoothing > ZERO && isfinite(r->smoothing)))
            FAIL(BUCKC_ERR_INVALID, "rti smoothing: expected eps > 0");
        if (!(r->step_limit > ZERO && r->step_limit <= ONE))
            FAIL(BUCKC_ERR_INVALID, "rti step_limit: expected 0 < limit <= 1");
        if (!(r->regularization >= ZERO && r->regularization < ONE))
            FAIL(BUCKC_ERR_INVALID, "rti regularization: expected 0 <= mu < 1");
        if (!(r->move_damping >= ZERO && r->move_damping < ONE))
            FAIL(BUCKC_ERR_INVALID, "rti move_damping: expected 0 <= rho < 1");
        if (r->qp_iterations < 1)
            FAIL(BUCKC_ERR_INVALID, "rti qp_iterations: expected >= 1");
        if (r->line_search != 0 && r->line_search != 1)
            FAIL(BUCKC_ERR_INVALID, "rti line_search: expected 0 or 1");
        if (r->reuse_jacobian != 0 && r->reuse_jacobian != 1)
            FAIL(BUCKC_ERR_INVALID, "rti reuse_jacobian: expected 0 or 1");
        if (r->reweightings < 0 || r->reweightings > 3)
            FAIL(BUCKC_ERR_INVALID, "rti reweightings: expected 0, 1, 2 or 3");
        if (r->reweightings > 0 && r->line_search)
            FAIL(BUCKC_ERR_INVALID, "rti reweightings: expected 0 with the line search");
        if (!(r->reweighting_tolerance >= ZERO && r->reweighting_tolerance < ONE))
            FAIL(BUCKC_ERR_INVALID, "rti reweighting_tolerance: expected 0 <= tolerance < 1");
        if (!(r->reference_step >= ZERO && isfinite(r->reference_step)) || !(r->load_step >= ZERO && isfinite(r->load_step))
            || !(r->innovation >= ZERO && isfinite(r->innovation))
            || !(r->startup_region >= ZERO && isfinite(r->startup_region))
            || !(r->error_region >= ZERO && isfinite(r->error_region)))
            FAIL(BUCKC_ERR_INVALID, "rti fallback thresholds: expected >= 0 (0: never)");
        if (!(r->duty_resolution >= ZERO && r->duty_resolution < ONE))
            FAIL(BUCKC_ERR_INVALID, "rti duty_resolution: expected 0 <= quantum < 1");
    }
    memset(c, 0, sizeof(*c));
    status = buckc_optimizer_init(&c->optimizer, &config->horizon, config->duty_min, config->duty_max, what);
    if (status != BUCKC_OK)
        return status;
    if (config->rti.enabled && c->optimizer.n_blocks > BUCKC_QP_MAX_VARIABLES)
        FAIL(BUCKC_ERR_LIMIT, "rti: more move blocks than BUCKC_QP_MAX_VARIABLES");
    c->config = config;
#ifdef BUCKC_FLOAT32
    /* gamma^j by products in float (j ulp at most off the exact power, 1.4e-6 at j = 23): libms' powf differ
     * in the last bit (glibc's and newlib's do), the products are the same on every IEEE target, so the
     * Cortex-M4F's duties equal the host float32 build's; and newlib's powf would add 3 KiB of flash */
    {
        buckc_real power = ONE;
        for (j = 0; j < config->horizon.horizon; ++j) {
            c->weights[j] = power;
            power *= config->horizon.discount;
        }
    }
#else
    for (j = 0; j < config->horizon.horizon; ++j) /* discount ** np.arange(horizon) */
        c->weights[j] = pow(config->horizon.discount, (double)j);
#endif
    buckc_predictive_reset(c);
    return BUCKC_OK;
}

void buckc_predictive_reset(BuckcPredictive *c)
{
    BuckcPredictiveState *s = &c->state;
    memset(s, 0, sizeof(*s));
    s->delays = predictor_delays(c->config);
    s->previous_duty = ZERO;
    s->conductance = ONE / c->config->nominal_load;
    s->previous_reference = NAN;
    s->starting = 1;
    s->best_cost = NAN;
    buckc_predictive_clear_caches(c); /* PredictiveController.reset: predictor.clear_cache() */
}

void buckc_predictive_clear_caches(BuckcPredictive *c)
{
#if BUCKC_HAVE_CIRCUIT_PREDICTORS
    buckc_averaged_cache_clear(&c->averaged_cache);
    buckc_switched_cache_clear(&c->switched_cache);
    c->table = NULL;
#else
    (void)c; /* the NN predictor caches nothing */
#endif
}

const BuckcPredictiveState *buckc_predictive_state(const BuckcPredictive *c)
{
    return &c->state;
}

/* the predictor's rollout of one sequence at the sample's context (Predictor.rollout) */
static void predict(BuckcPredictive *c, const buckc_real *duties, int horizon, buckc_real *predicted)
{
    const BuckcPredictorConfig *predictor = &c->config->predictor;
    switch (predictor->kind) {
    case BUCKC_PREDICTOR_NN:
        buckc_nn_shared_rollout(&predictor->nn, &c->nn, duties, horizon, predicted);
        break;
#if BUCKC_HAVE_CIRCUIT_PREDICTORS
    case BUCKC_PREDICTOR_AVERAGED:
        buckc_averaged_rollout(&c->averaged, duties, horizon, predicted);
        break;
    default:
        buckc_switched_rollout(c->table, c->state.history[0], c->context_previous_duty, duties, horizon,
                               c->context_disturbance, predicted);
        break;
#else
    default: /* refused at init */
        break;
#endif
    }
}

/* Predictor.linearize at the sample's context, the blocks of the horizon settings */
static void linearize(BuckcPredictive *c, const buckc_real *duties, buckc_real *out, buckc_real *jacobian)
{
    const BuckcPredictorConfig *predictor = &c->config->predictor;
    const BuckcOptimizer *o = &c->optimizer;
    int horizon = o->settings.horizon;
    switch (predictor->kind) {
    case BUCKC_PREDICTOR_NN:
        buckc_nn_sensitivities(&predictor->nn, &c->nn.history[0][0], predictor->nn.n_extras ? c->nn.extras : NULL,
                               c->nn.disturbance, duties, horizon, o->block_of_step, o->n_blocks, out, jacobian);
        break;
#if BUCKC_HAVE_CIRCUIT_PREDICTORS
    case BUCKC_PREDICTOR_AVERAGED:
        buckc_averaged_linearize(&c->averaged, duties, horizon, o->block_of_step, o->n_blocks, out, jacobian);
        break;
    default:
        buckc_switched_linearize(c->table, c->state.history[0], c->context_previous_duty, duties, horizon,
                                 c->context_disturbance, o->block_of_step, o->n_blocks, out, jacobian);
        break;
#else
    default: /* refused at init */
        break;
#endif
    }
}

int buckc_predictive_linearize(BuckcPredictive *c, const buckc_real *duties, buckc_real *out, buckc_real *jacobian)
{
    if (c->optimizer.n_blocks > BUCKC_QP_MAX_VARIABLES)
        return BUCKC_ERR_LIMIT;
    linearize(c, duties, out, jacobian);
    return BUCKC_OK;
}

/* eq. 23: sum_j gamma^j BUCKC_SQRT((iL - iref)^2 + (vo - vref)^2) over the predicted states */
static buckc_real sequence_cost(void *user, const buckc_real *duties, int horizon, buckc_real *first_prediction)
{
    BuckcPredictive *c = (BuckcPredictive *)user;
    buckc_real predicted[BUCKC_MAX_HORIZON][2], total = ZERO;
    int j;
    predict(c, duties, horizon, &predicted[0][0]);
    for (j = 0; j < horizon; ++j) {
        buckc_real e0 = predicted[j][0] - c->target[0], e1 = predicted[j][1] - c->target[1];
        e0 *= e0;
        e1 *= e1;
        total += BUCKC_SQRT(e0 + e1) * c->weights[j];
    }
    if (first_prediction != NULL) {
        first_prediction[0] = predicted[0][0];
        first_prediction[1] = predicted[0][1];
    }
    return total;
}

/* ------------------------------------------------------------------ the real-time iteration */

/* RealTimeIteration.costs: (smoothed, exact eq. 16) of one predicted trajectory */
static void rti_costs(const BuckcPredictive *c, const buckc_real *predicted, buckc_real *smoothed, buckc_real *exact)
{
    buckc_real eps = c->config->rti.smoothing, sum_smoothed = ZERO, sum_exact = ZERO;
    int j, horizon = c->optimizer.settings.horizon;
    for (j = 0; j < horizon; ++j) {
        buckc_real e0 = predicted[2 * j] - c->target[0], e1 = predicted[2 * j + 1] - c->target[1];
        buckc_real squared = e0 * e0 + e1 * e1;
        sum_smoothed += BUCKC_SQRT(squared + eps * eps) * c->weights[j];
        sum_exact += BUCKC_SQRT(squared) * c->weights[j];
    }
    *smoothed = sum_smoothed;
    *exact = sum_exact;
}

/* RealTimeIteration.model: the gradient and the reweighted (IRLS) Hessian + mu I of the smoothed cost, with the
 * first move's proximal term; first_move = u_0 - d_prev */
static void rti_model(const BuckcPredictive *c, const buckc_real *predicted, const buckc_real *jacobian,
                      buckc_real first_move, buckc_real *gradient,
                      buckc_real hessian[BUCKC_QP_MAX_VARIABLES][BUCKC_QP_MAX_VARIABLES])
{
    int nb = c->optimizer.n_blocks, horizon = c->optimizer.settings.horizon, j, a, b;
    buckc_real eps = c->config->rti.smoothing, trace = ZERO, mean_diagonal, mu;
    for (a = 0; a < nb; ++a) {
        gradient[a] = ZERO;
        for (b = 0; b < nb; ++b)
            hessian[a][b] = ZERO;
    }
    for (j = 0; j < horizon; ++j) {
        buckc_real e0 = predicted[2 * j] - c->target[0], e1 = predicted[2 * j + 1] - c->target[1];
        buckc_real s = BUCKC_SQRT(e0 * e0 + e1 * e1 + eps * eps), weight = c->weights[j] / s;
        const buckc_real *j0 = jacobian + (2 * j) * nb, *j1 = jacobian + (2 * j + 1) * nb;
        /* causality: step j's state does not depend on the blocks after its own (their Jacobian columns are zeros,
         * as every predictor's linearisation writes them), whose terms would add +-0 to each sum: left out, the
         * sums are the same bits */
        int active = c->optimizer.block_of_step[j] + 1;
        /* two blocks' terms per pair (buckc_pair.h: each lane the scalar expression, the same bits), a last odd
         * one alone: no lane writes past `active` */
        for (a = 0; a + 1 < active; a += 2)
            buckc_pair_store(gradient + a, buckc_pair_add(buckc_pair_load(gradient + a), buckc_pair_mul(
                buckc_pair_add(buckc_pair_mul(buckc_pair_load(j0 + a), buckc_pair_splat(e0)),
                               buckc_pair_mul(buckc_pair_load(j1 + a), buckc_pair_splat(e1))),
                buckc_pair_splat(weight))));
        if (a < active)
            gradient[a] += (j0[a] * e0 + j1[a] * e1) * weight;
        for (a = 0; a < active; ++a) {
            /* the upper triangle: the lower one is the same products (mirrored below) */
            buckc_pair w = buckc_pair_splat(weight), j0a = buckc_pair_splat(j0[a]), j1a = buckc_pair_splat(j1[a]);
            for (b = a; b + 1 < active; b += 2)
                buckc_pair_store(&hessian[a][b], buckc_pair_add(buckc_pair_load(&hessian[a][b]), buckc_pair_mul(
                    w, buckc_pair_add(buckc_pair_mul(j0a, buckc_pair_load(j0 + b)),
                                      buckc_pair_mul(j1a, buckc_pair_load(j1 + b))))));
            if (b < active)
                hessian[a][b] += weight * (j0[a] * j0[b] + j1[a] * j1[b]);
        }
    }
    for (a = 1; a < nb; ++a) /* j0[b] j0[a] = j0[a] j0[b] exactly: the full sums, bit for bit */
        for (b = 0; b < a; ++b)
            hessian[a][b] = hessian[b][a];
    for (a = 0; a < nb; ++a)
        trace += hessian[a][a];
    mean_diagonal = trace / (buckc_real)nb;
    mu = c->config->rti.regularization * mean_diagonal + BUCKC_REAL_LITERAL(1e-12);
    for (a = 0; a < nb; ++a)
        hessian[a][a] += mu;
    if (c->config->rti.move_damping > ZERO) {
        buckc_real rho = c->config->rti.move_damping * mean_diagonal;
        hessian[0][0] += rho;
        gradient[0] += rho * first_move;
    }
}

static void expand(const BuckcOptimizer *o, const buckc_real *moves, buckc_real *duties)
{
    int t;
    for (t = 0; t < o->settings.horizon; ++t)
        duties[t] = moves[o->block_of_step[t]];
}

/* RealTimeIteration.solve: the plan sequence[horizon] from the warm start; returns its exact cost (NaN where the
 * plan was not rolled out) and writes its first predicted state */
static buckc_real rti_solve(BuckcPredictive *c, const buckc_real *warm, buckc_real *sequence, buckc_real first[2])
{
    const BuckcRtiSettings *st = &c->config->rti;
    const BuckcOptimizer *o = &c->optimizer;
    BuckcPredictiveState *state = &c->state;
    int nb = o->n_blocks, horizon = o->settings.horizon, b, iteration, sweep, rolled_out = 1;
    buckc_real u[BUCKC_QP_MAX_VARIABLES], trial[BUCKC_QP_MAX_VARIABLES], delta[BUCKC_QP_MAX_VARIABLES];
    buckc_real step[BUCKC_QP_MAX_VARIABLES], shifted_lower[BUCKC_QP_MAX_VARIABLES];
    buckc_real shifted_upper[BUCKC_QP_MAX_VARIABLES], linear[BUCKC_MAX_HORIZON * 2];
    buckc_real lower[BUCKC_QP_MAX_VARIABLES], upper[BUCKC_QP_MAX_VARIABLES], gradient[BUCKC_QP_MAX_VARIABLES];
    buckc_real hessian[BUCKC_QP_MAX_VARIABLES][BUCKC_QP_MAX_VARIABLES];
    buckc_real duties[BUCKC_MAX_HORIZON], predicted[BUCKC_MAX_HORIZON * 2], trial_predicted[BUCKC_MAX_HORIZON * 2];
    buckc_real jacobian[BUCKC_MAX_HORIZON * 2 * BUCKC_QP_MAX_VARIABLES];
    buckc_real smoothed, exact, radius = st->step_limit;
    for (b = 0; b < nb; ++b) { /* the previous solution shifted by one sample, at the block starts */
        int k = o->block_starts[b] + 1;
        buckc_real v = warm[k < horizon ? k : horizon - 1];
        if (v < o->low) v = o->low; /* np.minimum(np.maximum(center, low), high) */
        if (v > o->high) v = o->high;
        u[b] = v;
    }
    expand(o, u, duties);
    linearize(c, duties, predicted, jacobian);
    if (st->line_search) /* without it the costs decide nothing and the plan's is NaN: not computed */
        rti_costs(c, predicted, &smoothed, &exact);
    else
        smoothed = exact = NAN;
    rti_model(c, predicted, jacobian, u[0] - state->previous_duty, gradient, hessian);
    state->qp_iterations = state->accepted = state->reweighted = 0;
    for (iteration = 0; iteration < st->iterations; ++iteration) {
        buckc_real trial_smoothed, trial_exact;
        int final = iteration + 1 == st->iterations;
        for (b = 0; b < nb; ++b) {
            buckc_real lo = o->low - u[b], hi = o->high - u[b];
            lower[b] = lo > -radius ? lo : -radius;
            upper[b] = hi < radius ? hi : radius;
        }
        state->qp_iterations += buckc_box_qp(nb, &hessian[0][0], BUCKC_QP_MAX_VARIABLES, gradient, lower, upper,
                                             st->qp_iterations, delta, NULL);
        if (st->reweightings > 0) /* the last QP's step, which the reweightings' stop rule reads */
            memcpy(step, delta, sizeof(buckc_real) * (size_t)nb);
        for (sweep = 0; sweep < st->reweightings; ++sweep) { /* the same linearisation, reweighted at its errors */
            buckc_real largest = ZERO;
            int j;
            for (b = 0; b < nb; ++b) /* np.max(np.abs(last)): NaN does not stop it */
                if (BUCKC_FABS(step[b]) > largest || isnan(step[b]))
                    largest = BUCKC_FABS(step[b]);
            if (largest <= st->reweighting_tolerance)
                break;
            state->reweighted += 1;
            for (j = 0; j < 2 * horizon; ++j) { /* predicted + J delta, block by block (as the Python twin), the
                                                   * active blocks (rti_model says why) */
                buckc_real v = predicted[j];
                int active = o->block_of_step[j / 2] + 1;
                for (b = 0; b < active; ++b)
                    v += jacobian[j * nb + b] * delta[b];
                linear[j] = v;
            }
            rti_model(c, linear, jacobian, u[0] + delta[0] - state->previous_duty, gradient, hessian);
            for (b = 0; b < nb; ++b) {
                shifted_lower[b] = lower[b] - delta[b];
                shifted_upper[b] = upper[b] - delta[b];
            }
            state->qp_iterations += buckc_box_qp(nb, &hessian[0][0], BUCKC_QP_MAX_VARIABLES, gradient, shifted_lower,
                                                 shifted_upper, st->qp_iterations, step, NULL);
            for (b = 0; b < nb; ++b)
                delta[b] = delta[b] + step[b];
        }
        for (b = 0; b < nb; ++b) {
            buckc_real v = u[b] + delta[b];
            if (v < o->low) v = o->low;
            if (v > o->high) v = o->high;
            trial[b] = v;
        }
        if (final && !st->line_search) { /* taken unevaluated */
            memcpy(u, trial, sizeof(buckc_real) * (size_t)nb);
            rolled_out = 0;
            state->accepted += 1;
            break;
        }
        expand(o, trial, duties);
        if (final || st->reuse_jacobian) /* reused: the first step's sensitivities stay in jacobian */
            predict(c, duties, horizon, trial_predicted);
        else
            linearize(c, duties, trial_predicted, jacobian);
        if (st->line_search)
            rti_costs(c, trial_predicted, &trial_smoothed, &trial_exact);
        else
            trial_smoothed = trial_exact = NAN;
        if (!st->line_search || trial_smoothed <= smoothed * BUCKC_RTI_ACCEPT_TOLERANCE) {
            memcpy(u, trial, sizeof(buckc_real) * (size_t)nb);
            memcpy(predicted, trial_predicted, sizeof(buckc_real) * 2 * (size_t)horizon);
            smoothed = trial_smoothed;
            exact = trial_exact;
            state->accepted += 1;
            if (!final)
                rti_model(c, predicted, jacobian, u[0] - state->previous_duty, gradient, hessian);
        } else {
            radius *= BUCKC_REAL_LITERAL(0.25);
        }
    }
    if (st->duty_resolution > ZERO) { /* BUCKC_FLOOR(u / q + 1/2) q, within the limits */
        buckc_real q = st->duty_resolution;
        for (b = 0; b < nb; ++b) {
            buckc_real v = BUCKC_FLOOR(u[b] / q + BUCKC_REAL_LITERAL(0.5)) * q;
            if (v < o->low) v = o->low;
            if (v > o->high) v = o->high;
            if (v != u[b])
                rolled_out = 0;
            u[b] = v;
        }
    }
    expand(o, u, sequence);
    if (!rolled_out) {
        if (st->line_search) { /* the plan's cost stays known, as the line search's plans' are */
            predict(c, sequence, horizon, predicted);
            rti_costs(c, predicted, &smoothed, &exact);
        } else { /* its first state only: what the disturbance estimate needs */
            predict(c, sequence, 1, predicted);
            exact = NAN;
        }
    }
    first[0] = predicted[0];
    first[1] = predicted[1];
    return exact;
}

/* PredictiveController.fallback_reason */
static int fallback_reason(const BuckcPredictive *c, buckc_real reference, buckc_real voltage, buckc_real conductance,
                           buckc_real previous_conductance, buckc_real surprise)
{
    const BuckcRtiSettings *st = &c->config->rti;
    const BuckcPredictiveState *s = &c->state;
    if (!s->have_warm)
        return BUCKC_FALLBACK_COLD_START;
    if (s->starting && st->startup_region != ZERO && BUCKC_FABS(reference - voltage) > st->startup_region)
        return BUCKC_FALLBACK_STARTUP;
    if (st->error_region != ZERO && BUCKC_FABS(reference - voltage) > st->error_region)
        return BUCKC_FALLBACK_LARGE_ERROR;
    if (st->reference_step != ZERO && BUCKC_FABS(reference - s->previous_reference) > st->reference_step)
        return BUCKC_FALLBACK_REFERENCE_STEP;
    if (st->load_step != ZERO && BUCKC_FABS(conductance - previous_conductance) > st->load_step * previous_conductance)
        return BUCKC_FALLBACK_LOAD_STEP;
    if (st->innovation != ZERO && surprise > st->innovation)
        return BUCKC_FALLBACK_PREDICTION_ERROR;
    return BUCKC_FALLBACK_NONE;
}

buckc_real buckc_predictive_search_last(BuckcPredictive *c, buckc_real *sequence)
{
    BuckcOptimizer optimizer = c->optimizer; /* a copy: the controller's diagnostics stay as they are */
    const BuckcPredictiveState *s = &c->state;
    return buckc_optimizer_solve(&optimizer, sequence_cost, c, s->warm_before_valid ? s->warm_before : NULL,
                                 s->anchor, sequence, NULL);
}

buckc_real buckc_predictive_cost(BuckcPredictive *c, const buckc_real *duties, buckc_real *first_prediction)
{
    return sequence_cost(c, duties, c->config->horizon.horizon, first_prediction);
}

int buckc_predictive_step(BuckcPredictive *c, const BuckcMeasurement *m, buckc_real *duty)
{
    const BuckcPredictiveConfig *config = c->config;
    BuckcPredictiveState *s = &c->state;
    buckc_real current, voltage, load, input_voltage, anchor, first[2], sequence[BUCKC_MAX_HORIZON];
    buckc_real surprise, previous_conductance;
    int delays = s->delays, d, fallback;
    if (m == NULL || duty == NULL)
        return BUCKC_ERR_NULL;
    if (!isfinite(m->inductor_current))
        return BUCKC_ERR_NO_INDUCTOR_CURRENT;
    current = m->inductor_current;
    voltage = m->output_voltage;
    if (!s->have_history) {
        for (d = 0; d < delays; ++d) {
            s->history[d][0] = current;
            s->history[d][1] = voltage;
            s->history[d][2] = s->previous_duty;
        }
        s->have_history = 1;
    } else {
        if (delays > 1) {
            for (d = delays - 1; d >= 1; --d)
                memcpy(s->history[d], s->history[d - 1], sizeof(s->history[d]));
            s->history[1][2] = s->previous_duty; /* the duty applied after that sample */
        }
        s->history[0][0] = current;
        s->history[0][1] = voltage;
        s->history[0][2] = ZERO;
    }
    surprise = ZERO;
    if (s->have_predicted) { /* the filtered one-step prediction error */
        buckc_real alpha = config->horizon.bias_filter;
        buckc_real b0 = s->bias[0], b1 = s->bias[1];
        surprise = BUCKC_FABS(voltage - (s->predicted[1] + b1));
        s->bias[0] = (1 - alpha) * b0 + alpha * (current - s->predicted[0]);
        s->bias[1] = (1 - alpha) * b1 + alpha * (voltage - s->predicted[1]);
    }
    previous_conductance = s->conductance;
    s->conductance = buckc_estimate_conductance(voltage, m->load_current, m->inductor_current, s->conductance);
    load = ONE / s->conductance;
    c->target[0] = m->reference * s->conductance;
    c->target[1] = m->reference;
    input_voltage = isfinite(m->input_voltage) ? m->input_voltage : config->nominal_input_voltage;
    c->context_previous_duty = s->previous_duty;
    c->context_disturbance[0] = s->bias[0];
    c->context_disturbance[1] = s->bias[1];
    switch (config->predictor.kind) {
    case BUCKC_PREDICTOR_NN: { /* NNPredictor.rollout's extra signals */
        const BuckcNnConfig *nn = &config->predictor.nn;
        buckc_real extras[BUCKC_NN_MAX_EXTRAS];
        int e;
        for (e = 0; e < nn->n_extras; ++e) {
            switch (nn->extras[e]) {
            case BUCKC_EXTRA_LOAD_CURRENT: extras[e] = m->load_current; break;
            case BUCKC_EXTRA_INPUT_VOLTAGE: extras[e] = input_voltage; break;
            default: extras[e] = s->conductance; break;
            }
        }
        buckc_nn_shared_prepare(nn, &s->history[0][0], nn->n_extras ? extras : NULL, s->bias, &c->nn);
        break;
    }
#if BUCKC_HAVE_CIRCUIT_PREDICTORS
    case BUCKC_PREDICTOR_AVERAGED:
        buckc_averaged_prepare(&config->predictor.averaged, &c->averaged_cache, load, s->previous_duty,
                               input_voltage, s->history[0], s->bias, &c->averaged);
        break;
    default:
        c->table = buckc_switched_cached(&config->predictor.switched, &c->switched_cache, load, input_voltage);
        if (!(c->table->condition <= BUCKC_SWITCHED_MAX_CONDITION))
            return BUCKC_ERR_ILL_CONDITIONED; /* SwitchedModelPredictor._table's refusal */
        break;
#else
    default: /* refused at init */
        (void)load;
        break;
#endif
    }
    anchor = input_voltage > ZERO ? m->reference / input_voltage : s->previous_duty;
    s->anchor = anchor; /* the problem, for buckc_predictive_search_last */
    s->warm_before_valid = s->have_warm;
    memcpy(s->warm_before, s->warm, sizeof(s->warm));
    fallback = config->rti.enabled ? fallback_reason(c, m->reference, voltage, s->conductance, previous_conductance,
                                                     surprise)
                                   : BUCKC_FALLBACK_NONE;
    if (fallback != BUCKC_FALLBACK_COLD_START && fallback != BUCKC_FALLBACK_STARTUP)
        s->starting = 0;
    s->previous_reference = m->reference;
    if (config->rti.enabled && fallback == BUCKC_FALLBACK_NONE) {
        s->best_cost = rti_solve(c, s->warm, sequence, first);
        s->last_solver = BUCKC_SOLVER_RTI;
        s->evaluations = s->passes = 0;
    } else {
        s->best_cost = buckc_optimizer_solve(&c->optimizer, sequence_cost, c, s->have_warm ? s->warm : NULL, anchor,
                                             sequence, first);
        s->last_solver = BUCKC_SOLVER_SEARCH;
        s->evaluations = c->optimizer.evaluations;
        s->passes = c->optimizer.passes;
        s->best_call = c->optimizer.best_call;
        s->best_row = c->optimizer.best_row;
        s->qp_iterations = s->accepted = s->reweighted = 0;
    }
    s->last_fallback = fallback;
    /* the model's own one-step prediction (the disturbance is added after each step) */
    s->predicted[0] = first[0] - s->bias[0];
    s->predicted[1] = first[1] - s->bias[1];
    s->have_predicted = 1;
    memcpy(s->warm, sequence, sizeof(buckc_real) * (size_t)config->horizon.horizon);
    s->have_warm = 1;
    s->previous_duty = sequence[0];
    *duty = sequence[0];
    return BUCKC_OK;
}
