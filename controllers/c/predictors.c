/*
 * predictors.c -- twin of controllers/predictors.py:
 *   buckc_expm2                 expm2 (and expm2_many, the same formula per duration)
 *   buckc_circuit_matrix        circuit_matrix
 *   buckc_measured_from_state   measured_from_state
 *   buckc_averaged_*            AveragedModelPredictor._discrete (with its cache), .rollout and .linearize
 *   buckc_switched_*            SwitchedModelPredictor._interval, _table (with its cache),
 *                               _lookup, .rollout and .linearize, and _compose / _affine_power inside them
 * Cache semantics and conventions: predictors.h and buckc.h.
 */
#include <math.h>
#include <string.h>

#include "predictors.h"

/* ---------------------------------------------------------------- 2x2 helpers */

static void matmul2(const double a[4], const double b[4], double out[4])
{
    double r[4];
    r[0] = a[0] * b[0] + a[1] * b[2];
    r[1] = a[0] * b[1] + a[1] * b[3];
    r[2] = a[2] * b[0] + a[3] * b[2];
    r[3] = a[2] * b[1] + a[3] * b[3];
    memcpy(out, r, sizeof(r));
}

static void matvec2(const double a[4], const double x[2], double out[2])
{
    double r0 = a[0] * x[0] + a[1] * x[1];
    double r1 = a[2] * x[0] + a[3] * x[1];
    out[0] = r0;
    out[1] = r1;
}

void buckc_solve2(const double a[4], const double b[2], double x[2])
{
    double a00 = a[0], a01 = a[1], a10 = a[2], a11 = a[3], b0 = b[0], b1 = b[1];
    double l, u11, y1, x1;
    if (fabs(a10) > fabs(a00)) { /* partial pivoting: the first largest |a_i0| */
        double t;
        t = a00; a00 = a10; a10 = t;
        t = a01; a01 = a11; a11 = t;
        t = b0; b0 = b1; b1 = t;
    }
    l = a10 / a00;
    u11 = a11 - l * a01;
    y1 = b1 - l * b0;
    x1 = y1 / u11;
    x[0] = (b0 - a01 * x1) / a00;
    x[1] = x1;
}

void buckc_inverse2(const double a[4], double inverse[4])
{
    static const double e0[2] = {1.0, 0.0}, e1[2] = {0.0, 1.0};
    double c0[2], c1[2];
    buckc_solve2(a, e0, c0);
    buckc_solve2(a, e1, c1);
    inverse[0] = c0[0];
    inverse[1] = c1[0];
    inverse[2] = c0[1];
    inverse[3] = c1[1];
}

/* ---------------------------------------------------------------- closed forms */

void buckc_expm2(const double a[4], double t, double out[4])
{
    double s = 0.5 * (a[0] + a[3]);
    double m[4];
    double delta, z, c, g, scale;
    m[0] = a[0] - s;
    m[1] = a[1];
    m[2] = a[2];
    m[3] = a[3] - s;
    delta = m[0] * m[0] + m[1] * m[2];
    z = delta * t * t;
    if (fabs(z) < 1e-3) {
        c = 1 + z / 2 * (1 + z / 12 * (1 + z / 30));
        g = t * (1 + z / 6 * (1 + z / 20 * (1 + z / 42)));
        scale = exp(s * t);
    } else if (delta < 0) {
        double w = sqrt(-delta);
        c = cos(w * t);
        g = sin(w * t) / w;
        scale = exp(s * t);
    } else { /* over-damped: e^(st) cosh(wt) etc. from the separate exponentials */
        double w = sqrt(delta);
        double e1 = exp((s + w) * t), e2 = exp((s - w) * t);
        c = 0.5 * (e1 + e2);
        g = 0.5 * (e1 - e2) / w;
        out[0] = c + g * m[0];
        out[1] = g * m[1];
        out[2] = g * m[2];
        out[3] = c + g * m[3];
        return;
    }
    out[0] = scale * (c + g * m[0]);
    out[1] = scale * (g * m[1]);
    out[2] = scale * (g * m[2]);
    out[3] = scale * (c + g * m[3]);
}

