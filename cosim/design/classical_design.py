"""The classical baselines a power-electronics engineer would design, each by a stated method from
the averaged small-signal model (:mod:`controllers.small_signal`), with the sensor's sampling and
the one-sample computation delay in that model.

* :func:`design_current_mode` -- average-current-mode control (:mod:`controllers.current_mode`).
  Method: loop shaping of each PI at the nominal operating point. The inner (current) loop's
  crossover is the target fc_i (fsw/10) or, where a phase margin >= the target cannot be had there,
  the highest frequency below it where it can; the PI's zero sits at fc/m with the smallest m of
  (10, 8, 6, 5, 4, 3, 2.5, 2) that keeps the margins (the most integral action); the gain puts
  |L(fc)| = 1 exactly on the discrete model. The outer (voltage) loop is designed the same way on
  the plant with the inner loop closed, its crossover target a fifth of the inner's. The current
  limit is the outer loop's saturation (an input: the inductor's rating).
* :func:`design_type_iii` -- a voltage-mode Type-III compensator (integrator, two zeros, two poles)
  by Venable's K-factor method: at a candidate crossover fc the phase boost needed for the target
  phase margin over the plant's phase (delays included) is b = PM - 90 - angle(P(fc)); K =
  tan^2(b/4 + 45 deg) places the double zero at fc/sqrt(K) and the double pole at fc sqrt(K); the
  compensator is discretised by Tustin prewarped at fc, and its gain sets |L(fc)| = 1 on the exact
  discrete model. The crossover is the highest candidate from the target (fsw/10) down whose exact
  margins meet both targets at the nominal point and whose loop is stable at every corner of the
  envelope (a Type-III tuned at 6 Ohm must not ring itself unstable at 100 Ohm).

Candidates are searched on a log grid from the target crossover down to a twentieth of it; each is
checked on the exact discrete loop (:class:`controllers.small_signal.Loop`), not on the
approximation the placement used. Each design's gains, crossovers and margins -- at the nominal
point and at the corners of the envelope -- are written by :func:`write_design` to
``results/tuning/<kind>__<pipeline>.json``; :func:`envelope_margins` gives the same for any linear
controller (the reproduction adds the nominal and the envelope PI).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.signal import bilinear

from controllers.compensator import CompensatorCoefficients, CompensatorController
from controllers.current_mode import CurrentModeController, CurrentModeGains
from controllers.predictors import CircuitParameters
from controllers.small_signal import (
    CURRENT,
    DUTY,
    VOLTAGE,
    Loop,
    OperatingPoint,
    delay_polynomial,
    discrete_plant,
    margins,
    pi_polynomials,
    pmul,
    unit_circle,
)
from cosim.base.files import atomic_write_text, json_text
from cosim.fmi.binding import BUILTIN_SPEC

METHOD_CURRENT_MODE = (
    "average-current-mode control: inner PI crossover at the target (fsw/10) or the highest frequency below it with "
    "PM and GM at their targets, zero at fc/m (smallest m of 10 ... 2 that keeps them), |L(fc)| = 1 on the exact "
    "discrete small-signal model (ZOH, averaging sensor, computation delay); outer PI the same on the plant with the "
    "inner loop closed, target a fifth of the inner crossover; current limit as the outer saturation")
METHOD_TYPE_III = {
    "pole-zero": "Type-III voltage mode by pole-zero placement (double zero on the LC resonance, poles on the ESR zero "
                 "or the Nyquist frequency and on the Nyquist frequency), Tustin prewarped at fc, |L(fc)| = 1 on the "
                 "exact discrete model; fc the highest candidate from fsw/10 down meeting PM and GM at the nominal "
                 "point with a stable loop at every envelope corner",
    "k-factor": "Type-III voltage mode by the K-factor method (boost = PM - 90 - plant phase at fc, K = "
                "tan^2(boost/4 + 45), double zero at fc/sqrt(K), double pole at fc sqrt(K)), Tustin prewarped at fc, "
                "|L(fc)| = 1 on the exact discrete model; fc the highest candidate from fsw/10 down meeting PM and GM "
                "at the nominal point with a stable loop at every envelope corner"}
ZERO_RATIOS = (10.0, 8.0, 6.0, 5.0, 4.0, 3.0, 2.5, 2.0, 1.5, 1.0, 0.7, 0.5, 0.35, 0.25)
MAX_BOOST_DEG = 170.0
#: extra phase margin [deg] the current-mode design gives its inner loop, tried in turn
INNER_MARGIN_STEPS = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0)
CANDIDATES = 120  # crossover candidates per design, log-spaced from the target down to a twentieth


@dataclass(frozen=True)
class Envelope:
    """The operating envelope a design is checked over (its corners); the defaults are the paper study's (Table II's
    envelope), a plant's come from its converter spec (:func:`targets_for`)."""

    references: tuple[float, float] = BUILTIN_SPEC.output_voltage_range  # [V]
    loads: tuple[float, float] = BUILTIN_SPEC.load_resistance_range  # [Ohm]
    supplies: tuple[float, float] = BUILTIN_SPEC.input_voltage_range  # [V]

    def corners(self) -> list[OperatingPoint]:
        return [OperatingPoint(v, r, s) for v in self.references for r in self.loads for s in self.supplies]


