"""The classical baselines: the discrete small-signal model against closed forms, each design's margins
against its specification, the C twins against their Python references (directly, on the plant FMU and
through the exported controller FMU), and the envelope PI's tuning."""

from __future__ import annotations

import math
import subprocess
from dataclasses import replace

import numpy as np
import pytest
from conftest import cli, one_line_error
from scipy.integrate import simpson
from scipy.linalg import expm
from scipy.signal import cont2discrete

from controllers.base import Measurement
from controllers.native import SOURCE_DIR, native_twin
from controllers.small_signal import (
    CURRENT,
    DUTY,
    VOLTAGE,
    OperatingPoint,
    continuous_model,
    discrete_plant,
    margins,
    unit_circle,
)
from cosim.design.classical_design import (
    DesignTargets,
    controller_from_description,
    design_current_mode,
    design_current_mode_no_delay,
    design_type_iii,
    targets_for,
)
from cosim.design.plants import plant_binding
from cosim.design.vocabulary import MISMATCH, NOMINAL, SWITCHING_PERIOD
from cosim.study.vocabulary import PAPER_SPEC

TS = SWITCHING_PERIOD
NOMINAL_POINT = OperatingPoint(12.0, 6.0, 48.0)


@pytest.fixture(scope="module")
def designs():
    targets = DesignTargets()
    return design_current_mode(NOMINAL, targets), design_type_iii(NOMINAL, targets)


# ------------------------------------------------------------------ the small-signal model


def test_sampled_plant_is_the_zero_order_hold_discretisation():
    a, b, c, d = continuous_model(MISMATCH, NOMINAL_POINT)
    phi, gamma, cd, dd, _ = cont2discrete((a, b, c, d), TS, method="zoh")
    plant = discrete_plant(MISMATCH, NOMINAL_POINT, TS, sensor="sample")
    for f in (50.0, 2e3, 2e4):
        z = unit_circle(f, TS)
        reference = cd @ np.linalg.solve(z * np.eye(2) - phi, gamma) + dd
        for o in (CURRENT, VOLTAGE):
            for i in range(2):
                assert plant.response(o, i, z) == pytest.approx(reference[o, i], rel=1e-9)
    # DC: duty -> vo is the drive voltage over the parasitics' divider, duty -> iL that over R
    plant = discrete_plant(NOMINAL, NOMINAL_POINT, TS, sensor="sample")
    assert plant.response(VOLTAGE, DUTY, 1.0) == pytest.approx(48.0, rel=1e-9)
    assert plant.response(CURRENT, DUTY, 1.0) == pytest.approx(8.0, rel=1e-9)


def test_averaging_sensor_reads_the_period_mean():
    """The duty held at 1 for one period from rest: the model's reading at each later sample equals the
    mean of the continuous response over the period before it (integrated on a fine grid)."""
    a, b, c, _ = continuous_model(NOMINAL, NOMINAL_POINT)
    plant = discrete_plant(NOMINAL, NOMINAL_POINT, TS, sensor="average")
    # impulse response of the model: the inverse z-transform of num/den by long division
    num, den = plant.num[VOLTAGE][DUTY], plant.den
    n = 6
    h = np.zeros(n)
    padded = np.concatenate([np.zeros(len(den) - len(num)), num, np.zeros(n)])
    remainder = padded.copy()
    for k in range(n):
        h[k] = remainder[k] / den[0]
        remainder[k:k + len(den)] -= h[k] * den
    t = np.linspace(0, TS, 101)
    exponentials = [expm(a * tau) for tau in t]
    forced = [np.linalg.solve(a, (e - np.eye(2)) @ b[:, 0]) for e in exponentials]
    x = np.zeros(2)
    expected = []
    for k in range(n):
        states = [e @ x + (f if k == 0 else 0.0) for e, f in zip(exponentials, forced)]
        expected.append(simpson(np.array([c[1] @ s for s in states]), x=t) / TS)
        x = states[-1]
    assert h[0] == 0.0  # the reading at the duty's own sample does not see it
    assert np.allclose(h[1:], expected[:-1], rtol=1e-6, atol=1e-9)


def test_margins_of_a_delayed_integrator_in_closed_form():
    """L(z) = a / (z (z - 1)): crossover where 2 sin(w Ts / 2) = a, PM = 90 deg - 1.5 w Ts, GM = -20 log a
    at w Ts = pi/3."""
    a = 0.3
    m = margins(lambda z: a / (z * (z - 1)), TS)
    theta = 2 * math.asin(a / 2)
    assert m.crossover_hz == pytest.approx(theta / (2 * math.pi * TS), rel=1e-4)
    assert m.phase_margin_deg == pytest.approx(90 - 1.5 * math.degrees(theta), abs=0.01)
    assert m.gain_margin_db == pytest.approx(-20 * math.log10(a), abs=0.01)
    assert m.phase_crossover_hz == pytest.approx(1 / (6 * TS), rel=1e-3)


