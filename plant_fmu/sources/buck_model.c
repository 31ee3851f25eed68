/* Buck converter equations and their exact piecewise solution; see buck_model.h. */
#include "buck_model.h"

#include <float.h>
#include <math.h>
#include <stdio.h>
#include <string.h>

#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif

/* A time within this fraction of a PWM period of an edge is "on" the edge. It absorbs the
 * rounding of importer clocks (t = n*h accumulates ~1e-16 relative per step). */
#define PHASE_TOLERANCE 1e-9
/* Model exchange event update: an inductor current below this counts as zero [A]; a drive
 * within this fraction of the input voltage of zero counts as reached. */
#define EVENT_CURRENT_TOLERANCE 1e-9
#define EVENT_VOLTAGE_TOLERANCE 1e-9
/* Averaged DCM integrator (Dormand-Prince 5(4) on v_C alone) tolerances. */
#define DCM_RELATIVE_TOLERANCE 1e-11
#define DCM_ABSOLUTE_TOLERANCE_VOLTAGE 1e-10 /* [V] */
#define DCM_FIRST_STEP 1e-7                  /* [s] */
#define MAX_GUARD_SAMPLES 1000000
/* A call makes at most this many consecutive regime changes without time advancing (by more than
 * a few clock resolutions) before it gives up and reports the step as failed. */
#define MAX_STALLED_TRANSITIONS 64

typedef enum { TOPOLOGY_SWITCH_ON, TOPOLOGY_SWITCH_OFF, TOPOLOGY_AVERAGED } Topology;

/* ------------------------------------------------------------------------------------------ */
/* Defaults and validation                                                                    */

void buck_set_defaults(BuckModel *m) {
    memset(m, 0, sizeof *m);
    m->p.inductance = 220e-6;
    m->p.capacitance = 10e-6;
    m->p.switching_frequency = 75e3;
    m->p.plant_mode = MODE_AVERAGED;
    m->p.pwm_carrier = CARRIER_SAWTOOTH;
    m->u.duty_cycle = 0.0;
    m->u.input_voltage = 48.0;
    m->u.load_resistance = 6.0;
    m->conduction = CONDUCTION_CONTINUOUS;
    m->pwm_period = 0;
    m->pwm_latched = false;
}

typedef struct {
    const char *name;
    double value;
    const char *unit;
    int strictly_positive;
} Rule;

const char *buck_check(const BuckModel *m, bool check_states, char *buffer, size_t size) {
    const Rule rules[] = {
        {"inductance", m->p.inductance, "H", 1},
        {"capacitance", m->p.capacitance, "F", 1},
        {"switching_frequency", m->p.switching_frequency, "Hz", 1},
        {"load_resistance", m->u.load_resistance, "Ohm", 1},
        {"input_voltage", m->u.input_voltage, "V", 0},
        {"inductor_resistance", m->p.inductor_resistance, "Ohm", 0},
        {"switch_on_resistance", m->p.switch_on_resistance, "Ohm", 0},
        {"diode_forward_voltage", m->p.diode_forward_voltage, "V", 0},
        {"capacitor_esr", m->p.capacitor_esr, "Ohm", 0},
        {"inductor_current", m->inductor_current, "A", 0},
    };
    size_t count = sizeof rules / sizeof rules[0] - (check_states ? 0 : 1); /* the state rule is last */
    for (size_t i = 0; i < count; ++i) {
        const Rule *r = &rules[i];
        int bad = !isfinite(r->value) || (r->strictly_positive ? r->value <= 0.0 : r->value < 0.0);
        if (bad) {
            snprintf(buffer, size, "%s = %g %s is invalid: expected a finite value %s 0%s", r->name,
                     r->value, r->unit, r->strictly_positive ? ">" : ">=",
                     strcmp(r->name, "inductor_current") == 0 ? " (the diode blocks reverse current)" : "");
            return buffer;
        }
    }
    if (check_states && !isfinite(m->capacitor_voltage)) {
        snprintf(buffer, size, "capacitor_voltage = %g V is invalid: expected a finite value",
                 m->capacitor_voltage);
        return buffer;
    }
    if (m->p.plant_mode != MODE_AVERAGED && m->p.plant_mode != MODE_SWITCHED) {
        snprintf(buffer, size, "plant_mode = %d is invalid: expected 0 (averaged) or 1 (switched)",
                 m->p.plant_mode);
        return buffer;
    }
    if (m->p.pwm_carrier != CARRIER_SAWTOOTH && m->p.pwm_carrier != CARRIER_TRIANGLE) {
        snprintf(buffer, size, "pwm_carrier = %d is invalid: expected 0 (sawtooth) or 1 (triangle)",
                 m->p.pwm_carrier);
        return buffer;
    }
    return NULL;
}

/* ------------------------------------------------------------------------------------------ */
/* Circuit quantities                                                                         */

/* v_o = k (v_C + ESR i_L) with k = R / (R + ESR): the output node between ESR branch and load. */
static double esr_divider(const BuckModel *m) {
    return m->u.load_resistance / (m->u.load_resistance + m->p.capacitor_esr);
}

static double output_voltage_of(const BuckModel *m, double current, double capacitor_voltage) {
    return esr_divider(m) * (capacitor_voltage + m->p.capacitor_esr * current);
}

double buck_output_voltage(const BuckModel *m) {
    return output_voltage_of(m, m->inductor_current, m->capacitor_voltage);
}

double buck_average_output_voltage(const BuckModel *m) {
    if (m->p.plant_mode == MODE_SWITCHED && m->have_average) return m->average_voltage;
    return buck_output_voltage(m);
}