void buckc_circuit_matrix(const BuckcCircuitParameters *p, double load, double switch_resistance, double a[4])
{
    double k = load / (load + p->capacitor_esr);
    a[0] = -(switch_resistance + p->inductor_resistance + k * p->capacitor_esr) / p->inductance;
    a[1] = -k / p->inductance;
    a[2] = k / p->capacitance;
    a[3] = -1.0 / ((load + p->capacitor_esr) * p->capacitance);
}

void buckc_measured_from_state(const BuckcCircuitParameters *p, double load, double t[4])
{
    double k = load / (load + p->capacitor_esr);
    t[0] = 1.0;
    t[1] = 0.0;
    t[2] = k * p->capacitor_esr;
    t[3] = k;
}

/* Python's round(x, digits) as a cache key (see predictors.h) */
static double cache_key(double x, double scale)
{
    return nearbyint(x * scale);
}

/* ---------------------------------------------------------------- averaged model */

int buckc_averaged_check(const BuckcAveragedConfig *config, const char **what)
{
    if (config == NULL) {
        if (what) *what = "averaged config is NULL";
        return BUCKC_ERR_NULL;
    }
    if (!(config->sample_period > 0.0 && isfinite(config->sample_period))) {
        if (what) *what = "averaged sample_period: expected a finite value > 0";
        return BUCKC_ERR_INVALID;
    }
    return BUCKC_OK;
}

void buckc_averaged_discrete(const BuckcAveragedConfig *config, double load, double switch_resistance,
                             double phi[4], double gamma[2])
{
    const BuckcCircuitParameters *p = &config->parameters;
    double a[4], r[2], v0 = 1.0 / p->inductance;
    buckc_circuit_matrix(p, load, switch_resistance, a);
    buckc_expm2(a, config->sample_period, phi);
    r[0] = (phi[0] - 1.0) * v0 + phi[1] * 0.0; /* (Phi - I) @ [1/L, 0] */
    r[1] = phi[2] * v0 + (phi[3] - 1.0) * 0.0;
    buckc_solve2(a, r, gamma);
}

void buckc_averaged_cache_clear(BuckcAveragedCache *cache)
{
    cache->count = 0;
}

void buckc_averaged_cached(const BuckcAveragedConfig *config, BuckcAveragedCache *cache, double load,
                           double switch_resistance, double phi[4], double gamma[2])
{
    double key_load, key_switch;
    BuckcAveragedEntry *entry;
    int i;
    if (cache == NULL) {
        buckc_averaged_discrete(config, load, switch_resistance, phi, gamma);
        return;
    }
    key_load = cache_key(load, 1e9);
    key_switch = cache_key(switch_resistance, 1e12);
    for (i = 0; i < cache->count; ++i) {
        entry = &cache->entries[i];
        if (entry->key_load == key_load && entry->key_switch == key_switch) {
            memcpy(phi, entry->phi, sizeof(entry->phi));
            memcpy(gamma, entry->gamma, sizeof(entry->gamma));
            return;
        }
    }
    if (cache->count > 256) /* Python: if len(self._cache) > 256: self._cache.clear() */
        cache->count = 0;
    entry = &cache->entries[cache->count++];
    entry->key_load = key_load;
    entry->key_switch = key_switch;
    buckc_averaged_discrete(config, load, switch_resistance, entry->phi, entry->gamma);
    memcpy(phi, entry->phi, sizeof(entry->phi));
    memcpy(gamma, entry->gamma, sizeof(entry->gamma));
}

void buckc_averaged_prepare(const BuckcAveragedConfig *config, BuckcAveragedCache *cache, double load,
                            double previous_duty, double input_voltage, const double y0[2],
                            const double disturbance[2], BuckcAveragedStep *step)
{
    const BuckcCircuitParameters *p = &config->parameters;
    double phi[4], gamma[2], to_y[4], to_x[4], t_phi[4];
    buckc_averaged_cached(config, cache, load, previous_duty * p->switch_on_resistance, phi, gamma);
    buckc_measured_from_state(p, load, to_y);
    buckc_inverse2(to_y, to_x);
    matmul2(to_y, phi, t_phi); /* (to_y @ phi) @ to_x */
    matmul2(t_phi, to_x, step->phi_y);
    matvec2(to_y, gamma, step->gamma_y);
    step->drive = input_voltage + p->diode_forward_voltage;
    step->forward = p->diode_forward_voltage;
    step->y0[0] = y0[0];
    step->y0[1] = y0[1];
    step->disturbance[0] = disturbance[0];
    step->disturbance[1] = disturbance[1];
}

