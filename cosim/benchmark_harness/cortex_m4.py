"""The float32 controllers on a Cortex-M4F, measured without a chip.

The float32 build of a C twin (``controllers/c``, ``buckc_real`` = float) is cross-compiled with the
GNU Arm Embedded toolchain of the distribution (``gcc-arm-none-eabi``, newlib's libm) for a Cortex-M4
with its single-precision FPU, into a bare-metal image of our own (``cortex_m4/``: vector table and
start-up code, linker script, semihosting, the replay loop; no vendor SDK), which QEMU's Cortex-M4
machine (``qemu-system-arm -M mps2-an386``) executes:

* :func:`replay_on_cortex_m4` replays recorded measurements through the controller's step and reads
  the duties back (semihosting), to compare with the host's float32 build;
* the same run with QEMU's execution trace (``-d exec,nochain,in_asm``: every translated block's
  instructions and every block executed) gives the **instructions executed per step** and, from the
  executed instruction mix, the **cycles** per step by the Cortex-M4 TRM's cycle tables
  (:data:`CYCLE_TABLE`: each entry, its source and the assumptions in its docstring); the Debian QEMU
  ships no TCG plugins, and ``-icount`` with the board's 25 MHz timers resolves only 40 instructions,
  so the trace it is;
* :func:`footprint` links the controller object once with a minimal main and once without it: the
  difference in text, data and bss is the controller's flash and RAM, its library functions
  included; the replay measures the stack the steps use (a painted stack) and ``-fstack-usage``
  gives each function's frame;
* :func:`measure_tanh` runs the tanh probe (``cortex_m4/tanh_probe.c``): what the float32 build's
  tanh costs a call, the cost model's calibration (:mod:`controllers.cost_model`).

**Adding a controller** is a row of :data:`EMBEDDED_CONTROLLERS`: the ``controllers/codegen.py`` kind
whose float32 configuration it reads, its C files (which must have a float32 build), the C type of its
state and C expressions for init, reset and step over the names ``state``, ``what``, ``m``, ``duty``
(and, optionally, the struct maxima to build it with). The build, the replay, the counts, the cycles
and the footprint follow from the row.
"""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import tempfile
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from controllers.codegen import (
    KIND_COMPENSATOR,
    KIND_CURRENT_MODE,
    KIND_EXPLICIT,
    KIND_PI,
    KIND_PREDICTIVE,
    config_header,
    controller_kind,
)
from controllers.native import FLOAT32_SOURCES, SOURCE_DIR, cache_dir, compiler
from controllers.predictive import FULL_GRID_LIMIT

HERE = Path(__file__).parent / "cortex_m4"
CONTROLLER_FMU_DIR = Path(__file__).resolve().parents[1] / "fmi" / "controller_fmu"

#: the target: a Cortex-M4 with the FPv4 single-precision FPU, hard-float ABI (the issue's flags)
ARM_FLAGS = ("-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard")
#: -O2 as the issue asks; -ffp-contract=off as on the host (no fused multiply-add: the same roundings as the
#: host float32 build; VMLA/VFMA cost 3 cycles on the M4, a VMUL and a VADD 1 each, so fusing saves nothing);
#: -Wdouble-promotion: no expression silently in double (software floating point on this core)
C_FLAGS = ("-O2", "-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-Wdouble-promotion", "-ffp-contract=off",
           "-ffunction-sections", "-fdata-sections", "-fstack-usage", "-DBUCKC_FLOAT32")
LINK_FLAGS = ("-nostartfiles", "--specs=nano.specs", "--specs=nosys.specs", "-Wl,--gc-sections")
LIBRARIES = ("-lm",)
LINKER_SCRIPT = HERE / "mps2_an386.ld"
QEMU = ("qemu-system-arm", "-M", "mps2-an386", "-cpu", "cortex-m4", "-nographic", "-monitor", "none", "-serial",
        "none", "-semihosting-config", "enable=on,target=native")
TOOLS = ("arm-none-eabi-gcc", "arm-none-eabi-size", "arm-none-eabi-nm", "qemu-system-arm")
#: the Debian packages that provide them (scripts/bootstrap.sh installs them when run as root)
PACKAGES = ("gcc-arm-none-eabi", "libnewlib-arm-none-eabi", "qemu-system-arm")
#: ISR entry (12 cycles) and exit (12), lazy stacking of the FP context when the step uses the FPU
#: (+18: 17 words pushed, ARMv7-M), the ADC result read and the PWM compare write over the bus: an allowance,
#: the same as the cost model's (controllers.cost_model.CostModel.interrupt)
ISR_ALLOWANCE = 200.0
#: the exception frame of an interrupt with FP context (ARMv7-M: 8 + 18 words), counted in the controller's RAM
EXCEPTION_FRAME_BYTES = 26 * 4
CLOCK_HZ = 170e6  # an STM32G4 at full speed
TIMEOUT_S = 300


class EmbeddedError(RuntimeError):
    """The cross build or the emulator failed; the message says which command and why."""


# ------------------------------------------------------------------------------------------ the controllers


@dataclass(frozen=True)
class EmbeddedController:
    """How the controller object (``cortex_m4/controller_instance.c``) drives one C twin."""

    label: str
    kind: str  # controllers.codegen's kind: the configuration the generated header holds
    sources: tuple[str, ...]  # its files in controllers/c (each with a float32 build)
    state: str  # the C type of its state
    init: str  # C expressions over `state`, `what`, `m`, `duty`
    reset: str
    step: str
    limits: Callable[[object], dict[str, int]] = field(default=lambda controller: {})  # -D maxima for its struct


def _policy_limits(controller) -> dict[str, int]:
    hidden = controller.policy.config.hidden
    return {"BUCKC_POLICY_MAX_WIDTH": max(7, *hidden), "BUCKC_POLICY_MAX_HIDDEN_LAYERS": len(hidden)}