double buck_average_inductor_current(const BuckModel *m) {
    if (m->p.plant_mode == MODE_SWITCHED && m->have_average) return m->average_current;
    return m->inductor_current;
}

double buck_average_load_current(const BuckModel *m) {
    if (m->p.plant_mode == MODE_SWITCHED && m->have_average) return m->average_load_current;
    return buck_output_voltage(m) / m->u.load_resistance;
}

void buck_set_load_resistance(BuckModel *m, double resistance) {
    if (m->p.plant_mode == MODE_SWITCHED && resistance != m->u.load_resistance && m->u.load_resistance > 0.0) {
        m->load_charge_before_change += (m->period_flux - m->flux_at_load_change) / m->u.load_resistance;
        m->flux_at_load_change = m->period_flux;
    }
    m->u.load_resistance = resistance;
}

double buck_applied_duty(const BuckModel *m) {
    if (m->p.plant_mode == MODE_SWITCHED && m->pwm_latched) return m->pwm_duty;
    return m->u.duty_cycle;
}

/* The switch node seen by the inductor: an ideal source behind a series resistance. */
typedef struct {
    double voltage;    /* [V] */
    double resistance; /* [Ohm] */
} SwitchNode;

static SwitchNode switch_node(const BuckModel *m, Topology topology) {
    SwitchNode node;
    double d = m->u.duty_cycle; /* used by the averaged topology only */
    switch (topology) {
    case TOPOLOGY_SWITCH_ON:
        node.voltage = m->u.input_voltage;
        node.resistance = m->p.switch_on_resistance;
        break;
    case TOPOLOGY_SWITCH_OFF:
        node.voltage = -m->p.diode_forward_voltage;
        node.resistance = 0.0;
        break;
    default: /* averaged over a period in continuous conduction (eq. 3 plus parasitics) */
        node.voltage = d * m->u.input_voltage - (1.0 - d) * m->p.diode_forward_voltage;
        node.resistance = d * m->p.switch_on_resistance;
        break;
    }
    return node;
}

/* While blocked (i_L = 0), current starts to flow once v_o falls below this voltage. */
static double unblock_threshold(const BuckModel *m, Topology topology) {
    if (topology == TOPOLOGY_SWITCH_ON || (topology == TOPOLOGY_AVERAGED && m->u.duty_cycle > 0.0))
        return m->u.input_voltage;
    return -m->p.diode_forward_voltage;
}

static double capacitor_rate(const BuckModel *m, double current, double capacitor_voltage) {
    double R = m->u.load_resistance, esr = m->p.capacitor_esr;
    return (R * current - capacitor_voltage) / ((R + esr) * m->p.capacitance);
}

/* ------------------------------------------------------------------------------------------ */
/* Closed-form flow of a linear interval: x' = A x + b, b = (b0, 0)                           */

typedef struct {
    double a11, a12, a21, a22;
    double b0;
    double eq0, eq1;       /* equilibrium -A^-1 b */
    double s;              /* trace / 2 */
    double m11, m12, m21;  /* M = A - s I (m22 = -m11); M^2 = delta I */
    double delta, w;       /* w = sqrt(|delta|) */
    double det;            /* det A > 0 */
} Flow;

static void flow_init(Flow *f, const BuckModel *m, SwitchNode node) {
    double L = m->p.inductance, C = m->p.capacitance;
    double R = m->u.load_resistance, esr = m->p.capacitor_esr;
    double k = esr_divider(m);
    f->a11 = -(node.resistance + m->p.inductor_resistance + k * esr) / L;
    f->a12 = -k / L;
    f->a21 = k / C;
    f->a22 = -1.0 / ((R + esr) * C);
    f->b0 = node.voltage / L;
    double det = f->a11 * f->a22 - f->a12 * f->a21; /* > 0 for every valid parameter set */
    f->det = det;
    f->eq0 = -f->a22 * f->b0 / det;
    f->eq1 = f->a21 * f->b0 / det;
    f->s = 0.5 * (f->a11 + f->a22);
    f->m11 = 0.5 * (f->a11 - f->a22);
    f->m12 = f->a12;
    f->m21 = f->a21;
    f->delta = f->m11 * f->m11 + f->a12 * f->a21;
    f->w = sqrt(fabs(f->delta));
}

/* x(t) = eq + exp(At)(x0 - eq), exp(At) = ec I + es M. */
static void flow_eval(const Flow *f, const double x0[2], double t, double x[2]) {
    double ec, es;
    double z = f->delta * t * t;
    if (fabs(z) < 1e-3) { /* series: robust near critical damping */
        double e = exp(f->s * t);
        ec = e * (1.0 + z / 2.0 * (1.0 + z / 12.0 * (1.0 + z / 30.0 * (1.0 + z / 56.0))));
        es = e * t * (1.0 + z / 6.0 * (1.0 + z / 20.0 * (1.0 + z / 42.0 * (1.0 + z / 72.0))));
    } else if (f->delta < 0.0) { /* under-damped: the LC ringing */
        double e = exp(f->s * t);
        ec = e * cos(f->w * t);
        es = e * sin(f->w * t) / f->w;
    } else { /* over-damped: combine exponentials first so nothing overflows */
        double e1 = exp((f->s + f->w) * t), e2 = exp((f->s - f->w) * t);
        ec = 0.5 * (e1 + e2);
        es = 0.5 * (e1 - e2) / f->w;
    }
    double d0 = x0[0] - f->eq0, d1 = x0[1] - f->eq1;
    x[0] = f->eq0 + ec * d0 + es * (f->m11 * d0 + f->m12 * d1);
    x[1] = f->eq1 + ec * d1 + es * (f->m21 * d0 - f->m11 * d1);
}