# ------------------------------------------------------------------ the designs against their specification


def test_current_mode_design_meets_its_specification(designs):
    design, _ = designs
    t = design.targets
    loops = design.loops
    inner, outer, duty = loops["inner (current)"], loops["outer (voltage, inner closed)"], loops["duty"]
    for loop in (inner, outer):
        assert loop["closed_loop_stable"]
        assert loop["phase_margin_deg"] >= t.phase_margin_deg - 1e-6
        assert loop["gain_margin_db"] >= t.gain_margin_db - 1e-6
    assert duty["closed_loop_stable"] and duty["phase_margin_deg"] >= t.cascade_phase_margin_deg - 1e-6
    assert duty["gain_margin_db"] >= t.gain_margin_db - 1e-6
    # crossovers: at most the targets, the outer at most a fifth of the inner
    assert inner["crossover_hz"] <= t.crossover_target_hz * 1.05
    assert outer["crossover_hz"] <= t.outer_crossover_ratio * inner["crossover_hz"] * 1.05
    assert design.meets()
    # the current limit is the outer loop's saturation: a start-up asks for no more than it
    controller = design.controller
    controller.reset()
    for _ in range(3):
        controller.step(Measurement(0.0, 12.0, 0.0, inductor_current=0.0, input_voltage=48.0))
    assert controller.voltage_integral <= t.current_limit


def test_delay_free_current_mode_design_meets_its_specification_at_the_target_crossovers(designs):
    """Without the computation delay (the map's like-for-like row) the same method reaches both crossover
    targets: the inner loop at fsw/10 = 7.5 kHz, the outer at a fifth of it (1.5 kHz; 521 Hz with the delay),
    with every margin target kept; the controller applies its duty in the sample it computes it."""
    delayed, _ = designs
    design = design_current_mode_no_delay(NOMINAL, DesignTargets(), "CMC (no delay)")
    t = design.targets
    assert t.computation_delay == 0 and design.controller.gains.computation_delay == 0
    inner, outer, duty = (design.loops[k] for k in ("inner (current)", "outer (voltage, inner closed)", "duty"))
    assert inner["crossover_hz"] == pytest.approx(t.crossover_target_hz, rel=1e-3)  # 7500 Hz
    assert outer["crossover_hz"] == pytest.approx(t.outer_crossover_ratio * inner["crossover_hz"], rel=1e-3)
    for loop in (inner, outer):
        assert loop["closed_loop_stable"] and loop["phase_margin_deg"] >= t.phase_margin_deg - 1e-6
        assert loop["gain_margin_db"] >= t.gain_margin_db - 1e-6
    assert duty["closed_loop_stable"] and duty["phase_margin_deg"] >= t.cascade_phase_margin_deg - 1e-6
    assert duty["gain_margin_db"] >= t.gain_margin_db - 1e-6
    assert design.meets() and not any(n.startswith("outer crossover") for n in design.notes)
    assert outer["crossover_hz"] > 2.5 * delayed.loops["outer (voltage, inner closed)"]["crossover_hz"]
    # no delay: the first duty answers the first measurement (the delayed controller's is the pending 0)
    m = Measurement(0.0, 12.0, 11.0, inductor_current=0.0, input_voltage=48.0)
    free = design.controller
    free.reset()
    delayed.controller.reset()
    assert free.step(m) > 0.0 and delayed.controller.step(m) == 0.0
    free.reset()
    twin = native_twin(free)
    for measurement in _measurements(2, 200):
        assert twin.step(measurement) == free.step(measurement)


def test_type_iii_design_meets_its_specification_over_the_envelope(designs):
    _, design = designs
    t = design.targets
    duty = design.loops["duty"]
    assert duty["closed_loop_stable"] and duty["phase_margin_deg"] >= t.phase_margin_deg - 1e-6
    assert duty["gain_margin_db"] >= t.gain_margin_db - 1e-6
    assert all(corner["loops"]["duty"]["closed_loop_stable"] for corner in design.envelope)
    placement = design.controller.design
    k = placement["k_factor"]
    assert placement["zeros_hz"][0] == pytest.approx(placement["crossover_hz"] / math.sqrt(k))
    assert placement["poles_hz"][1] == pytest.approx(placement["crossover_hz"] * math.sqrt(k))
    # the discretised compensator has its integrator pole at z = 1
    assert abs(sum(design.controller.coefficients.denominator)) < 1e-9