def _predictive_limits(controller) -> dict[str, int]:
    """The online NNPC's maxima sized to its network and horizon (predictive.h's and nn_model.h's defaults fit
    every configuration the host runs: a 32-wide, 4-layer network's weights and a 16-block, 640-move lattice, 30 KiB
    of flash and 11 KiB of RAM a Cortex-M4F build does not need). The search's pattern moves are at most
    1 + 8 nb + 2 nb (nb - 1) + 8 (predictive.c), a full lattice at most FULL_GRID_LIMIT."""
    network, settings = controller.predictor.model.config, controller.settings
    blocks = len(settings.blocks)
    return {"BUCKC_NN_MAX_WIDTH": max(network.n_inputs, *network.hidden),
            "BUCKC_NN_MAX_HIDDEN_LAYERS": len(network.hidden), "BUCKC_MAX_HORIZON": settings.horizon,
            "BUCKC_MAX_BLOCKS": blocks, "BUCKC_MAX_LEVELS": settings.levels,
            "BUCKC_MAX_LATTICE": max(FULL_GRID_LIMIT, 1 + 8 * blocks + 2 * blocks * (blocks - 1) + 8)}


#: one row per controller that runs on the Cortex-M4F
EMBEDDED_CONTROLLERS = (
    EmbeddedController("PI", KIND_PI, ("pi.c",), "BuckcPi", "buckc_pi_init(state, &PI_CONFIG, what)",
                       "buckc_pi_reset(state)",
                       "(*duty = buckc_pi_step(state, m->reference, m->output_voltage), BUCKC_OK)"),
    EmbeddedController("explicit NNPC", KIND_EXPLICIT, ("explicit_policy.c", "load_estimate.c"), "BuckcPolicy",
                       "buckc_policy_init(state, &POLICY_CONFIG, what)", "buckc_policy_reset(state)",
                       "buckc_policy_step(state, m, duty)", _policy_limits),
    EmbeddedController("current-mode", KIND_CURRENT_MODE, ("current_mode.c",), "BuckcCurrentMode",
                       "buckc_current_mode_init(state, &CURRENT_MODE_CONFIG, what)", "buckc_current_mode_reset(state)",
                       "buckc_current_mode_step(state, m, duty)"),
    EmbeddedController("Type-III", KIND_COMPENSATOR, ("compensator.c",), "BuckcCompensator",
                       "buckc_compensator_init(state, &COMPENSATOR_CONFIG, what)", "buckc_compensator_reset(state)",
                       "buckc_compensator_step(state, m, duty)"),
    # the NN predictor's controller (the circuit predictors have no float32 build: codegen refuses them), with the
    # optimizer its settings choose: the real-time iteration and the search it falls back to, or the search alone
    EmbeddedController("online NNPC", KIND_PREDICTIVE, ("predictive.c", "nn_model.c", "box_qp.c", "load_estimate.c"),
                       "BuckcPredictive", "buckc_predictive_init(state, &PREDICTIVE_CONFIG, what)",
                       "buckc_predictive_reset(state)", "buckc_predictive_step(state, m, duty)", _predictive_limits),
)


def embedded_controller(controller) -> EmbeddedController:
    kind = controller_kind(controller)
    for row in EMBEDDED_CONTROLLERS:
        if row.kind == kind:
            return row
    names = ", ".join(row.label for row in EMBEDDED_CONTROLLERS)
    raise ValueError(f"{controller.name} has no Cortex-M4F build: the embedded controllers are {names}")


def entry_header(row: EmbeddedController) -> str:
    """``controller_entry.h``: the row as the controller object's macros (generated, data only)."""
    headers = sorted({f'#include "{Path(s).stem}.h"' for s in row.sources})
    return "\n".join(["/* Generated by buck-cosim (cosim/benchmark_harness/cortex_m4.py) -- do not edit. */",
                      "#ifndef CONTROLLER_ENTRY_H", "#define CONTROLLER_ENTRY_H", *headers,
                      f"#define CONTROLLER_STATE {row.state}", f"#define CONTROLLER_INIT {row.init}",
                      f"#define CONTROLLER_RESET {row.reset}", f"#define CONTROLLER_STEP {row.step}", "#endif", ""])


def _float_literal(value: float) -> str:
    if math.isnan(value):
        return "NAN"
    if math.isinf(value):
        return "INFINITY" if value > 0 else "-INFINITY"
    text = str(np.float32(value))
    return (text if any(c in text for c in ".eEn") else text + ".0") + "f"


def replay_header(measurements: np.ndarray) -> str:
    """``replay_data.h``: the measurements as float32 (the floats the host's float32 build gets too)."""
    rows = np.asarray(measurements, dtype=float)
    body = ",\n".join("    {" + ", ".join(_float_literal(v) for v in row) + "}" for row in rows)
    return "\n".join(["/* Generated by buck-cosim (cosim/benchmark_harness/cortex_m4.py): recorded measurements. */",
                      "#include <math.h>", f"#define REPLAY_SAMPLES {len(rows)}u",
                      f"static const float REPLAY_MEASUREMENTS[{len(rows)}][6] = {{", body, "};", ""])


# ------------------------------------------------------------------------------------------ tools and build


def toolchain_problem() -> str | None:
    """None when the cross compiler, newlib's libm and QEMU are here, else one line saying what is missing."""
    missing = [tool for tool in TOOLS if shutil.which(tool) is None]
    if not missing:
        done = subprocess.run(["arm-none-eabi-gcc", *ARM_FLAGS, "-print-file-name=libm.a"], capture_output=True,
                              text=True, timeout=60)
        if not Path(done.stdout.strip()).is_absolute():
            missing.append("newlib's libm.a (libnewlib-arm-none-eabi)")
    if not missing:
        return None
    return (f"{', '.join(missing)} not found: the Cortex-M4F build needs the Debian packages {' '.join(PACKAGES)} "
            "(make installs them when run as root)")


