"""The FMI 3.0 twin of fixed_step_buck.py: python_buck3.py's converter as a fixed-step FMU
(canHandleVariableCommunicationStepSize="false", DefaultExperiment stepSize, any other step refused)."""

from buck_math import off_step
from python_buck3 import PyBuck3
from pythonfmu3 import DefaultExperiment, Fmi3Slave, Fmi3Status

STEP = 1e-5  # [s] the one communication step


class FixedStepBuck3(PyBuck3, Fmi3Slave):  # Fmi3Slave named: pythonfmu3's builder finds the class by it
    description = "Averaged buck converter with losses, FMI 3.0, fixed communication step of 10 us"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.default_experiment = DefaultExperiment(start_time=0.0, stop_time=0.05, step_size=STEP)

    def do_step(self, current_time, step_size):
        refusal = off_step(current_time, step_size, STEP)
        if refusal:
            self.log(refusal, Fmi3Status.error)
            return False
        return super().do_step(current_time, step_size)
