"""The float32 controllers on a Cortex-M4F (cosim/benchmark_harness/cortex_m4.py): the trace counter and
the TRM cycle table on a known trace, and (marker ``embedded``: the cross toolchain and QEMU) the
bare-metal image replaying recorded closed-loop measurements in qemu-system-arm -M mps2-an386, its
duties against the host's float32 build, its counts and its footprint."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from controllers import float32, native
from controllers.base import Measurement
from controllers.explicit_policy import load_policy
from controllers.pi import PIController
from cosim.benchmark_harness import cortex_m4, record_measurements
from cosim.benchmark_harness.cortex_m4 import CYCLE_TABLE, CYCLE_TABLE_LOW, count_steps
from cosim.design.experiments import explicit_nnpc, scenarios_for
from cosim.design.plants import plant_binding
from cosim.design.vocabulary import SWITCHING_PERIOD
from cosim.study.vocabulary import PAPER_SPEC

FIXTURES = Path(__file__).parent / "fixtures"

#: a hand-made QEMU log: main calls the markers around a step that runs one block, then one that returns
TRACE = """\
----------------
IN: main
0x00000100:  f000 f810  bl       #0x124

Trace 0: 0x7f0000000100 [00000000/00000100/00000110/ff000200] main
----------------
IN: buckc_step_begin
0x00000124:  4770       bx       lr

Trace 0: 0x7f0000000200 [00000000/00000124/00000110/ff000200] buckc_step_begin
----------------
IN: main
0x00000104:  f000 f800  bl       #0x200

