"""The float32 build of the C twins (``-DBUCKC_FLOAT32``, controllers/c/buckc.h) against the double
build: per step within the derived bound of controllers/float32.py on recorded closed-loop inputs, and
in closed loop on the plant FMU within 1 % of IAE and 0.2 points of overshoot (the PI, the explicit
NNPC, the current-mode controller and the Type-III, the paper's four scenarios, both plants, 13.33 us);
the float32 controller FMU."""

from __future__ import annotations

import ctypes
import functools
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from controllers import float32, native
from controllers.base import Measurement
from controllers.explicit_policy import load_policy
from controllers.nn_model import load_model
from controllers.pi import PIController
from cosim.design.classical_design import design_current_mode, design_type_iii, targets_for
from cosim.design.experiments import explicit_nnpc, nnpc, scenarios_for
from cosim.design.plants import plant_binding
from cosim.design.vocabulary import NOMINAL, SWITCHING_PERIOD
from cosim.master import simulate
from cosim.metrics import run_metrics
from cosim.study.vocabulary import PAPER_SPEC

FIXTURES = Path(__file__).parent / "fixtures"
MODES = ("averaged", "switched")
#: the reproduction's PI tuned at 13.33 us on each nominal plant (results/tuning/pi__nominal-<mode>__13p33us.json)
PI_GAINS = {"averaged": (0.008292317390441936, 189.35716172405384),
            "switched": (0.007026878992716469, 172.92168103154324)}
#: the per-step tolerance in duty: the derived bound's largest value on these inputs stays below it
TOLERANCE = 2e-5


def policy(mode: str):
    """The reproduction's explicit NNPC of the nominal plant (7-14-1, copied from results/models)."""
    return load_policy(FIXTURES / f"explicit_nominal_{mode}_13p33us.pt", expect_period=SWITCHING_PERIOD)


@functools.lru_cache(maxsize=None)
def classical(mode: str):
    """The reproduction's current-mode controller and Type-III of the nominal plant at 13.33 us, designed
    as make reproduce designs them (results/tuning/current-mode__nominal-<mode>__13p33us.json, ...)."""
    targets = targets_for(plant_binding("nominal", mode), SWITCHING_PERIOD)
    return design_current_mode(NOMINAL, targets).controller, design_type_iii(NOMINAL, targets).controller


def controllers(mode: str):
    kp, ki = PI_GAINS[mode]
    return [PIController(kp, ki, SWITCHING_PERIOD), explicit_nnpc(policy(mode)), *classical(mode)]


class Recording:
    """A controller whose measurements are kept (the per-step tests replay them)."""

    def __init__(self, inner):
        self.inner, self.rows = inner, []
        self.name, self.sample_period, self.duty_limits = inner.name, inner.sample_period, inner.duty_limits

    def reset(self):
        self.inner.reset()

    def step(self, m):
        duty = self.inner.step(m)
        self.rows.append((m, duty))
        return duty

    def describe(self):
        return self.inner.describe()


@pytest.fixture(scope="module")
def closed_loop():
    """(mode, scenario, controller) -> {precision: (metrics, [(measurement, duty), ...])}: 64 runs."""
    runs = {}
    for mode in MODES:
        binding = plant_binding("nominal", mode)
        for controller in controllers(mode):
            for scenario in scenarios_for(SWITCHING_PERIOD, spec=PAPER_SPEC):
                for precision in native.PRECISIONS:
                    twin = Recording(native.native_twin(controller, precision))
                    metrics = run_metrics(simulate(binding, twin, scenario))
                    runs.setdefault((mode, scenario.name, controller.name), {})[precision] = (metrics, twin.rows)
    return runs


def test_the_float32_build_is_single_precision():
    lib32, lib64 = native.library("float32"), native.library("float64")
    assert lib32.buckc_real_name() == b"float32" and lib64.buckc_real_name() == b"float64"
    for name in ("PolicyConfigC", "PiConfig", "MeasurementC", "NnConfig", "CurrentModeC", "CompensatorC"):
        small, large = (ctypes.sizeof(getattr(native.real_mirrors(p), name)) for p in ("float32", "float64"))
        assert small < large, name
    pi32, pi64 = (native.NativePIController(0.0123, 171.0, SWITCHING_PERIOD, precision=p) for p in ("float32", "float64"))
    m = Measurement(0.0, 12.0, 11.9, 1.0, 2.0, 48.0)
    d32, d64 = pi32.step(m), pi64.step(m)
    assert d32 != d64 and d32 == float(np.float32(d32)) and abs(d32 - d64) < 1e-6
    online = nnpc(load_model(FIXTURES / "nnpc_nominal_averaged_13p33us.pt", expect_period=SWITCHING_PERIOD),
                  SWITCHING_PERIOD)
    with pytest.raises(ValueError, match="NNPC has no float32 build: the predictive controller's C files compute in "
                                         "double here"):
        native.native_twin(online, "float32")