def _run(argv: list[str], what: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    try:
        done = subprocess.run(argv, capture_output=True, text=True, cwd=cwd, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired) as error:
        raise EmbeddedError(f"{what} failed: {error}") from None
    if done.returncode != 0:
        tail = "\n".join((done.stdout + done.stderr).strip().splitlines()[-12:])
        raise EmbeddedError(f"{what} failed (exit {done.returncode}): {' '.join(argv[:3])} ...\n{tail}")
    return done


@dataclass
class Build:
    """The Cortex-M4F build of one controller: the object a firmware links, and the test images."""

    folder: Path
    row: EmbeddedController
    controller_object: Path  # controller.o: the controller's code, configuration and state (relocatable)
    replay: Path  # replay.elf: the QEMU test image
    footprint: Path  # footprint.elf: a minimal main calling the controller
    baseline: Path  # baseline.elf: the same main without it
    stack_usage: dict[str, int]  # -fstack-usage: bytes of each function's frame (the controller's files)


class _Compiler:
    """arm-none-eabi-gcc with the target's flags, the controller's maxima and the include folders."""

    def __init__(self, controller, row: EmbeddedController, folder: Path):
        self.folder = folder
        self.defines = [f"-D{k}={v}" for k, v in sorted(row.limits(controller).items())]
        self.includes = [f"-I{folder}", f"-I{SOURCE_DIR}", f"-I{CONTROLLER_FMU_DIR}", f"-I{HERE}"]

    def __call__(self, source: Path, output: str, extra: tuple[str, ...] = ()) -> Path:
        target = self.folder / output
        _run(["arm-none-eabi-gcc", *ARM_FLAGS, *C_FLAGS, *self.defines, *self.includes, *extra, "-c", str(source),
              "-o", str(target)], f"cross-compiling {source.name}", self.folder)
        return target


def _generated_headers(controller, folder: Path) -> EmbeddedController:
    """controller_config.h (float32 data) and controller_entry.h (the row) in ``folder``; returns the row."""
    row = embedded_controller(controller)
    folder.mkdir(parents=True, exist_ok=True)
    for name in row.sources:
        if name not in FLOAT32_SOURCES:
            raise EmbeddedError(f"controllers/c/{name} has no float32 build (controllers.native.FLOAT32_SOURCES)")
    (folder / "controller_config.h").write_text(config_header(controller, precision="float32"), encoding="utf-8")
    (folder / "controller_entry.h").write_text(entry_header(row), encoding="utf-8")
    return row


def _controller_object(controller, folder: Path) -> tuple[EmbeddedController, _Compiler, Path]:
    """controller.o in ``folder``: the row's C files and controller_instance.c with the generated headers,
    linked into one relocatable object (``-r``); sections stay apart, so a firmware's --gc-sections keeps
    only what it calls."""
    row = _generated_headers(controller, folder)
    compile_ = _Compiler(controller, row, folder)
    objects = [compile_(SOURCE_DIR / name, f"{Path(name).stem}.o") for name in row.sources]
    objects.append(compile_(HERE / "controller_instance.c", "controller_instance.o"))
    target = folder / "controller.o"
    _run(["arm-none-eabi-gcc", *ARM_FLAGS, "-r", "-nostdlib", *map(str, objects), "-o", str(target)],
         "linking controller.o", folder)
    return row, compile_, target


def export_object(controller, folder: Path) -> Path:
    """The controller as a firmware links it: ``folder``/controller.o (the float32 build for a Cortex-M4F:
    code, configuration, state; see docs/guide/embedded.md) beside the headers a firmware's
    source includes (buckc_controller.h, buckc.h and the buckc_tanhf.h it includes; compile it with
    -DBUCKC_FLOAT32). Returns controller.o."""
    problem = toolchain_problem()
    if problem:
        raise EmbeddedError(problem)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="buck-cosim-m4-", dir=_scratch()) as tmp:
        _, _, built = _controller_object(controller, Path(tmp))
        for path in (built, Path(tmp) / "controller_config.h", HERE / "buckc_controller.h", SOURCE_DIR / "buckc.h",
                     SOURCE_DIR / "buckc_tanhf.h"):
            staged = folder / f".{path.name}.tmp"
            shutil.copyfile(path, staged)
            staged.replace(folder / path.name)
    return folder / "controller.o"


def build(controller, measurements: np.ndarray, folder: Path) -> Build:
    """Cross-compile ``controller``'s float32 build and the images around it into ``folder``."""
    folder = Path(folder)
    row, compile_, controller_object = _controller_object(controller, folder)
    (folder / "replay_data.h").write_text(replay_header(measurements), encoding="utf-8")
    runtime = [compile_(HERE / "startup.c", "startup.o"), compile_(HERE / "semihosting.c", "semihosting.o")]
    images = {}
    for name, objects in (("replay", [compile_(HERE / "replay.c", "replay.o"), controller_object]),
                          ("footprint", [compile_(HERE / "footprint.c", "footprint.o"), controller_object]),
                          ("baseline", [compile_(HERE / "footprint.c", "baseline.o", ("-DBUCKC_BASELINE",))])):
        images[name] = folder / f"{name}.elf"
        _run(["arm-none-eabi-gcc", *ARM_FLAGS, *LINK_FLAGS, "-T", str(LINKER_SCRIPT), f"-Wl,-Map={name}.map",
              *map(str, runtime + objects), *LIBRARIES, "-o", str(images[name])], f"linking {name}.elf", folder)
    usage = {}
    for su in [folder / f"{Path(n).stem}.su" for n in row.sources] + [folder / "controller_instance.su"]:
        for line in su.read_text().splitlines():  # file:line:col:function<TAB>bytes<TAB>static|dynamic
            parts = line.split("\t")
            usage[parts[0].rsplit(":", 1)[-1]] = int(parts[1])
    return Build(folder, row, controller_object, images["replay"], images["footprint"], images["baseline"], usage)


# ------------------------------------------------------------------------------------------ sizes


def section_sizes(elf: Path) -> dict[str, int]:
    done = _run(["arm-none-eabi-size", "-A", "-d", str(elf)], "arm-none-eabi-size", elf.parent, timeout=60)
    sizes = {}
    for line in done.stdout.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].startswith(".") and parts[1].isdigit():
            sizes[parts[0]] = int(parts[1])
    return sizes


def berkeley_sizes(path: Path) -> dict[str, int]:
    """text, data, bss as ``arm-none-eabi-size`` reports them (Berkeley format)."""
    done = _run(["arm-none-eabi-size", str(path)], "arm-none-eabi-size", path.parent, timeout=60)
    values = done.stdout.splitlines()[1].split()
    return {"text": int(values[0]), "data": int(values[1]), "bss": int(values[2])}


@dataclass(frozen=True)
class Footprint:
    flash: int  # [bytes] code + constant data + initial values of .data the controller adds to a firmware
    ram: int  # [bytes] .data + .bss it adds (its state), without the stack
    text: int
    data: int
    bss: int
    object_sizes: dict[str, int]  # controller.o itself (text, data, bss)