def ccm_boundary_load(parameters: CircuitParameters, op: OperatingPoint, switching_frequency: float) -> float:
    """The lightest load [Ohm] at which ``op`` stays in CCM: 2 L fsw / (1 - D) (the ripple's valley at 0)."""
    duty = op.output_voltage / op.input_voltage
    return 2 * parameters.inductance * switching_frequency / (1 - duty)


def design_corners(parameters: CircuitParameters, targets: "DesignTargets") -> list[tuple[OperatingPoint, bool]]:
    """The envelope's corners where the averaged CCM model holds: a corner beyond the CCM boundary (the
    light-load ones) moves to 0.95 x the boundary load -- the lightest-damped point the CCM model
    describes; beyond it the converter is in DCM, where the LC resonance is gone. (point, moved)."""
    out = []
    for op in targets.envelope.corners():
        boundary = 0.95 * ccm_boundary_load(parameters, op, targets.switching_frequency)
        out.append((OperatingPoint(op.output_voltage, boundary, op.input_voltage), True)
                   if op.load_resistance > boundary else (op, False))
    return out


ENVELOPE = Envelope()


@dataclass(frozen=True)
class DesignTargets:
    """What the designs are asked for (SI units)."""

    sample_period: float = BUILTIN_SPEC.switching_period  # [s] one sample per PWM period
    switching_frequency: float = BUILTIN_SPEC.switching_frequency  # [Hz]
    inner_crossover_fraction: float = 0.1  # current loop (and Type-III) crossover target, of fsw
    outer_crossover_ratio: float = 0.2  # the voltage loop's target, of the inner loop's achieved crossover
    phase_margin_deg: float = 60.0  # every loop: the current-mode controller's inner and outer, the Type-III's
    gain_margin_db: float = 6.0
    cascade_phase_margin_deg: float = 45.0  # the current-mode cascade broken at the duty (both loops closed)
    computation_delay: int = 1  # [samples]
    sensor: str = "average"  # what the controller reads (controllers.small_signal.SENSORS)
    modulator: str = "trailing-edge"  # how the duty reaches the circuit (controllers.small_signal.MODULATORS)
    operating_point: OperatingPoint = OperatingPoint(BUILTIN_SPEC.output_voltage, BUILTIN_SPEC.load_resistance,
                                                     BUILTIN_SPEC.input_voltage)
    current_limit: float = BUILTIN_SPEC.inductor_current_limit  # [A] the current-mode controller's inductor-current limit
    duty_limits: tuple[float, float] = (0.0, 1.0)
    envelope: Envelope = ENVELOPE

    @property
    def crossover_target_hz(self) -> float:
        return self.inner_crossover_fraction * self.switching_frequency