#: a C program that runs buckc_tanhf (controllers/c/buckc_tanhf.h) over the floats and prints its largest
#: absolute distance from tanh (libm's in double; below 2^-7 its Taylor series to x^5, within 1e-16)
TANHF_CHECK = r"""
#include <math.h>
#include <stdio.h>
#include <stdint.h>
#include <string.h>
#include "buckc_tanhf.h"

static double worst = 0.0;
static int odd = 1;

static void check(uint32_t bits, int both_signs)
{
    float x;
    double a, reference, error;
    memcpy(&x, &bits, sizeof x);
    a = x;
    reference = a < 0.0078125 ? a - a * a * a / 3.0 + 2.0 * a * a * a * a * a / 15.0 : tanh(a);
    error = fabs((double)buckc_tanhf(x) - reference);
    if (!(error <= worst)) worst = error; /* a NaN result makes it NaN */
    if (both_signs && buckc_tanhf(-x) != -buckc_tanhf(x)) odd = 0;
}

int main(void)
{
    uint32_t bits, small = 0x3C000000u /* 2^-7 */, high = 0x41180000u /* 9.5 */, infinity = 0x7F800000u;
    float nan = NAN, inf = INFINITY;
    for (bits = 0; bits < small; bits += 32u) check(bits, 1);
    printf("%.9g", worst);
    worst = 0.0;
    for (bits = small; bits <= high; ++bits) check(bits, (bits & 31u) == 0u);
    printf(" %.9g", worst);
    worst = 0.0;
    for (bits = high; bits <= infinity; bits += 4096u) check(bits, 1);
    printf(" %.9g %d %d\n", worst, odd, buckc_tanhf(nan) != buckc_tanhf(nan) && buckc_tanhf(-inf) == -1.0f
           && buckc_tanhf(9.0f) == 1.0f);
    return 0;
}
"""


def test_the_float32_builds_tanh_is_within_its_stated_error_on_every_float(tmp_path):
    """buckc_tanhf, the float32 build's tanh: within TANH_ERROR (absolute) of tanh on every float from 2^-7 to
    9.5, every 32nd one below and every 4096th above (both signs: it is odd), NaN in NaN out, -inf -> -1;
    compiled with the float32 build's flags. Not vacuous: its error reaches 1e-7."""
    import subprocess

    source = tmp_path / "check.c"
    source.write_text(TANHF_CHECK)
    flags = [f for f in native.precision_flags("float32") if f not in ("-shared", "-fPIC")]
    built = subprocess.run([*native.compiler(), *flags, f"-I{native.SOURCE_DIR}", str(source), "-o",
                            str(tmp_path / "check"), "-lm"], capture_output=True, text=True)
    assert built.returncode == 0, built.stderr
    done = subprocess.run([str(tmp_path / "check")], capture_output=True, text=True, timeout=300)
    below, middle, above, odd, special = done.stdout.split()
    assert odd == "1" and special == "1"
    errors = [float(below), float(middle), float(above)]
    assert max(errors) <= float32.TANH_ERROR, errors
    assert max(errors) > 1e-7 and float(above) <= 3.1e-8  # measured 1.19e-7, 1.18e-7; 1 - tanh(9.5) above