void buckc_averaged_rollout(const BuckcAveragedStep *step, const double *duties, int n, double *out)
{
    const double *py = step->phi_y, *gy = step->gamma_y;
    double i_l = step->y0[0], v_o = step->y0[1];
    int j;
    for (j = 0; j < n; ++j) {
        double node = duties[j] * step->drive - step->forward;
        double i_next = (i_l * py[0] + v_o * py[1]) + node * gy[0]; /* y @ phi_y.T + node gamma_y */
        double v_next = (i_l * py[2] + v_o * py[3]) + node * gy[1];
        if (i_next < 0.0) /* the diode, on the model's own prediction */
            i_next = 0.0;
        i_next += step->disturbance[0];
        v_next += step->disturbance[1];
        out[2 * j] = i_next;
        out[2 * j + 1] = v_next;
        i_l = i_next;
        v_o = v_next;
    }
}

void buckc_averaged_linearize(const BuckcAveragedStep *step, const double *duties, int n, const int *block_of_step,
                              int n_blocks, double *out, double *jacobian)
{
    const double *py = step->phi_y, *gy = step->gamma_y;
    double i_l = step->y0[0], v_o = step->y0[1], sens[2][BUCKC_SENSITIVITY_DIRECTIONS];
    int j, c;
    for (c = 0; c < n_blocks; ++c)
        sens[0][c] = sens[1][c] = 0.0;
    for (j = 0; j < n; ++j) {
        double node = duties[j] * step->drive - step->forward;
        double i_next = (i_l * py[0] + v_o * py[1]) + node * gy[0];
        double v_next = (i_l * py[2] + v_o * py[3]) + node * gy[1];
        int b = block_of_step[j];
        for (c = 0; c < n_blocks; ++c) { /* phi_y @ sensitivity */
            double s0 = py[0] * sens[0][c] + py[1] * sens[1][c];
            double s1 = py[2] * sens[0][c] + py[3] * sens[1][c];
            sens[0][c] = s0;
            sens[1][c] = s1;
        }
        sens[0][b] += gy[0] * step->drive;
        sens[1][b] += gy[1] * step->drive;
        if (i_next < 0.0) { /* the diode: the clipped current has no sensitivity */
            i_next = 0.0;
            for (c = 0; c < n_blocks; ++c)
                sens[0][c] = 0.0;
        }
        i_l = i_next + step->disturbance[0];
        v_o = v_next + step->disturbance[1];
        out[2 * j] = i_l;
        out[2 * j + 1] = v_o;
        for (c = 0; c < n_blocks; ++c) {
            jacobian[(2 * j) * n_blocks + c] = sens[0][c];
            jacobian[(2 * j + 1) * n_blocks + c] = sens[1][c];
        }
    }
}

/* ---------------------------------------------------------------- switched model */

typedef struct {
    double m[4];
    double v[2];
} Affine;

/* _compose(first, then): x -> B (A x + a) + b */
static Affine compose(const Affine *first, const Affine *then)
{
    Affine r;
    double bv[2];
    matmul2(then->m, first->m, r.m);
    matvec2(then->m, first->v, bv);
    r.v[0] = bv[0] + then->v[0];
    r.v[1] = bv[1] + then->v[1];
    return r;
}

static Affine identity_map(void)
{
    Affine r;
    r.m[0] = 1.0; r.m[1] = 0.0; r.m[2] = 0.0; r.m[3] = 1.0;
    r.v[0] = 0.0; r.v[1] = 0.0;
    return r;
}

/* _affine_power: binary powering, in Python's order */
static Affine affine_power(const Affine *step, long times)
{
    Affine result = identity_map(), base = *step;
    while (times) {
        if (times & 1)
            result = compose(&result, &base);
        times >>= 1;
        if (times)
            base = compose(&base, &base);
    }
    return result;
}