@dataclass
class Design:
    """A designed controller and the numbers that justify it."""

    kind: str
    controller: object
    method: str
    targets: DesignTargets
    loops: dict  # loop name -> Margins.describe() at the nominal point
    envelope: list = field(default_factory=list)  # per corner: the operating point and the loops' margins
    notes: list = field(default_factory=list)

    def phase_margin_target(self, loop: str) -> float:
        """The phase margin a loop must keep: the cascade broken at the duty has its own target."""
        cascade = self.kind == "current-mode" and loop == "duty"
        return self.targets.cascade_phase_margin_deg if cascade else self.targets.phase_margin_deg

    def meets(self) -> bool:
        """Every loop at the nominal point meets its phase- and gain-margin targets and is stable."""
        t = self.targets
        return all(m["closed_loop_stable"] and m["phase_margin_deg"] is not None
                   and m["phase_margin_deg"] >= self.phase_margin_target(loop) - 1e-6
                   and (m["gain_margin_db"] is None or m["gain_margin_db"] >= t.gain_margin_db - 1e-6)
                   for loop, m in self.loops.items())

    def describe(self) -> dict:
        targets = asdict(self.targets)
        return {"kind": self.kind, "method": self.method, "controller": self.controller.describe(),
                "targets": targets, "crossover_target_hz": self.targets.crossover_target_hz,
                "nominal_point": asdict(self.targets.operating_point), "loops": self.loops,
                "meets_targets": self.meets(), "envelope_corners": self.envelope, "notes": self.notes}


def _loop_ok(m, targets: DesignTargets, fc: float) -> bool:
    return (m.stable and math.isfinite(m.phase_margin_deg) and m.phase_margin_deg >= targets.phase_margin_deg
            and m.gain_margin_db >= targets.gain_margin_db
            and math.isfinite(m.crossover_hz) and abs(m.crossover_hz / fc - 1) < 0.05)


def _candidates(target: float) -> np.ndarray:
    return np.geomspace(target, target / 20, CANDIDATES)


def _pi_search(shape_of, characteristic_of, target: float, targets: DesignTargets, ts: float, also=None):
    """The PI (kp, ki) for the loop ``shape_of(kp, ki)(z)`` (linear in kp for a fixed zero) by the
    crossover search of the module docstring; ``characteristic_of(kp, ki)`` its closed-loop polynomial;
    ``also(kp, ki)``: a further check a candidate must pass. Returns (kp, ki, fc, margins) or None."""
    for fc in _candidates(target):
        zc = unit_circle(fc, ts)
        for ratio in ZERO_RATIOS[::-1]:  # the highest zero (most integral action) first
            wz = 2 * math.pi * fc / ratio
            unit = abs(shape_of(1.0, wz)(zc))
            if not math.isfinite(unit) or unit == 0:
                continue
            kp = 1.0 / unit
            ki = kp * wz
            loop = shape_of(kp, ki)
            stable = bool(np.all(np.abs(np.roots(characteristic_of(kp, ki))) < 1 - 1e-9))
            m = margins(loop, ts, stable)
            if _loop_ok(m, targets, fc) and (also is None or also(kp, ki)):
                return kp, ki, fc, m
    return None


def _current_mode_parts(plant, kp_i, ki_i, kp_v, ki_v, delay, vs, ts):
    """Polynomials of the cascade: the inner loop gain L_i, and the outer loop gain with the inner closed."""
    ci, integ = pi_polynomials(kp_i, ki_i, ts)
    cv, _ = pi_polynomials(kp_v, ki_v, ts)
    kden = vs * pmul(delay_polynomial(delay), integ)  # inner: d = (ci / kden) (i_ref - iL)
    num = plant.num
    inner_char = np.polyadd(pmul(plant.den, kden), pmul(ci, num[CURRENT][DUTY]))

    def inner(z):
        return np.polyval(ci, z) * plant.response(CURRENT, DUTY, z) / np.polyval(kden, z)

    def outer(z):  # i_ref -> vo with the inner loop closed, times the outer PI
        to_voltage = np.polyval(ci, z) * plant.response(VOLTAGE, DUTY, z) / np.polyval(kden, z) / (1 + inner(z))
        return np.polyval(cv, z) / np.polyval(integ, z) * to_voltage

    outer_char = padd_char(plant, ci, cv, integ, kden)
    return inner, outer, inner_char, outer_char


def padd_char(plant, ci, cv, integ, kden):
    """Closed-loop polynomial of the whole cascade (both loops closed)."""
    num = plant.num
    return np.polyadd(np.polyadd(pmul(plant.den, kden, integ), pmul(ci, integ, num[CURRENT][DUTY])),
                      pmul(ci, cv, num[VOLTAGE][DUTY]))