def test_the_tanh_polynomial_is_the_one_the_fitting_script_finds():
    """controllers/c/buckc_tanhf.h's 2^f polynomial, line for line, is what scripts/fit_tanhf.py prints."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, str(root / "scripts" / "fit_tanhf.py")], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    printed = [line.strip() for line in done.stdout.splitlines() if line.strip().startswith("p = ")]
    header = [line.strip() for line in (native.SOURCE_DIR / "buckc_tanhf.h").read_text().splitlines()
              if line.strip().startswith("p = ")]
    assert len(printed) == 7 and printed == header


def test_float32_and_double_agree_in_closed_loop_on_the_plant_fmu(closed_loop):
    """IAE within 1 %, overshoot within 0.2 points: PI, explicit NNPC, current-mode and Type-III, 4 scenarios,
    both plants, 13.33 us."""
    assert len(closed_loop) == 2 * 4 * 4
    assert {name for _, _, name in closed_loop} == {"PI", "NNPC-explicit", "CMC", "Type-III"}
    differs = 0
    for key, runs in closed_loop.items():
        (m64, rows64), (m32, rows32) = runs["float64"], runs["float32"]
        assert abs(m32["iae_Vs"] / m64["iae_Vs"] - 1) <= 0.01, (key, m32["iae_Vs"], m64["iae_Vs"])
        assert abs(m32["overshoot_pct"] - m64["overshoot_pct"]) <= 0.2, (key, m32["overshoot_pct"], m64["overshoot_pct"])
        assert len(rows32) == len(rows64) > 400
        differs += any(d32 != d64 for (_, d32), (_, d64) in zip(rows32, rows64))
    assert differs == len(closed_loop)  # the float32 runs really compute in float: every run's duties differ


def _state_copy(source, target):
    """The double state into the float32 one, each value rounded to float (arrays element by element)."""
    for name, _ in source._fields_:
        if name != "config":
            value = getattr(source, name)
            if isinstance(value, ctypes.Array):
                getattr(target, name)[:] = list(value)
            else:
                setattr(target, name, value)


def test_the_explicit_nnpc_steps_within_the_derived_bound_on_recorded_inputs(closed_loop):
    """Every recorded sample of the double runs: the float32 step from the double step's state (rounded to
    float) is within float32.policy_step_bound of the double step; the bound stays below TOLERANCE."""
    worst_bound = worst_error = 0.0
    for mode in MODES:
        p = policy(mode)
        controller = explicit_nnpc(p)
        twin64, twin32 = (native.native_twin(controller, precision) for precision in ("float64", "float32"))
        for scenario in scenarios_for(SWITCHING_PERIOD, spec=PAPER_SPEC):
            rows = closed_loop[(mode, scenario.name, controller.name)]["float64"][1]
            twin64.reset()
            for m, recorded in rows:
                bound = float32.policy_step_bound(p, m, twin64.state)
                _state_copy(twin64.state, twin32.state)
                d64, d32 = twin64.step(m), twin32.step(m)
                assert d64 == recorded
                assert abs(d32 - d64) <= bound, (mode, scenario.name, m, d32 - d64, bound)
                worst_bound, worst_error = max(worst_bound, bound), max(worst_error, abs(d32 - d64))
    assert worst_bound <= TOLERANCE, worst_bound
    assert 0 < worst_error < worst_bound / 10  # not vacuous: float32 differs, the bound is a bound, not a guess


def test_the_pi_steps_within_the_derived_bound_on_recorded_inputs(closed_loop):
    worst_bound = 0.0
    for mode in MODES:
        pi = controllers(mode)[0]
        twin64, twin32 = (native.NativePIController.from_python(pi, precision=p) for p in ("float64", "float32"))
        for scenario in scenarios_for(SWITCHING_PERIOD, spec=PAPER_SPEC):
            twin64.reset()
            for m, _ in closed_loop[(mode, scenario.name, pi.name)]["float64"][1]:
                bound = float32.pi_step_bound(pi.kp, pi.ki, pi.sample_period, pi.duty_limits, twin64.integral,
                                              m.reference, m.output_voltage)
                twin32.state.integral = twin64.state.integral
                d64, d32 = twin64.step(m), twin32.step(m)
                assert abs(d32 - d64) <= bound, (mode, scenario.name, m, d32 - d64, bound)
                worst_bound = max(worst_bound, bound)
    assert worst_bound <= TOLERANCE, worst_bound


@pytest.mark.parametrize("index,bound_of", [(2, float32.current_mode_step_bound), (3, float32.compensator_step_bound)])
def test_the_classical_twins_step_within_the_derived_bound_on_recorded_inputs(closed_loop, index, bound_of):
    """The current-mode controller and the Type-III on every recorded sample of their double runs: the duty
    the float32 step computes from the double step's state (rounded to float) -- the one it holds for the
    next sample, both designs have a computation delay of one -- within the derived bound of the double
    step's; the duty returned is the held one rounded to float; the bound stays below TOLERANCE."""
    worst_bound = worst_error = 0.0
    for mode in MODES:
        controller = controllers(mode)[index]
        assert controller.coefficients.computation_delay if index == 3 else controller.gains.computation_delay
        twin64, twin32 = (native.native_twin(controller, precision) for precision in native.PRECISIONS)
        for scenario in scenarios_for(SWITCHING_PERIOD, spec=PAPER_SPEC):
            twin64.reset()
            for m, recorded in closed_loop[(mode, scenario.name, controller.name)]["float64"][1]:
                bound = bound_of(controller, m, twin64.state)
                _state_copy(twin64.state, twin32.state)
                d64, d32 = twin64.step(m), twin32.step(m)
                assert d64 == recorded and d32 == float(np.float32(d64))  # the held duties, the same up to rounding
                computed64, computed32 = twin64.state.pending_duty, twin32.state.pending_duty
                assert abs(computed32 - computed64) <= bound, (mode, scenario.name, m, computed32 - computed64, bound)
                worst_bound, worst_error = max(worst_bound, bound), max(worst_error, abs(computed32 - computed64))
    assert worst_bound <= TOLERANCE, worst_bound
    assert 0 < worst_error < worst_bound  # float32 differs, within the bound