/* Integral of x(t) over [0, h] from x0 to x1 = x(h): eq h + A^-1 (x1 - x0), exact and free. */
static void flow_integral(const Flow *f, const double x0[2], const double x1[2], double h, double out[2]) {
    double d0 = x1[0] - x0[0], d1 = x1[1] - x0[1];
    out[0] = f->eq0 * h + (f->a22 * d0 - f->a12 * d1) / f->det;
    out[1] = f->eq1 * h + (-f->a21 * d0 + f->a11 * d1) / f->det;
}

/* Switched mode: add integrals of i_L and v_C over a segment to the period sums. */
static void accumulate(BuckModel *m, double current_integral, double capacitor_integral) {
    if (m->p.plant_mode != MODE_SWITCHED) return;
    m->period_charge += current_integral;
    m->period_flux += esr_divider(m) * (capacitor_integral + m->p.capacitor_esr * current_integral);
}

/* Publish the means of the period that ends now and start the next one. */
static void finish_period(BuckModel *m) {
    double span = m->time - m->period_start;
    if (span > 0.0) {
        m->average_current = m->period_charge / span;
        m->average_voltage = m->period_flux / span;
        m->average_load_current = (m->load_charge_before_change
                                   + (m->period_flux - m->flux_at_load_change) / m->u.load_resistance) / span;
        m->have_average = true;
    }
    m->period_charge = 0.0;
    m->period_flux = 0.0;
    m->load_charge_before_change = 0.0;
    m->flux_at_load_change = 0.0;
    m->period_start = m->time;
}

/* A guard g(x) = c0 x0 + c1 x1 + k: the regime holds while g >= 0. */
typedef struct {
    double c0, c1, k;
} Guard;

static double guard_value(const Guard *g, const double x[2]) {
    return g->c0 * x[0] + g->c1 * x[1] + g->k;
}

/* dg/dt along the flow, itself a linear guard. */
static Guard guard_rate(const Guard *g, const Flow *f) {
    Guard r;
    r.c0 = g->c0 * f->a11 + g->c1 * f->a21;
    r.c1 = g->c0 * f->a12 + g->c1 * f->a22;
    r.k = g->c0 * f->b0;
    return r;
}

/* With g(lo) >= 0 > g(hi), shrink the bracket (safeguarded Newton) to the resolution of the
 * absolute clock and return its upper end, where g < 0: the new regime starts there. */
static double refine_crossing(const Flow *f, const double x0[2], const Guard *g, double lo, double hi,
                              double clock) {
    Guard rate = guard_rate(g, f);
    double resolution = 4.0 * DBL_EPSILON * (clock + hi);
    double t = 0.5 * (lo + hi);
    for (int i = 0; i < 200 && hi - lo > resolution; ++i) {
        double x[2];
        flow_eval(f, x0, t, x);
        double value = guard_value(g, x);
        if (value >= 0.0) lo = t; else hi = t;
        double slope = guard_value(&rate, x);
        double next = slope != 0.0 ? t - value / slope : 0.5 * (lo + hi);
        if (!(next > lo && next < hi)) {
            next = 0.5 * (lo + hi);
        } else if (fabs(next - t) < resolution) { /* converged: probe across the root to close the bracket */
            next = value >= 0.0 ? fmin(t + resolution, hi) : fmax(t - resolution, lo);
            if (!(next > lo && next < hi)) next = 0.5 * (lo + hi);
        }
        t = next;
    }
    return hi;
}

/* Earliest t in [0, h] where g leaves g >= 0 along the flow from x0, or INFINITY. Samples are
 * at most a quarter of the ringing period apart; g has at most one extremum between two samples
 * (its rate is a damped sinusoid), so a dip below zero between samples is found from the sign
 * change of the rate. */
static double first_crossing(const Flow *f, const double x0[2], double h, const Guard *g, double clock) {
    Guard rate = guard_rate(g, f);
    long n = 1;
    if (f->delta < 0.0) {
        double spacing = 0.5 * M_PI / f->w;
        double count = ceil(h / spacing);
        n = count < 1.0 ? 1 : (count > MAX_GUARD_SAMPLES ? MAX_GUARD_SAMPLES : (long)count);
    }
    double ta = 0.0;
    double ga = guard_value(g, x0), ra = guard_value(&rate, x0);
    if (ga < 0.0) return 0.0;
    for (long i = 1; i <= n; ++i) {
        double tb = i == n ? h : h * (double)i / (double)n;
        double xb[2];
        flow_eval(f, x0, tb, xb);
        double gb = guard_value(g, xb), rb = guard_value(&rate, xb);
        if (gb < 0.0) return refine_crossing(f, x0, g, ta, tb, clock);
        if (ra < 0.0 && rb > 0.0) { /* a minimum in between: is it below zero? */
            Guard falling = {-rate.c0, -rate.c1, -rate.k};
            double tm = refine_crossing(f, x0, &falling, ta, tb, clock);
            double xm[2];
            flow_eval(f, x0, tm, xm);
            if (guard_value(g, xm) < 0.0) return refine_crossing(f, x0, g, ta, tm, clock);
        }
        ta = tb;
        ga = gb;
        ra = rb;
    }
    return INFINITY;
}

