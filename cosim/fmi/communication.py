"""How the master may step a plant FMU: with any communication step, or with one fixed step for the whole run.

Many exporting tools (a fixed-step Simulink export, most code generators) make co-simulation FMUs that declare
``canHandleVariableCommunicationStepSize="false"`` (FMI 2.0 and FMI 3.0 alike) and step only by the step they were
generated for, given in ``DefaultExperiment stepSize`` or in their documentation. For such an FMU the master takes
one communication step ``h`` for the whole run and steps the plant by ``h`` from one instant to the next; the control
period, the record period and every plant event (load, supply, parameter) must then lie on the grid of ``h``
(:func:`cosim.master.check_communication_step` refuses what does not, before anything runs).

The step ``h`` comes from, first that found:

1. the binding file's ``step`` key (any co-simulation FMU: the master then steps it by ``step`` only);
2. the FMU's ``DefaultExperiment stepSize``, if it cannot vary its step;
3. the control period, if it cannot vary its step and gives no stepSize.

Model exchange has no communication step (fmpy's CVode integrates between the instants): always variable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: two times closer than this fraction of the step are the same grid point
GRID_TOLERANCE = 1e-9
#: where a fixed step comes from (messages name it)
FROM_BINDING = "the binding's step"
FROM_DEFAULT_EXPERIMENT = "the FMU's DefaultExperiment stepSize"
FROM_CONTROL_PERIOD = "the control period (the FMU cannot vary its step and declares no DefaultExperiment stepSize)"


@dataclass(frozen=True)
class CommunicationStep:
    """How a plant may be stepped: ``fixed`` False -- any step; True -- one step ``step`` [s] for the whole run
    (None: the control period, known per run) taken from ``source``."""

    fixed: bool = False
    step: float | None = None
    source: str = ""

    def for_run(self, control_period: float) -> float | None:
        """The step of a run at ``control_period`` [s]: None for a variable-step plant."""
        if not self.fixed:
            return None
        return self.step if self.step is not None else control_period

    def describe(self, control_period: float) -> str:
        """``"1e-05 s (the FMU's DefaultExperiment stepSize)"``."""
        return f"{self.for_run(control_period):.6g} s ({self.source})"


VARIABLE = CommunicationStep()


def declared_step(model_description) -> float | None:
    """The FMU's ``DefaultExperiment stepSize`` [s] if it declares a positive, finite one, else None."""
    experiment = getattr(model_description, "defaultExperiment", None)
    try:
        step = float(experiment.stepSize)
    except (AttributeError, TypeError, ValueError):
        return None
    return step if step > 0 and math.isfinite(step) else None


def can_vary_step(model_description) -> bool:
    """Does the FMU's co-simulation interface accept communication steps of different lengths?"""
    cs = getattr(model_description, "coSimulation", None)
    return cs is None or bool(cs.canHandleVariableCommunicationStepSize)


def communication_step(binding, model_description, interface: str) -> CommunicationStep:
    """How the master steps ``binding``'s plant through ``interface`` ("co-simulation" or "model-exchange")."""
    if interface != "co-simulation":
        return VARIABLE
    if binding.step is not None:
        return CommunicationStep(True, binding.step, f"{FROM_BINDING} in {binding.origin}")
    if can_vary_step(model_description):
        return VARIABLE
    step = declared_step(model_description)
    if step is not None:
        return CommunicationStep(True, step, FROM_DEFAULT_EXPERIMENT)
    return CommunicationStep(True, None, FROM_CONTROL_PERIOD)


def grid_index(t: float, step: float) -> int | None:
    """``n`` if ``t`` [s] is the grid point ``n * step`` -- within :data:`GRID_TOLERANCE` of a step plus the rounding
    of ``t`` itself (a time of 200 s carries about 3e-14 s of it) -- else None."""
    n = round(t / step)
    return n if abs(t - n * step) <= GRID_TOLERANCE * step + 4 * math.ulp(t) else None


def record_period_for(step: CommunicationStep, wanted: float, control_period: float) -> float:
    """A recording period for a run at ``control_period`` [s] as close to ``wanted`` [s] as the plant allows: ``wanted``
    for a variable-step plant or one already on its grid, else the nearest whole number (>= 1) of its fixed steps
    (e.g. 1e-4 s for 10 us wanted of a plant that steps by 0.1 ms). For periods the workbench chooses itself (PI
    tuning's recording, figures, the study); a period a user gives is checked, never changed."""
    h = step.for_run(control_period)
    if h is None or grid_index(wanted, h):
        return wanted
    return max(1, round(wanted / h)) * h
