"""The C99 twins of the controllers (``controllers/c/``): build, load and drive them from Python.

``controllers/c`` holds hand-written C versions of the PI, the NN forward pass and rollouts, the
averaged and switched circuit predictors, the horizon optimizer and the predictive controller's
step -- operation by operation the arithmetic of the Python references, with no allocation, no
mutable globals and configuration as plain data (see ``controllers/c/buckc.h``). This module
compiles them into one shared library, mirrors their structs with :mod:`ctypes`, and offers
:class:`NativePIController` and :class:`NativePredictiveController`, which implement the
controller protocol of :mod:`controllers.base` and are built *from* the Python controllers.

Why it calls the C compiler itself rather than fmpy's build helper: ``fmpy.build`` compiles an
FMU folder (``modelDescription.xml`` + ``sources/``) through CMake into
``binaries/<platform>/<id>.so`` -- the right tool for the plant FMU. The twins are not an FMU:
they are one plain in-process library for the twin tests, for fast reproduction runs and for
timing the controller without Python in the loop, so one compiler invocation (no CMake, no FMI
glue) is all it takes. It is cached like the plant: under ``$BUCK_COSIM_CACHE`` (or
``~/.cache/buck-cosim``) by a hash of the sources, flags and compiler version, built in a
temporary folder there and moved into place atomically, so concurrent processes never load a
half-written library.

Flags: ``-std=c99 -Wall -Wextra -Wpedantic -Werror`` (the twins must compile clean), ``-O2`` (no
value-changing optimisation: no ``-ffast-math``) and ``-ffp-contract=off``, which keeps a compiler
from fusing ``a*b + c`` into one FMA -- numpy rounds each ufunc separately, and GCC in GNU mode or
clang in any mode would otherwise fuse on targets with FMA.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from controllers.base import Measurement, check_duty_limits, check_sample_period
from controllers.compensator import CompensatorController
from controllers.current_mode import CurrentModeController
from controllers.explicit_policy import N_FEATURES, ExplicitPolicyController
from controllers.nn_config import ACTIVATIONS, EXTRA_SIGNALS
from controllers.pi import PIController, check_gains
from controllers.predictive import PredictiveController
from controllers.predictors import (
    CARRIERS,
    SENSOR_MODELS,
    AveragedModelPredictor,
    CircuitParameters,
    NNPredictor,
    PredictionContext,
    SwitchedModelPredictor,
)

if TYPE_CHECKING:  # torch loads with the NN model's module (seconds): only where a network is trained or read
    from controllers.nn_model import NNPlantModel

SOURCE_DIR = Path(__file__).parent / "c"
FLAGS = ("-O2", "-fPIC", "-shared", "-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-ffp-contract=off")
LIBRARIES = ("-lm",)
LIBRARY_NAME = "buckc"


class NativeBuildError(RuntimeError):
    """The C twins could not be compiled (or no compiler was found); the message names the log."""


# ------------------------------------------------------------------------------------------ build

def cache_dir() -> Path:
    """``$BUCK_COSIM_CACHE`` or ``~/.cache/buck-cosim`` (the plant FMU's cache too)."""
    configured = os.environ.get("BUCK_COSIM_CACHE")
    return Path(configured) if configured else Path.home() / ".cache" / "buck-cosim"


def compiler() -> list[str]:
    """The C compiler Python was built with (``sysconfig``'s CC) if it is installed here, else ``cc``."""
    configured = shlex.split(sysconfig.get_config_var("CC") or "")
    if configured and shutil.which(configured[0]):
        return configured
    if shutil.which("cc"):
        return ["cc"]
    raise NativeBuildError("no C compiler found: neither sysconfig's CC "
                           f"({sysconfig.get_config_var('CC')!r}) nor 'cc' is on PATH")


def _compiler_version(command: list[str]) -> str:
    try:
        out = subprocess.run([*command, "--version"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as error:
        raise NativeBuildError(f"C compiler {' '.join(command)} does not run: {error}") from None
    return (out.stdout or out.stderr).strip().splitlines()[0] if (out.stdout or out.stderr).strip() else "unknown"


def _suffix() -> str:
    return {"darwin": ".dylib", "win32": ".dll"}.get(sys.platform, ".so")


def source_digest(source_dir: Path = SOURCE_DIR, command: list[str] | None = None) -> str:
    """Hash of everything that determines the library: sources, flags, compiler and platform."""
    return _digest(sorted(Path(source_dir).glob("*.[ch]")), FLAGS, command or compiler())


def _digest(files, flags, command: list[str], extra: bytes = b"") -> str:
    digest = hashlib.sha256()
    digest.update(f"{_compiler_version(command)} {' '.join(command)} {flags} {LIBRARIES} {sys.platform} "
                  f"{sysconfig.get_platform()}".encode())
    for path in files:
        digest.update(Path(path).name.encode())
        digest.update(Path(path).read_bytes())
    digest.update(extra)
    return digest.hexdigest()[:16]


def build_c(name: str, sources: list[Path], headers: list[Path], flags: tuple[str, ...], suffix: str,
            generated: dict[str, str] | None = None, force: bool = False) -> Path:
    """Compile C ``sources`` (with ``headers`` and ``generated`` header texts beside them) into one
    file under the cache, once per hash of everything that determines it; built in a temporary
    folder and moved into place atomically. Raises :class:`NativeBuildError` naming the log."""
    command = compiler()
    files = sorted({Path(f) for f in (*sources, *headers)})
    generated = generated or {}
    extra = "".join(f"{k}\n{v}" for k, v in sorted(generated.items())).encode()
    key = _digest(files, flags, command, extra)
    folder = cache_dir()
    target = folder / f"{name}-{key}{suffix}"
    if target.is_file() and not force:
        return target
    folder.mkdir(parents=True, exist_ok=True)
    log = folder / f"{name}-{key}.build.log"
    with tempfile.TemporaryDirectory(dir=folder, prefix=f".{name}-build-") as tmp:
        for header, text in generated.items():
            (Path(tmp) / header).write_text(text, encoding="utf-8")
        includes = sorted({f"-I{Path(f).parent}" for f in files} | {f"-I{tmp}"})
        staged = Path(tmp) / f"{name}{suffix}"
        argv = [*command, *flags, *includes, *map(str, sorted(sources)), "-o", str(staged), *LIBRARIES]
        try:
            done = subprocess.run(argv, capture_output=True, text=True, timeout=600)
        except (OSError, subprocess.TimeoutExpired) as error:
            log.write_text(f"$ {shlex.join(argv)}\n{error}\n")
            raise NativeBuildError(f"compiling {name} failed ({error}); compiler log: {log}") from None
        log.write_text(f"$ {shlex.join(argv)}\n{done.stdout}{done.stderr}")
        if done.returncode != 0 or not staged.is_file():
            raise NativeBuildError(f"compiling {name} failed (exit {done.returncode}); compiler log: {log}")
        os.replace(staged, target)  # atomic: a concurrent build writes the same bytes
    return target


#: the arithmetic of a build of the twins (``buckc_real`` in ``controllers/c/buckc.h``)
PRECISIONS = ("float64", "float32")
#: the files with a float32 build (buckc.h): predictors.c (the circuit predictors) computes in double only, and
#: predictive.c's float32 build (the online NNPC) has no ctypes mirrors here: the Cortex-M4F image and its host
#: build run it (cosim/benchmark_harness/cortex_m4.py)
FLOAT32_SOURCES = ("buckc.c", "pi.c", "load_estimate.c", "nn_model.c", "explicit_policy.c", "current_mode.c",
                   "compensator.c", "box_qp.c", "predictive.c")
#: what a float32 build adds to FLAGS: buckc_real = float, and no expression silently computed in double
FLOAT32_FLAGS = ("-DBUCKC_FLOAT32", "-Wdouble-promotion")


def check_precision(precision: str) -> str:
    if precision not in PRECISIONS:
        raise ValueError(f"precision {precision!r} is unknown: expected one of {', '.join(PRECISIONS)}")
    return precision


def precision_sources(precision: str, source_dir: Path = SOURCE_DIR) -> list[Path]:
    """The C files of a build of the twins in ``precision`` (float32: those with a float32 build)."""
    files = sorted(Path(source_dir).glob("*.c"))
    if check_precision(precision) == "float32":
        files = [f for f in files if f.name in FLOAT32_SOURCES]
    return files


def precision_flags(precision: str) -> tuple[str, ...]:
    return FLAGS + (FLOAT32_FLAGS if check_precision(precision) == "float32" else ())


#: the build variants :func:`library` takes besides the default: ``scalar-pairs`` computes buckc_pair.h's pairs as
#: two scalars where the default build uses SSE2 (the tests check that both give the same bits)
VARIANT_DEFINES = {"default": (), "scalar-pairs": ("-DBUCKC_SCALAR_PAIRS",)}


def build_library(source_dir: Path = SOURCE_DIR, force: bool = False, precision: str = "float64",
                  variant: str = "default") -> Path:
    """Path of the compiled twins in ``precision`` (``float64``: all of them; ``float32``: the files with a
    float32 build, compiled with ``-DBUCKC_FLOAT32``) and ``variant`` (:data:`VARIANT_DEFINES`), compiling once
    per source hash; raises :class:`NativeBuildError`."""
    source_dir = Path(source_dir)
    name = LIBRARY_NAME if precision == "float64" else f"{LIBRARY_NAME}-{precision}"
    if variant not in VARIANT_DEFINES:
        raise ValueError(f"build variant {variant!r} is unknown: expected one of {', '.join(VARIANT_DEFINES)}")
    name += "" if variant == "default" else f"-{variant}"
    try:
        return build_c(name, precision_sources(precision, source_dir), sorted(source_dir.glob("*.h")),
                       precision_flags(precision) + VARIANT_DEFINES[variant], _suffix(), force=force)
    except NativeBuildError as error:
        raise NativeBuildError(str(error).replace(f"compiling {name}", f"compiling the C controller twins "
                                                                        f"({precision})")) from None


# ------------------------------------------------------------------------------------------ struct mirrors

def _limits(source_dir: Path = SOURCE_DIR) -> dict[str, int]:
    """The integer ``#define BUCKC_...`` maxima of the headers (one source of truth for the mirrors)."""
    limits = {}
    for header in sorted(source_dir.glob("*.h")):
        for name, value in re.findall(r"^#define\s+(BUCKC_\w+)\s+(\d+)\b", header.read_text(), flags=re.M):
            limits[name] = int(value)
    return limits


LIMITS = _limits()
MAX_HIDDEN_LAYERS = LIMITS["BUCKC_NN_MAX_HIDDEN_LAYERS"]
MAX_WIDTH = LIMITS["BUCKC_NN_MAX_WIDTH"]
MAX_DELAYS = LIMITS["BUCKC_NN_MAX_DELAYS"]
MAX_EXTRAS = LIMITS["BUCKC_NN_MAX_EXTRAS"]
MAX_LAYERS = MAX_HIDDEN_LAYERS + 1
CACHE_KEYS = LIMITS["BUCKC_PY_CACHE_KEYS"]
MAX_GRID = LIMITS["BUCKC_SWITCHED_MAX_GRID"]
TABLES = LIMITS["BUCKC_SWITCHED_TABLES"]
COLUMNS = LIMITS["BUCKC_SWITCHED_COLUMNS"]
MAX_HORIZON = LIMITS["BUCKC_MAX_HORIZON"]
MAX_BLOCKS = LIMITS["BUCKC_MAX_BLOCKS"]
MAX_LEVELS = LIMITS["BUCKC_MAX_LEVELS"]
MAX_LATTICE = LIMITS["BUCKC_MAX_LATTICE"]
QP_MAX_VARIABLES = LIMITS["BUCKC_QP_MAX_VARIABLES"]
NN_MAX_DIRECTIONS = LIMITS["BUCKC_NN_MAX_DIRECTIONS"]
NEAR_OFFSETS = LIMITS["BUCKC_NEAR_OFFSETS"]
POLICY_MAX_HIDDEN_LAYERS = LIMITS["BUCKC_POLICY_MAX_HIDDEN_LAYERS"]
POLICY_MAX_WIDTH = LIMITS["BUCKC_POLICY_MAX_WIDTH"]
POLICY_MAX_LAYERS = POLICY_MAX_HIDDEN_LAYERS + 1
COMPENSATOR_MAX_ORDER = LIMITS["BUCKC_COMPENSATOR_MAX_ORDER"]
assert LIMITS["BUCKC_POLICY_INPUTS"] == N_FEATURES, "explicit_policy.h and explicit_policy.FEATURES disagree"

OK, ERR_NULL, ERR_LIMIT, ERR_INVALID, ERR_NO_INDUCTOR_CURRENT, ERR_ILL_CONDITIONED = 0, -1, -2, -3, -4, -5
PREDICTOR_NN, PREDICTOR_AVERAGED, PREDICTOR_SWITCHED = 0, 1, 2
SOLVERS = ("search", "rti")  # BUCKC_SOLVER_...: the names PredictiveController.last_solver uses
#: BUCKC_FALLBACK_...: the reasons PredictiveController.fallback_reason gives ("" for none)
FALLBACKS = ("", "cold start", "reference step", "load step", "prediction error", "start-up", "large error")

c_double, c_int = ctypes.c_double, ctypes.c_int


def _array(kind, *shape):
    for size in reversed(shape):
        kind = kind * size
    return kind


class RealMirrors:
    """The ctypes mirrors of the structs written in ``buckc_real`` (``controllers/c/buckc.h``), for one
    precision: built from the one definition below, with ``c_double`` for the float64 build and
    ``c_float`` for the float32 build (:data:`REAL_MIRRORS`)."""

    def __init__(self, precision: str, real):
        self.precision, self.real = precision, real

        class PiConfig(ctypes.Structure):
            _fields_ = [("kp", real), ("ki", real), ("sample_period", real), ("duty_min", real), ("duty_max", real)]

        class Pi(ctypes.Structure):
            _fields_ = [("config", PiConfig), ("integral", real)]

        class NnConfig(ctypes.Structure):
            _fields_ = [("delays", c_int), ("n_extras", c_int), ("extras", _array(c_int, MAX_EXTRAS)),
                        ("n_hidden", c_int), ("hidden", _array(c_int, MAX_HIDDEN_LAYERS)), ("activation", c_int),
                        ("residual", c_int), ("weights", _array(real, MAX_LAYERS, MAX_WIDTH, MAX_WIDTH)),
                        ("biases", _array(real, MAX_LAYERS, MAX_WIDTH))]

        class NnShared(ctypes.Structure):
            _fields_ = [("fast", c_int), ("history", _array(real, MAX_DELAYS, 3)), ("extras", _array(real, MAX_EXTRAS)),
                        ("disturbance", _array(real, 2)), ("constant", _array(real, MAX_WIDTH)),
                        ("z0", _array(real, MAX_WIDTH)), ("b2", _array(real, 2))]

        class MeasurementC(ctypes.Structure):
            _fields_ = [("time", real), ("reference", real), ("output_voltage", real), ("inductor_current", real),
                        ("load_current", real), ("input_voltage", real)]

        class PolicyConfigC(ctypes.Structure):
            _fields_ = [("sample_period", real), ("duty_min", real), ("duty_max", real), ("nominal_load", real),
                        ("integral_gain", real), ("integral_band", real), ("n_hidden", c_int),
                        ("hidden", _array(c_int, POLICY_MAX_HIDDEN_LAYERS)),
                        ("weights", _array(real, POLICY_MAX_LAYERS, POLICY_MAX_WIDTH, POLICY_MAX_WIDTH)),
                        ("biases", _array(real, POLICY_MAX_LAYERS, POLICY_MAX_WIDTH))]

        class PolicyC(ctypes.Structure):
            _fields_ = [("config", ctypes.c_void_p), ("have_history", c_int), ("previous_current", real),
                        ("previous_voltage", real), ("previous_duty", real), ("conductance", real),
                        ("integral", real), ("last_output", real)]

        class CurrentModeConfigC(ctypes.Structure):
            _fields_ = [("sample_period", real), ("duty_min", real), ("duty_max", real),
                        ("nominal_input_voltage", real), ("kp_voltage", real), ("ki_voltage", real),
                        ("kp_current", real), ("ki_current", real), ("current_limit", real),
                        ("computation_delay", c_int)]

        class CurrentModeC(ctypes.Structure):
            _fields_ = [("config", CurrentModeConfigC), ("voltage_integral", real), ("current_integral", real),
                        ("pending_duty", real)]

        class CompensatorConfigC(ctypes.Structure):
            _fields_ = [("sample_period", real), ("duty_min", real), ("duty_max", real),
                        ("nominal_input_voltage", real), ("order", c_int),
                        ("numerator", _array(real, COMPENSATOR_MAX_ORDER + 1)),
                        ("denominator", _array(real, COMPENSATOR_MAX_ORDER + 1)), ("computation_delay", c_int)]

        class CompensatorC(ctypes.Structure):
            _fields_ = [("config", CompensatorConfigC), ("state", _array(real, COMPENSATOR_MAX_ORDER)),
                        ("pending_duty", real)]

        self.PiConfig, self.Pi, self.NnConfig, self.NnShared = PiConfig, Pi, NnConfig, NnShared
        self.CurrentModeConfigC, self.CurrentModeC = CurrentModeConfigC, CurrentModeC
        self.CompensatorConfigC, self.CompensatorC = CompensatorConfigC, CompensatorC
        self.MeasurementC, self.PolicyConfigC, self.PolicyC = MeasurementC, PolicyConfigC, PolicyC
        #: mirror -> C type name, checked against sizeof() in the library when it is loaded
        self.names = {PiConfig: "BuckcPiConfig", Pi: "BuckcPi", NnConfig: "BuckcNnConfig", NnShared: "BuckcNnShared",
                      MeasurementC: "BuckcMeasurement", PolicyConfigC: "BuckcPolicyConfig", PolicyC: "BuckcPolicy",
                      CurrentModeConfigC: "BuckcCurrentModeConfig", CurrentModeC: "BuckcCurrentMode",
                      CompensatorConfigC: "BuckcCompensatorConfig", CompensatorC: "BuckcCompensator"}

    def signatures(self) -> dict:
        """restype, argtypes of the functions written in buckc_real (both builds have them)."""
        real, rp, P = self.real, ctypes.POINTER(self.real), ctypes.POINTER
        return {
            "buckc_real_name": (ctypes.c_char_p, []),
            "buckc_pair_backend": (ctypes.c_char_p, []),
            "buckc_status_text": (ctypes.c_char_p, [c_int]),
            "buckc_struct_size": (ctypes.c_size_t, [ctypes.c_char_p]),
            "buckc_pi_init": (c_int, [P(self.Pi), P(self.PiConfig), P(ctypes.c_char_p)]),
            "buckc_pi_reset": (None, [P(self.Pi)]),
            "buckc_pi_step": (real, [P(self.Pi), real, real]),
            "buckc_estimate_conductance": (real, [real, real, real, real]),
            "buckc_nn_check": (c_int, [P(self.NnConfig), P(ctypes.c_char_p)]),
            "buckc_nn_activate": (None, [c_int, rp, c_int, rp]),
            "buckc_nn_forward": (None, [P(self.NnConfig), rp, rp]),
            "buckc_nn_rollout": (None, [P(self.NnConfig), rp, rp, rp, c_int, rp, rp]),
            "buckc_nn_shared_prepare": (None, [P(self.NnConfig), rp, rp, rp, P(self.NnShared)]),
            "buckc_nn_shared_rollout": (None, [P(self.NnConfig), P(self.NnShared), rp, c_int, rp]),
            "buckc_nn_sensitivities": (c_int, [P(self.NnConfig), rp, rp, rp, rp, c_int, P(c_int), c_int, rp, rp]),
            "buckc_box_qp": (c_int, [c_int, rp, c_int, rp, rp, rp, c_int, rp, P(c_int)]),
            "buckc_policy_init": (c_int, [P(self.PolicyC), P(self.PolicyConfigC), P(ctypes.c_char_p)]),
            "buckc_policy_reset": (None, [P(self.PolicyC)]),
            "buckc_policy_forward": (real, [P(self.PolicyConfigC), rp]),
            "buckc_policy_step": (c_int, [P(self.PolicyC), P(self.MeasurementC), rp]),
            "buckc_current_mode_init": (c_int, [P(self.CurrentModeC), P(self.CurrentModeConfigC), P(ctypes.c_char_p)]),
            "buckc_current_mode_reset": (None, [P(self.CurrentModeC)]),
            "buckc_current_mode_step": (c_int, [P(self.CurrentModeC), P(self.MeasurementC), rp]),
            "buckc_compensator_init": (c_int, [P(self.CompensatorC), P(self.CompensatorConfigC), P(ctypes.c_char_p)]),
            "buckc_compensator_reset": (None, [P(self.CompensatorC)]),
            "buckc_compensator_step": (c_int, [P(self.CompensatorC), P(self.MeasurementC), rp]),
        }

    @property
    def dtype(self) -> type:
        """The numpy type of ``buckc_real`` in this build."""
        return np.float64 if self.real is c_double else np.float32


#: the mirrors of each build, from the one definition of :class:`RealMirrors`
REAL_MIRRORS = {"float64": RealMirrors("float64", c_double), "float32": RealMirrors("float32", ctypes.c_float)}


def real_mirrors(precision: str = "float64") -> RealMirrors:
    return REAL_MIRRORS[check_precision(precision)]


_DOUBLE = REAL_MIRRORS["float64"]
PiConfig, Pi, NnConfig, NnShared = _DOUBLE.PiConfig, _DOUBLE.Pi, _DOUBLE.NnConfig, _DOUBLE.NnShared
MeasurementC, PolicyConfigC, PolicyC = _DOUBLE.MeasurementC, _DOUBLE.PolicyConfigC, _DOUBLE.PolicyC
CurrentModeConfigC, CurrentModeC = _DOUBLE.CurrentModeConfigC, _DOUBLE.CurrentModeC
CompensatorConfigC, CompensatorC = _DOUBLE.CompensatorConfigC, _DOUBLE.CompensatorC


class CircuitParametersC(ctypes.Structure):
    _fields_ = [("inductance", c_double), ("capacitance", c_double), ("inductor_resistance", c_double),
                ("switch_on_resistance", c_double), ("diode_forward_voltage", c_double), ("capacitor_esr", c_double)]


class AveragedConfig(ctypes.Structure):
    _fields_ = [("parameters", CircuitParametersC), ("sample_period", c_double)]


class AveragedEntry(ctypes.Structure):
    _fields_ = [("key_load", c_double), ("key_switch", c_double), ("phi", _array(c_double, 4)),
                ("gamma", _array(c_double, 2))]


class AveragedCache(ctypes.Structure):
    _fields_ = [("count", c_int), ("entries", AveragedEntry * CACHE_KEYS)]


class AveragedStep(ctypes.Structure):
    _fields_ = [("phi_y", _array(c_double, 4)), ("gamma_y", _array(c_double, 2)), ("drive", c_double),
                ("forward", c_double), ("y0", _array(c_double, 2)), ("disturbance", _array(c_double, 2))]


class SwitchedConfig(ctypes.Structure):
    _fields_ = [("parameters", CircuitParametersC), ("sample_period", c_double), ("switching_frequency", c_double),
                ("carrier", c_int), ("sensor", c_int), ("grid_points", c_int)]


class SwitchedTable(ctypes.Structure):
    _fields_ = [("load", c_double), ("input_voltage", c_double), ("points", c_int), ("condition", c_double),
                ("rows", _array(c_double, MAX_GRID, COLUMNS))]


class SwitchedKey(ctypes.Structure):
    _fields_ = [("key_load", c_double), ("key_input", c_double), ("load", c_double), ("input_voltage", c_double)]


class SwitchedCache(ctypes.Structure):
    _fields_ = [("n_keys", c_int), ("keys", SwitchedKey * CACHE_KEYS), ("n_tables", c_int), ("next_table", c_int),
                ("tables", SwitchedTable * TABLES)]


class HorizonSettingsC(ctypes.Structure):
    _fields_ = [("horizon", c_int), ("n_blocks", c_int), ("blocks", _array(c_int, MAX_BLOCKS)), ("discount", c_double),
                ("levels", c_int), ("refine_iterations", c_int), ("duty_tolerance", c_double),
                ("bias_filter", c_double)]


class Optimizer(ctypes.Structure):
    _fields_ = [("settings", HorizonSettingsC), ("low", c_double), ("high", c_double), ("n_blocks", c_int),
                ("block_of_step", _array(c_int, MAX_HORIZON)), ("block_starts", _array(c_int, MAX_BLOCKS)),
                ("spacing", c_double), ("grid", _array(c_double, MAX_LEVELS)), ("coarse", _array(c_double, 5)),
                ("global_is_full", c_int), ("n_global", c_int), ("full_lattice", c_int), ("n_lattice", c_int),
                ("lattice", _array(ctypes.c_byte, MAX_LATTICE, MAX_BLOCKS)), ("shrink", c_double),
                ("warm_step", c_double), ("warm_span", c_double), ("near_offsets", _array(c_double, NEAR_OFFSETS)),
                ("stage_candidates_cold", c_int), ("stage_candidates_warm", c_int), ("evaluations", c_int),
                ("passes", c_int), ("best_call", c_int), ("best_row", c_int), ("warm_count", c_int),
                ("near_warm", c_int)]


class PredictorConfig(ctypes.Structure):
    _fields_ = [("kind", c_int), ("nn", NnConfig), ("averaged", AveragedConfig), ("switched", SwitchedConfig)]


class RtiSettingsC(ctypes.Structure):
    _fields_ = [("enabled", c_int), ("iterations", c_int), ("line_search", c_int), ("reuse_jacobian", c_int),
                ("reweightings", c_int), ("smoothing", c_double),
                ("step_limit", c_double), ("regularization", c_double), ("move_damping", c_double),
                ("reweighting_tolerance", c_double),
                ("qp_iterations", c_int),
                ("reference_step", c_double), ("load_step", c_double), ("innovation", c_double),
                ("startup_region", c_double), ("error_region", c_double), ("duty_resolution", c_double)]


class PredictiveConfig(ctypes.Structure):
    _fields_ = [("sample_period", c_double), ("duty_min", c_double), ("duty_max", c_double),
                ("nominal_load", c_double), ("nominal_input_voltage", c_double), ("horizon", HorizonSettingsC),
                ("predictor", PredictorConfig), ("rti", RtiSettingsC)]


class PredictiveState(ctypes.Structure):
    _fields_ = [("delays", c_int), ("have_history", c_int), ("history", _array(c_double, MAX_DELAYS, 3)),
                ("have_warm", c_int), ("warm", _array(c_double, MAX_HORIZON)), ("bias", _array(c_double, 2)),
                ("have_predicted", c_int), ("predicted", _array(c_double, 2)), ("previous_duty", c_double),
                ("conductance", c_double), ("previous_reference", c_double), ("starting", c_int),
                ("best_cost", c_double),
                ("evaluations", c_int), ("passes", c_int), ("best_call", c_int), ("best_row", c_int),
                ("last_solver", c_int), ("last_fallback", c_int), ("qp_iterations", c_int), ("accepted", c_int),
                ("reweighted", c_int),
                ("warm_before_valid", c_int), ("warm_before", _array(c_double, MAX_HORIZON)), ("anchor", c_double)]


class AdaptationSettingsC(ctypes.Structure):
    _fields_ = [("forgetting", c_double), ("initial_covariance", c_double), ("duty_margin", c_double),
                ("min_change_current", c_double), ("min_change_voltage", c_double), ("min_change_duty", c_double),
                ("load_change", c_double), ("max_step", c_double), ("max_deviation", c_double),
                ("error_memory", c_double), ("fallback_ratio", c_double), ("checkpoint_every", c_int),
                ("warmup", c_int)]


class AdaptationConfigC(ctypes.Structure):
    _fields_ = [("settings", AdaptationSettingsC), ("nominal_load", c_double), ("nominal_input_voltage", c_double),
                ("output_scale", _array(c_double, 2))]


#: ctypes mirror -> C type name of the double-only structs (predictors.h, predictive.h), checked like RealMirrors'
PREDICTIVE_MIRRORS = {AdaptationSettingsC: "BuckcAdaptationSettings", AdaptationConfigC: "BuckcAdaptationConfig",CircuitParametersC: "BuckcCircuitParameters", AveragedConfig: "BuckcAveragedConfig",
                      AveragedStep: "BuckcAveragedStep", SwitchedConfig: "BuckcSwitchedConfig",
                      SwitchedTable: "BuckcSwitchedTable", HorizonSettingsC: "BuckcHorizonSettings",
                      Optimizer: "BuckcOptimizer", PredictorConfig: "BuckcPredictorConfig", RtiSettingsC: "BuckcRtiSettings",
                      PredictiveConfig: "BuckcPredictiveConfig", PredictiveState: "BuckcPredictiveState"}
MIRRORS = {**_DOUBLE.names, **PREDICTIVE_MIRRORS}

COST_FUNCTION = ctypes.CFUNCTYPE(c_double, ctypes.c_void_p, ctypes.POINTER(c_double), c_int, ctypes.POINTER(c_double))

_P = ctypes.POINTER
_D = _P(c_double)
_PREDICTIVE_SIGNATURES = {  # the double-only functions (predictors.c, predictive.c)
    "buckc_expm2": (None, [_D, c_double, _D]),
    "buckc_circuit_matrix": (None, [_P(CircuitParametersC), c_double, c_double, _D]),
    "buckc_measured_from_state": (None, [_P(CircuitParametersC), c_double, _D]),
    "buckc_solve2": (None, [_D, _D, _D]),
    "buckc_inverse2": (None, [_D, _D]),
    "buckc_averaged_check": (c_int, [_P(AveragedConfig), _P(ctypes.c_char_p)]),
    "buckc_averaged_discrete": (None, [_P(AveragedConfig), c_double, c_double, _D, _D]),
    "buckc_averaged_cached": (None, [_P(AveragedConfig), _P(AveragedCache), c_double, c_double, _D, _D]),
    "buckc_averaged_prepare": (None, [_P(AveragedConfig), _P(AveragedCache), c_double, c_double, c_double, _D, _D,
                                      _P(AveragedStep)]),
    "buckc_averaged_rollout": (None, [_P(AveragedStep), _D, c_int, _D]),
    "buckc_averaged_linearize": (None, [_P(AveragedStep), _D, c_int, _P(c_int), c_int, _D, _D]),
    "buckc_switched_check": (c_int, [_P(SwitchedConfig), _P(c_int), _P(ctypes.c_char_p)]),
    "buckc_switched_table": (None, [_P(SwitchedConfig), c_double, c_double, _P(SwitchedTable)]),
    "buckc_switched_cached": (_P(SwitchedTable), [_P(SwitchedConfig), _P(SwitchedCache), c_double, c_double]),
    "buckc_switched_lookup": (None, [_P(SwitchedTable), c_double, _D]),
    "buckc_switched_rollout": (None, [_P(SwitchedTable), _D, c_double, _D, c_int, _D, _D]),
    "buckc_switched_linearize": (None, [_P(SwitchedTable), _D, c_double, _D, c_int, _D, _P(c_int), c_int, _D, _D]),
    "buckc_optimizer_init": (c_int, [_P(Optimizer), _P(HorizonSettingsC), c_double, c_double, _P(ctypes.c_char_p)]),
    "buckc_optimizer_solve": (c_double, [_P(Optimizer), COST_FUNCTION, ctypes.c_void_p, _D, c_double, _D, _D]),
    "buckc_predictive_size": (ctypes.c_size_t, []),
    "buckc_predictive_init": (c_int, [ctypes.c_void_p, _P(PredictiveConfig), _P(ctypes.c_char_p)]),
    "buckc_predictive_reset": (None, [ctypes.c_void_p]),
    "buckc_predictive_step": (c_int, [ctypes.c_void_p, _P(MeasurementC), _D]),
    "buckc_predictive_clear_caches": (None, [ctypes.c_void_p]),
    "buckc_predictive_state": (_P(PredictiveState), [ctypes.c_void_p]),
    "buckc_predictive_cost": (c_double, [ctypes.c_void_p, _D, _D]),
    "buckc_predictive_search_last": (c_double, [ctypes.c_void_p, _D]),
    "buckc_predictive_linearize": (c_int, [ctypes.c_void_p, _D, _D, _D]),
    "buckc_adaptive_size": (ctypes.c_size_t, []),
    "buckc_adaptive_init": (c_int, [ctypes.c_void_p, _P(PredictiveConfig), _P(AdaptationConfigC), _P(ctypes.c_char_p)]),
    "buckc_adaptive_reset": (None, [ctypes.c_void_p]),
    "buckc_adaptive_step": (c_int, [ctypes.c_void_p, _P(MeasurementC), _D]),
    "buckc_adaptive_counters": (_P(c_int), [ctypes.c_void_p]),
    "buckc_adaptive_output_layer": (None, [ctypes.c_void_p, _D]),
    "buckc_adaptive_inner": (ctypes.c_void_p, [ctypes.c_void_p]),
}


@functools.lru_cache(maxsize=None)
def library(precision: str = "float64", variant: str = "default") -> ctypes.CDLL:
    """The loaded twins of ``precision`` and build ``variant`` (built on first use), with argument types set and
    the struct layouts checked; the float32 library has the files of :data:`FLOAT32_SOURCES` only."""
    mirrors = real_mirrors(precision)
    lib = ctypes.CDLL(str(build_library(precision=precision, variant=variant)))
    double = precision == "float64"
    for name, (restype, argtypes) in {**mirrors.signatures(), **(_PREDICTIVE_SIGNATURES if double else {})}.items():
        function = getattr(lib, name)
        function.restype, function.argtypes = restype, argtypes
    if lib.buckc_real_name().decode() != precision:
        raise RuntimeError(f"controllers/native.py: the {precision} library was built as {lib.buckc_real_name()!r}")
    for mirror, c_name in {**mirrors.names, **(PREDICTIVE_MIRRORS if double else {})}.items():
        size = lib.buckc_struct_size(c_name.encode())
        if size != ctypes.sizeof(mirror):
            raise RuntimeError(f"controllers/native.py: the ctypes mirror of {c_name} ({precision}) has "
                               f"{ctypes.sizeof(mirror)} bytes, the C struct {size}: update the mirror after editing "
                               "the header")
    return lib


def status_text(status: int) -> str:
    return library().buckc_status_text(status).decode()


def _check(status: int, what: ctypes.c_char_p, owner: str) -> None:
    if status != OK:
        detail = what.value.decode() if what.value else status_text(status)
        raise ValueError(f"{owner}: the C twin refuses the configuration: {detail} ({status_text(status)})")


def _pointer(array: np.ndarray, precision: str = "float64"):
    mirrors = REAL_MIRRORS[precision]
    if array.dtype != mirrors.dtype:
        raise TypeError(f"a {array.dtype} array handed to the {precision} twins")
    return array.ctypes.data_as(ctypes.POINTER(mirrors.real))


# ------------------------------------------------------------------------------------------ configs from Python

def circuit_parameters(p: CircuitParameters) -> CircuitParametersC:
    return CircuitParametersC(p.inductance, p.capacitance, p.inductor_resistance, p.switch_on_resistance,
                              p.diode_forward_voltage, p.capacitor_esr)


def nn_config(model: NNPlantModel, precision: str = "float64"):
    """The folded weights of ``model``'s numpy path (``_weights`` / ``_biases``, read only) as a C config
    (``precision``'s mirror: in float32 every weight rounded to the nearest float)."""
    config = model.config
    problems = []
    if config.delays > MAX_DELAYS:
        problems.append(f"delays {config.delays} > BUCKC_NN_MAX_DELAYS ({MAX_DELAYS})")
    if len(config.hidden) > MAX_HIDDEN_LAYERS:
        problems.append(f"{len(config.hidden)} hidden layers > BUCKC_NN_MAX_HIDDEN_LAYERS ({MAX_HIDDEN_LAYERS})")
    if max(config.hidden) > MAX_WIDTH:
        problems.append(f"hidden layer of {max(config.hidden)} units > BUCKC_NN_MAX_WIDTH ({MAX_WIDTH})")
    if len(config.extra_signals) > MAX_EXTRAS:
        problems.append(f"{len(config.extra_signals)} extra signals > BUCKC_NN_MAX_EXTRAS ({MAX_EXTRAS})")
    if config.n_inputs > MAX_WIDTH:
        problems.append(f"{config.n_inputs} inputs > BUCKC_NN_MAX_WIDTH ({MAX_WIDTH})")
    if problems:
        raise ValueError(f"network {config.label} has no C twin: " + "; ".join(problems))
    c = real_mirrors(precision).NnConfig()
    c.delays = config.delays
    c.n_extras = len(config.extra_signals)
    for i, name in enumerate(config.extra_signals):
        c.extras[i] = EXTRA_SIGNALS.index(name)
    c.n_hidden = len(config.hidden)
    for i, size in enumerate(config.hidden):
        c.hidden[i] = size
    c.activation = list(ACTIVATIONS).index(config.activation)
    c.residual = int(config.residual)
    weights = np.ctypeslib.as_array(c.weights)
    biases = np.ctypeslib.as_array(c.biases)
    folded_w, folded_b = model._weights, model._biases  # the numpy path's layers, x @ W + b
    if len(folded_w) != len(config.hidden) + 1:
        raise ValueError(f"network {config.label}: {len(folded_w)} folded layers, expected {len(config.hidden) + 1}")
    for layer, (w, b) in enumerate(zip(folded_w, folded_b)):
        rows, cols = w.shape
        weights[layer, :rows, :cols] = w
        biases[layer, :cols] = b
    return c


def horizon_config(settings, owner: str) -> HorizonSettingsC:
    blocks = tuple(settings.blocks)
    problems = []
    if settings.horizon > MAX_HORIZON:
        problems.append(f"horizon {settings.horizon} > BUCKC_MAX_HORIZON ({MAX_HORIZON})")
    if len(blocks) > MAX_BLOCKS:
        problems.append(f"{len(blocks)} blocks > BUCKC_MAX_BLOCKS ({MAX_BLOCKS})")
    if settings.levels > MAX_LEVELS:
        problems.append(f"levels {settings.levels} > BUCKC_MAX_LEVELS ({MAX_LEVELS})")
    if problems:
        raise ValueError(f"{owner}: horizon settings have no C twin: " + "; ".join(problems))
    c = HorizonSettingsC()
    c.horizon = settings.horizon
    c.n_blocks = len(blocks)
    for i, size in enumerate(blocks):
        c.blocks[i] = size
    c.discount = settings.discount
    c.levels = settings.levels
    c.refine_iterations = settings.refine_iterations
    c.duty_tolerance = settings.duty_tolerance
    c.bias_filter = settings.bias_filter
    return c


def rti_config(settings, owner: str) -> RtiSettingsC:
    """:class:`~controllers.predictive.RtiSettings` (or None: the search alone) as the C settings."""
    c = RtiSettingsC()
    if settings is None:
        return c
    c.enabled = 1
    c.iterations = settings.iterations
    c.line_search = int(settings.line_search)
    c.reuse_jacobian = int(settings.reuse_jacobian)
    c.reweightings = settings.reweightings
    c.smoothing = settings.smoothing
    c.step_limit = settings.step_limit
    c.regularization = settings.regularization
    c.move_damping = settings.move_damping
    c.reweighting_tolerance = settings.reweighting_tolerance
    c.qp_iterations = settings.qp_iterations
    c.reference_step = settings.reference_step
    c.load_step = settings.load_step
    c.innovation = settings.innovation
    c.startup_region = settings.startup_region
    c.error_region = settings.error_region
    c.duty_resolution = settings.duty_resolution
    return c


def predictor_config(predictor) -> PredictorConfig:
    """One of the three Python predictors as a C predictor configuration (ValueError for others)."""
    c = PredictorConfig()
    if isinstance(predictor, NNPredictor):
        c.kind = PREDICTOR_NN
        c.nn = nn_config(predictor.model)
    elif isinstance(predictor, AveragedModelPredictor):
        c.kind = PREDICTOR_AVERAGED
        c.averaged = AveragedConfig(circuit_parameters(predictor.parameters), predictor.sample_period)
    elif isinstance(predictor, SwitchedModelPredictor):
        points = len(predictor.duty_grid)
        if points > MAX_GRID:
            raise ValueError(f"switched model {predictor.name!r}: {points} duty-grid points > "
                             f"BUCKC_SWITCHED_MAX_GRID ({MAX_GRID})")
        if not np.array_equal(predictor.duty_grid, np.linspace(0.0, 1.0, points)):
            raise ValueError(f"switched model {predictor.name!r}: the duty grid is not linspace(0, 1, {points}), "
                             "the only grid the C twin builds")
        c.kind = PREDICTOR_SWITCHED
        c.switched = SwitchedConfig(circuit_parameters(predictor.parameters), predictor.sample_period,
                                    predictor.switching_frequency, CARRIERS.index(predictor.carrier),
                                    SENSOR_MODELS.index(predictor.sensor), points)
    else:
        raise ValueError(f"predictor {type(predictor).__name__} ({getattr(predictor, 'name', '?')!r}) has no C twin: "
                         "expected NNPredictor, AveragedModelPredictor or SwitchedModelPredictor")
    return c


# ------------------------------------------------------------------------------------------ controllers

class NativePIController:
    """:class:`controllers.pi.PIController` in C (``controllers/c/pi.c``); same protocol, same numbers
    (``precision="float32"``: the float32 build, its duties within the bound of :mod:`controllers.float32`)."""

    def __init__(self, kp: float, ki: float, sample_period: float = 1e-3,
                 duty_limits: tuple[float, float] = (0.0, 1.0), name: str = "PI", tuning: dict | None = None,
                 precision: str = "float64"):
        self.kp, self.ki = check_gains(kp, ki)
        self.sample_period = check_sample_period(sample_period, "PI")
        self.duty_limits = check_duty_limits(duty_limits, "PI")
        self.name = name
        self.tuning = tuning or {}
        self.precision = check_precision(precision)
        self._lib = library(precision)
        mirrors = real_mirrors(precision)
        self._pi = mirrors.Pi()
        what = ctypes.c_char_p()
        config = mirrors.PiConfig(self.kp, self.ki, self.sample_period, *self.duty_limits)
        _check(self._lib.buckc_pi_init(ctypes.byref(self._pi), ctypes.byref(config), ctypes.byref(what)), what, name)
        self._step = self._lib.buckc_pi_step
        self._ref = ctypes.byref(self._pi)

    @classmethod
    def from_python(cls, pi: PIController, precision: str = "float64") -> "NativePIController":
        return cls(pi.kp, pi.ki, pi.sample_period, pi.duty_limits, pi.name, pi.tuning, precision)

    @property
    def integral(self) -> float:
        return self._pi.integral

    @property
    def state(self):
        """The C PI (its copy of the configuration and the integral; a live view)."""
        return self._pi

    def linear_model(self, input_voltage: float | None = None):
        return PIController(self.kp, self.ki, self.sample_period, self.duty_limits).linear_model(input_voltage)

    def reset(self) -> None:
        self._lib.buckc_pi_reset(self._ref)

    def step(self, measurement: Measurement) -> float:
        return self._step(self._ref, measurement.reference, measurement.output_voltage)

    def describe(self) -> dict:
        return {"type": "PI", "name": self.name, "kp_per_V": self.kp, "ki_per_V_s": self.ki,
                "sample_period_s": self.sample_period, "duty_limits": list(self.duty_limits),
                "anti_windup": "conditional integration (clamping)", "tuning": self.tuning,
                "implementation": "C twin (controllers/c/pi.c)" + _build_note(self.precision)}


def _build_note(precision: str) -> str:
    return "" if precision == "float64" else f", {precision} build"


class _MeasurementStepper:
    """The step the C predictive controller and the C explicit policy share: the whole measurement copied into
    one ``buckc_measurement``, the C step called on it, the duty it wrote returned; a failed step is an error
    naming the controller. A subclass binds its C step function and state once, with :meth:`_bind_step`."""

    name: str
    precision: str = "float64"

    def _bind_step(self, step_function, handle) -> None:
        """Call ``step_function(handle, &measurement, &duty)`` at every :meth:`step` (arguments built once)."""
        mirrors = real_mirrors(self.precision)
        self._measurement = mirrors.MeasurementC()
        self._duty = mirrors.real()
        self._step = step_function
        self._args = (handle, ctypes.byref(self._measurement), ctypes.byref(self._duty))

    def step(self, m: Measurement) -> float:
        c = self._measurement
        c.time, c.reference, c.output_voltage = m.time, m.reference, m.output_voltage
        c.inductor_current, c.load_current, c.input_voltage = m.inductor_current, m.load_current, m.input_voltage
        status = self._step(*self._args)
        if status != OK:
            if status == ERR_NO_INDUCTOR_CURRENT:
                raise ValueError(f"{self.name} needs the inductor current: the plant binding has no "
                                 "inductor_current role")
            if status == ERR_ILL_CONDITIONED:
                raise ValueError(self._ill_conditioned(m))
            raise RuntimeError(f"{self.name}: the C step failed: {status_text(status)}")
        return self._duty.value


class NativePredictiveController(_MeasurementStepper):
    """:class:`controllers.predictive.PredictiveController` in C (``controllers/c/predictive.c``).

    Build it with :meth:`from_python`; it holds its own copy of the configuration (the C struct
    points at it) and its own predictor caches, which start empty and, as Python's, survive
    :meth:`reset`.
    """

    def __init__(self, config: PredictiveConfig, name: str, description: dict | None = None):
        self._lib = library()
        self._config = config  # the C controller keeps a pointer to it
        self.name = name
        self.sample_period = check_sample_period(config.sample_period, name)
        self.duty_limits = check_duty_limits((config.duty_min, config.duty_max), name)
        self._description = description or {}
        size = self._lib.buckc_predictive_size()
        self._memory = (c_double * (size // ctypes.sizeof(c_double) + 1))()  # 8-byte aligned
        self._handle = ctypes.cast(self._memory, ctypes.c_void_p)
        what = ctypes.c_char_p()
        _check(self._lib.buckc_predictive_init(self._handle, ctypes.byref(config), ctypes.byref(what)), what, name)
        self._state = self._lib.buckc_predictive_state(self._handle).contents
        self._bind_step(self._lib.buckc_predictive_step, self._handle)

    @classmethod
    def from_python(cls, controller: PredictiveController) -> "NativePredictiveController":
        config = PredictiveConfig()
        config.sample_period = controller.sample_period
        config.duty_min, config.duty_max = controller.duty_limits
        config.nominal_load = controller.nominal_load
        config.nominal_input_voltage = controller.nominal_input_voltage
        config.horizon = horizon_config(controller.settings, controller.name)
        config.predictor = predictor_config(controller.predictor)
        config.rti = rti_config(controller.rti, controller.name)
        return cls(config, controller.name, controller.describe())

    def _ill_conditioned(self, m: Measurement) -> str:
        """The switched model's refusal, worded as its Python reference's."""
        from controllers.predictors import ill_conditioned

        config = self._config.predictor.switched
        periods = round(config.sample_period * config.switching_frequency)
        load = 1.0 / self._state.conductance
        supply = m.input_voltage if math.isfinite(m.input_voltage) else self._config.nominal_input_voltage
        table = self._lib.buckc_switched_cached(ctypes.byref(config), ctypes.byref(SwitchedCache()), load, supply)
        return ill_conditioned(self.name, load, supply, periods, table.contents.condition)

    @property
    def config(self) -> PredictiveConfig:
        return self._config

    @property
    def nominal_input_voltage(self) -> float:
        """The supply [V] assumed for samples without a supply reading (as the Python controller's)."""
        return self._config.nominal_input_voltage

    @property
    def state(self) -> PredictiveState:
        """The C controller's state between samples (a live view: read, do not write)."""
        return self._state

    def reset(self) -> None:
        self._lib.buckc_predictive_reset(self._handle)

    def clear_caches(self) -> None:
        self._lib.buckc_predictive_clear_caches(self._handle)

    def cost(self, duties) -> tuple[float, np.ndarray]:
        """Eq. 23 cost of one per-step duty sequence at the last step's context, and its first prediction."""
        duties = np.ascontiguousarray(duties, dtype=float)
        first = np.empty(2)
        value = self._lib.buckc_predictive_cost(self._handle, _pointer(duties), _pointer(first))
        return value, first

    @property
    def rti(self):
        """Whether the real-time iteration plans (as :attr:`PredictiveController.rti`, truthy or None)."""
        return self._config.rti if self._config.rti.enabled else None

    @property
    def last_solver(self) -> str:
        return SOLVERS[self._state.last_solver]

    @property
    def last_fallback(self) -> str:
        return FALLBACKS[self._state.last_fallback]

    @property
    def best_cost(self) -> float:
        return self._state.best_cost

    @property
    def plan_sequence(self) -> np.ndarray | None:
        """:attr:`PredictiveController.plan_sequence`: the last step's per-step plan (None before the first)."""
        return np.array(self._state.warm[:self._config.horizon.horizon]) if self._state.have_warm else None

    def search_last_sample(self) -> tuple[np.ndarray, float]:
        """:meth:`PredictiveController.search_last_sample` in C: the search on the last step's problem."""
        sequence = np.empty(self._config.horizon.horizon)
        best = self._lib.buckc_predictive_search_last(self._handle, _pointer(sequence))
        return sequence, best

    def linearize(self, duties) -> tuple[np.ndarray, np.ndarray]:
        """The predictor's linearisation (states, Jacobian to the blocks) at the last step's context."""
        duties = np.ascontiguousarray(duties, dtype=float)
        n, nb = self._config.horizon.horizon, self._config.horizon.n_blocks
        out, jacobian = np.empty((n, 2)), np.empty((n, 2, nb))
        status = self._lib.buckc_predictive_linearize(self._handle, _pointer(duties), _pointer(out),
                                                      _pointer(jacobian))
        if status != OK:
            raise ValueError(f"{self.name}: {status_text(status)}")
        return out, jacobian

    def describe(self) -> dict:
        return {**self._description, "name": self.name, "implementation": "C twin (controllers/c/predictive.c)"}


class NativeAdaptiveNNPC(_MeasurementStepper):
    """:class:`controllers.adaptation.AdaptiveNNPC` in C (``controllers/c/adaptation.c``): the recursive least
    squares on the output layer, its guards and fallback, and the NNPC it adapts (``predictive.c``), in one C step.
    Build it with :meth:`from_python`; it starts from the offline output layer, as the Python controller's reset
    does."""

    COUNTERS = ("samples", "updates", "saturated", "steady", "load_step", "bounded", "fallbacks", "checkpoints")

    def __init__(self, predictive: PredictiveConfig, config: AdaptationConfigC, name: str, description: dict,
                 features: int):
        self._lib = library()
        self._predictive, self._adaptation = predictive, config  # copied by init; kept for describe and tests
        self.name = name
        self.sample_period = check_sample_period(predictive.sample_period, name)
        self.duty_limits = check_duty_limits((predictive.duty_min, predictive.duty_max), name)
        self.nominal_load = config.nominal_load
        self.nominal_input_voltage = config.nominal_input_voltage
        self._description, self._features = description, features
        size = self._lib.buckc_adaptive_size()
        self._memory = (c_double * (size // ctypes.sizeof(c_double) + 1))()  # 8-byte aligned, never moved
        self._handle = ctypes.cast(self._memory, ctypes.c_void_p)
        what = ctypes.c_char_p()
        _check(self._lib.buckc_adaptive_init(self._handle, ctypes.byref(predictive), ctypes.byref(config),
                                             ctypes.byref(what)), what, name)
        inner = self._lib.buckc_adaptive_inner(self._handle)
        self._state = self._lib.buckc_predictive_state(inner).contents
        self._bind_step(self._lib.buckc_adaptive_step, self._handle)

    @classmethod
    def from_python(cls, adaptive) -> "NativeAdaptiveNNPC":
        """The C twin of an :class:`~controllers.adaptation.AdaptiveNNPC` (its inner NNPC Python or C), from its
        offline output layer and settings."""
        inner = adaptive.inner
        config = (inner.config if isinstance(inner, NativePredictiveController)
                  else NativePredictiveController.from_python(inner).config)
        predictive = PredictiveConfig.from_buffer_copy(config)
        nn = predictive.predictor.nn
        offline = adaptive._offline  # (hidden + 1, 2): the offline weights and bias
        weights, biases = np.ctypeslib.as_array(nn.weights), np.ctypeslib.as_array(nn.biases)
        weights[nn.n_hidden, :len(offline) - 1, :2] = offline[:-1]
        biases[nn.n_hidden, :2] = offline[-1]
        settings = AdaptationSettingsC(**{name: getattr(adaptive.settings, name) for name, _ in
                                          AdaptationSettingsC._fields_})
        scale = (c_double * 2)(*adaptive._scale)
        adaptation = AdaptationConfigC(settings, adaptive.nominal_load, adaptive.nominal_input_voltage, scale)
        return cls(predictive, adaptation, adaptive.name, adaptive.describe(), len(offline))

    def reset(self) -> None:
        self._lib.buckc_adaptive_reset(self._handle)

    @property
    def predictive_config(self) -> PredictiveConfig:
        """The NNPC's configuration it was built from (the offline output layer)."""
        return self._predictive

    @property
    def adaptation_config(self) -> AdaptationConfigC:
        return self._adaptation

    @property
    def counters(self) -> dict[str, int]:
        """:attr:`AdaptiveNNPC.counters` of the C controller."""
        values = self._lib.buckc_adaptive_counters(self._handle)
        return {name: values[i] for i, name in enumerate(self.COUNTERS)}

    @property
    def output_weights(self) -> np.ndarray:
        """The adapted output layer [weights; bias], (hidden + 1, 2), physical units."""
        theta = np.empty((self._features, 2))
        self._lib.buckc_adaptive_output_layer(self._handle, _pointer(theta))
        return theta

    @property
    def rti(self):
        return self._predictive.rti if self._predictive.rti.enabled else None

    @property
    def last_solver(self) -> str:
        return SOLVERS[self._state.last_solver]

    def describe(self) -> dict:
        return {**self._description, "implementation": "C twin (controllers/c/adaptation.c around predictive.c)"}


def policy_config(controller: ExplicitPolicyController, precision: str = "float64"):
    """The explicit policy's folded weights and settings as a C configuration (``precision``'s mirror;
    ValueError above the C maxima)."""
    policy = controller.policy
    hidden = policy.config.hidden
    problems = []
    if len(hidden) > POLICY_MAX_HIDDEN_LAYERS:
        problems.append(f"{len(hidden)} hidden layers > BUCKC_POLICY_MAX_HIDDEN_LAYERS ({POLICY_MAX_HIDDEN_LAYERS})")
    if max(hidden) > POLICY_MAX_WIDTH:
        problems.append(f"hidden layer of {max(hidden)} units > BUCKC_POLICY_MAX_WIDTH ({POLICY_MAX_WIDTH})")
    if problems:
        raise ValueError(f"policy {policy.config.label} has no C twin: " + "; ".join(problems))
    c = real_mirrors(precision).PolicyConfigC()
    c.sample_period = policy.sample_period
    c.duty_min, c.duty_max = policy.duty_limits
    c.nominal_load = controller.nominal_load
    c.integral_gain = policy.config.integral_gain
    c.integral_band = policy.config.integral_band
    c.n_hidden = len(hidden)
    for i, size in enumerate(hidden):
        c.hidden[i] = size
    weights = np.ctypeslib.as_array(c.weights)
    biases = np.ctypeslib.as_array(c.biases)
    for layer, (w, b) in enumerate(zip(policy.weights, policy.biases)):
        rows, cols = w.shape
        weights[layer, :rows, :cols] = w
        biases[layer, :cols] = b
    return c


class NativeExplicitPolicyController(_MeasurementStepper):
    """:class:`controllers.explicit_policy.ExplicitPolicyController` in C (``controllers/c/explicit_policy.c``);
    ``precision="float32"``: the float32 build (``config`` then a float32 mirror, :func:`policy_config`)."""

    def __init__(self, config, name: str, description: dict | None = None, precision: str = "float64",
                 sample_period: float | None = None, duty_limits: tuple[float, float] | None = None):
        """``sample_period`` [s] and ``duty_limits``: the controller's own (default: the configuration's); a
        float32 configuration holds them rounded to float, and a master must sample at the exact period."""
        self.precision = check_precision(precision)
        mirrors = real_mirrors(precision)
        if not isinstance(config, mirrors.PolicyConfigC):
            raise TypeError(f"{name}: the configuration is not a {precision} BuckcPolicyConfig mirror")
        self._lib = library(precision)
        self._config = config  # the C policy keeps a pointer to it
        self.name = name
        self.sample_period = check_sample_period(config.sample_period if sample_period is None else sample_period,
                                                 name)
        self.duty_limits = check_duty_limits((config.duty_min, config.duty_max) if duty_limits is None
                                             else duty_limits, name)
        self._description = description or {}
        self._policy = mirrors.PolicyC()
        what = ctypes.c_char_p()
        _check(self._lib.buckc_policy_init(ctypes.byref(self._policy), ctypes.byref(config), ctypes.byref(what)),
               what, name)
        self._bind_step(self._lib.buckc_policy_step, ctypes.byref(self._policy))

    @classmethod
    def from_python(cls, controller: ExplicitPolicyController,
                    precision: str = "float64") -> "NativeExplicitPolicyController":
        return cls(policy_config(controller, precision), controller.name, controller.describe(), precision,
                   controller.sample_period, controller.duty_limits)

    @property
    def config(self):
        return self._config

    @property
    def state(self):
        """The C policy's state between samples (a live view: read, do not write)."""
        return self._policy

    def reset(self) -> None:
        self._lib.buckc_policy_reset(ctypes.byref(self._policy))

    def forward(self, x) -> float:
        x = np.ascontiguousarray(x, dtype=real_mirrors(self.precision).dtype)
        return self._lib.buckc_policy_forward(ctypes.byref(self._config), _pointer(x, self.precision))

    def describe(self) -> dict:
        return {**self._description, "name": self.name,
                "implementation": "C twin (controllers/c/explicit_policy.c)" + _build_note(self.precision)}


def current_mode_config(controller: CurrentModeController, precision: str = "float64"):
    """The C configuration of a current-mode controller (``precision``'s mirror: float32 rounds each value)."""
    g = controller.gains
    low, high = controller.duty_limits
    return real_mirrors(precision).CurrentModeConfigC(
        controller.sample_period, low, high, controller.nominal_input_voltage, g.kp_voltage, g.ki_voltage, g.kp_current,
        g.ki_current, g.current_limit, g.computation_delay)


def compensator_config(controller: CompensatorController, precision: str = "float64"):
    """The C configuration of a compensator (``precision``'s mirror: float32 rounds each coefficient)."""
    k = controller.coefficients
    if k.order > COMPENSATOR_MAX_ORDER:
        raise ValueError(f"compensator of order {k.order} has no C twin: > BUCKC_COMPENSATOR_MAX_ORDER "
                         f"({COMPENSATOR_MAX_ORDER})")
    c = real_mirrors(precision).CompensatorConfigC()
    c.sample_period = controller.sample_period
    c.duty_min, c.duty_max = controller.duty_limits
    c.nominal_input_voltage = controller.nominal_input_voltage
    c.order = k.order
    for i, (b, a) in enumerate(zip(k.numerator, k.denominator)):
        c.numerator[i], c.denominator[i] = b, a
    c.computation_delay = k.computation_delay
    return c


class _LinearTwin(_MeasurementStepper):
    """A classical controller's C twin: its configuration copied into the C state, one step per sample
    (``precision``: the build of the twins it runs in)."""

    def __init__(self, controller, state, config, init, reset, step, precision: str):
        self.precision = check_precision(precision)
        self.name = controller.name
        # the Python controller's (double) period and limits: a float32 config's period rounded to float would
        # drift off the master's sample instants
        self.sample_period, self.duty_limits = controller.sample_period, controller.duty_limits
        self._description = controller.describe()
        name = self.name
        self._state = state
        self._reset = reset
        what = ctypes.c_char_p()
        _check(init(ctypes.byref(state), ctypes.byref(config), ctypes.byref(what)), what, name)
        self._bind_step(step, ctypes.byref(state))

    @property
    def state(self):
        """The C controller's state between samples (a live view: read, do not write)."""
        return self._state

    def reset(self) -> None:
        self._reset(ctypes.byref(self._state))


class NativeCurrentModeController(_LinearTwin):
    """:class:`controllers.current_mode.CurrentModeController` in C (``controllers/c/current_mode.c``;
    ``precision="float32"``: the float32 build, its duties within
    :func:`controllers.float32.current_mode_step_bound`)."""

    def __init__(self, controller: CurrentModeController, precision: str = "float64"):
        lib = library(precision)
        self.python = controller
        self.gains, self.nominal_input_voltage = controller.gains, controller.nominal_input_voltage
        super().__init__(controller, real_mirrors(precision).CurrentModeC(), current_mode_config(controller, precision),
                         lib.buckc_current_mode_init, lib.buckc_current_mode_reset, lib.buckc_current_mode_step,
                         precision)

    def linear_model(self, input_voltage: float | None = None):
        return self.python.linear_model(input_voltage)

    def describe(self) -> dict:
        return {**self._description,
                "implementation": "C twin (controllers/c/current_mode.c)" + _build_note(self.precision)}


class NativeCompensatorController(_LinearTwin):
    """:class:`controllers.compensator.CompensatorController` in C (``controllers/c/compensator.c``;
    ``precision="float32"``: the float32 build, its duties within
    :func:`controllers.float32.compensator_step_bound`)."""

    def __init__(self, controller: CompensatorController, precision: str = "float64"):
        lib = library(precision)
        self.python = controller
        self.coefficients, self.nominal_input_voltage = controller.coefficients, controller.nominal_input_voltage
        super().__init__(controller, real_mirrors(precision).CompensatorC(), compensator_config(controller, precision),
                         lib.buckc_compensator_init, lib.buckc_compensator_reset, lib.buckc_compensator_step,
                         precision)

    def linear_model(self, input_voltage: float | None = None):
        return self.python.linear_model(input_voltage)

    def describe(self) -> dict:
        return {**self._description,
                "implementation": "C twin (controllers/c/compensator.c)" + _build_note(self.precision)}


def native_twin(controller, precision: str = "float64"):
    """The C twin of a Python PI, predictive or explicit-policy controller (an adaptive NNPC: the
    same adaptation around the twin of its NNPC); any other controller is returned as it is.
    ``precision="float32"``: the float32 build, which the PI, the explicit NNPC, the current-mode controller
    and the compensator have (a predictive controller is a ValueError saying so)."""
    from controllers.adaptation import AdaptiveNNPC

    check_precision(precision)
    if isinstance(controller, AdaptiveNNPC):
        twin = native_twin(controller.inner, precision)
        return controller if twin is controller.inner else controller.with_inner(twin)
    if isinstance(controller, PIController):
        return NativePIController.from_python(controller, precision)
    if isinstance(controller, PredictiveController):
        if precision != "float64":
            raise ValueError(f"{controller.name} has no {precision} build: the predictive controller's C files "
                             "compute in double here (predictive.c's float32 build runs in the Cortex-M4F image, "
                             "cosim/benchmark_harness/cortex_m4.py); float32: the PI, the explicit NNPC, "
                             "the current-mode controller and the compensator")
        return NativePredictiveController.from_python(controller)
    if isinstance(controller, ExplicitPolicyController):
        return NativeExplicitPolicyController.from_python(controller, precision)
    if isinstance(controller, CurrentModeController):
        return NativeCurrentModeController(controller, precision)
    if isinstance(controller, CompensatorController):
        return NativeCompensatorController(controller, precision)
    return controller


# ------------------------------------------------------------------------------------------ predictors and optimizer

class NativePredictor:
    """A C predictor behind the Python :class:`~controllers.predictors.Predictor` protocol (one C
    rollout per candidate; for checking the twins, not for speed)."""

    def __init__(self, predictor):
        self._lib = library()
        self.name = f"{predictor.name} (C twin)"
        self.delays = predictor.delays
        self.config = predictor_config(predictor)
        self._extras = tuple(predictor.model.config.extra_signals) if isinstance(predictor, NNPredictor) else ()
        self.averaged_cache = AveragedCache()
        self.switched_cache = SwitchedCache()

    def clear_cache(self) -> None:
        self.averaged_cache = AveragedCache()
        self.switched_cache = SwitchedCache()

    def rollout(self, context: PredictionContext, duties: np.ndarray, disturbance: np.ndarray) -> np.ndarray:
        duties = np.ascontiguousarray(duties, dtype=float)
        m, n = duties.shape
        out = np.empty((m, n, 2))
        dist = np.ascontiguousarray(disturbance, dtype=float)
        history = np.ascontiguousarray(context.history, dtype=float)
        lib, kind = self._lib, self.config.kind
        if kind == PREDICTOR_NN:
            signals = {"load_current": context.load_current, "input_voltage": context.input_voltage,
                       "load_conductance": context.load_conductance}
            extras = np.array([signals[s] for s in self._extras] or [0.0])
            shared = NnShared()
            lib.buckc_nn_shared_prepare(ctypes.byref(self.config.nn), _pointer(history),
                                        _pointer(extras) if self._extras else None, _pointer(dist),
                                        ctypes.byref(shared))
            for i in range(m):
                lib.buckc_nn_shared_rollout(ctypes.byref(self.config.nn), ctypes.byref(shared), _pointer(duties[i]),
                                            n, _pointer(out[i]))
        elif kind == PREDICTOR_AVERAGED:
            step = AveragedStep()
            y0 = np.ascontiguousarray(history[0, :2])
            lib.buckc_averaged_prepare(ctypes.byref(self.config.averaged), ctypes.byref(self.averaged_cache),
                                       context.load_resistance, context.previous_duty, context.input_voltage,
                                       _pointer(y0), _pointer(dist), ctypes.byref(step))
            for i in range(m):
                lib.buckc_averaged_rollout(ctypes.byref(step), _pointer(duties[i]), n, _pointer(out[i]))
        else:
            table = lib.buckc_switched_cached(ctypes.byref(self.config.switched), ctypes.byref(self.switched_cache),
                                              context.load_resistance, context.input_voltage)
            y0 = np.ascontiguousarray(history[0, :2])
            for i in range(m):
                lib.buckc_switched_rollout(table, _pointer(y0), context.previous_duty, _pointer(duties[i]), n,
                                           _pointer(dist), _pointer(out[i]))
        return out

    def linearize(self, context: PredictionContext, duties: np.ndarray, disturbance: np.ndarray,
                  block_of_step: np.ndarray, n_blocks: int) -> tuple[np.ndarray, np.ndarray]:
        """The C linearisations (``buckc_nn_sensitivities``, ``buckc_averaged_linearize``,
        ``buckc_switched_linearize``) behind :meth:`~controllers.predictors.Predictor.linearize`."""
        duties = np.ascontiguousarray(duties, dtype=float)
        n = len(duties)
        out, jacobian = np.empty((n, 2)), np.empty((n, 2, n_blocks))
        dist = np.ascontiguousarray(disturbance, dtype=float)
        history = np.ascontiguousarray(context.history, dtype=float)
        blocks = np.ascontiguousarray(block_of_step, dtype=np.intc)
        block_pointer = blocks.ctypes.data_as(ctypes.POINTER(c_int))
        lib, kind = self._lib, self.config.kind
        if kind == PREDICTOR_NN:
            signals = {"load_current": context.load_current, "input_voltage": context.input_voltage,
                       "load_conductance": context.load_conductance}
            extras = np.array([signals[s] for s in self._extras]) if self._extras else None
            return nn_sensitivities(self.config.nn, history, duties, extras, dist, blocks, n_blocks)
        y0 = np.ascontiguousarray(history[0, :2])
        if kind == PREDICTOR_AVERAGED:
            step = AveragedStep()
            lib.buckc_averaged_prepare(ctypes.byref(self.config.averaged), ctypes.byref(self.averaged_cache),
                                       context.load_resistance, context.previous_duty, context.input_voltage,
                                       _pointer(y0), _pointer(dist), ctypes.byref(step))
            lib.buckc_averaged_linearize(ctypes.byref(step), _pointer(duties), n, block_pointer, n_blocks,
                                         _pointer(out), _pointer(jacobian))
        else:
            table = lib.buckc_switched_cached(ctypes.byref(self.config.switched), ctypes.byref(self.switched_cache),
                                              context.load_resistance, context.input_voltage)
            lib.buckc_switched_linearize(table, _pointer(y0), context.previous_duty, _pointer(duties), n,
                                         _pointer(dist), block_pointer, n_blocks, _pointer(out), _pointer(jacobian))
        return out, jacobian

    def describe(self) -> dict:
        return {"type": "C twin", "name": self.name}


class NativeOptimizer:
    """The C :c:func:`buckc_optimizer_solve` on a Python cost of one sequence (for twin tests)."""

    def __init__(self, settings, duty_limits: tuple[float, float]):
        self._lib = library()
        self.optimizer = Optimizer()
        self._settings = horizon_config(settings, "optimizer")
        self.horizon = settings.horizon
        what = ctypes.c_char_p()
        low, high = check_duty_limits(duty_limits, "optimizer")
        _check(self._lib.buckc_optimizer_init(ctypes.byref(self.optimizer), ctypes.byref(self._settings), low, high,
                                              ctypes.byref(what)), what, "optimizer")

    def solve(self, cost_of_sequence, warm: np.ndarray | None = None, anchor: float = 0.5) -> tuple[np.ndarray, float]:
        """``cost_of_sequence(duties (horizon,)) -> float``; returns (sequence, best cost)."""
        errors = []

        def callback(_user, duties, horizon, first):
            try:
                value = float(cost_of_sequence(np.ctypeslib.as_array(duties, (horizon,)).copy()))
            except Exception as error:  # an exception cannot cross the C frames
                errors.append(error)
                value = math.nan
            first[0] = first[1] = math.nan
            return value

        function = COST_FUNCTION(callback)
        sequence = np.empty(self.horizon)
        warm_array = None if warm is None else np.ascontiguousarray(warm, dtype=float)
        best = self._lib.buckc_optimizer_solve(ctypes.byref(self.optimizer), function, None,
                                               None if warm_array is None else _pointer(warm_array), anchor,
                                               _pointer(sequence), None)
        if errors:
            raise errors[0]
        return sequence, best

    @property
    def evaluations(self) -> int:
        return self.optimizer.evaluations

    @property
    def passes(self) -> int:
        return self.optimizer.passes

    @property
    def best_location(self) -> tuple[int, int]:
        return self.optimizer.best_call, self.optimizer.best_row


# ------------------------------------------------------------------------------------------ building blocks for tests

def expm2(a: np.ndarray, t: float) -> np.ndarray:
    out = np.empty(4)
    library().buckc_expm2(_pointer(np.ascontiguousarray(a, dtype=float).ravel()), t, _pointer(out))
    return out.reshape(2, 2)


def _precision_of(config) -> str:
    return next(p for p, m in REAL_MIRRORS.items() if isinstance(config, (m.NnConfig, m.PolicyConfigC, m.PiConfig)))


def nn_activate(z: np.ndarray, activation: str = "tanh", precision: str = "float64") -> np.ndarray:
    """The NN twins' hidden-layer activation (``buckc_nn_activate``: ``buckc_tanh`` for tanh in double,
    ``buckc_tanhf`` in float32) of every element of ``z``, returned as float64."""
    dtype = REAL_MIRRORS[check_precision(precision)].dtype
    z = np.ascontiguousarray(np.ravel(z), dtype=dtype)
    out = np.empty_like(z)
    library(precision).buckc_nn_activate(list(ACTIVATIONS).index(activation), _pointer(z, precision), len(z),
                                         _pointer(out, precision))
    return out.astype(float)


def nn_forward(config, x: np.ndarray) -> np.ndarray:
    """``NNPlantModel.predict`` in C, one row at a time, in the precision of ``config``'s mirror
    (:func:`nn_config`); float32 rows are rounded to float on the way in, the outputs returned as float64."""
    precision = _precision_of(config)
    dtype = REAL_MIRRORS[precision].dtype
    x = np.ascontiguousarray(np.atleast_2d(x), dtype=dtype)
    out = np.empty((len(x), 2), dtype=dtype)
    lib = library(precision)
    for i in range(len(x)):
        lib.buckc_nn_forward(ctypes.byref(config), _pointer(x[i], precision), _pointer(out[i], precision))
    return out.astype(float)


def estimate_conductance(output_voltage: float, load_current: float, inductor_current: float, previous: float,
                         precision: str = "float64") -> float:
    """``load_estimate.estimate_conductance`` in C (``controllers/c/load_estimate.c``), in ``precision``."""
    return library(precision).buckc_estimate_conductance(output_voltage, load_current, inductor_current, previous)


def nn_rollout(config, histories: np.ndarray, duties: np.ndarray, extras: np.ndarray | None = None,
               disturbance: np.ndarray | None = None) -> np.ndarray:
    """``NNPlantModel.rollout`` in C: histories (M, delays, 3), duties (M, N), extras (M, E) -> (M, N, 2), in the
    precision of ``config``'s mirror (float32: inputs rounded to float, outputs returned as float64)."""
    precision = _precision_of(config)
    dtype = REAL_MIRRORS[precision].dtype
    histories = np.ascontiguousarray(histories, dtype=dtype)
    duties = np.ascontiguousarray(duties, dtype=dtype)
    m, n = duties.shape
    out = np.empty((m, n, 2), dtype=dtype)
    ex = None if extras is None else np.ascontiguousarray(extras, dtype=dtype)
    dist = None if disturbance is None else np.ascontiguousarray(disturbance, dtype=dtype)
    lib = library(precision)
    for i in range(m):
        lib.buckc_nn_rollout(ctypes.byref(config), _pointer(histories[i], precision),
                             None if ex is None else _pointer(ex[i], precision), _pointer(duties[i], precision), n,
                             None if dist is None else _pointer(dist, precision), _pointer(out[i], precision))
    return out.astype(float)


def nn_rollout_shared(config, history: np.ndarray, duties: np.ndarray, extras: np.ndarray | None = None,
                      disturbance: np.ndarray | None = None) -> np.ndarray:
    """``NNPlantModel.rollout_shared`` in C: one history (delays, 3) for all candidates (``config``'s precision)."""
    precision = _precision_of(config)
    mirrors = REAL_MIRRORS[precision]
    history = np.ascontiguousarray(history, dtype=mirrors.dtype)
    duties = np.ascontiguousarray(duties, dtype=mirrors.dtype)
    m, n = duties.shape
    out = np.empty((m, n, 2), dtype=mirrors.dtype)
    ex = None if extras is None or not len(extras) else np.ascontiguousarray(extras, dtype=mirrors.dtype)
    dist = None if disturbance is None else np.ascontiguousarray(disturbance, dtype=mirrors.dtype)
    shared = mirrors.NnShared()
    lib = library(precision)
    lib.buckc_nn_shared_prepare(ctypes.byref(config), _pointer(history, precision),
                                None if ex is None else _pointer(ex, precision),
                                None if dist is None else _pointer(dist, precision), ctypes.byref(shared))
    for i in range(m):
        lib.buckc_nn_shared_rollout(ctypes.byref(config), ctypes.byref(shared), _pointer(duties[i], precision), n,
                                    _pointer(out[i], precision))
    return out.astype(float)


def box_qp(h, g, lower, upper, max_iterations: int, precision: str = "float64") -> tuple[np.ndarray, int, bool]:
    """:func:`controllers.box_qp.solve_box_qp` in C (``controllers/c/box_qp.c``), in ``precision``."""
    dtype = REAL_MIRRORS[check_precision(precision)].dtype
    n = len(g)
    arrays = [np.ascontiguousarray(a, dtype=dtype) for a in (h, g, lower, upper)]
    x = np.empty(n, dtype=dtype)
    converged = c_int()
    used = library(precision).buckc_box_qp(n, *(_pointer(a, precision) for a in arrays[:1]), n,
                                           *(_pointer(a, precision) for a in arrays[1:]), max_iterations,
                                           _pointer(x, precision), ctypes.byref(converged))
    if used < 0:
        raise ValueError(f"box QP with {n} variables: {status_text(used)}")
    return x.astype(float), used, bool(converged.value)


def nn_sensitivities(config, history: np.ndarray, duties: np.ndarray, extras: np.ndarray | None,
                     disturbance: np.ndarray | None, block_of_step: np.ndarray,
                     n_blocks: int) -> tuple[np.ndarray, np.ndarray]:
    """``NNPlantModel.rollout_sensitivities`` in C, in the precision of ``config``'s mirror."""
    precision = _precision_of(config)
    dtype = REAL_MIRRORS[precision].dtype
    n = len(duties)
    history, duties = (np.ascontiguousarray(a, dtype=dtype) for a in (history, duties))
    ex = None if extras is None or not len(extras) else np.ascontiguousarray(extras, dtype=dtype)
    dist = None if disturbance is None else np.ascontiguousarray(disturbance, dtype=dtype)
    blocks = np.ascontiguousarray(block_of_step, dtype=np.intc)
    out, jacobian = np.empty((n, 2), dtype=dtype), np.empty((n, 2, n_blocks), dtype=dtype)
    status = library(precision).buckc_nn_sensitivities(
        ctypes.byref(config), _pointer(history, precision), None if ex is None else _pointer(ex, precision),
        None if dist is None else _pointer(dist, precision), _pointer(duties, precision), n,
        blocks.ctypes.data_as(ctypes.POINTER(c_int)), n_blocks, _pointer(out, precision), _pointer(jacobian, precision))
    if status != OK:
        raise ValueError(f"nn sensitivities for {n_blocks} blocks: {status_text(status)}")
    return out.astype(float), jacobian.astype(float)


def switched_table(predictor: SwitchedModelPredictor, load: float, input_voltage: float) -> np.ndarray:
    """``SwitchedModelPredictor._table`` computed in C (no cache): (grid_points, 24)."""
    config = predictor_config(predictor).switched
    table = SwitchedTable()
    library().buckc_switched_table(ctypes.byref(config), load, input_voltage, ctypes.byref(table))
    return np.ctypeslib.as_array(table.rows)[:table.points].copy()


def switched_rollout_with_table(table: np.ndarray, y0, previous_duty: float, duties: np.ndarray,
                                disturbance) -> np.ndarray:
    """The C switched rollout on a given table (e.g. Python's own), for all candidates."""
    c_table = SwitchedTable()
    c_table.points = len(table)
    np.ctypeslib.as_array(c_table.rows)[:len(table)] = table
    duties = np.ascontiguousarray(duties, dtype=float)
    m, n = duties.shape
    out = np.empty((m, n, 2))
    y = np.ascontiguousarray(y0, dtype=float)
    dist = np.ascontiguousarray(disturbance, dtype=float)
    lib = library()
    for i in range(m):
        lib.buckc_switched_rollout(ctypes.byref(c_table), _pointer(y), previous_duty, _pointer(duties[i]), n,
                                   _pointer(dist), _pointer(out[i]))
    return out