def _loops_of(controller, plant) -> dict:
    """Margins of the loops of a linear controller on ``plant``: at the duty (what an injection there
    measures) and, for the current-mode controller, its inner and outer loops."""
    ts = plant.sample_period
    vs = plant.operating_point.input_voltage
    loops = {"duty": Loop(plant, controller.linear_model(vs)).margins().describe()}
    if isinstance(controller, CurrentModeController):
        g = controller.gains
        inner, outer, inner_char, outer_char = _current_mode_parts(plant, g.kp_current, g.ki_current, g.kp_voltage,
                                                                   g.ki_voltage, g.computation_delay, vs, ts)
        loops["inner (current)"] = margins(inner, ts, bool(np.all(np.abs(np.roots(inner_char)) < 1 - 1e-9))).describe()
        loops["outer (voltage, inner closed)"] = margins(outer, ts, bool(np.all(np.abs(np.roots(outer_char))
                                                                              < 1 - 1e-9))).describe()
    return loops


def envelope_margins(controller, parameters: CircuitParameters, targets: DesignTargets) -> list[dict]:
    """Per envelope corner (:func:`design_corners`: light loads at the CCM boundary): the point, whether
    it was moved there from the envelope's own load, and the margins of the controller's loops."""
    rows = []
    for op, moved in design_corners(parameters, targets):
        plant = discrete_plant(parameters, op, targets.sample_period, targets.sensor, targets.modulator)
        rows.append({"operating_point": asdict(op), "load_at_ccm_boundary": moved, "loops": _loops_of(controller, plant)})
    return rows


def design_current_mode(parameters: CircuitParameters, targets: DesignTargets = DesignTargets(),
                        name: str = "CMC") -> Design:
    """Average-current-mode control designed by the method of the module docstring."""
    op, ts, delay = targets.operating_point, targets.sample_period, targets.computation_delay
    vs = op.input_voltage
    plant = discrete_plant(parameters, op, ts, targets.sensor, targets.modulator)
    notes = []

    def inner_shape(kp, ki):
        return _current_mode_parts(plant, kp, ki, 0.0, 0.0, delay, vs, ts)[0]

    def inner_char(kp, ki):
        return _current_mode_parts(plant, kp, ki, 0.0, 0.0, delay, vs, ts)[2]

    found = None
    for extra in INNER_MARGIN_STEPS:  # the inner loop's own margin, raised until the cascade at the duty keeps the target
        inner_targets = replace(targets, phase_margin_deg=targets.phase_margin_deg + extra)
        inner = _pi_search(inner_shape, inner_char, targets.crossover_target_hz, inner_targets, ts)
        if inner is None:
            continue
        kp_i, ki_i, fc_i, _ = inner
        outer_target = targets.outer_crossover_ratio * fc_i

        def outer_shape(kp, ki):
            return _current_mode_parts(plant, kp_i, ki_i, kp, ki, delay, vs, ts)[1]

        def outer_char(kp, ki):
            return _current_mode_parts(plant, kp_i, ki_i, kp, ki, delay, vs, ts)[3]

        def duty_loop_ok(kp, ki):  # the cascade broken at the duty, where an injection measures it
            gains = CurrentModeGains(kp, ki, kp_i, ki_i, targets.current_limit, delay)
            m = Loop(plant, CurrentModeController(gains, ts, targets.duty_limits, vs).linear_model(vs)).margins()
            return m.stable and m.phase_margin_deg >= targets.cascade_phase_margin_deg \
                and m.gain_margin_db >= targets.gain_margin_db

        outer = _pi_search(outer_shape, outer_char, outer_target, targets, ts, duty_loop_ok)
        if outer is not None:
            found = (extra, inner, outer)
            break
    if found is None:
        raise ValueError(f"no current-mode design meets PM >= {targets.phase_margin_deg} deg and GM >= "
                         f"{targets.gain_margin_db} dB in every loop below {targets.crossover_target_hz:g} Hz")
    extra, (kp_i, ki_i, fc_i, _), (kp_v, ki_v, fc_v, _) = found
    outer_target = targets.outer_crossover_ratio * fc_i
    if extra:
        notes.append(f"the inner loop is designed for {targets.phase_margin_deg + extra:g} deg of phase margin: with "
                     f"{targets.phase_margin_deg:g} deg alone, the outer loop's gain near the inner crossover leaves "
                     f"the cascade broken at the duty below {targets.cascade_phase_margin_deg:g} deg")
    if fc_i < 0.95 * targets.crossover_target_hz:
        notes.append(f"inner crossover {fc_i:.0f} Hz instead of the target {targets.crossover_target_hz:.0f} Hz "
                     f"(fsw/{targets.switching_frequency / fc_i:.1f}): the zero-order hold, the averaging sensor and "
                     f"{delay} sample(s) of computation delay cost {360 * fc_i * ts * (1 + delay):.0f} deg there, and "
                     f"above it the phase margins fall below their targets")
    if fc_v < 0.95 * outer_target:
        notes.append(f"outer crossover {fc_v:.0f} Hz instead of the target {outer_target:.0f} Hz (a fifth of the "
                     "inner): higher, the outer PI's proportional gain near the inner crossover takes the cascade "
                     "broken at the duty below the margin targets")
    gains = CurrentModeGains(kp_voltage=kp_v, ki_voltage=ki_v, kp_current=kp_i, ki_current=ki_i,
                             current_limit=targets.current_limit, computation_delay=delay)
    controller = CurrentModeController(gains, ts, targets.duty_limits, vs, name,
                                       design={"method": METHOD_CURRENT_MODE, "inner_crossover_hz": fc_i,
                                               "outer_crossover_hz": fc_v})
    design = Design("current-mode", controller, METHOD_CURRENT_MODE, targets, _loops_of(controller, plant),
                    notes=notes)
    design.envelope = envelope_margins(controller, parameters, targets)
    return design


