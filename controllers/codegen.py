"""Data for the C twins: a controller's configuration as a C header of ``static const`` structs.

A controller FMU or the C benchmark harness is the hand-written algorithms of ``controllers/c``
compiled with one generated header, ``controller_config.h``. The header holds data only -- the
kind of controller, its name and GUID, and the configuration structs the algorithms read (the
PI's gains and limits, the predictive controller's horizon settings, circuit parameters and
the network's folded weights, or the explicit policy's folded weights and integral term) --
written from the same ctypes mirrors :mod:`controllers.native` hands to the in-process twins, so an FMU computes exactly what the twins compute. Numbers are
written with 17 significant digits (``repr``), which a C compiler reads back to the same double.

``precision="float32"`` writes the data of the float32 build (``buckc_real`` = float, see
``controllers/c/buckc.h``): the PI's, the explicit policy's, the current-mode controller's or the
compensator's configuration from the float32 mirrors, every number the shortest literal that reads
back to the same float, with an ``f`` suffix, and a guard that stops a compilation without ``-DBUCKC_FLOAT32``.
A predictive controller's float32 data is its double configuration rounded to float, field by field (the
float32 build of predictive.c has no host mirror: it runs in the Cortex-M4F image and the host's build of that
image, cosim/benchmark_harness/cortex_m4.py); only the NN predictor's (the online NNPC's): the circuit predictors
of the MPC baselines compute in double only, a ValueError says so.
"""

from __future__ import annotations

import ctypes
import hashlib
import math
import uuid

import numpy as np

from controllers.adaptation import AdaptiveNNPC
from controllers.compensator import CompensatorController
from controllers.current_mode import CurrentModeController
from controllers.explicit_policy import ExplicitPolicyController
from controllers.native import (
    NativeAdaptiveNNPC,
    PredictiveConfig,
    check_precision,
    compensator_config,
    current_mode_config,
    native_twin,
    real_mirrors,
)
from controllers.pi import PIController
from controllers.predictive import PredictiveController
from controllers.predictors import NNPredictor

KIND_PI, KIND_PREDICTIVE, KIND_EXPLICIT = "CONTROLLER_PI", "CONTROLLER_PREDICTIVE", "CONTROLLER_EXPLICIT"
KIND_CURRENT_MODE, KIND_COMPENSATOR = "CONTROLLER_CURRENT_MODE", "CONTROLLER_COMPENSATOR"
#: the adaptive NNPC (controllers/c/adaptation.c): its header holds the NNPC's and the adaptation's configurations;
#: the C benchmark harness runs it, no controller FMU does
KIND_ADAPTIVE = "CONTROLLER_ADAPTIVE"


def _number(value, precision: str = "float64") -> str:
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"a configuration value is {value}: the C twins need finite numbers")
        if precision == "float32":  # the shortest text that reads back to this float
            text = str(np.float32(value))
            return (text if any(c in text for c in ".eE") else text + ".0") + "f"
        text = repr(value)
        return text if any(c in text for c in ".eE") else text + ".0"
    return str(int(value))


def _is_zero(value) -> bool:
    if isinstance(value, ctypes.Structure):
        return all(_is_zero(getattr(value, name)) for name, _ in value._fields_)
    if isinstance(value, ctypes.Array):
        return all(_is_zero(v) for v in value)
    return value == 0


def initializer(value, precision: str = "float64") -> str:
    """A C initializer for a ctypes value: designated fields for structs, designated indices for
    arrays, zeros left out (C zero-fills what an initializer does not name); floating-point numbers
    as literals of ``precision`` (a float32 mirror's values with an ``f`` suffix)."""
    if isinstance(value, ctypes.Structure):
        parts = [f".{name} = {initializer(getattr(value, name), precision)}" for name, _ in value._fields_
                 if not _is_zero(getattr(value, name))]
        return "{" + ", ".join(parts) + "}" if parts else "{0}"
    if isinstance(value, ctypes.Array):
        parts = [f"[{i}] = {initializer(v, precision)}" for i, v in enumerate(value) if not _is_zero(v)]
        return "{" + ", ".join(parts) + "}" if parts else "{0}"
    return _number(value, precision)


def controller_kind(controller) -> str:
    if isinstance(controller, AdaptiveNNPC):
        return KIND_ADAPTIVE
    if isinstance(controller, PIController):
        return KIND_PI
    if isinstance(controller, PredictiveController):
        return KIND_PREDICTIVE
    if isinstance(controller, ExplicitPolicyController):
        return KIND_EXPLICIT
    if isinstance(controller, CurrentModeController):
        return KIND_CURRENT_MODE
    if isinstance(controller, CompensatorController):
        return KIND_COMPENSATOR
    raise ValueError(f"controller {getattr(controller, 'name', controller)!r} ({type(controller).__name__}) has no C "
                     "twin to generate: expected the PI, a predictive controller (NNPC, MPC), the adaptive NNPC, the "
                     "explicit NNPC, the current-mode controller or a compensator (Type-III)")