def test_the_classical_bounds_take_the_supply_each_build_takes():
    """An input voltage that underflows in float: the double build divides by it, the float32 build by the
    nominal; the bound covers the jump (and the C twins do take those branches)."""
    controller = classical("switched")[1]
    m = Measurement(0.0, 12.0, 11.0, 2.0, 2.0, 1e-60)
    twin64, twin32 = (native.native_twin(replace_delay(controller), p) for p in native.PRECISIONS)
    d64, d32 = twin64.step(m), twin32.step(m)
    assert d64 == 1.0 and 0 < d32 < 1  # 1e-60 V clips the double duty to 1; float32 divides by 48 V
    bound = float32.compensator_step_bound(replace_delay(controller), m, native.native_twin(controller).state)
    assert abs(d32 - d64) <= bound and bound > 0.5


def replace_delay(controller):
    """The compensator without its computation delay (the step returns what it computes)."""
    from controllers.compensator import CompensatorController

    return CompensatorController(replace(controller.coefficients, computation_delay=0), controller.sample_period,
                                 controller.duty_limits, controller.nominal_input_voltage, controller.name)


def test_the_nn_forward_pass_is_within_the_derived_bound_on_recorded_inputs(closed_loop):
    """An NNPC network of 13.33 us (7-10-2, two delays, the load conductance: the fixture of the network before the
    envelope data; today's adds the supply voltage) on its inputs built from the
    recorded explicit-NNPC runs: [iL, vo, d](k-1), [iL, vo, d](k-2), G(k-1)."""
    model = load_model(FIXTURES / "nnpc_nominal_averaged_13p33us.pt", expect_period=SWITCHING_PERIOD)
    config = model.config
    assert config.delays == 2 and config.extra_signals == ("load_conductance",)
    configs = {p: native.nn_config(model, p) for p in native.PRECISIONS}
    rows = []
    for mode in MODES:
        for scenario in scenarios_for(SWITCHING_PERIOD, spec=PAPER_SPEC):
            record = closed_loop[(mode, scenario.name, "NNPC-explicit")]["float64"][1]
            g = 1 / 6.0
            for (m1, d1), (m2, d2) in zip(record[1:], record[:-1]):
                g = native.estimate_conductance(m1.output_voltage, m1.load_current, m1.inductor_current, g)
                rows.append([m1.inductor_current, m1.output_voltage, d1, m2.inductor_current, m2.output_voltage, d2, g])
    x = np.array(rows)
    y64, y32 = native.nn_forward(configs["float64"], x), native.nn_forward(configs["float32"], x)
    bounds = np.array([float32.nn_forward_bound(model._weights, model._biases, config.activation, config.residual, r)
                       for r in x])
    assert np.all(np.abs(y32 - y64) <= bounds)
    assert 0 < np.max(np.abs(y32 - y64)) and np.max(bounds[:, 0]) < 1e-4 and np.max(bounds[:, 1]) < 1e-3


def test_the_load_estimate_is_within_its_bound_at_the_thresholds_too():
    from controllers.load_estimate import MIN_CURRENT, MIN_VOLTAGE

    rng = np.random.default_rng(4)
    voltages = [MIN_VOLTAGE, np.nextafter(MIN_VOLTAGE, 1), np.float32(MIN_VOLTAGE), 0.0, 12.0, 1e-3]
    currents = [MIN_CURRENT, np.float32(MIN_CURRENT), np.nextafter(MIN_CURRENT, 1), 0.0, math.nan, 2.0]
    cases = [(float(v), float(i), float(j)) for v in voltages for i in currents for j in currents]
    cases += [tuple(row) for row in rng.uniform(-1, 15, (500, 3))]
    for vo, io, il in cases:
        d64 = native.estimate_conductance(vo, io, il, 0.125)
        d32 = native.estimate_conductance(vo, io, il, 0.125, precision="float32")
        value, bound = float32.conductance_bound(vo, io, il, 0.125)
        assert d64 == value and abs(d32 - d64) <= bound, (vo, io, il, d32, d64, bound)