def type_iii_coefficients(fc: float, zeros_hz: tuple[float, float], poles_hz: tuple[float, float], integrator: float,
                          ts: float) -> tuple[np.ndarray, np.ndarray]:
    """Tustin (prewarped at ``fc``) of wI (1 + s/wz1)(1 + s/wz2) / (s (1 + s/wp1)(1 + s/wp2)): (numerator,
    denominator) in powers of z^-1, denominator[0] = 1."""
    wc = 2 * math.pi * fc
    (wz1, wz2), (wp1, wp2) = (2 * math.pi * f for f in zeros_hz), (2 * math.pi * f for f in poles_hz)
    num_s = integrator * np.polymul([1 / wz1, 1.0], [1 / wz2, 1.0])
    den_s = np.polymul([1.0, 0.0], np.polymul([1 / wp1, 1.0], [1 / wp2, 1.0]))
    fs = wc / (2 * math.tan(wc * ts / 2))  # bilinear's s = 2 fs (z - 1)/(z + 1), prewarped at wc
    b, a = bilinear(num_s, den_s, fs)
    return np.asarray(b, dtype=float), np.asarray(a, dtype=float)


TYPE_III_METHODS = ("k-factor", "pole-zero")


def _type_iii_placement(method: str, fc: float, plant, parameters: CircuitParameters, targets: DesignTargets):
    """(zeros_hz, poles_hz, details) of a Type-III at crossover ``fc``, or None where the method cannot place one."""
    ts, delay = targets.sample_period, targets.computation_delay
    if method == "k-factor":
        zc = unit_circle(fc, ts)
        plant_phase = math.degrees(np.angle(plant.response(VOLTAGE, DUTY, zc) / zc ** delay))
        boost = (targets.phase_margin_deg - 90.0 - plant_phase + 180.0) % 360.0 - 180.0
        if not 0 < boost <= MAX_BOOST_DEG:
            return None
        k = math.tan(math.radians(boost / 4 + 45.0)) ** 2
        return (fc / math.sqrt(k),) * 2, (fc * math.sqrt(k),) * 2, {"k_factor": k, "phase_boost_deg": boost}
    resonance = 1 / (2 * math.pi * math.sqrt(parameters.inductance * parameters.capacitance))
    nyquist = 0.5 / ts
    esr = parameters.capacitor_esr
    esr_zero = 1 / (2 * math.pi * esr * parameters.capacitance) if esr > 0 else nyquist
    return (resonance, resonance), (min(esr_zero, nyquist), nyquist), {"lc_resonance_hz": resonance}