/* _interval for one duration: (state at its end, integral of the state over it) as affine maps */
static void interval(const double a[4], const double a_inv[4], double voltage, double inductance, double duration,
                     Affine *end, Affine *integral)
{
    double drive0 = voltage / inductance;
    double e_minus_i[4], g_minus_t[4], ag[4];
    buckc_expm2(a, duration, end->m);
    e_minus_i[0] = end->m[0] - 1.0;
    e_minus_i[1] = end->m[1] - 0.0;
    e_minus_i[2] = end->m[2] - 0.0;
    e_minus_i[3] = end->m[3] - 1.0;
    matmul2(a_inv, e_minus_i, integral->m); /* int_0^tau e^(A s) ds */
    end->v[0] = integral->m[0] * drive0 + integral->m[1] * 0.0;
    end->v[1] = integral->m[2] * drive0 + integral->m[3] * 0.0;
    g_minus_t[0] = integral->m[0] - duration;
    g_minus_t[1] = integral->m[1] - duration * 0.0;
    g_minus_t[2] = integral->m[2] - duration * 0.0;
    g_minus_t[3] = integral->m[3] - duration;
    matmul2(a_inv, g_minus_t, ag);
    integral->v[0] = ag[0] * drive0 + ag[1] * 0.0;
    integral->v[1] = ag[2] * drive0 + ag[3] * 0.0;
}

int buckc_switched_check(const BuckcSwitchedConfig *config, int *periods, const char **what)
{
    double exact, whole;
    if (config == NULL) {
        if (what) *what = "switched config is NULL";
        return BUCKC_ERR_NULL;
    }
    exact = config->sample_period * config->switching_frequency;
    whole = nearbyint(exact); /* Python's round(): ties to even */
    if (!(whole >= 1.0) || !(fabs(exact - whole) <= 1e-6 * exact) || whole > 1e9) {
        if (what) *what = "switched sample_period: not a whole number of switching periods";
        return BUCKC_ERR_INVALID;
    }
    if (config->carrier != BUCKC_CARRIER_SAWTOOTH && config->carrier != BUCKC_CARRIER_TRIANGLE) {
        if (what) *what = "switched carrier: unknown code";
        return BUCKC_ERR_INVALID;
    }
    if (config->sensor != BUCKC_SENSOR_PERIOD_AVERAGE && config->sensor != BUCKC_SENSOR_PERIOD_START) {
        if (what) *what = "switched sensor: unknown code";
        return BUCKC_ERR_INVALID;
    }
    if (config->grid_points < 2) {
        if (what) *what = "switched grid_points: expected >= 2";
        return BUCKC_ERR_INVALID;
    }
    if (config->grid_points > BUCKC_SWITCHED_MAX_GRID) {
        if (what) *what = "switched grid_points: above BUCKC_SWITCHED_MAX_GRID";
        return BUCKC_ERR_LIMIT;
    }
    if (periods)
        *periods = (int)whole;
    return BUCKC_OK;
}

/* The 2-norm condition number of a 2x2 matrix, sigma_max / sigma_min (inf if singular): the singular
 * values squared are the eigenvalues of M^T M, (f +- sqrt(f^2 - 4 det^2)) / 2 with f = |M|_F^2. */
static double condition2(const double m[4])
{
    double f = m[0] * m[0] + m[1] * m[1] + m[2] * m[2] + m[3] * m[3];
    double det = m[0] * m[3] - m[1] * m[2];
    double root = sqrt(fmax(f * f - 4.0 * det * det, 0.0));
    double small = 2.0 * det * det / (f + root); /* sigma_min^2, without cancellation */
    return small > 0.0 ? sqrt((f + root) / 2.0 / small) : INFINITY;
}