def footprint(result: Build) -> Footprint:
    """What the controller adds to a firmware: footprint.elf minus baseline.elf, section by section."""
    with_it, without = section_sizes(result.footprint), section_sizes(result.baseline)

    def delta(*names):
        return sum(with_it.get(n, 0) - without.get(n, 0) for n in names)

    text, data, bss = delta(".text", ".ARM.exidx"), delta(".data"), delta(".bss")
    return Footprint(text + data, data + bss, text, data, bss, berkeley_sizes(result.controller_object))


# ------------------------------------------------------------------------------------------ the emulator


def _symbols(elf: Path) -> dict[str, tuple[int, int]]:
    done = _run(["arm-none-eabi-nm", "-S", "--defined-only", str(elf)], "arm-none-eabi-nm", elf.parent, timeout=60)
    symbols = {}
    for line in done.stdout.splitlines():
        parts = line.split()
        if len(parts) == 4:
            symbols[parts[3]] = (int(parts[0], 16) & ~1, int(parts[1], 16))
    return symbols


@dataclass
class CortexM4Replay:
    """A replay executed by QEMU's Cortex-M4: the float duties, and per step what the trace counted."""

    duty: np.ndarray  # float32 duties, per sample
    stack_bytes: int  # the deepest stack the steps used (below the call site's stack pointer)
    instructions: np.ndarray | None = None  # executed per step (None: the run was not traced)
    cycles: np.ndarray | None = None  # per step, the TRM's table with its upper assumptions (CYCLE_TABLE)
    cycles_low: np.ndarray | None = None  # per step, with its lower assumptions
    mix: Counter | None = None  # instruction classes executed over the selected steps (all by default)
    functions: Counter | None = None  # cycles (upper table) per function over the selected steps


def _execute(image: Path, steps: int, what: str, log: Path | None) -> list[str]:
    """Run ``image`` in ``qemu-system-arm -M mps2-an386`` (with ``log``: QEMU's execution trace written there)
    and return its semihosting console's lines, the last of which must be ``done <steps>``."""
    argv = [*QEMU, "-kernel", str(image)]
    if log is not None:
        argv += ["-d", "exec,nochain,in_asm", "-D", str(log)]
    try:  # QEMU writes the semihosting console to stderr
        done = subprocess.run(argv, capture_output=True, text=True, timeout=TIMEOUT_S, cwd=image.parent)
    except (OSError, subprocess.TimeoutExpired) as error:
        raise EmbeddedError(f"the Cortex-M4F {what} image did not finish in QEMU: {error}") from None
    lines = (done.stdout + done.stderr).splitlines()
    if done.returncode != 0 or not lines or lines[-1] != f"done {steps}":
        problem = next((line for line in lines if line.startswith(("error:", "fault:"))), "\n".join(lines[-5:]))
        raise EmbeddedError(f"the Cortex-M4F {what} image failed in QEMU (exit {done.returncode}): {problem}")
    return lines


def _printed_floats(lines: list[str], key: str, count: int) -> np.ndarray:
    """The floats an image printed as ``<key> <k> <8 hex digits>`` lines, in the order of k."""
    bits = np.zeros(count, dtype=np.uint32)
    for line in lines:
        if line.startswith(key + " "):
            _, k, value = line.split()
            bits[int(k)] = int(value, 16)
    return bits.view(np.float32).astype(float)


def replay_on_cortex_m4(result: Build, samples: int, trace: bool = False,
                        select: np.ndarray | None = None) -> CortexM4Replay:
    """Run the replay image in ``qemu-system-arm -M mps2-an386``; with ``trace``, count what each step executed
    (the mix and the cycles per function over the steps ``select`` marks, all by default)."""
    log = result.folder / "trace.log" if trace else None
    lines = _execute(result.replay, samples, "replay", log)
    stack = next((int(line.split()[1]) for line in lines if line.startswith("stack ")), -1)
    out = CortexM4Replay(_printed_floats(lines, "duty", samples), stack)
    if trace:
        counts = count_steps(log, _symbols(result.replay), samples, select)
        out.instructions, out.cycles, out.cycles_low, out.mix, out.functions = counts
        log.unlink()
    return out


def host_replay(controller, measurements: np.ndarray) -> np.ndarray:
    """The float duties of the host's float32 build of the same replay image: the row's C files,
    controller_instance.c and replay.c with the same generated headers and maxima, compiled by the host's C
    compiler with ``-DBUCKC_FLOAT32 -ffp-contract=off`` and ``host_runtime.c`` in place of the start-up code and
    semihosting. The same float operations in the same order as the target's, so its duties equal the target's
    where the step calls no libm function that differs between glibc and newlib. It needs no host binding of the
    controller's float32 structs: the online NNPC, whose float32 build has none (controllers/native.py), is
    compared through it."""
    with tempfile.TemporaryDirectory(prefix="buck-cosim-m4-host-", dir=_scratch()) as tmp:
        folder = Path(tmp)
        row = _generated_headers(controller, folder)
        (folder / "replay_data.h").write_text(replay_header(measurements), encoding="utf-8")
        defines = [f"-D{k}={v}" for k, v in sorted(row.limits(controller).items())]
        sources = [SOURCE_DIR / name for name in row.sources] + [HERE / "controller_instance.c", HERE / "replay.c",
                                                                 HERE / "host_runtime.c"]
        image = folder / "replay_host"
        _run([*compiler(), "-O2", "-std=c99", "-Wall", "-Wextra", "-Werror", "-Wdouble-promotion", "-ffp-contract=off",
              "-DBUCKC_FLOAT32", *defines, f"-I{folder}", f"-I{SOURCE_DIR}", f"-I{CONTROLLER_FMU_DIR}", f"-I{HERE}",
              *map(str, sources), "-lm", "-o", str(image)], "compiling the host's build of the replay image", folder)
        done = _run([str(image)], "the host's build of the replay image", folder, timeout=TIMEOUT_S)
        lines = done.stdout.splitlines()
        if not lines or lines[-1] != f"done {len(measurements)}":
            raise EmbeddedError(f"the host's build of the replay image stopped early: {lines[-1:] or 'no output'}")
        return _printed_floats(lines, "duty", len(measurements))