def design_type_iii(parameters: CircuitParameters, targets: DesignTargets = DesignTargets(),
                    name: str = "Type-III", method: str = "k-factor") -> Design:
    """The Type-III compensator (module docstring): ``method`` "pole-zero" (the double zero on the LC
    resonance, the poles on the capacitor's ESR zero -- or the Nyquist frequency without ESR -- and the
    Nyquist frequency) or "k-factor" (Venable). Either way the crossover is the highest candidate from
    the target down whose exact margins meet the targets with a stable loop at every envelope corner."""
    if method not in TYPE_III_METHODS:
        raise ValueError(f"Type-III method {method!r} is unknown: expected one of {', '.join(TYPE_III_METHODS)}")
    op, ts, delay = targets.operating_point, targets.sample_period, targets.computation_delay
    vs = op.input_voltage
    plant = discrete_plant(parameters, op, ts, targets.sensor, targets.modulator)
    corner_plants = [(c, discrete_plant(parameters, c, ts, targets.sensor, targets.modulator)) for c, _ in design_corners(parameters, targets)]
    chosen = best_short = None  # best_short: the largest gain margin among loops meeting all but the GM target
    all_but_gain_margin = replace(targets, gain_margin_db=-math.inf)
    for fc in _candidates(targets.crossover_target_hz):
        placed = _type_iii_placement(method, fc, plant, parameters, targets)
        if placed is None:
            continue
        zeros, poles, details = placed
        zc = unit_circle(fc, ts)
        b, a = type_iii_coefficients(fc, zeros, poles, 1.0, ts)
        unit = CompensatorController(CompensatorCoefficients(tuple(b), tuple(a), delay), ts, targets.duty_limits, vs)
        gain = 1.0 / abs(Loop(plant, unit.linear_model(vs)).loop_gain(zc))
        coefficients = CompensatorCoefficients(tuple(float(x) for x in gain * b), tuple(float(x) for x in a), delay)
        controller = CompensatorController(coefficients, ts, targets.duty_limits, vs, name)
        m = Loop(plant, controller.linear_model(vs)).margins()
        if not _loop_ok(m, all_but_gain_margin, fc):
            continue
        if not all(Loop(p, controller.linear_model(c.input_voltage)).stable for c, p in corner_plants):
            continue
        if m.gain_margin_db < targets.gain_margin_db:
            if best_short is None or m.gain_margin_db > best_short[0]:
                best_short = (m.gain_margin_db, (fc, zeros, poles, details, gain, coefficients))
            continue
        chosen = (fc, zeros, poles, details, gain, coefficients)
        break
    short_of_gain_margin = chosen is None and best_short is not None
    if short_of_gain_margin:
        chosen = best_short[1]
    if chosen is None:
        raise ValueError(f"no Type-III crossover ({method}) below {targets.crossover_target_hz:g} Hz meets PM >= "
                         f"{targets.phase_margin_deg} deg and GM >= {targets.gain_margin_db} dB with a stable loop "
                         "over the envelope")
    fc, zeros, poles, details, gain, coefficients = chosen
    wc = 2 * math.pi * fc
    placement = {"placement": method, "crossover_hz": fc, **details, "zeros_hz": list(zeros),
                 "poles_hz": [0.0, *poles], "integrator_gain_V_per_V_s": gain, "prewarp_rad_s": wc}
    controller = CompensatorController(coefficients, ts, targets.duty_limits, vs, name,
                                       design={"method": METHOD_TYPE_III[method], **placement})
    notes = []
    if fc < 0.95 * targets.crossover_target_hz:
        notes.append(f"crossover {fc:.0f} Hz instead of the target {targets.crossover_target_hz:.0f} Hz: higher, the "
                     "margins fall below their targets (the zero-order hold, the averaging sensor and "
                     f"{delay} sample(s) of computation delay cost {360 * fc * ts * (1 + delay):.0f} deg at the "
                     "crossover) or the loop is unstable at a corner of the envelope")
    if short_of_gain_margin:
        notes.append(f"target not met: no crossover gives GM >= {targets.gain_margin_db} dB with PM >= "
                     f"{targets.phase_margin_deg} deg and a stable loop over the envelope; the design with the "
                     f"largest gain margin ({best_short[0]:.2f} dB) is used")
    if max(poles) > 0.5 / ts * 1.0001:
        notes.append(f"the double pole ({max(poles):.0f} Hz) lies above the Nyquist frequency ({0.5 / ts:.0f} Hz): "
                     "Tustin maps it inside, and the exact discrete margins are what count")
    design = Design("type-iii", controller, METHOD_TYPE_III[method], targets, _loops_of(controller, plant),
                    notes=notes)
    design.envelope = envelope_margins(controller, parameters, targets)
    return design