void buckc_switched_table(const BuckcSwitchedConfig *config, double load, double input_voltage,
                          BuckcSwitchedTable *table)
{
    const BuckcCircuitParameters *p = &config->parameters;
    int points = config->grid_points, i, k;
    long periods = (long)nearbyint(config->sample_period * config->switching_frequency);
    double period = 1.0 / config->switching_frequency;
    double step = 1.0 / (double)(points - 1); /* np.linspace(0, 1, points): i * step, the last = 1 */
    double a_on[4], a_off[4], inv_on[4], inv_off[4], to_y[4];
    buckc_circuit_matrix(p, load, p->switch_on_resistance, a_on);
    buckc_circuit_matrix(p, load, 0.0, a_off);
    buckc_inverse2(a_on, inv_on);
    buckc_inverse2(a_off, inv_off);
    buckc_measured_from_state(p, load, to_y);
    table->load = load;
    table->input_voltage = input_voltage;
    table->points = points;
    table->condition = 0.0;
    for (i = 0; i < points; ++i) {
        double d = i == points - 1 ? 1.0 : (double)i * step + 0.0;
        double durations[3];
        const double *mats[3], *invs[3];
        double voltages[3];
        int n_intervals;
        Affine state = identity_map(), mean, before_last, full, seen;
        double h_mat[4], h_vec[2], h_inv[4], k_mat[4], k_h[2], condition;
        double *row = table->rows[i];
        memset(&mean, 0, sizeof(mean));
        if (config->carrier == BUCKC_CARRIER_SAWTOOTH) {
            n_intervals = 2;
            mats[0] = a_on; invs[0] = inv_on; voltages[0] = input_voltage; durations[0] = d * period;
            mats[1] = a_off; invs[1] = inv_off; voltages[1] = -p->diode_forward_voltage;
            durations[1] = (1 - d) * period;
        } else {
            double off = 0.5 * (1 - d) * period;
            n_intervals = 3;
            mats[0] = a_off; invs[0] = inv_off; voltages[0] = -p->diode_forward_voltage; durations[0] = off;
            mats[1] = a_on; invs[1] = inv_on; voltages[1] = input_voltage; durations[1] = d * period;
            mats[2] = a_off; invs[2] = inv_off; voltages[2] = -p->diode_forward_voltage; durations[2] = off;
        }
        for (k = 0; k < n_intervals; ++k) {
            Affine end, integral, swept;
            interval(mats[k], invs[k], voltages[k], p->inductance, durations[k], &end, &integral);
            swept = compose(&state, &integral);
            mean.m[0] = mean.m[0] + swept.m[0];
            mean.m[1] = mean.m[1] + swept.m[1];
            mean.m[2] = mean.m[2] + swept.m[2];
            mean.m[3] = mean.m[3] + swept.m[3];
            mean.v[0] = mean.v[0] + swept.v[0];
            mean.v[1] = mean.v[1] + swept.v[1];
            state = compose(&state, &end);
        }
        for (k = 0; k < 4; ++k)
            mean.m[k] = mean.m[k] / period;
        mean.v[0] = mean.v[0] / period;
        mean.v[1] = mean.v[1] / period;
        before_last = affine_power(&state, periods - 1);
        full = compose(&before_last, &state); /* x(k+1) = F x(k) + f */
        seen = config->sensor == BUCKC_SENSOR_PERIOD_AVERAGE ? compose(&before_last, &mean) : full;
        matmul2(to_y, seen.m, h_mat);
        h_vec[0] = seen.v[0] * to_y[0] + seen.v[1] * to_y[1]; /* seen[1] @ to_y.T */
        h_vec[1] = seen.v[0] * to_y[2] + seen.v[1] * to_y[3];
        condition = condition2(h_mat);
        if (!(condition <= table->condition)) /* a larger one, or NaN: counts as singular */
            table->condition = isnan(condition) ? INFINITY : condition;
        buckc_inverse2(h_mat, h_inv);
        matmul2(full.m, h_inv, k_mat);
        matvec2(k_mat, h_vec, k_h);
        row[0] = k_mat[0]; row[1] = k_mat[1]; row[2] = k_mat[2]; row[3] = k_mat[3];
        row[4] = full.v[0] - k_h[0];
        row[5] = full.v[1] - k_h[1];
        row[6] = h_mat[0]; row[7] = h_mat[1]; row[8] = h_mat[2]; row[9] = h_mat[3];
        row[10] = h_vec[0];
        row[11] = h_vec[1];
    }
    for (i = 0; i < points; ++i) /* slopes to the next grid point, zero on the last */
        for (k = 0; k < 12; ++k)
            table->rows[i][12 + k] = i + 1 < points ? table->rows[i + 1][k] - table->rows[i][k] : 0.0;
}

void buckc_switched_cache_clear(BuckcSwitchedCache *cache)
{
    cache->n_keys = 0;
    cache->n_tables = 0;
    cache->next_table = 0;
}