#: cortex_m4/tanh_probe.c's batch and steps
PROBE_BATCH, PROBE_STEPS = 16, 16


@dataclass
class TanhProbe:
    """buckc_tanhf on the Cortex-M4F (``cortex_m4/tanh_probe.c``): its values and its cycles per call."""

    arguments: np.ndarray  # the floats it was given, [-4.5, 4.5)
    values: np.ndarray  # what it returned on the target
    cycles: np.ndarray  # per call (a step over its batch), upper reading of the TRM table
    cycles_low: np.ndarray  # the same, lower reading


def probe_arguments() -> np.ndarray:
    """x_k = -4.5 + 9 k / 256 as tanh_probe.c computes them in float (every operation exact)."""
    k = np.arange(PROBE_BATCH * PROBE_STEPS, dtype=np.float32)
    return (np.float32(-4.5) + np.float32(9.0) * k / np.float32(PROBE_BATCH * PROBE_STEPS)).astype(float)


def measure_tanh() -> TanhProbe:
    """Cross-compile the tanh probe with the controllers' flags and run it in QEMU, traced: what buckc_tanhf
    costs a call inlined in a loop (the cost model's tanh, :mod:`controllers.cost_model`)."""
    problem = toolchain_problem()
    if problem:
        raise EmbeddedError(problem)
    with tempfile.TemporaryDirectory(prefix="buck-cosim-m4-", dir=_scratch()) as tmp:
        folder = Path(tmp)
        image = folder / "tanh_probe.elf"
        sources = [HERE / "startup.c", HERE / "semihosting.c", HERE / "tanh_probe.c"]
        _run(["arm-none-eabi-gcc", *ARM_FLAGS, *C_FLAGS, f"-I{SOURCE_DIR}", f"-I{HERE}", *LINK_FLAGS, "-T",
              str(LINKER_SCRIPT), *map(str, sources), *LIBRARIES, "-o", str(image)], "building the tanh probe",
             folder)
        log = folder / "trace.log"
        lines = _execute(image, PROBE_STEPS, "tanh probe", log)
        _, high, low, _, _ = count_steps(log, _symbols(image), PROBE_STEPS)
        return TanhProbe(probe_arguments(), _printed_floats(lines, "tanh", PROBE_BATCH * PROBE_STEPS),
                         high / PROBE_BATCH, low / PROBE_BATCH)


# ------------------------------------------------------------------------------------------ cycles