def config_header(controller, name: str | None = None, precision: str = "float64") -> str:
    """``controller_config.h`` for a Python PI, predictive, explicit-policy, current-mode or compensator
    controller (data only), in ``precision`` (float32: the controllers with a float32 build, for a build with
    ``-DBUCKC_FLOAT32``)."""
    kind = controller_kind(controller)
    if kind == KIND_ADAPTIVE:
        return _adaptive_header(controller, name or controller.name, check_precision(precision))
    if kind == KIND_PREDICTIVE and check_precision(precision) == "float32" and not isinstance(controller.predictor,
                                                                                              NNPredictor):
        raise ValueError(f"{controller.name} has no float32 build: its {type(controller.predictor).__name__} "
                         "(controllers/c/predictors.c) computes in double only; the online NNPC (NN predictor) has one")
    # the configuration the twins run, checked (a predictive controller's: the double one, rounded below)
    twin = native_twin(controller, "float64" if kind == KIND_PREDICTIVE else check_precision(precision))
    mirrors = real_mirrors(precision)
    pi, policy = mirrors.PiConfig(), mirrors.PolicyConfigC()
    predictive = PredictiveConfig()
    current_mode, compensator = mirrors.CurrentModeConfigC(), mirrors.CompensatorConfigC()
    if kind == KIND_PI:
        pi = mirrors.PiConfig(twin.kp, twin.ki, twin.sample_period, *twin.duty_limits)
    elif kind == KIND_PREDICTIVE:
        predictive = twin.config
    elif kind == KIND_EXPLICIT:
        policy = twin.config
    elif kind == KIND_CURRENT_MODE:
        current_mode = current_mode_config(controller, precision)
    else:
        compensator = compensator_config(controller, precision)
    name = name or controller.name
    body = [f"static const int CONTROLLER_KIND = {kind};",
            f"static const BuckcPiConfig PI_CONFIG = {initializer(pi, precision)};"]
    if precision == "float64" or kind == KIND_PREDICTIVE:
        body.append(f"static const BuckcPredictiveConfig PREDICTIVE_CONFIG = {initializer(predictive, precision)};")
    body.append(f"static const BuckcPolicyConfig POLICY_CONFIG = {initializer(policy, precision)};")
    body.append(f"static const BuckcCurrentModeConfig CURRENT_MODE_CONFIG = {initializer(current_mode, precision)};")
    body.append(f"static const BuckcCompensatorConfig COMPENSATOR_CONFIG = {initializer(compensator, precision)};")
    data = "\n".join(body)
    guid = "{" + str(uuid.UUID(hashlib.sha256((name + data).encode()).hexdigest()[:32])) + "}"
    includes = ['#include "controller_variables.h"', '#include "pi.h"']
    includes += ['#include "predictive.h"'] if precision == "float64" or kind == KIND_PREDICTIVE else []
    includes += ['#include "explicit_policy.h"']
    includes += ['#include "current_mode.h"', '#include "compensator.h"']
    # the sample clock of an FMU stays in double: a float Ts would drift off the master's sample instants
    period = _number(float(controller.sample_period))
    clock = [] if precision == "float64" else [f"#define CONTROLLER_SAMPLE_PERIOD {period} /* [s], double */"]
    guard = [] if precision == "float64" else [
        "#ifndef BUCKC_FLOAT32",
        '#error "controller_config.h holds float32 data: compile with -DBUCKC_FLOAT32 (the float32 build)"',
        "#endif", ""]
    lines = ["/* Generated by buck-cosim (controllers/codegen.py) -- data only, do not edit.",
             f" * {name}: the configuration the hand-written C twins in controllers/c read"
             + ("" if precision == "float64" else f" ({precision} build)") + ". */",
             "#ifndef CONTROLLER_CONFIG_H", "#define CONTROLLER_CONFIG_H", "", *guard, *includes, "",
             f"#define CONTROLLER_NAME {_c_string(name)}",
             f'#define CONTROLLER_GUID "{guid}"', *clock, "", data, "", "#endif", ""]
    return "\n".join(lines)


def _adaptive_header(controller, name: str, precision: str) -> str:
    """``controller_config.h`` of an adaptive NNPC: its NNPC's configuration (the offline network) as
    PREDICTIVE_CONFIG and the adaptation's as ADAPTATION_CONFIG (double only: adaptation.c has no float32 build)."""
    if precision != "float64":
        raise ValueError(f"{controller.name} has no {precision} build: controllers/c/adaptation.c computes in double")
    twin = NativeAdaptiveNNPC.from_python(controller)
    data = "\n".join([f"static const int CONTROLLER_KIND = {KIND_ADAPTIVE};",
                      f"static const BuckcPredictiveConfig PREDICTIVE_CONFIG = {initializer(twin.predictive_config)};",
                      f"static const BuckcAdaptationConfig ADAPTATION_CONFIG = {initializer(twin.adaptation_config)};"])
    guid = "{" + str(uuid.UUID(hashlib.sha256((name + data).encode()).hexdigest()[:32])) + "}"
    return "\n".join(["/* Generated by buck-cosim (controllers/codegen.py) -- data only, do not edit.",
                      f" * {name}: the configuration the hand-written C twins in controllers/c read. */",
                      "#ifndef CONTROLLER_CONFIG_H", "#define CONTROLLER_CONFIG_H", "",
                      '#include "controller_variables.h"', '#include "adaptation.h"', '#include "predictive.h"', "",
                      f"#define CONTROLLER_NAME {_c_string(name)}", f'#define CONTROLLER_GUID "{guid}"',
                      "#define ADAPTIVE_CONTROLLER 1", "", data, "",
                      "#endif", ""])


def header_guid(header: str) -> str:
    """The GUID a generated header declares."""
    for line in header.splitlines():
        if line.startswith("#define CONTROLLER_GUID "):
            return line.split('"')[1]
    raise ValueError("not a generated controller_config.h: no CONTROLLER_GUID")


def _c_string(text: str) -> str:
    escaped = text.replace("\\", "\\\\").replace('"', '\\"')
    return f'"{escaped}"'