/* ------------------------------------------------------------------------------------------ */
/* Averaged model: the CCM/DCM boundary and the reduced-order (quasi-static) DCM current      */
/*
 * Within a PWM period the switch conducts for d Ts, the diode for d2 Ts, and in discontinuous
 * conduction (DCM, d + d2 < 1) nothing for the rest: the inductor current returns to zero in every
 * period. With on = Vs - vo - (R_on + DCR) i and off = V_F + vo + DCR i the voltages across L while
 * the switch and the diode conduct (resistive drops at the period-mean current i), the full-order
 * averaged model (Sun et al., IEEE TPEL 16(4), 2001) makes i a state,
 *     L di/dt = d on - d2 off,   d2 = 2 L f_sw i / (d on) - d,
 * whose linearisation in i has the time constant  tau = d on / (2 f_sw off)  (ideal parts:
 * d (Vs - vo) / (2 f_sw (V_F + vo))). At its equilibrium tau = d2 / (2 f_sw), and DCM means
 * d2 < 1 - d, so tau < Ts / 2 = 6.7 us at 75 kHz -- 1e-13 s at d = 1e-9, where the explicit
 * integrator this replaces could not follow it (a 1 ms step did not return in 100 s).
 * The output's time scales are far slower: in DCM the converter feeds the capacitor like a current
 * source with output resistance r = -(di/dvo)^-1 = 2 L f_sw ((V_F + vo) / (d (Vs + V_F)))^2 >= 2 L f_sw
 * (= 33 Ohm; DCM needs V_F + vo > d (Vs + V_F)), so vo moves with C (R || r) >= 36 us at the 4 Ohm
 * end of the workbench's loads (60 us at 6 Ohm, 2 ms at 200 Ohm), and in CCM with the LC period
 * 2 pi sqrt(L C) = 295 us. More to the point, the switched circuit has no memory here: in DCM the
 * current starts every period at zero, so its period mean is a function of d and vo in that period
 * -- the full-order model's fast mode is an artefact of averaging, a lag shorter than the period
 * the averages are taken over. So the averaged DCM current is solved algebraically: the
 * reduced-order model, di/dt = 0 in the equation above, i.e.
 *     f(i) = d^2 (on + off) on - 2 L f_sw i off = 0,
 * a quadratic in i (on, off and on + off = Vs + V_F - R_on i are linear in i and v_C); its root in
 * [0, i_b] is the period mean (ideal parts: d^2 Vs (Vs - vo) / (2 L f_sw vo), the textbook result,
 * exact for the switched circuit at constant vo; tests/test_plant_fmu.py checks it against the
 * switched plant). Only v_C is then integrated in DCM, a non-stiff scalar ODE, at a cost per
 * simulated second that does not depend on d. Nothing limits the duty any more (the former 1 ps
 * minimum on-time existed only to keep the stiff mode away from the explicit integrator).
 *
 * Boundary: CCM holds while i >= i_b = d on / (2 L f_sw) (half the ripple, the guard g below). On
 * g = 0 the DCM root equals i_b, and the sign of the CCM rate there, the margin L di/dt(i_b, v_C),
 * tells which side the current is pushed to: DCM proper while it is negative (root below i_b).
 * While it is positive but i_b rises faster than the CCM current (v_C falling), the full-order
 * model slides along the boundary for about d Ts / 2; the reduced model keeps i = i_b there (the
 * DCM regime's current is the root below the boundary, i_b above it -- continuous in v_C) and
 * returns to CCM once the CCM flow leaves the boundary upwards (sigma >= 0 below, the rate of g
 * along the CCM flow at i = i_b, in volts).
 *
 * The state i_L: in CCM a state with the closed-form flow. In DCM it is algebraic, i_L = i_q(v_C):
 * entering DCM from CCM below the boundary (margin < 0), i_L drops from i_b to the root (the
 * sub-period decay the full-order model would resolve); any input change re-settles it the same
 * way (a duty step up out of DCM starts CCM at i_b). v_C, the slow state, is continuous throughout.
 * Model exchange keeps i_L a continuous state in DCM too, with the chain-rule derivative
 * di_q/dv_C * dv_C/dt, so it tracks the root to the solver's tolerance, while dv_C/dt uses the
 * root itself (no stiffness); each regime change is an event that resets i_L (states changed).
 * Derivatives, event indicators and co-simulation all call the functions below. */

/* CCM holds while g(i_L, v_C) = i_L - d on(i_L, v_C) / (2 L f_sw) >= 0 (half the ripple). */
static Guard continuous_conduction_guard(const BuckModel *m) {
    double q = m->u.duty_cycle / (2.0 * m->p.inductance * m->p.switching_frequency);
    double k = esr_divider(m);
    Guard g;
    g.c0 = 1.0 + q * (m->p.switch_on_resistance + m->p.inductor_resistance + k * m->p.capacitor_esr);
    g.c1 = q * k;
    g.k = -q * m->u.input_voltage;
    return g;
}

/* i_b(v_C): the current on the boundary g = 0 [A]. */
static double boundary_current(const BuckModel *m, double capacitor_voltage) {
    Guard g = continuous_conduction_guard(m);
    return -(g.c1 * capacitor_voltage + g.k) / g.c0;
}

/* L di_L/dt of the averaged CCM model (eq. 3 plus parasitics) [V]. */
static double ccm_drive(const BuckModel *m, double current, double capacitor_voltage) {
    SwitchNode node = switch_node(m, TOPOLOGY_AVERAGED);
    return node.voltage - (node.resistance + m->p.inductor_resistance) * current
           - output_voltage_of(m, current, capacitor_voltage);
}