def test_the_float32_controller_fmus_give_the_float32_twins_duties(tmp_path):
    """export-controller --precision float32: the FMU (f32_*.c wrappers, float data) driven by the master gives
    the in-process float32 twin's duty at every sample, bit for bit; fmpy's validation finds nothing."""
    from fmpy.validation import validate_fmu

    from cosim.fmi.controller import open_controller
    from cosim.fmi.controller_export import export_controller

    for controller in controllers("switched"):
        binary, source = export_controller(controller, tmp_path / f"{controller.name.replace('-', '_')}.fmu",
                                           precision="float32")
        assert validate_fmu(str(binary)) == []
        fmu = open_controller(str(binary))
        assert "float32 build" in fmu.describe()["description"]
        twin = native.native_twin(controller, "float32")
        for mode in MODES:
            scenario = replace(scenarios_for(SWITCHING_PERIOD, ("reference_up",), spec=PAPER_SPEC)[0], duration=0.002,
                               settle=0.001)
            frames = [simulate(plant_binding("nominal", mode), c, scenario).frame for c in (twin, fmu)]
            ours, exported = (f.loc[f["control_sample"], "duty_cycle"].to_numpy() for f in frames)
            assert len(ours) == 151 and np.array_equal(ours, exported), (controller.name, mode)
        fmu.close()


def test_a_float32_header_refuses_a_double_compilation(tmp_path):
    from controllers.codegen import config_header

    header = config_header(controllers("averaged")[0], precision="float32")
    assert "#error" in header and ".kp = 0.007026879f" not in header  # averaged gains, float literals
    assert ".kp = 0.008292317f" in header
    source = tmp_path / "probe.c"
    (tmp_path / "controller_config.h").write_text(header)
    source.write_text('#include "controller_config.h"\nint main(void) { return (int)PI_CONFIG.kp; }\n')
    import subprocess

    argv = [*native.compiler(), "-std=c99", f"-I{native.SOURCE_DIR}",
            f"-I{Path(native.__file__).parents[1] / 'cosim' / 'fmi' / 'controller_fmu'}", "-fsyntax-only", str(source)]
    done = subprocess.run([*argv, f"-I{tmp_path}"], capture_output=True, text=True)
    assert done.returncode != 0 and "compile with -DBUCKC_FLOAT32" in done.stderr
    assert subprocess.run([*argv, f"-I{tmp_path}", "-DBUCKC_FLOAT32"], capture_output=True).returncode == 0


def test_export_controller_float32_refuses_a_controller_without_a_float32_build(tmp_path):
    from conftest import cli, one_line_error

    done = cli("export-controller", "nnpc", "--precision", "float32", "--out", str(tmp_path / "n.fmu"))
    one_line_error(done, 2, "nnpc has no float32 controller FMU")
    assert not list(tmp_path.iterdir())


def test_the_float32_rollouts_follow_the_float32_forward_pass():
    """The rollout and the shared-history rollout of nn_model.c in float32: the same numbers as feeding the
    float32 forward pass its own predictions, and within 1e-4 of the double rollout over 23 steps."""
    model = load_model(FIXTURES / "nnpc_nominal_averaged_13p33us.pt", expect_period=SWITCHING_PERIOD)
    c32, c64 = native.nn_config(model, "float32"), native.nn_config(model)
    history = np.array([[2.0, 11.9, 0.26], [2.1, 11.8, 0.25]])
    duties = np.random.default_rng(2).uniform(0.2, 0.3, (3, 23))
    extras = np.array([1 / 6.0])
    rolled = native.nn_rollout(c32, np.repeat(history[None], 3, axis=0), duties, np.repeat(extras[None], 3, axis=0))
    shared = native.nn_rollout_shared(c32, history, duties, extras)
    assert np.array_equal(rolled, shared)
    window = np.float32(history).copy()
    for j in range(3):
        window[0, 2] = duties[0, j]
        y = native.nn_forward(c32, np.concatenate([window.ravel(), extras]))[0]
        assert np.array_equal(y, rolled[0, j])
        window = np.vstack([[y[0], y[1], 0.0], window[:-1]]).astype(np.float32)
    double = native.nn_rollout(c64, np.repeat(history[None], 3, axis=0), duties, np.repeat(extras[None], 3, axis=0))
    assert 0 < np.max(np.abs(rolled - double)) < 1e-4