const BuckcSwitchedTable *buckc_switched_cached(const BuckcSwitchedConfig *config, BuckcSwitchedCache *cache,
                                                double load, double input_voltage)
{
    double key_load = cache_key(load, 1e9), key_input = cache_key(input_voltage, 1e9);
    double use_load = load, use_input = input_voltage;
    BuckcSwitchedTable *table;
    int i, found = 0;
    for (i = 0; i < cache->n_keys; ++i) {
        const BuckcSwitchedKey *key = &cache->keys[i];
        if (key->key_load == key_load && key->key_input == key_input) {
            use_load = key->load; /* Python's entry was computed from these */
            use_input = key->input_voltage;
            found = 1;
            break;
        }
    }
    if (!found) {
        BuckcSwitchedKey *key;
        if (cache->n_keys > 256)
            cache->n_keys = 0;
        key = &cache->keys[cache->n_keys++];
        key->key_load = key_load;
        key->key_input = key_input;
        key->load = load;
        key->input_voltage = input_voltage;
    }
    for (i = 0; i < cache->n_tables; ++i) {
        table = &cache->tables[i];
        if (table->load == use_load && table->input_voltage == use_input)
            return table;
    }
    if (cache->n_tables < BUCKC_SWITCHED_TABLES) {
        table = &cache->tables[cache->n_tables++];
    } else {
        table = &cache->tables[cache->next_table];
        cache->next_table = (cache->next_table + 1) % BUCKC_SWITCHED_TABLES;
    }
    buckc_switched_table(config, use_load, use_input, table);
    return table;
}

void buckc_switched_lookup(const BuckcSwitchedTable *table, double duty, double values[12])
{
    int last = table->points - 1, index, k;
    double position = duty, fraction;
    const double *row;
    if (position < 0.0) position = 0.0; /* np.clip(duties, 0, 1) */
    if (position > 1.0) position = 1.0;
    position = position * last;
    if (!(position >= 0.0)) { /* NaN: Python would index out of range */
        for (k = 0; k < 12; ++k)
            values[k] = NAN;
        return;
    }
    index = (int)position;
    if (index > last - 1)
        index = last - 1;
    fraction = position - (double)index;
    row = table->rows[index];
    for (k = 0; k < 12; ++k)
        values[k] = row[k] + fraction * row[12 + k];
}

void buckc_switched_rollout(const BuckcSwitchedTable *table, const double y0[2], double previous_duty,
                            const double *duties, int n, const double disturbance[2], double *out)
{
    double k[12], h[12];
    double i_l = y0[0], v_o = y0[1];
    int j;
    buckc_switched_lookup(table, previous_duty, k);
    for (j = 0; j < n; ++j) {
        double s00, s01, s10, s11, c0, c1, i_next, v_next;
        buckc_switched_lookup(table, duties[j], h); /* K, kappa at d(j-1); H, h at d(j) */
        s00 = h[6] * k[0] + h[7] * k[2];
        s01 = h[6] * k[1] + h[7] * k[3];
        s10 = h[8] * k[0] + h[9] * k[2];
        s11 = h[8] * k[1] + h[9] * k[3];
        c0 = h[6] * k[4] + h[7] * k[5] + h[10];
        c1 = h[8] * k[4] + h[9] * k[5] + h[11];
        i_next = s00 * i_l;
        i_next += s01 * v_o;
        i_next += c0;
        if (i_next < 0.0) /* the diode, on the model's own prediction */
            i_next = 0.0;
        v_next = s10 * i_l;
        v_next += s11 * v_o;
        v_next += c1;
        i_next += disturbance[0];
        v_next += disturbance[1];
        out[2 * j] = i_next;
        out[2 * j + 1] = v_next;
        i_l = i_next;
        v_o = v_next;
        memcpy(k, h, sizeof(k));
    }
}