@dataclass(frozen=True)
class CycleTable:
    """Cycles of the Cortex-M4's instructions, from the ARM Cortex-M4 Processor Technical Reference Manual
    (r0p1; ARM DDI 0439, reissued as ARM 100166_0001_00): section 3.3.1, Table 3-1 "Processor instruction set
    summary" (the integer core), section 3.3.2 "Load/store timings", and the FPU chapter's instruction-set
    table ("Table 7-1" in DDI 0439). Every entry, and where it comes from:

    ====================================================  ========================  =========================
    instructions                                          cycles                    source
    ====================================================  ========================  =========================
    data processing (MOV, ADD, SUB, CMP, logic, shifts,   1                         Table 3-1
    bit fields, extend, saturate, IT, ...)
    MOV PC / ADD PC (writes PC)                           1 + P                     Table 3-1
    MUL, MLA, MLS, SMULL, UMULL, SMLAL, UMLAL             1                         Table 3-1
    SDIV, UDIV                                            2 ... 12 (early           Table 3-1 and its note
                                                          termination): upper 12,
                                                          lower 2
    LDR, LDRB, LDRH, LDRSB, LDRSH (single load)           2                         Table 3-1
    ... pipelined behind a single load (LDR [any]) whose  1                         3.3.2 (lower reading
    destination does not form this address                                          only, see below)
    LDR Rx, [PC, #imm] (literal; VLDR [PC] alike)         + 1 in the upper reading  3.3.2 ("might add a
                                                                                    cycle": fetch contention)
    LDR PC, [...]                                         2 + P, never pipelined    3.3.2 ("at least five")
    STR, STRB, STRH with an immediate offset (incl.       1                         3.3.2 ("always one
    pre-/post-indexed)                                                              cycle")
    STR, STRB, STRH with a register offset                2 (1 behind a single      Table 3-1, 3.3.2
                                                          load, lower reading)
    LDRD, STRD                                            1 + N = 3, never          Table 3-1, 3.3.2
                                                          pipelined
    LDM, STM, PUSH, POP (N registers)                     1 + N, never pipelined    Table 3-1, 3.3.2
    POP / LDM with PC                                     1 + N + P                 Table 3-1
    B<cc> not taken / taken                               1 / 1 + P                 Table 3-1
    B, BL, BX, BLX                                        1 + P                     Table 3-1
    CBZ, CBNZ not taken / taken                           1 / 1 + P                 Table 3-1
    TBB, TBH                                              2 + P (lower), 3 + P      Table 3-1; 3.3.2 ("at
                                                          (upper)                   least six cycles")
    any load or store whose address register the          + 1                       3.3.2 ("no forwarding
    immediately preceding data-processing instruction                               path")
    wrote
    VADD, VSUB, VMUL, VNMUL, VNEG, VABS, VCMP(E), VCVT,   1                         FPU table
    VMOV immediate or S <- S, VMOV half of D <-> core
    VMOV one S <-> one core register, two S / one D <->   2                         FPU table
    two core registers
    VMRS, VMSR                                            1                         FPU table
    VMLA, VMLS, VNMLA, VNMLS, VFMA, VFMS, VFNMA, VFNMS    3                         FPU table
    VDIV, VSQRT                                           14                        FPU table
    VLDR / VSTR of a single, of a double                  2, 3 (1 less behind a     FPU table; the pipelining
                                                          single load, lower        is assumed like LDR's
                                                          reading)                  (the TRM states it for
                                                                                    LDR/STR)
    VLDM, VSTM, VPUSH, VPOP (N singles / N doubles)       1 + N / 1 + 2 N           FPU table
    ====================================================  ========================  =========================

    ``P``, the pipeline refill after a taken branch, is 1 to 3 cycles "depending on the alignment and width
    of the target instruction, and whether the processor manages to speculate the address early" (Table 3-1's
    legend); a single load or store pipelines behind a single load (LDR [any]) when the load's destination
    does not form the next address (3.3.2), but the TRM's note says 32-bit opcodes at odd halfword addresses
    "might not pipeline optimally". Hence two readings: the *upper* (:data:`CYCLE_TABLE`: P = 3, SDIV 12,
    nothing pipelines, the literal load's extra cycle) and the *lower* (:data:`CYCLE_TABLE_LOW`: P = 1, SDIV 2,
    every pipelining the rule allows). Assumptions of both: zero-wait-state memory for code and data (the
    mps2-an386's SSRAM; on an STM32G4, code in CCM SRAM, or flash behind the ART accelerator hitting), no
    cache, the write buffer never full, no interrupt during the step; a conditional instruction in an IT
    block costs its count whether or not it executes (the trace cannot tell); the FPU's result latencies
    (GCC's cortex-m4-fpu.md models 2 cycles for VADD/VMUL results) and VDIV's out-of-order completion are
    not modelled -- the table's counts are issue cycles."""

    refill: float  # P
    divide: float  # SDIV/UDIV
    pipelines: bool  # a single load or store behind a single load costs one cycle less (3.3.2)
    literal_penalty: float  # LDR Rx, [PC, #imm]: fetch contention
    table_branch: float  # TBB/TBH, before P

    def cycles(self, mnemonic: str, operands: str, taken: bool, previous: tuple[str, str] | None = None) -> float:
        """Cycles of one executed instruction; ``taken``: a branch that was taken; ``previous``: the mnemonic
        and operands of the instruction executed just before it in the step (None at its start)."""
        base, _ = _base(mnemonic)
        stall = 1.0 if _address_stall(base, operands, previous) else 0.0
        return self._cycles(base, mnemonic, operands, taken, previous) + stall

    def _cycles(self, base: str, mnemonic: str, operands: str, taken: bool, previous) -> float:
        writes_pc = bool(re.match(r"pc\b", operands))
        if base in ("b", "bl", "bx", "blx"):
            return 1.0 + self.refill if (taken or base != "b") else 1.0
        if base in ("cbz", "cbnz"):
            return 1.0 + self.refill if taken else 1.0
        if base in ("tbb", "tbh"):
            return self.table_branch + self.refill
        if base in _MULTIPLE_LOADS:
            return 1.0 + _register_count(operands) + (self.refill if re.search(r"\bpc\b", operands) else 0.0)
        if base in _MULTIPLE_STORES:
            return 1.0 + _register_count(operands)
        if base in ("ldrd", "strd"):
            return 3.0
        if base in ("vldm", "vldmia", "vldmdb", "vstm", "vstmia", "vstmdb", "vpush", "vpop"):
            return 1.0 + _single_count(operands)
        if base in _SINGLE_LOADS or base in _SINGLE_STORES or base in ("vldr", "vstr"):
            if base in _SINGLE_LOADS and writes_pc:
                return 2.0 + self.refill
            if base in _SINGLE_STORES:
                cost = 2.0 if _register_offset(operands) else 1.0
            else:
                cost = 3.0 if (base == "vldr" or base == "vstr") and re.match(r"d\d", operands) else 2.0
                cost += self.literal_penalty if re.search(r"\[pc\b", operands) else 0.0
            if self.pipelines and _pipelines_behind(operands, previous):
                cost = max(1.0, cost - 1.0)
            return cost
        if base in ("sdiv", "udiv"):
            return self.divide
        if base in ("vdiv", "vsqrt"):
            return 14.0
        if base in ("vmla", "vmls", "vnmla", "vnmls", "vfma", "vfms", "vfnma", "vfnms"):
            return 3.0
        if base == "vmov":
            return 2.0 if _core_registers(operands) and not re.search(r"d\d+\[", operands) \
                and any(re.fullmatch(r"[sd]\d+", r) for r in _operand_list(operands)) else 1.0
        if writes_pc:  # mov pc, ..., add pc, ...
            return 1.0 + self.refill
        return 1.0


CYCLE_TABLE = CycleTable(refill=3.0, divide=12.0, pipelines=False, literal_penalty=1.0, table_branch=3.0)
CYCLE_TABLE_LOW = CycleTable(refill=1.0, divide=2.0, pipelines=True, literal_penalty=0.0, table_branch=2.0)

_CONDITIONS = ("eq", "ne", "cs", "hs", "cc", "lo", "mi", "pl", "vs", "vc", "hi", "ls", "ge", "lt", "gt", "le", "al")
_SINGLE_LOADS = ("ldr", "ldrb", "ldrh", "ldrsb", "ldrsh", "ldrex", "ldrexb", "ldrexh", "ldrt", "ldrbt", "ldrht")
_SINGLE_STORES = ("str", "strb", "strh", "strt", "strbt", "strht")
_MULTIPLE_LOADS = ("ldm", "ldmia", "ldmdb", "ldmfd", "pop")
_MULTIPLE_STORES = ("stm", "stmia", "stmdb", "stmfd", "push")
#: instructions that compare or control and write no core register
_NO_DESTINATION = ("cmp", "cmn", "tst", "teq", "it", "nop", "bkpt", "dsb", "dmb", "isb", "cpsie", "cpsid", "svc")
_CORE_REGISTER = re.compile(r"(r\d+|sb|sl|fp|ip|sp|lr|pc)")
#: the mnemonics the table prices differently from 1 cycle (and the FPU moves of the mix)
_PRICED = {"b", "bl", "bx", "blx", "cbz", "cbnz", "tbb", "tbh", "ldrd", "strd", "sdiv", "udiv", "mul", "mla", "mls",
           "smull", "umull", "smlal", "umlal", "vdiv", "vsqrt", "vmla", "vmls", "vnmla", "vnmls", "vfma", "vfms",
           "vfnma", "vfnms", "vldr", "vstr", "vldm", "vldmia", "vldmdb", "vstm", "vstmia", "vstmdb", "vpush", "vpop",
           "vmov", "vmrs", "vmsr", "vcvt", "vcvtr", "mov", "add", *_SINGLE_LOADS, *_SINGLE_STORES, *_MULTIPLE_LOADS,
           *_MULTIPLE_STORES}