def test_impossible_targets_are_refused():
    with pytest.raises(ValueError, match="PM >= 179.0 deg and GM >= 80.0 dB"):
        design_type_iii(NOMINAL, replace(DesignTargets(), phase_margin_deg=179.0, gain_margin_db=80.0))
    with pytest.raises(ValueError, match="sample once per PWM period"):
        targets_for(plant_binding("nominal", "switched"), 1e-3)


def test_a_type_iii_short_of_its_gain_margin_is_the_best_there_is_and_says_so():
    """The mismatch-study switched plant (L +20 %, C -20 %, parasitics, the averaging sensor): no
    crossover reaches GM >= 6 dB at PM >= 60 deg (the largest is 5.67 dB near 4.8 kHz, with 6 of 8
    envelope corners stable there); the design is the stable one with the largest gain margin, and says
    that the target is not met instead of stopping the reproduction."""
    targets = targets_for(plant_binding("mismatch", "switched"), SWITCHING_PERIOD)
    design = design_type_iii(MISMATCH, targets)
    duty = design.loops["duty"]
    assert not design.meets() and 5.0 < duty["gain_margin_db"] < targets.gain_margin_db
    assert duty["closed_loop_stable"] and duty["phase_margin_deg"] >= targets.phase_margin_deg - 1e-6
    assert all(corner["loops"]["duty"]["closed_loop_stable"] for corner in design.envelope)
    assert any(note.startswith("target not met: no crossover gives GM >= 6.0 dB") for note in design.notes)


def test_a_design_rebuilds_from_its_description(designs):
    for design in designs:
        again = controller_from_description(design.controller.describe())
        assert again.describe() == design.controller.describe()


# ------------------------------------------------------------------ the C twins


def _measurements(seed: int, n: int = 400):
    rng = np.random.default_rng(seed)
    for k in range(n):
        yield Measurement(k * TS, float(rng.uniform(0, 20)), float(rng.uniform(0, 22)),
                          inductor_current=float(rng.uniform(0, 9)), load_current=math.nan,
                          input_voltage=float(rng.choice([math.nan, 36.0, 48.0, 60.0])))


def test_twins_give_the_python_duty_bit_for_bit(designs):
    for design in designs:
        python, c = design.controller, native_twin(design.controller)
        assert type(c) is not type(python)
        for seed in (0, 1):
            python.reset()
            c.reset()
            for m in _measurements(seed):
                assert c.step(m) == python.step(m)


def test_twins_on_the_switched_plant_and_as_controller_fmus(designs, tmp_path):
    from cosim.design.experiments import scenarios_for
    from cosim.fmi.controller import open_controller
    from cosim.fmi.controller_export import export_controller
    from cosim.master import simulate

    binding = plant_binding("nominal", "switched")
    scenario = scenarios_for(TS, ("load_change",), spec=PAPER_SPEC)[0]
    for design in designs:
        python = design.controller
        fmu, _ = export_controller(python, tmp_path / f"{design.kind}.fmu")
        reference = simulate(binding, python, scenario).frame["duty_cycle"].to_numpy()
        twin = simulate(binding, native_twin(python), scenario).frame["duty_cycle"].to_numpy()
        exported = open_controller(fmu)
        try:
            through_fmu = simulate(binding, exported, scenario).frame["duty_cycle"].to_numpy()
        finally:
            exported.close()
        assert np.array_equal(twin, reference)
        assert np.max(np.abs(through_fmu - reference)) <= 1e-12


def test_twins_compile_in_single_precision():
    for source in ("current_mode.c", "compensator.c"):
        done = subprocess.run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-DBUCKC_FLOAT32",
                               "-fsyntax-only", str(SOURCE_DIR / source)], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr


def test_the_mismatched_circuit_moves_the_design(designs):
    """The design is a function of the plant parameters: the mismatch-study circuit (L +20 %, C -20 %,
    parasitics) gets other gains, still meeting the targets."""
    other = design_current_mode(MISMATCH)
    assert other.meets()
    assert other.controller.gains != designs[0].controller.gains


# ------------------------------------------------------------------ the envelope PI and the command line


def test_envelope_pi_tuning_quick_and_its_errors():
    from cosim.design.pi_tuning import envelope_points, tune_pi_envelope

    binding = plant_binding("nominal", "averaged")
    tuning = tune_pi_envelope(binding, TS, points=envelope_points(binding.converter)[:2], quick=True)
    assert tuning.kp >= 0 and tuning.ki > 0 and tuning.evaluations == 10
    assert "max over operating points (3, 4, 48), (3, 100, 48)" in tuning.method
    with pytest.raises(ValueError, match="aggregate 'mean' is unknown"):
        tune_pi_envelope(binding, TS, aggregate="mean")


def test_cli_refuses_a_design_at_the_wrong_rate():
    done = cli("run", "startup", "--controller", "current-mode", "--control-period", "1e-3")
    one_line_error(done, 2, "current-mode is designed for one sample per PWM period")