def linear_design(kind: str, controller, parameters: CircuitParameters, targets: DesignTargets, method: str) -> Design:
    """The margins of a controller designed otherwise (the PIs tuned on the plant FMU), for the same file."""
    plant = discrete_plant(parameters, targets.operating_point, targets.sample_period, targets.sensor, targets.modulator)
    design = Design(kind, controller, method, targets, _loops_of(controller, plant))
    design.envelope = envelope_margins(controller, parameters, targets)
    return design


def write_design(design: Design, path: Path) -> Path:
    """``results/tuning/<kind>__<pipeline>.json``: gains, crossovers, margins (strict JSON)."""
    return atomic_write_text(Path(path), json_text(design.describe()) + "\n")


def controller_from_file(path: Path, name: str | None = None):
    """The controller a design file describes (the current-mode or Type-III; ValueError otherwise)."""
    data = json.loads(Path(path).read_text(encoding="utf-8"))
    return controller_from_description(data["controller"], name)


def controller_from_description(c: dict, name: str | None = None):
    """A current-mode or compensator controller from its ``describe()`` (a design file's ``controller``)."""
    if c["type"] == "average-current-mode control":
        gains = CurrentModeGains(c["kp_voltage"], c["ki_voltage"], c["kp_current"], c["ki_current"],
                                 c["current_limit"], int(c["computation_delay"]))
        return CurrentModeController(gains, c["sample_period_s"], tuple(c["duty_limits"]),
                                     c["nominal_input_voltage_V"], name or c["name"], c.get("design"))
    if c["type"] == "discrete compensator (voltage mode)":
        coefficients = CompensatorCoefficients(tuple(c["numerator"]), tuple(c["denominator"]),
                                               int(c["computation_delay"]))
        return CompensatorController(coefficients, c["sample_period_s"], tuple(c["duty_limits"]),
                                     c["nominal_input_voltage_V"], name or c["name"], c.get("design"))
    raise ValueError(f"controller type {c.get('type')!r} is not a designed classical controller")


__all__ = ["DesignTargets", "Envelope", "Design", "design_current_mode", "design_current_mode_no_delay",
           "design_type_iii", "linear_design",
           "envelope_margins", "write_design", "controller_from_file"]


# ---------------------------------------------------------------------------------------------
# The designs for a plant binding (command line, reproduction, sweeps)


def targets_for(binding, control_period: float) -> DesignTargets:
    """The design targets for a plant binding at ``control_period``, at its converter spec's nominal point, switching
    frequency, inductor-current limit and envelope corners (:mod:`cosim.converter_spec`; each refused, naming its key,
    where the spec does not give it): the sensor it gives the controllers (the built-in switched FMU's period mean,
    else its plain outputs = a sample), its modulator (the built-in switched FMU's sawtooth PWM, else a held duty) and
    the one-sample computation delay. Designs need one sample per PWM period (a ValueError otherwise)."""
    spec = binding.converter
    purpose = "the classical designs"
    switching_frequency = spec.require("switching_frequency", purpose)
    if not spec.samples_once_per_pwm_period(control_period):
        raise ValueError(f"the classical designs sample once per PWM period ({1 / switching_frequency:.6g} s), not "
                         f"every {control_period:.6g} s")
    point = OperatingPoint(*(spec.require(key, purpose) for key in ("output_voltage", "load_resistance",
                                                                      "input_voltage")))
    envelope = Envelope(*(spec.operating_range(key, purpose) for key in ("output_voltage", "load_resistance",
                                                                         "input_voltage")))
    spec_values = dict(switching_frequency=switching_frequency, operating_point=point, envelope=envelope,
                       current_limit=spec.require("inductor_current_limit", "the current-mode design's current limit"))
    from cosim.fmi.binding import PLANT_MODE_CODES

    switched = binding.parameters.get("plant_mode") == PLANT_MODE_CODES["switched"]
    averaging = binding.roles.get("measured_output_voltage") is not None and \
        binding.roles["measured_output_voltage"].variable.startswith("average")
    sawtooth = binding.parameters.get("pwm_carrier", 0) == 0
    return DesignTargets(sample_period=control_period, sensor="average" if (switched and averaging) else "sample",
                         modulator="trailing-edge" if (switched and sawtooth) else "zoh", **spec_values)