/* The CCM drive on the boundary [V]: < 0 pushes the current below i_b (DCM). */
static double boundary_margin(const BuckModel *m, double capacitor_voltage) {
    return ccm_drive(m, boundary_current(m, capacitor_voltage), capacitor_voltage);
}

/* L / g.c0 times dg/dt along the CCM flow at i_L = i_b(v_C) [V]: >= 0 when the CCM current leaves
 * the boundary upwards. */
static double boundary_departure(const BuckModel *m, double capacitor_voltage) {
    Guard g = continuous_conduction_guard(m);
    double ib = boundary_current(m, capacitor_voltage);
    return ccm_drive(m, ib, capacitor_voltage)
           + m->p.inductance * g.c1 / g.c0 * capacitor_rate(m, ib, capacitor_voltage);
}

/* The DCM regime's current i_q(v_C) [A] and its slope di_q/dv_C [A/V]: the root of f below the
 * boundary while the margin is negative, i_b on and above it, 0 once vo reaches Vs. */
static double dcm_current(const BuckModel *m, double capacitor_voltage, double *slope) {
    double d = m->u.duty_cycle, k = esr_divider(m);
    double ib = boundary_current(m, capacitor_voltage);
    *slope = 0.0;
    if (ib <= 0.0) return 0.0; /* vo >= Vs (or d = 0): no current */
    if (!(ccm_drive(m, ib, capacitor_voltage) < 0.0)) { /* on or above the boundary */
        Guard g = continuous_conduction_guard(m);
        *slope = -g.c1 / g.c0;
        return ib;
    }
    double ron = m->p.switch_on_resistance, dcr = m->p.inductor_resistance, esr = m->p.capacitor_esr;
    double a0 = m->u.input_voltage + m->p.diode_forward_voltage, a1 = ron; /* on + off = a0 - a1 i */
    double b0 = m->u.input_voltage - k * capacitor_voltage, b1 = ron + dcr + k * esr; /* on = b0 - b1 i */
    double c0 = m->p.diode_forward_voltage + k * capacitor_voltage, c1 = dcr + k * esr; /* off = c0 + c1 i */
    double p = 2.0 * m->p.inductance * m->p.switching_frequency, d2 = d * d;
    /* f(i) = A i^2 + B i + C0 with f(0) = C0 > 0 > f(i_b): its smaller positive root, in the form
     * that neither cancels (B < 0 there) nor divides by A (A = 0 for ideal parts) */
    double A = d2 * a1 * b1 - p * c1;
    double B = -d2 * (a0 * b1 + a1 * b0) - p * c0;
    double C0 = d2 * a0 * b0;
    double root = 2.0 * C0 / (-B + sqrt(fmax(B * B - 4.0 * A * C0, 0.0)));
    double i = fmin(fmax(root, 0.0), ib);
    double dfdi = 2.0 * A * i + B;                          /* < 0 at this root */
    double dfdv = -k * (d2 * (a0 - a1 * i) + p * i);        /* df/dv_C */
    *slope = dfdi < 0.0 ? -dfdv / dfdi : 0.0;
    return i;
}

/* dv_C/dt in the DCM regime [V/s]. */
static double dcm_rate(const BuckModel *m, double capacitor_voltage) {
    double slope;
    return capacitor_rate(m, dcm_current(m, capacitor_voltage, &slope), capacitor_voltage);
}

/* The DCM regime ends (CCM resumes) once the margin and the departure are both >= -tolerance. */
static int dcm_ends(const BuckModel *m, double capacitor_voltage, double tolerance) {
    return boundary_margin(m, capacitor_voltage) >= -tolerance
           && boundary_departure(m, capacitor_voltage) >= -tolerance;
}

/* Enter CCM on the boundary: i_L = i_b, nudged up by rounding until g >= 0, so the CCM flow does
 * not see the crossing it started from. */
static void enter_ccm_on_boundary(BuckModel *m) {
    Guard g = continuous_conduction_guard(m);
    double i = fmax(boundary_current(m, m->capacitor_voltage), 0.0);
    for (int n = 0; n < 8; ++n) {
        double x[2] = {i, m->capacitor_voltage};
        if (guard_value(&g, x) >= 0.0) break;
        i = nextafter(i, INFINITY);
    }
    m->inductor_current = i;
    m->conduction = CONDUCTION_CONTINUOUS;
}

/* Averaged mode, not blocked: decide the regime for the present state and inputs and settle i_L
 * where the regime makes it algebraic. A CCM current on or above the boundary keeps CCM (i_L a
 * state); below it, the DCM regime -- unless the CCM flow is pushed up there (dcm_ends), then CCM
 * starting on the boundary. Co-simulation passes zero tolerances; model exchange's event update
 * passes its own, since the solver stops on a crossing, where an indicator is zero to rounding: a
 * CCM current within current_tolerance above the boundary counts as on it, a DCM margin within
 * voltage_tolerance below zero as reached. */
static void settle_averaged(BuckModel *m, double current_tolerance, double voltage_tolerance) {
    double vc = m->capacitor_voltage;
    if (m->conduction == CONDUCTION_CONTINUOUS) {
        Guard g = continuous_conduction_guard(m);
        double x[2] = {m->inductor_current, vc};
        /* above the boundary: CCM, i_L a state (a zero current with d > 0 sits on a boundary that
         * vo = Vs has shrunk to zero: the DCM regime's, where the switch drives current again) */
        if (guard_value(&g, x) >= current_tolerance && (m->inductor_current > 0.0 || m->u.duty_cycle == 0.0)) return;
        if (dcm_ends(m, vc, 0.0)) { /* on or below it but pushed up: CCM resumes on the boundary */
            if (guard_value(&g, x) < 0.0) enter_ccm_on_boundary(m);
            return;
        }
    } else if (dcm_ends(m, vc, voltage_tolerance)) {
        enter_ccm_on_boundary(m);
        return;
    }
    double slope;
    m->inductor_current = dcm_current(m, vc, &slope);
    m->conduction = CONDUCTION_DISCONTINUOUS;
}