Trace 0: 0x7f0000000300 [00000000/00000104/00000110/ff000200] main
----------------
IN: step
0x00000200:  ed9f 7a02  vldr     s14, [pc, #8]
0x00000204:  ee87 0a87  vdiv.f32 s0, s15, s14
0x00000208:  2800       cmp      r0, #0
0x0000020a:  d001       beq      #0x210

Trace 0: 0x7f0000000400 [00000000/00000200/00000110/ff000200] step
----------------
IN: step
0x0000020c:  b510       push     {r4, lr}
0x0000020e:  bd10       pop      {r4, pc}

Trace 0: 0x7f0000000500 [00000000/0000020c/00000110/ff000200] step
----------------
IN: main
0x00000108:  f000 f80e  bl       #0x128

Trace 0: 0x7f0000000600 [00000000/00000108/00000110/ff000200] main
----------------
IN: buckc_step_end
0x00000128:  4770       bx       lr

Trace 0: 0x7f0000000700 [00000000/00000128/00000110/ff000200] buckc_step_end
Trace 0: 0x7f0000000100 [00000000/00000100/00000110/ff000200] main
Trace 0: 0x7f0000000200 [00000000/00000124/00000110/ff000200] buckc_step_begin
Trace 0: 0x7f0000000300 [00000000/00000104/00000110/ff000200] main
Trace 0: 0x7f0000000400 [00000000/00000200/00000110/ff000200] step
----------------
IN: step
0x00000210:  4770       bx       lr

Trace 0: 0x7f0000000800 [00000000/00000210/00000110/ff000200] step
Trace 0: 0x7f0000000600 [00000000/00000108/00000110/ff000200] main
Trace 0: 0x7f0000000700 [00000000/00000128/00000110/ff000200] buckc_step_end
"""
SYMBOLS = {"main": (0x100, 0x20), "buckc_step_begin": (0x124, 2), "buckc_step_end": (0x128, 2), "step": (0x200, 0x12)}


def test_the_trace_counter_counts_the_steps_instructions_and_prices_them_by_the_trm(tmp_path):
    """Step 1 falls through its beq (not taken) into push/pop {pc}; step 2 takes the beq to a bx lr. The
    replay loop's own instructions (main) and the markers are not the controller's."""
    log = tmp_path / "trace.log"
    log.write_text(TRACE)
    instructions, high, low, mix, functions = count_steps(log, SYMBOLS, samples=2)
    assert instructions.tolist() == [6, 5]
    # vldr [pc] 2 (+1 literal, upper) + vdiv 14 + cmp 1 + beq not taken 1 + push {r4, lr} 1+2 + pop {r4, pc} 1+2+P
    assert high[0] == 3 + 14 + 1 + 1 + 3 + 3 + CYCLE_TABLE.refill
    # vldr + vdiv + cmp + beq taken (1+P) + bx lr (1+P)
    assert high[1] == 3 + 14 + 1 + (1 + CYCLE_TABLE.refill) + (1 + CYCLE_TABLE.refill)
    assert low[1] == 2 + 14 + 1 + (1 + CYCLE_TABLE_LOW.refill) + (1 + CYCLE_TABLE_LOW.refill)
    assert mix["fp-div/sqrt"] == 2 and mix["branch"] == 2 + 1 and set(functions) == {"step"}


def test_a_trace_with_a_missing_step_is_an_error(tmp_path):
    log = tmp_path / "trace.log"
    log.write_text(TRACE)
    with pytest.raises(cortex_m4.EmbeddedError, match="holds 2 steps, the replay 3"):
        count_steps(log, SYMBOLS, samples=3)


@pytest.mark.parametrize("mnemonic,operands,taken,previous,upper,lower", [
    # FPU table: arithmetic 1, multiply-accumulate (chained or fused) 3, VDIV/VSQRT 14, VPUSH/VLDM 1 + N singles
    ("vmul.f32", "s15, s14, s15", False, None, 1, 1), ("vmla.f32", "s0, s1, s2", False, None, 3, 3),
    ("vfma.f32", "s12, s14, s13", False, None, 3, 3), ("vsqrt.f32", "s0, s0", False, None, 14, 14),
    ("vpush", "{d8, d9}", False, None, 5, 5), ("vldmia", "r3!, {s16, s17, s18}", False, None, 4, 4),
    # VMOV: one single <-> one core register 2 (corrected: was 1), two <-> two 2, immediate / S <- S / half of D 1
    ("vmov", "r3, s0", False, None, 2, 2), ("vmov", "s15, r3", False, None, 2, 2),
    ("vmov", "r0, r1, d0", False, None, 2, 2),
    ("vmov.f32", "s15, #1.000000e+00", False, None, 1, 1), ("vmovgt.f32", "s0, s1", False, None, 1, 1),
    ("vmov.32", "r0, d0[1]", False, None, 1, 1), ("vmrs", "apsr_nzcv, fpscr", False, None, 1, 1),
    # VLDR of a double 3 (corrected: was 2), of a single 2; a literal load one more in the upper reading
    ("vldr", "d8, [r3]", False, None, 3, 3), ("vldr", "s14, [r1, #0x28]", False, None, 2, 2),
    ("ldr", "r0, [pc, #0x68]", False, None, 3, 2),
    # 3.3.2: STR with an immediate offset always 1 (corrected: was 2); with a register offset 2
    ("str", "r5, [r2, #4]", False, None, 1, 1), ("strb", "r3, [r6], #1", False, None, 1, 1),
    ("str", "r1, [r3, r2]", False, None, 2, 2), ("str", "r1, [r3, r2]", False, ("ldr", "r0, [r4]"), 2, 1),
    # 3.3.2: a single load pipelines behind a single load (lower reading) unless that load forms its address,
    # never behind a store (corrected: the lower reading pipelined behind any load or store)
    ("ldr.w", "r3, [r2, #4]", False, None, 2, 2), ("ldr", "r3, [r2]", False, ("ldr", "r1, [r0]"), 2, 1),
    ("ldr", "r3, [r1]", False, ("ldr", "r1, [r0]"), 2, 2), ("ldr", "r3, [r2]", False, ("str", "r1, [r0]"), 2, 2),
    ("ldrd", "r2, r4, [sp, #0xc]", False, ("ldr", "r1, [r0]"), 3, 3), ("ldr", "pc, [sp], #4", True, None, 5, 3),
    # 3.3.2: an address formed by the preceding data-processing instruction stalls one cycle (added)
    ("ldr", "r3, [r2, #4]", False, ("adds", "r2, #4"), 3, 3),
    ("vldr", "s14, [lr, #32]", False, ("add.w", "lr, r3, r7"), 3, 3),
    ("ldr", "r0, [r2]", False, ("bic", "r2, r2, #3"), 3, 3), ("ldr", "r0, [r2]", False, ("cmp", "r2, #0"), 2, 2),
    ("push", "{r4, lr}", False, ("sub", "sp, #8"), 4, 4), ("ldr", "r0, [r2]", False, ("vmov", "r2, s0"), 2, 2),
    # Table 3-1: branches 1 + P taken, 1 not; TBB 2 + P (the upper reading 3 + P: 3.3.2's "at least six")
    ("bls", "#0x40", True, None, 4, 2), ("bls", "#0x40", False, None, 1, 1), ("bl", "#0x800", True, None, 4, 2),
    ("cbz", "r0, #0x20", False, None, 1, 1), ("tbb", "[pc, r3]", True, None, 6, 3),
    ("pop", "{r4, r5, r6, pc}", True, None, 8, 6),
    ("pop.w", "{r4, r5, r6, r7, r8, sb, sl, fp, pc}", True, None, 13, 11),
    # Table 3-1: SDIV 2-12, the multiplies 1 (MLA and the long ones too, on the M4)
    ("sdiv", "r0, r1, r2", False, None, 12, 2), ("muls", "r0, r1, r0", False, None, 1, 1),
    ("mla", "r0, r1, r2, r3", False, None, 1, 1), ("umull", "r2, r3, r6, r1", False, None, 1, 1),
    ("movs", "r0, #1", False, None, 1, 1), ("mov", "pc, lr", True, None, 4, 2)])
def test_the_cycle_table_follows_the_trm(mnemonic, operands, taken, previous, upper, lower):
    assert CYCLE_TABLE.cycles(mnemonic, operands, taken, previous) == upper
    assert CYCLE_TABLE_LOW.cycles(mnemonic, operands, taken, previous) == lower


# ------------------------------------------------------------------ on the emulated Cortex-M4F


def _recorded(controller, count: int = 150):
    """A short closed loop on the nominal switched plant: start-up from rest (saturation, the load estimate's
    threshold) and a load step."""
    scenarios = scenarios_for(SWITCHING_PERIOD, ("startup", "load_change"), spec=PAPER_SPEC)
    rows = [record_measurements(plant_binding("nominal", "switched"), native.native_twin(controller),
                                replace(s, duration=0.001)) for s in scenarios]
    return np.concatenate(rows)[: 2 * count]


def _host_float32(controller, measurements) -> np.ndarray:
    twin = native.native_twin(controller, "float32")
    twin.reset()
    return np.array([twin.step(Measurement(*row)) for row in measurements])


@pytest.mark.embedded
def test_the_pi_on_the_cortex_m4f_gives_the_host_float32_duties_bit_for_bit(tmp_path):
    """No libm in the PI: the same float operations in the same order on both targets."""
    pi = PIController(0.007026878992716469, 172.92168103154324, SWITCHING_PERIOD)
    measurements = _recorded(pi)
    measured = cortex_m4.measure(pi, measurements, keep=tmp_path)
    run = measured.replay
    assert np.array_equal(run.duty, _host_float32(pi, measurements))
    assert len(run.instructions) == len(measurements) and 20 <= run.instructions.min() <= run.instructions.max() < 80
    assert np.all(run.instructions <= run.cycles_low) and np.all(run.cycles_low <= run.cycles)
    assert measured.footprint.flash > 0 and measured.footprint.bss >= 24  # BuckcPi: five floats and the integral
    assert (tmp_path / "controller.o").is_file() and measured.footprint.object_sizes["text"] > 0


@pytest.mark.embedded
def test_the_explicit_nnpc_on_the_cortex_m4f_gives_the_host_float32_duties_bit_for_bit():
    """Its tanh is buckc_tanhf (no libm): the target's duties are the host float32 build's, bit for bit, and
    the step calls no library function. The trace sees the network's work: >= 3 instructions per
    multiply-accumulate (the weight's load, the multiply, the add), a division per step (the load estimate)
    and one per tanh not saturated, on most steps."""
    policy = load_policy(FIXTURES / "explicit_nominal_switched_13p33us.pt", expect_period=SWITCHING_PERIOD)
    controller = explicit_nnpc(policy)
    measurements = _recorded(controller, 60)
    measured = cortex_m4.measure(controller, measurements)
    run = measured.replay
    assert np.array_equal(run.duty, _host_float32(controller, measurements))
    macs = policy.config.macs()
    assert np.all(run.instructions >= 3 * macs)
    assert len(measurements) < run.mix["fp-div/sqrt"] <= 15 * len(measurements)
    assert run.functions["buckc_policy_forward"] > 0 and all(name.startswith("buckc_") for name in run.functions)
    # the configuration of 7-14-1 floats (weights and biases) is in the flash the controller adds
    assert measured.footprint.flash >= 4 * (7 * 14 + 14 + 14 + 1)
    assert 0 < run.stack_bytes <= 1024
    assert measured.stack_usage["buckc_policy_forward"] > 0


@pytest.mark.embedded
@pytest.mark.parametrize("index", [0, 1], ids=["current-mode", "Type-III"])
def test_the_classical_controllers_on_the_cortex_m4f_give_the_host_float32_duties_bit_for_bit(index):
    """The current-mode controller and the Type-III as make reproduce designs them (nominal switched plant,
    13.33 us): no libm in their steps, so the target's duties are the host float32 build's, bit for bit, on a
    replay that saturates and regulates; their state is all the RAM they take beside the stack."""
    import ctypes

    from cosim.design.classical_design import design_current_mode, design_type_iii, targets_for
    from cosim.design.vocabulary import NOMINAL

    targets = targets_for(plant_binding("nominal", "switched"), SWITCHING_PERIOD)
    controller = (design_current_mode, design_type_iii)[index](NOMINAL, targets).controller
    measurements = _recorded(controller)
    measured = cortex_m4.measure(controller, measurements)
    run = measured.replay
    host = _host_float32(controller, measurements)
    assert np.array_equal(run.duty, host)
    assert np.any((host > 0) & (host < 1)) and np.any(host == 0) | np.any(host == 1)
    assert 40 <= run.instructions.min() <= run.instructions.max() < 200  # two PIs or a third-order filter
    assert np.all(run.instructions <= run.cycles_low) and np.all(run.cycles_low <= run.cycles)
    assert run.mix["fp-div/sqrt"] == len(measurements)  # the input-voltage feed-forward: one VDIV per step
    state = (native.real_mirrors("float32").CurrentModeC, native.real_mirrors("float32").CompensatorC)[index]
    assert measured.footprint.bss == ctypes.sizeof(state) and measured.footprint.data == 0
    assert 0 < measured.footprint.flash < 4096 and 0 <= run.stack_bytes <= 64


@pytest.mark.embedded
def test_the_tanh_probe_measures_buckc_tanhf_on_the_cortex_m4f():
    """The target's buckc_tanhf within float32.TANH_ERROR of tanh on the probe's 256 arguments in [-4.5, 4.5);
    a call costs its VDIV (14), the polynomial's 12 operations and the rest: 40 to 80 cycles, the lower
    reading at most the upper."""
    probe = cortex_m4.measure_tanh()
    assert len(probe.values) == 256 and probe.arguments[0] == -4.5 and probe.arguments[-1] < 4.5
    assert np.max(np.abs(probe.values - np.tanh(probe.arguments))) <= float32.TANH_ERROR
    assert np.all((40 <= probe.cycles_low) & (probe.cycles_low <= probe.cycles) & (probe.cycles <= 80))


@pytest.mark.embedded
def test_a_controller_without_a_cortex_m4f_build_is_refused_by_name():
    """The MPC baselines' circuit predictors compute in double only (predictors.c); a controller without a C twin
    has no float32 build either."""
    from controllers.base import Controller
    from cosim.design.experiments import model_mpc
    from cosim.design.vocabulary import NOMINAL

    mpc = model_mpc(NOMINAL, SWITCHING_PERIOD, "MPC-oracle")
    with pytest.raises(ValueError, match="MPC-oracle has no float32 build: its AveragedModelPredictor"):
        cortex_m4.measure(mpc, np.zeros((2, 6)))

    class Hold(Controller):
        name = "hold"
        sample_period = SWITCHING_PERIOD

        def step(self, measurement):
            return 0.25

    with pytest.raises(ValueError, match="'hold' \\(Hold\\) has no C twin to generate"):
        cortex_m4.measure(Hold(), np.zeros((2, 6)))


def _online_nnpc(horizon: int | None = None):
    """The online NNPC with the real-time iteration at 13.33 us on the fixture network (7-7-2); ``horizon``: a
    shorter one keeps the search's fallback steps small enough to trace in a test."""
    from controllers.nn_model import load_model
    from cosim.design.experiments import nnpc

    model = load_model(FIXTURES / "nnpc_nominal_averaged_13p33us.pt", expect_period=SWITCHING_PERIOD)
    return nnpc(model, SWITCHING_PERIOD, "NNPC (rti)", horizon=horizon, optimizer="rti")


def _double_twin(controller, measurements):
    """(duties, solver per step) of the double C twin on ``measurements``."""
    twin = native.native_twin(controller)
    twin.reset()
    duties, solvers = [], []
    for row in measurements:
        duties.append(twin.step(Measurement(*row)))
        solvers.append(twin.last_solver)
    return np.array(duties), np.array(solvers)


#: one count of a 13-bit DPWM (the duty resolution the 1 ms NNPC rounds to): the float32 online NNPC's duties stay
#: within it of the double twin's. Not a derived bound -- an optimizer's plan is not Lipschitz in its rounding --
#: but the resolution a converter's PWM has; measured on the replays: 2.7e-5 (13.33 us, 8-10-2), 1.8e-8 (1 ms)
DPWM_COUNT = 1.0 / 8192


def test_the_online_nnpcs_float32_build_stays_within_a_pwm_count_of_the_double_twin():
    """The host's float32 build of the Cortex-M4F image (no cross toolchain needed) on a recorded start-up and load
    change at 13.33 us: the RTI and the search it falls back to (the start-up region), in float, command what the
    double twin commands to within one DPWM count, and not the same bits (it is the float32 build)."""
    controller = _online_nnpc()
    measurements = _recorded(controller)
    host = cortex_m4.host_replay(controller, measurements)
    duty64, solvers = _double_twin(controller, measurements)
    assert {"rti", "search"} <= set(solvers)
    assert np.all(host == host.astype(np.float32)) and not np.array_equal(host, duty64)
    assert np.max(np.abs(host - duty64)) <= DPWM_COUNT


@pytest.mark.embedded
def test_the_online_nnpc_with_the_rti_on_the_cortex_m4f_gives_the_host_float32_duties_bit_for_bit():
    """predictive.c's float32 build with the NN predictor on the target: the same duties as the host's float32
    build of the same image, bit for bit (sqrtf and floorf are exact in both libms, the discount's powers are
    products). The search's fallback steps (the cold start and the start-up region) execute far more than an RTI
    step, which is the network's sensitivity pass, the Gauss-Newton model and the box QP."""
    controller = _online_nnpc(horizon=4)
    measurements = _recorded(controller, 30)  # 60 samples of the start-up: the search plans it to within 0.1 V
    measured = cortex_m4.measure(controller, measurements)
    run = measured.replay
    assert np.array_equal(run.duty, cortex_m4.host_replay(controller, measurements))
    _, solvers = _double_twin(controller, measurements)
    rti = solvers == "rti"
    assert 0 < np.count_nonzero(~rti) < np.count_nonzero(rti)
    assert run.instructions[~rti].min() > 10 * run.instructions[rti].max()
    for name in ("buckc_nn_sensitivities", "rti_model", "buckc_box_qp", "buckc_optimizer_solve"):
        assert run.functions[name] > 0, name
    assert np.all(run.instructions <= run.cycles_low) and np.all(run.cycles_low <= run.cycles)
    assert 0 < measured.footprint.flash < 24 * 1024 and 0 < run.stack_bytes <= 4096


def test_the_replay_data_are_the_floats_the_host_build_gets():
    rows = np.array([[0.1, 12.0, 1 / 3, np.nan, 1e-7, 48.0]])
    header = cortex_m4.replay_header(rows)
    literals = header.split("{", 2)[2].split("}")[0].split(", ")
    assert literals[3] == "NAN"
    for text, value in zip(literals, rows[0]):
        if text != "NAN":
            assert np.float32(text.rstrip("f")) == np.float32(value), (text, value)
    assert float32.U > 2.0 ** -24  # the bound covers the double build's rounding too


@pytest.mark.embedded
def test_export_controller_writes_the_object_a_firmware_links(tmp_path):
    """export-controller --precision float32 --cortex-m4 DIR: controller.o defines the three calls of
    buckc_controller.h and needs only newlib's libm; a firmware for an STM32G4 memory map links it."""
    import subprocess

    from conftest import cli, one_line_error

    (tmp_path / "afile").write_text("x")  # a folder that cannot be made is refused before the FMU is written
    one_line_error(cli("export-controller", "pi", "--kp", "0.007", "--ki", "170", "--control-period", "1/75e3",
                       "--precision", "float32", "--out", str(tmp_path / "pi.fmu"), "--cortex-m4",
                       str(tmp_path / "afile" / "m4")), 2, f"cannot create output folder {tmp_path / 'afile' / 'm4'}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]
    done = cli("export-controller", "pi", "--kp", "0.007", "--ki", "170", "--control-period", "1/75e3", "--precision",
               "float32", "--out", str(tmp_path / "pi.fmu"), "--cortex-m4", str(tmp_path / "m4"))
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in (tmp_path / "m4").iterdir()) == ["buckc.h", "buckc_controller.h", "buckc_tanhf.h",
                                                                   "controller.o", "controller_config.h"]
    symbols = subprocess.run(["arm-none-eabi-nm", str(tmp_path / "m4" / "controller.o")], capture_output=True,
                             text=True).stdout
    for name in ("buckc_controller_init", "buckc_controller_reset", "buckc_controller_step"):
        assert f" T {name}" in symbols
    main = tmp_path / "main.c"
    main.write_text('#include "buckc_controller.h"\nvolatile float vo, out;\nint main(void) {\n'
                    '    const char *what; buckc_real duty = 0; BuckcMeasurement m = {0, 12, 0, 1, 1, 48};\n'
                    '    if (buckc_controller_init(&what) != BUCKC_OK) return 1;\n    m.output_voltage = vo;\n'
                    '    buckc_controller_step(&m, &duty); out = duty; return 0;\n}\n')
    script = tmp_path / "g4.ld"  # the image's linker script with an STM32G474's flash and SRAM
    script.write_text(cortex_m4.LINKER_SCRIPT.read_text()
                      .replace("ORIGIN = 0x00000000, LENGTH = 1M", "ORIGIN = 0x08000000, LENGTH = 512K")
                      .replace("ORIGIN = 0x20000000, LENGTH = 1M", "ORIGIN = 0x20000000, LENGTH = 128K"))
    arm = ["arm-none-eabi-gcc", *cortex_m4.ARM_FLAGS]
    link = subprocess.run([*arm, "-O2", "-DBUCKC_FLOAT32", f"-I{tmp_path / 'm4'}", f"-I{cortex_m4.HERE}",
                           *cortex_m4.LINK_FLAGS, "-T", str(script), str(cortex_m4.HERE / "startup.c"),
                           str(cortex_m4.HERE / "semihosting.c"), str(main), str(tmp_path / "m4" / "controller.o"),
                           "-lm", "-o", str(tmp_path / "fw.elf")], capture_output=True, text=True)
    assert link.returncode == 0, link.stderr
    table = subprocess.run(["arm-none-eabi-nm", str(tmp_path / "fw.elf")], capture_output=True, text=True).stdout
    assert any(line.startswith("08") and line.endswith(" T buckc_controller_step") for line in table.splitlines())


@pytest.mark.embedded
def test_export_controller_writes_the_type_iii_for_a_cortex_m4f(tmp_path):
    """export-controller type-iii --precision float32 --cortex-m4 DIR: the classical controllers have a float32
    build too; their controller.o needs no library function at all."""
    import subprocess

    from conftest import cli

    done = cli("export-controller", "type-iii", "--control-period", "1/75e3", "--precision", "float32", "--out",
               str(tmp_path / "t3.fmu"), "--cortex-m4", str(tmp_path / "m4"))
    assert done.returncode == 0, done.stderr
    symbols = subprocess.run(["arm-none-eabi-nm", str(tmp_path / "m4" / "controller.o")], capture_output=True,
                             text=True).stdout
    assert " T buckc_compensator_step" in symbols and " T buckc_controller_step" in symbols
    assert [line.split()[-1] for line in symbols.splitlines() if line.split()[0] == "U"] == []
