"""python_buck.py's converter exported as a fixed-step FMU, as Simulink's fixed-step export or a code generator
makes them: canHandleVariableCommunicationStepSize="false" (set when the FMU is built), its one step in
DefaultExperiment stepSize, and any other step refused with an error (fixed_step_buck3.py: its FMI 3.0 twin)."""

from buck_math import off_step
from python_buck import PyBuck
from pythonfmu import DefaultExperiment
from pythonfmu.enums import Fmi2Status

STEP = 1e-5  # [s] the one communication step


class FixedStepBuck(PyBuck):
    description = "Averaged buck converter with losses, fixed communication step of 10 us (duty in %, current in mA)"
    default_experiment = DefaultExperiment(start_time=0.0, stop_time=0.05, step_size=STEP)

    def do_step(self, current_time, step_size):
        refusal = off_step(current_time, step_size, STEP)
        if refusal:
            self.log(refusal, Fmi2Status.error)
            return False
        return super().do_step(current_time, step_size)