/* Current starts to flow again after the diode blocked (i_L = 0). */
static void leave_blocked(BuckModel *m, Topology topology, double current_tolerance, double voltage_tolerance) {
    m->inductor_current = 0.0;
    m->conduction = CONDUCTION_CONTINUOUS;
    if (topology == TOPOLOGY_AVERAGED) settle_averaged(m, current_tolerance, voltage_tolerance);
}

/* ------------------------------------------------------------------------------------------ */
/* Averaged DCM: Dormand-Prince 5(4) on v_C with error control                                */

/* One step; returns the scaled error norm (<= 1 is acceptable). */
static double dopri_step(const BuckModel *m, double x, double h, double *out) {
    static const double c[7][6] = {
        {0},
        {1.0 / 5.0},
        {3.0 / 40.0, 9.0 / 40.0},
        {44.0 / 45.0, -56.0 / 15.0, 32.0 / 9.0},
        {19372.0 / 6561.0, -25360.0 / 2187.0, 64448.0 / 6561.0, -212.0 / 729.0},
        {9017.0 / 3168.0, -355.0 / 33.0, 46732.0 / 5247.0, 49.0 / 176.0, -5103.0 / 18656.0},
        {35.0 / 384.0, 0.0, 500.0 / 1113.0, 125.0 / 192.0, -2187.0 / 6784.0, 11.0 / 84.0},
    };
    static const double e[7] = {71.0 / 57600.0, 0.0, -71.0 / 16695.0, 71.0 / 1920.0,
                                -17253.0 / 339200.0, 22.0 / 525.0, -1.0 / 40.0};
    double k[7];
    k[0] = dcm_rate(m, x);
    for (int s = 1; s < 7; ++s) {
        double y = x;
        for (int j = 0; j < s; ++j) y += h * c[s][j] * k[j];
        if (s == 6) *out = y;
        k[s] = dcm_rate(m, y);
    }
    double err = 0.0;
    for (int s = 0; s < 7; ++s) err += h * e[s] * k[s];
    double scale = DCM_ABSOLUTE_TOLERANCE_VOLTAGE + DCM_RELATIVE_TOLERANCE * fmax(fabs(x), fabs(*out));
    return fabs(err) / scale;
}

/* Integrate the DCM regime (v_C; i_L = i_q(v_C)) to t_end, or until CCM resumes. */
static void advance_discontinuous(BuckModel *m, double t_end) {
    double h = m->dcm_step > 0.0 ? m->dcm_step : DCM_FIRST_STEP;
    double min_step = 64.0 * DBL_EPSILON * fmax(fabs(t_end), 1e-9);
    double slope;
    while (m->time < t_end) {
        double remaining = t_end - m->time;
        int last = h >= remaining;
        double step = last ? remaining : h;
        double x = m->capacitor_voltage, xn;
        double err = dopri_step(m, x, step, &xn);
        double factor = err > 0.0 ? fmin(5.0, fmax(0.2, 0.9 * pow(err, -0.2))) : 5.0;
        if (err > 1.0 && step > min_step) {
            h = step * factor;
            continue;
        }
        if (dcm_ends(m, xn, 0.0)) { /* CCM resumes within this step: locate it by bisection */
            double lo = 0.0, hi = step;
            double resolution = 4.0 * DBL_EPSILON * (fabs(t_end) + step);
            while (hi - lo > resolution) {
                double mid = 0.5 * (lo + hi), xm;
                dopri_step(m, x, mid, &xm);
                if (dcm_ends(m, xm, 0.0)) {
                    hi = mid;
                    xn = xm;
                } else {
                    lo = mid;
                }
            }
            m->time = hi == remaining ? t_end : m->time + hi;
            m->capacitor_voltage = xn;
            enter_ccm_on_boundary(m);
            m->dcm_step = h;
            return;
        }
        m->time = last ? t_end : m->time + step;
        m->capacitor_voltage = xn;
        m->inductor_current = dcm_current(m, xn, &slope);
        if (!last || factor < 1.0) h = step * factor;
    }
    m->dcm_step = h;
}

/* ------------------------------------------------------------------------------------------ */
/* Piecewise-exact advance with a fixed circuit topology                                      */

