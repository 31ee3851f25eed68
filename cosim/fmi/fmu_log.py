"""FMU log messages, each to the instance that logged it.

FMUs log through a C callback with variadic arguments, which ctypes cannot receive, so fmpy
offers a native proxy (``fmpy.logging.addLoggerProxy``) that formats the message and calls one
Python logger -- but one for the whole process: the last FMU instantiated with it takes the
messages of all the others (a plant's error shows up in the controller's log). The workbench
therefore hands every FMU the same Python logger, :func:`_dispatch`, and tells the instances
apart by the ``componentEnvironment`` pointer the FMU passes back with each message: a small
integer handle per instance, mapped here to that instance's sink.
"""

from __future__ import annotations

import itertools
from ctypes import byref, c_void_p
from typing import Callable

import fmpy
from fmpy.fmi2 import (
    fmi2CallbackAllocateMemoryTYPE,
    fmi2CallbackFreeMemoryTYPE,
    fmi2CallbackFunctions,
    fmi2CallbackLoggerTYPE,
)

STATUS_NAMES = ("ok", "warning", "discard", "error", "fatal", "pending")
#: a sink receives (status name, category, message)
Sink = Callable[[str, str, str], None]
_SINKS: dict[int, Sink] = {}
_HANDLES = itertools.count(1)


def _dispatch(environment, instance_name, status, category, message) -> None:
    try:
        sink = _SINKS.get(environment or 0)
        if sink is not None:
            label = STATUS_NAMES[status] if 0 <= status < len(STATUS_NAMES) else str(status)
            sink(label, category.decode("utf-8", "replace") if category else "",
                 message.decode("utf-8", "replace") if message else "")
    except Exception:  # never let an exception cross the C boundary
        pass


_LOGGER = fmi2CallbackLoggerTYPE(_dispatch)  # alive as long as the module


def callbacks_for(sink: Sink) -> tuple[fmi2CallbackFunctions, int]:
    """FMI 2.0 callbacks whose log messages reach ``sink``, and the handle to :func:`release`."""
    from fmpy.logging import addLoggerProxy

    handle = next(_HANDLES)
    _SINKS[handle] = sink
    callbacks = fmi2CallbackFunctions()
    callbacks.logger = _LOGGER
    callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(fmpy.calloc)
    callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(fmpy.free)
    callbacks.componentEnvironment = c_void_p(handle)
    addLoggerProxy(byref(callbacks))  # the native formatter; its one Python logger is always _dispatch
    return callbacks, handle


def release(handle: int) -> None:
    """Stop delivering an instance's messages (after fmi2FreeInstance)."""
    _SINKS.pop(handle, None)