void buckc_switched_lookup_slope(const BuckcSwitchedTable *table, double duty, double values[12], double slopes[12])
{
    int last = table->points - 1, index, k;
    double position = duty, node;
    const double *row;
    buckc_switched_lookup(table, duty, values);
    if (position < 0.0) position = 0.0;
    if (position > 1.0) position = 1.0;
    position = position * last;
    if (!(position >= 0.0)) {
        for (k = 0; k < 12; ++k)
            slopes[k] = NAN;
        return;
    }
    node = floor(position + 0.5);
    if (fabs(position - node) <= BUCKC_SWITCHED_NODE_TOLERANCE && node > 0.0 && node < (double)last) {
        /* at an interior node: the mean of its two intervals' slopes (SwitchedModelPredictor.linearize) */
        const double *below = table->rows[(int)node - 1], *above = table->rows[(int)node];
        for (k = 0; k < 12; ++k)
            slopes[k] = (below[12 + k] + above[12 + k]) * 0.5 * (double)last;
        return;
    }
    index = (int)position;
    if (index > last - 1)
        index = last - 1;
    row = table->rows[index];
    for (k = 0; k < 12; ++k) /* table[index][12:] * last */
        slopes[k] = row[12 + k] * (double)last;
}

void buckc_switched_linearize(const BuckcSwitchedTable *table, const double y0[2], double previous_duty,
                              const double *duties, int n, const double disturbance[2], const int *block_of_step,
                              int n_blocks, double *out, double *jacobian)
{
    double k[12], h[12], dk[12], dh[12], sens[2][BUCKC_SENSITIVITY_DIRECTIONS];
    double i_l = y0[0], v_o = y0[1];
    int j, c;
    for (c = 0; c < n_blocks; ++c)
        sens[0][c] = sens[1][c] = 0.0;
    buckc_switched_lookup_slope(table, previous_duty, k, dk);
    for (j = 0; j < n; ++j) {
        double s00, s01, s10, s11, c0, c1, i_next, v_next, now0, now1;
        buckc_switched_lookup_slope(table, duties[j], h, dh); /* K, kappa at d(j-1); H, h at d(j) */
        s00 = h[6] * k[0] + h[7] * k[2];
        s01 = h[6] * k[1] + h[7] * k[3];
        s10 = h[8] * k[0] + h[9] * k[2];
        s11 = h[8] * k[1] + h[9] * k[3];
        c0 = h[6] * k[4] + h[7] * k[5] + h[10];
        c1 = h[8] * k[4] + h[9] * k[5] + h[11];
        i_next = s00 * i_l + s01 * v_o + c0;
        v_next = s10 * i_l + s11 * v_o + c1;
        /* the step's map differentiated in d(j) (through H, h) and in d(j-1) (through K, kappa) */
        now0 = (dh[6] * k[0] + dh[7] * k[2]) * i_l + (dh[6] * k[1] + dh[7] * k[3]) * v_o
               + dh[6] * k[4] + dh[7] * k[5] + dh[10];
        now1 = (dh[8] * k[0] + dh[9] * k[2]) * i_l + (dh[8] * k[1] + dh[9] * k[3]) * v_o
               + dh[8] * k[4] + dh[9] * k[5] + dh[11];
        for (c = 0; c < n_blocks; ++c) { /* S @ sensitivity */
            double t0 = s00 * sens[0][c] + s01 * sens[1][c];
            double t1 = s10 * sens[0][c] + s11 * sens[1][c];
            sens[0][c] = t0;
            sens[1][c] = t1;
        }
        sens[0][block_of_step[j]] += now0;
        sens[1][block_of_step[j]] += now1;
        if (j) {
            double before0 = (h[6] * dk[0] + h[7] * dk[2]) * i_l + (h[6] * dk[1] + h[7] * dk[3]) * v_o
                             + h[6] * dk[4] + h[7] * dk[5];
            double before1 = (h[8] * dk[0] + h[9] * dk[2]) * i_l + (h[8] * dk[1] + h[9] * dk[3]) * v_o
                             + h[8] * dk[4] + h[9] * dk[5];
            sens[0][block_of_step[j - 1]] += before0;
            sens[1][block_of_step[j - 1]] += before1;
        }
        if (i_next < 0.0) {
            i_next = 0.0;
            for (c = 0; c < n_blocks; ++c)
                sens[0][c] = 0.0;
        }
        i_l = i_next + disturbance[0];
        v_o = v_next + disturbance[1];
        out[2 * j] = i_l;
        out[2 * j + 1] = v_o;
        for (c = 0; c < n_blocks; ++c) {
            jacobian[(2 * j) * n_blocks + c] = sens[0][c];
            jacobian[(2 * j + 1) * n_blocks + c] = sens[1][c];
        }
        memcpy(k, h, sizeof(k));
        memcpy(dk, dh, sizeof(dk));
    }
}