static bool advance_topology(BuckModel *m, Topology topology, double t_end) {
    Flow flow;
    int flow_ready = 0;
    int stalls = 0;
    while (m->time < t_end && stalls < MAX_STALLED_TRANSITIONS) {
        double start = m->time;
        double h = t_end - m->time;
        if (m->conduction == CONDUCTION_BLOCKED) {
            /* i_L = 0: v_C discharges through R + ESR until v_o falls below the threshold. */
            double tau = (m->u.load_resistance + m->p.capacitor_esr) * m->p.capacitance;
            double threshold = unblock_threshold(m, topology);
            double vo = esr_divider(m) * m->capacitor_voltage;
            m->inductor_current = 0.0;
            if (threshold - vo > 0.0) {
                leave_blocked(m, topology, 0.0, 0.0);
            } else if (threshold - vo * exp(-h / tau) > 0.0) {
                double dt = tau * log(vo / threshold); /* same sign, |vo| > |threshold| here */
                if (!(dt >= 0.0 && dt < h)) dt = h;
                double v0 = m->capacitor_voltage;
                m->capacitor_voltage *= exp(-dt / tau);
                /* land exactly on the threshold, never a rounding error above it: the drive is >= 0 */
                m->capacitor_voltage = fmin(m->capacitor_voltage, threshold / esr_divider(m));
                accumulate(m, 0.0, tau * (v0 - m->capacitor_voltage));
                m->time = dt < h ? m->time + dt : t_end;
                leave_blocked(m, topology, 0.0, 0.0);
            } else {
                double v0 = m->capacitor_voltage;
                m->capacitor_voltage *= exp(-h / tau);
                accumulate(m, 0.0, tau * (v0 - m->capacitor_voltage));
                m->time = t_end;
            }
        } else if (m->conduction == CONDUCTION_CONTINUOUS) {
            if (!flow_ready) {
                flow_init(&flow, m, switch_node(m, topology));
                flow_ready = 1;
            }
            double x0[2] = {m->inductor_current, m->capacitor_voltage}, x[2];
            Guard positive_current = {1.0, 0.0, 0.0};
            double t_block = first_crossing(&flow, x0, h, &positive_current, fabs(start));
            double t_dcm = INFINITY;
            if (topology == TOPOLOGY_AVERAGED) {
                Guard ccm = continuous_conduction_guard(m);
                t_dcm = first_crossing(&flow, x0, h, &ccm, fabs(start));
            }
            double dt = fmin(h, fmin(t_block, t_dcm));
            flow_eval(&flow, x0, dt, x);
            double integral[2];
            flow_integral(&flow, x0, x, dt, integral);
            accumulate(m, integral[0], integral[1]);
            m->inductor_current = x[0];
            m->capacitor_voltage = x[1];
            m->time = dt < h ? m->time + dt : t_end;
            if (t_block <= dt && t_block <= t_dcm) {
                m->inductor_current = 0.0;
                m->conduction = CONDUCTION_BLOCKED;
            } else if (t_dcm <= dt) {
                settle_averaged(m, 0.0, 0.0); /* g < 0 here: the DCM regime, or CCM on the boundary */
            }
        } else {
            advance_discontinuous(m, t_end);
        }
        double resolution = 64.0 * DBL_EPSILON * fmax(fabs(t_end), 1e-9);
        stalls = m->time - start > resolution ? 0 : stalls + 1;
    }
    return m->time >= t_end; /* false: regimes kept alternating without progress (never jump ahead) */
}

/* ------------------------------------------------------------------------------------------ */
/* PWM                                                                                        */

static long long period_index(const BuckModel *m, double t) {
    return (long long)floor(t * m->p.switching_frequency + PHASE_TOLERANCE);
}

/* Latch the duty for the period containing t. A duty written at the very instant a period
 * starts applies to that period, whichever of the edge and the write the importer handled first. */
static void latch_period(BuckModel *m, double t) {
    long long k = period_index(m, t);
    int at_period_start = fabs(t * m->p.switching_frequency - (double)k) < PHASE_TOLERANCE;
    if (!m->pwm_latched || k != m->pwm_period || at_period_start) {
        m->pwm_latched = true;
        m->pwm_period = k;
        m->pwm_duty = m->u.duty_cycle;
    }
}

/* Switch state at time t in the latched period and the time of the next PWM edge. */
static int pwm_switch_on(const BuckModel *m, double t, double *next_edge) {
    double fsw = m->p.switching_frequency, d = m->pwm_duty;
    double k = (double)m->pwm_period;
    double on_start = m->p.pwm_carrier == CARRIER_TRIANGLE ? 0.5 * (1.0 - d) : 0.0;
    double on_end = m->p.pwm_carrier == CARRIER_TRIANGLE ? 0.5 * (1.0 + d) : d;
    double phase = t * fsw - k;
    if (phase < on_start - PHASE_TOLERANCE) {
        *next_edge = (k + on_start) / fsw;
        return 0;
    }
    if (phase < on_end - PHASE_TOLERANCE) {
        *next_edge = (k + on_end) / fsw;
        return 1;
    }
    *next_edge = (k + 1.0) / fsw;
    return 0;
}

static bool advance_switched(BuckModel *m, double t_end) {
    double edge_tolerance = PHASE_TOLERANCE / m->p.switching_frequency;
    while (m->time < t_end) {
        latch_period(m, m->time);
        double edge;
        int on = pwm_switch_on(m, m->time, &edge);
        /* An edge within tolerance of t_end belongs to the next step, so the importer's new
         * duty is latched when the next period starts. */
        double segment_end = edge > t_end - edge_tolerance ? t_end : edge;
        if (!advance_topology(m, on ? TOPOLOGY_SWITCH_ON : TOPOLOGY_SWITCH_OFF, segment_end)) return false;
        double period_end = ((double)m->pwm_period + 1.0) / m->p.switching_frequency;
        if (fabs(m->time - period_end) <= edge_tolerance) finish_period(m);
    }
    return true;
}

/* ------------------------------------------------------------------------------------------ */
/* Public entry points                                                                        */

static Topology current_topology(const BuckModel *m) {
    if (m->p.plant_mode == MODE_AVERAGED) return TOPOLOGY_AVERAGED;
    return m->switch_on ? TOPOLOGY_SWITCH_ON : TOPOLOGY_SWITCH_OFF;
}