def design_files(out_dir: Path, tag: str) -> dict[str, Path]:
    """Where the reproduction writes each design of pipeline ``tag`` (``results/tuning/``)."""
    folder = Path(out_dir) / "tuning"
    return {kind: folder / f"{kind}__{tag}.json" for kind in ("current-mode", "type-iii", "pi-envelope", "pi-margins",
                                                              NO_DELAY_FILE)}


#: the design file of the delay-free current-mode controller (``tuning/current-mode-no-delay__<pipeline>.json``)
NO_DELAY_FILE = "current-mode-no-delay"


def design_current_mode_no_delay(parameters: CircuitParameters, targets: DesignTargets, name: str) -> Design:
    """The current-mode controller designed by the same method without the one-sample computation delay
    (in the model and in the controller): the like-for-like baseline for the NNPC, which applies its duty
    in the sample it computes it. The same targets otherwise; with 1.5 samples of lag (hold and averaging
    sensor) less, both crossovers reach their targets (fsw/10 and a fifth of it)."""
    design = design_current_mode(parameters, replace(targets, computation_delay=0), name)
    design.notes.append("designed and run without the computation delay (a bound: a microcontroller needs time to "
                        "compute the duty), the like-for-like comparison with the NNPC, which has none")
    return design


#: the pipeline whose envelope the map measures: the envelope PI is tuned there only
ENVELOPE_PIPELINE_PLANT = "nominal-switched"


def in_pipeline(pipeline, binding, parameters: CircuitParameters, pi, out_dir: Path, quick: bool = False,
                timings: dict | None = None, log=None) -> list:
    """The study's hook, once per pipeline: at one sample per PWM period of the plant's converter (its spec's
    switching frequency), design the current-mode controller and the Type-III for the pipeline's circuit
    (``parameters``: the true circuit of a built-in plant, the spec's nominal circuit of a bound one), tune the
    envelope PI on the paper's nominal switched plant, write each design (and the PI's margins) to ``tuning/`` and
    return the controllers to run beside the others (none at other rates)."""
    import time

    from cosim.design.pi_tuning import tune_pi_envelope
    from cosim.design.vocabulary import CURRENT_MODE, CURRENT_MODE_NO_DELAY, PI_ENVELOPE, TYPE_III, pipeline_tag

    period = pipeline.control_period
    if not binding.converter.samples_once_per_pwm_period(period):
        return []
    start = time.perf_counter()
    tag = pipeline_tag(pipeline.plant_tag, period)
    files = design_files(out_dir, tag)
    targets = targets_for(binding, period)
    designs = [design_current_mode(parameters, targets, CURRENT_MODE), design_type_iii(parameters, targets, TYPE_III)]
    for design in designs:
        write_design(design, files[design.kind])
    if pipeline.plant_tag == ENVELOPE_PIPELINE_PLANT:  # the map's like-for-like row (not run at the nominal point)
        write_design(design_current_mode_no_delay(parameters, targets, CURRENT_MODE_NO_DELAY), files[NO_DELAY_FILE])
    write_design(linear_design("pi", pi, parameters, targets, pi.tuning.get("method", "")), files["pi-margins"])
    controllers = [d.controller for d in designs]
    if pipeline.plant_tag == ENVELOPE_PIPELINE_PLANT:
        tuning = tune_pi_envelope(binding, period, quick=quick)
        envelope_pi = tuning.controller(name=PI_ENVELOPE)
        design = linear_design("pi-envelope", envelope_pi, parameters, targets, tuning.method)
        design.notes.append(f"kp = {tuning.kp:.6g} 1/V, ki = {tuning.ki:.6g} 1/(V s); cost {tuning.cost:.4g} after "
                            f"{tuning.evaluations} evaluations; worst overshoot {tuning.worst_overshoot_pct:.2f} %")
        write_design(design, files["pi-envelope"])
        controllers.append(envelope_pi)
    if timings is not None:
        timings["classical_design_s"] = time.perf_counter() - start
    if log is not None:
        for d in designs:
            m = d.loops
            log(f"  {tag}: {d.controller.name}: " + "; ".join(
                f"{loop} crossover {v['crossover_hz']:.0f} Hz, PM {v['phase_margin_deg']:.1f} deg" for loop, v in m.items()))
    return controllers