def _base(mnemonic: str) -> tuple[str, bool]:
    """The instruction without its data-type suffix (.f32), width qualifier (.w), condition code (inside an
    IT block) and flag-setting S; and whether it had a condition code."""
    name = mnemonic.lower().split(".")[0]
    if name in _PRICED:
        return name, False
    if name[-2:] in _CONDITIONS and name[:-2] in _PRICED:
        return name[:-2], True
    if name.endswith("s") and name[:-1] in _PRICED:
        return name[:-1], False
    return name, False


def _operand_list(operands: str) -> list[str]:
    return [part.strip().rstrip("!") for part in re.split(r"[,\[\]{}]", operands) if part.strip()]


def _core_registers(operands: str) -> list[str]:
    return [r for r in _operand_list(operands) if _CORE_REGISTER.fullmatch(r)]


def _address_registers(base: str, operands: str) -> set[str]:
    """The core registers that form a load's or store's address: those inside [...] of a single transfer,
    the base register of LDM/STM/VLDM/VSTM, SP of PUSH/POP/VPUSH/VPOP; empty for other instructions."""
    if base in ("push", "pop", "vpush", "vpop"):
        return {"sp"}
    if base in _MULTIPLE_LOADS or base in _MULTIPLE_STORES or base.startswith(("vldm", "vstm")):
        return {operands.split(",")[0].strip().rstrip("!")}
    if base in _SINGLE_LOADS or base in _SINGLE_STORES or base in ("ldrd", "strd", "vldr", "vstr"):
        inside = re.search(r"\[([^\]]*)\]", operands)
        return set(_core_registers(inside.group(1))) if inside else set()
    return set()


def _written_by_data_processing(previous: tuple[str, str] | None) -> set[str]:
    """The core registers the previous instruction wrote, if it was an integer data-processing instruction
    (not a load, store, branch or FPU instruction): its destination (two for the long multiplies)."""
    if previous is None:
        return set()
    base, _ = _base(previous[0])
    if (base.startswith(("v", "ld", "st", "it")) or base in _BRANCHES or base in _NO_DESTINATION
            or base in _MULTIPLE_LOADS or base in _MULTIPLE_STORES):
        return set()
    registers = _operand_list(previous[1])
    count = 2 if base in ("smull", "umull", "smlal", "umlal") else 1
    return {r for r in registers[:count] if _CORE_REGISTER.fullmatch(r)}


def _address_stall(base: str, operands: str, previous) -> bool:
    """TRM 3.3.2: a load or store whose address depends on the result of the preceding data-processing
    operation stalls one cycle (no forwarding path)."""
    return bool(_address_registers(base, operands) & _written_by_data_processing(previous))


def _register_offset(operands: str) -> bool:
    """A single store's address has a register offset ([Rn, Rm{, LSL #n}]) rather than an immediate."""
    inside = re.search(r"\[([^\]]*)\]", operands)
    return bool(inside) and len(_core_registers(inside.group(1))) > 1


def _pipelines_behind(operands: str, previous) -> bool:
    """TRM 3.3.2: a single load or store pipelines behind a single load (LDR [any]; VLDR assumed alike) whose
    destination is not used to compute its address -- not behind a store, LDRD, LDM, or a load of PC."""
    if previous is None:
        return False
    base, _ = _base(previous[0])
    if not (base in _SINGLE_LOADS or base == "vldr") or re.match(r"pc\b", previous[1]):
        return False
    destination = _operand_list(previous[1])[0]
    return destination not in _address_registers("ldr", operands)


def _register_count(operands: str) -> int:
    inside = re.search(r"\{([^}]*)\}", operands)
    if not inside:
        return 1
    count = 0
    for part in inside.group(1).split(","):
        part = part.strip()
        span = re.match(r"([a-z]+)(\d+)\s*-\s*[a-z]+(\d+)", part)
        count += int(span.group(3)) - int(span.group(2)) + 1 if span else 1
    return count


def _single_count(operands: str) -> int:
    """Registers of a VLDM/VSTM/VPUSH/VPOP list in single-precision units (a dN is two)."""
    inside = re.search(r"\{([^}]*)\}", operands)
    if not inside:
        return 1
    total = 0
    for part in inside.group(1).split(","):
        part = part.strip()
        span = re.match(r"([sd])(\d+)\s*-\s*[sd](\d+)", part)
        n = int(span.group(3)) - int(span.group(2)) + 1 if span else 1
        total += n * (2 if part.startswith("d") else 1)
    return total


def instruction_class(mnemonic: str) -> str:
    """A coarse class for the reported mix: fp-arith, fp-div/sqrt, fp-memory, fp-move, load, store, branch,
    multiply, other (integer data processing)."""
    base, _ = _base(mnemonic)
    if base in ("vdiv", "vsqrt"):
        return "fp-div/sqrt"
    if base.startswith(("vldr", "vstr", "vldm", "vstm", "vpush", "vpop")):
        return "fp-memory"
    if base in ("vmov", "vmrs", "vmsr", "vcvt", "vcvtr"):
        return "fp-move"
    if base.startswith("v"):
        return "fp-arith"
    if base.startswith(("ldr", "ldm")) or base == "pop":
        return "load"
    if base.startswith(("str", "stm")) or base == "push":
        return "store"
    if base in ("b", "bl", "bx", "blx", "cbz", "cbnz", "tbb", "tbh"):
        return "branch"
    if base in ("mul", "mla", "mls", "smull", "umull", "smlal", "umlal", "sdiv", "udiv"):
        return "multiply"
    return "other"


_BRANCHES = ("b", "bl", "bx", "blx", "cbz", "cbnz", "tbb", "tbh")
_TRACE = re.compile(r"^Trace \d+: 0x[0-9a-f]+ \[[0-9a-f]+/([0-9a-f]+)/")
_INSN = re.compile(r"^0x([0-9a-f]+):\s+((?:[0-9a-f]{4}\s?)+)\s+(\S+)\s*(.*)$")


def _is_control(mnemonic: str, operands: str) -> bool:
    base, _ = _base(mnemonic)
    return base in _BRANCHES or (base in _MULTIPLE_LOADS and re.search(r"\bpc\b", operands) is not None) or bool(
        re.match(r"pc\b", operands))