void buck_start(BuckModel *m, double t) {
    m->time = t;
    m->pwm_period = 0;
    m->pwm_latched = false;
    m->dcm_step = 0.0;
    m->period_charge = 0.0;
    m->period_flux = 0.0;
    m->load_charge_before_change = 0.0;
    m->flux_at_load_change = 0.0;
    m->period_start = t;
    m->have_average = false;
    if (m->p.plant_mode == MODE_SWITCHED) {
        double edge;
        latch_period(m, t);
        m->switch_on = pwm_switch_on(m, t, &edge) != 0;
    }
    Topology topology = current_topology(m);
    double vo = esr_divider(m) * m->capacitor_voltage;
    if (m->inductor_current <= 0.0 && unblock_threshold(m, topology) - vo <= 0.0) {
        m->inductor_current = 0.0;
        m->conduction = CONDUCTION_BLOCKED;
    } else {
        m->conduction = CONDUCTION_CONTINUOUS;
        if (topology == TOPOLOGY_AVERAGED) settle_averaged(m, 0.0, 0.0);
    }
}

bool buck_advance(BuckModel *m, double t_end) {
    bool ok;
    if (m->p.plant_mode == MODE_SWITCHED) {
        ok = advance_switched(m, t_end);
    } else {
        /* inputs may have changed since the last step: re-decide CCM versus DCM */
        if (m->conduction != CONDUCTION_BLOCKED) settle_averaged(m, 0.0, 0.0);
        ok = advance_topology(m, TOPOLOGY_AVERAGED, t_end);
    }
    if (ok) m->time = t_end;
    return ok;
}

void buck_derivatives(const BuckModel *m, double dx[BUCK_STATES]) {
    double iL = m->inductor_current, vC = m->capacitor_voltage;
    int switched = m->p.plant_mode == MODE_SWITCHED;
    if (m->conduction == CONDUCTION_BLOCKED) {
        dx[0] = 0.0;
        dx[1] = capacitor_rate(m, 0.0, vC);
        dx[2] = 0.0;
        dx[3] = switched ? output_voltage_of(m, 0.0, vC) : 0.0;
        return;
    }
    dx[2] = switched ? iL : 0.0;
    dx[3] = switched ? output_voltage_of(m, iL, vC) : 0.0;
    if (m->conduction == CONDUCTION_DISCONTINUOUS) { /* averaged DCM: i_L = i_q(v_C), see above */
        double slope;
        double current = dcm_current(m, vC, &slope);
        dx[1] = capacitor_rate(m, current, vC);
        dx[0] = slope * dx[1];
        return;
    }
    SwitchNode node = switch_node(m, current_topology(m));
    double vo = output_voltage_of(m, iL, vC);
    dx[0] = (node.voltage - (node.resistance + m->p.inductor_resistance) * iL - vo) / m->p.inductance;
    dx[1] = capacitor_rate(m, iL, vC);
}

void buck_event_indicators(const BuckModel *m, double z[2]) {
    if (m->conduction == CONDUCTION_BLOCKED) {
        z[0] = unblock_threshold(m, current_topology(m)) - esr_divider(m) * m->capacitor_voltage;
        z[1] = 1.0;
        return;
    }
    if (m->conduction == CONDUCTION_DISCONTINUOUS) {
        /* the margin's zero is the kink between DCM proper and the boundary; CCM resumes once both
         * it and the departure are >= 0 */
        z[0] = boundary_margin(m, m->capacitor_voltage);
        z[1] = boundary_departure(m, m->capacitor_voltage);
        return;
    }
    z[0] = m->inductor_current;
    if (m->p.plant_mode == MODE_AVERAGED) {
        Guard g = continuous_conduction_guard(m); /* the CCM/DCM boundary */
        double x[2] = {m->inductor_current, m->capacitor_voltage};
        z[1] = guard_value(&g, x);
    } else {
        z[1] = 1.0;
    }
}

bool buck_update_discrete(BuckModel *m, double *next_event_time, bool *next_event_defined) {
    bool states_changed = false;
    *next_event_defined = false;
    if (m->p.plant_mode == MODE_SWITCHED) {
        double fsw = m->p.switching_frequency;
        double phase = m->time * fsw - floor(m->time * fsw + PHASE_TOLERANCE);
        if (fabs(phase) < PHASE_TOLERANCE && m->time - m->period_start > PHASE_TOLERANCE / fsw) {
            finish_period(m); /* the period integrals are states: they restart at zero */
            states_changed = true;
        }
        latch_period(m, m->time);
        m->switch_on = pwm_switch_on(m, m->time, next_event_time) != 0;
        *next_event_defined = true;
    }
    Topology topology = current_topology(m);
    double drive = unblock_threshold(m, topology) - esr_divider(m) * m->capacitor_voltage;
    double voltage_tolerance = EVENT_VOLTAGE_TOLERANCE * fmax(1.0, fabs(m->u.input_voltage));
    double before = m->inductor_current;
    if (m->conduction == CONDUCTION_BLOCKED) {
        /* The solver stops on the crossing itself, where the drive is zero to rounding; waiting for
         * it to turn positive would wait forever (the indicator no longer changes sign). */
        if (drive > -voltage_tolerance) leave_blocked(m, topology, EVENT_CURRENT_TOLERANCE, voltage_tolerance);
    } else if (m->inductor_current <= EVENT_CURRENT_TOLERANCE && drive <= 0.0) {
        m->conduction = CONDUCTION_BLOCKED;
        m->inductor_current = 0.0;
    } else if (topology == TOPOLOGY_AVERAGED) {
        settle_averaged(m, EVENT_CURRENT_TOLERANCE, voltage_tolerance);
    } else if (m->inductor_current < 0.0) {
        m->inductor_current = 0.0;
    }
    return states_changed || m->inductor_current != before;
}
