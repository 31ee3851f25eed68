"""Data for the C twins: a controller's configuration as a C header of ``static const`` structs.

A controller FMU or the C benchmark harness is the hand-written algorithms of ``controllers/c``
compiled with one generated header, ``controller_config.h``. The header holds data only -- the
kind of controller, its name and GUID, and the configuration structs the algorithms read (the
PI's gains and limits, the predictive controller's horizon settings, circuit parameters and
the network's folded weights, or the explicit policy's folded weights and integral term) --
written from the same ctypes mirrors :mod:`controllers.native` hands to the in-process twins, so an FMU computes exactly what the twins compute. Numbers are
written with 17 significant digits (``repr``), which a C compiler reads back to the same double.
"""

from __future__ import annotations

import ctypes
import hashlib
import math
import uuid

from controllers.compensator import CompensatorController
from controllers.current_mode import CurrentModeController
from controllers.explicit_policy import ExplicitPolicyController
from controllers.native import (
    CompensatorConfigC,
    CurrentModeConfigC,
    PiConfig,
    PolicyConfigC,
    PredictiveConfig,
    compensator_config,
    current_mode_config,
    native_twin,
)
from controllers.pi import PIController
from controllers.predictive import PredictiveController

KIND_PI, KIND_PREDICTIVE, KIND_EXPLICIT = "CONTROLLER_PI", "CONTROLLER_PREDICTIVE", "CONTROLLER_EXPLICIT"
KIND_CURRENT_MODE, KIND_COMPENSATOR = "CONTROLLER_CURRENT_MODE", "CONTROLLER_COMPENSATOR"


def _number(value) -> str:
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"a configuration value is {value}: the C twins need finite numbers")
        text = repr(value)
        return text if any(c in text for c in ".eE") else text + ".0"
    return str(int(value))


def _is_zero(value) -> bool:
    if isinstance(value, ctypes.Structure):
        return all(_is_zero(getattr(value, name)) for name, _ in value._fields_)
    if isinstance(value, ctypes.Array):
        return all(_is_zero(v) for v in value)
    return value == 0


def initializer(value) -> str:
    """A C initializer for a ctypes value: designated fields for structs, designated indices for
    arrays, zeros left out (C zero-fills what an initializer does not name)."""
    if isinstance(value, ctypes.Structure):
        parts = [f".{name} = {initializer(getattr(value, name))}" for name, _ in value._fields_
                 if not _is_zero(getattr(value, name))]
        return "{" + ", ".join(parts) + "}" if parts else "{0}"
    if isinstance(value, ctypes.Array):
        parts = [f"[{i}] = {initializer(v)}" for i, v in enumerate(value) if not _is_zero(v)]
        return "{" + ", ".join(parts) + "}" if parts else "{0}"
    return _number(value)


def controller_kind(controller) -> str:
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
                     "twin to generate: expected the PI, a predictive controller (NNPC, MPC), the explicit NNPC, the "
                     "current-mode controller or a compensator (Type-III)")


def config_header(controller, name: str | None = None) -> str:
    """``controller_config.h`` for a Python PI, predictive, explicit-policy, current-mode or compensator
    controller (data only)."""
    kind = controller_kind(controller)
    twin = native_twin(controller)  # the configuration the twins run, checked against the C maxima
    pi, predictive, policy = PiConfig(), PredictiveConfig(), PolicyConfigC()
    current_mode, compensator = CurrentModeConfigC(), CompensatorConfigC()
    if kind == KIND_PI:
        pi = PiConfig(twin.kp, twin.ki, twin.sample_period, *twin.duty_limits)
    elif kind == KIND_PREDICTIVE:
        predictive = twin.config
    elif kind == KIND_EXPLICIT:
        policy = twin.config
    elif kind == KIND_CURRENT_MODE:
        current_mode = current_mode_config(controller)
    else:
        compensator = compensator_config(controller)
    name = name or controller.name
    body = [f"static const int CONTROLLER_KIND = {kind};",
            f"static const BuckcPiConfig PI_CONFIG = {initializer(pi)};",
            f"static const BuckcPredictiveConfig PREDICTIVE_CONFIG = {initializer(predictive)};"]
    body.append(f"static const BuckcPolicyConfig POLICY_CONFIG = {initializer(policy)};")
    body.append(f"static const BuckcCurrentModeConfig CURRENT_MODE_CONFIG = {initializer(current_mode)};")
    body.append(f"static const BuckcCompensatorConfig COMPENSATOR_CONFIG = {initializer(compensator)};")
    data = "\n".join(body)
    guid = "{" + str(uuid.UUID(hashlib.sha256((name + data).encode()).hexdigest()[:32])) + "}"
    lines = ["/* Generated by buck-cosim (controllers/codegen.py) -- data only, do not edit.",
             f" * {name}: the configuration the hand-written C twins in controllers/c read. */",
             "#ifndef CONTROLLER_CONFIG_H", "#define CONTROLLER_CONFIG_H", "",
             '#include "controller_variables.h"', '#include "pi.h"', '#include "predictive.h"',
             '#include "explicit_policy.h"', '#include "current_mode.h"', '#include "compensator.h"', "",
             f"#define CONTROLLER_NAME {_c_string(name)}",
             f'#define CONTROLLER_GUID "{guid}"', "", data, "", "#endif", ""]
    return "\n".join(lines)


def header_guid(header: str) -> str:
    """The GUID a generated header declares."""
    for line in header.splitlines():
        if line.startswith("#define CONTROLLER_GUID "):
            return line.split('"')[1]
    raise ValueError("not a generated controller_config.h: no CONTROLLER_GUID")


def _c_string(text: str) -> str:
    escaped = text.replace("\\", "\\\\").replace('"', '\\"')
    return f'"{escaped}"'