def count_steps(log: Path, symbols: dict[str, tuple[int, int]], samples: int, select: np.ndarray | None = None):
    """Instructions and cycles per step from QEMU's ``-d exec,nochain,in_asm`` log: the blocks executed
    between each call of ``buckc_step_begin`` and ``buckc_step_end``, without the replay loop's own
    instructions (``main``) and the two marker functions: what the controller object and the library
    functions it calls executed. Taken branches: a block ending in a branch whose successor is not the
    next address. The instruction mix and the cycles per function add up the steps ``select`` marks (all by
    default).

    A block's price depends only on the instruction executed before it (the TRM's pairing rules look one
    back) and on whether its last branch was taken, so each (block, previous, taken) is priced once and
    looked up after: a search step of the online NNPC executes millions of blocks."""
    begin, end = symbols["buckc_step_begin"][0], symbols["buckc_step_end"][0]
    main_start, main_size = symbols["main"]
    excluded = [(main_start, main_start + main_size), (begin, begin + 2), (end, end + 2)]
    # address -> (its instructions, the address after it, whether its last instruction may branch)
    blocks: dict[int, tuple[list[tuple[int, int, str, str]], int, bool]] = {}
    prices: dict[int, dict] = {}  # block address -> (previous, taken) -> its price (dropped when retranslated)
    current: list | None = None
    steps_insn, steps_high, steps_low = [], [], []
    mix: Counter = Counter()
    functions: Counter = Counter()
    step_mix: Counter = Counter()  # the step's, added to mix and functions when it ends, if selected
    step_functions: Counter = Counter()
    starts = sorted((a, a + max(s, 2), name) for name, (a, s) in symbols.items() if s)

    def owner(address: int) -> str:
        return next((n for a, b, n in starts if a <= address < b), "?")

    def price(block, previous, taken: bool):
        """(instructions, upper cycles, lower cycles, classes, cycles per function, the last instruction)."""
        insn = high = low = 0.0
        classes: Counter = Counter()
        owners: Counter = Counter()
        for i, (address, size, mnemonic, operands) in enumerate(block):
            if any(a <= address < b for a, b in excluded):
                previous = None
                continue
            last_taken = taken and i == len(block) - 1
            cycles = CYCLE_TABLE.cycles(mnemonic, operands, last_taken, previous)
            insn += 1
            high += cycles
            low += CYCLE_TABLE_LOW.cycles(mnemonic, operands, last_taken, previous)
            classes[instruction_class(mnemonic)] += 1
            owners[owner(address)] += cycles
            previous = (mnemonic, operands)
        return insn, high, low, tuple(classes.items()), tuple(owners.items()), previous

    inside = False
    pending: list | None = None  # the last executed block of the step (its final branch awaits the successor)
    totals = [0.0, 0.0, 0.0]
    previous: tuple[str, str] | None = None  # the instruction executed before, for the TRM's pairing rules

    def account(translated, successor: int | None):
        nonlocal previous
        block, after, control = translated
        taken = control and successor is not None and successor != after
        known = prices.setdefault(block[0][0], {})
        key = (previous, taken)
        entry = known.get(key)
        if entry is None:
            entry = known[key] = price(block, previous, taken)
        insn, high, low, classes, owners, previous = entry
        totals[0] += insn
        totals[1] += high
        totals[2] += low
        for name, n in classes:
            step_mix[name] += n
        for name, cycles in owners:
            step_functions[name] += cycles

    with open(log, encoding="utf-8", errors="replace") as lines:
        for line in lines:
            if line.startswith("IN:"):
                current = []
                continue
            if current is not None:
                match = _INSN.match(line)
                if match:
                    size = len(match.group(2).replace(" ", "")) // 2
                    current.append((int(match.group(1), 16), size, match.group(3), match.group(4).strip()))
                    continue
                if current:
                    address, size, mnemonic, operands = current[-1]
                    blocks[current[0][0]] = (current, address + size, _is_control(mnemonic, operands))
                    prices.pop(current[0][0], None)
                current = None
            if not line.startswith("Trace"):
                continue
            match = _TRACE.match(line)
            if not match:
                continue
            pc = int(match.group(1), 16)
            if pending is not None:
                account(pending, pc)
                pending = None
            if pc == begin:
                inside, totals, previous = True, [0.0, 0.0, 0.0], None
                step_mix.clear()
                step_functions.clear()
            elif pc == end and inside:
                if select is None or (len(steps_insn) < len(select) and select[len(steps_insn)]):
                    mix.update(step_mix)
                    functions.update(step_functions)
                steps_insn.append(totals[0])
                steps_high.append(totals[1])
                steps_low.append(totals[2])
                inside = False
            elif inside:
                pending = blocks.get(pc)
                if pending is None:
                    raise EmbeddedError(f"the QEMU trace executes a block at 0x{pc:x} it never translated")
    if len(steps_insn) != samples:
        raise EmbeddedError(f"the QEMU trace holds {len(steps_insn)} steps, the replay {samples}")
    return np.array(steps_insn), np.array(steps_high), np.array(steps_low), mix, functions


# ------------------------------------------------------------------------------------------ one call


@dataclass
class Measured:
    """A controller measured on the Cortex-M4F (the replay traced, the footprint, the stack)."""

    label: str
    replay: CortexM4Replay
    footprint: Footprint
    stack_usage: dict[str, int]
    object_file: Path | None = None


def measure(controller, measurements: np.ndarray, keep: Path | None = None, trace: bool = True,
            select: np.ndarray | None = None) -> Measured:
    """Cross-compile ``controller`` (float32), replay ``measurements`` in QEMU (traced; the mix and the cycles
    per function over the samples ``select`` marks, all by default), size it. The build folder is temporary
    unless ``keep`` names a folder to write it to (controller.o and the images)."""
    problem = toolchain_problem()
    if problem:
        raise EmbeddedError(problem)
    with tempfile.TemporaryDirectory(prefix="buck-cosim-m4-", dir=_scratch()) as tmp:
        folder = Path(keep) if keep else Path(tmp)
        result = build(controller, measurements, folder)
        run = replay_on_cortex_m4(result, len(measurements), trace=trace, select=select)
        size = footprint(result)
        return Measured(result.row.label, run, size, result.stack_usage, result.controller_object if keep else None)


def _scratch() -> Path:
    folder = cache_dir() / "cortex-m4"
    folder.mkdir(parents=True, exist_ok=True)
    return folder

