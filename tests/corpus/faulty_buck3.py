"""The FMI 3.0 twin of faulty_buck.py (pythonfmu3): at fault_time it fails in the way fault_kind selects.

fault_kind: 0 none, 1 do_step reports failure (fmi3Discard), 2 do_step raises (fmi3Error), 3 the output turns
NaN, 4 do_step dereferences a null pointer (the process dies of SIGSEGV), 5 fmi3DoStep sets terminateSimulation.
Until then a first-order stand-in: Vout follows D * Vin with a 0.1 ms time constant; IL = Vout / Rload.
"""

import math

from pythonfmu3 import Float64, Fmi3Causality, Fmi3Slave, Fmi3StepResult, Fmi3Variability, Int32


class FaultyBuck3(Fmi3Slave):
    author = "buck-cosim test corpus"
    description = "A plant that fails on purpose (FMI 3.0)"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.duty = 0.0
        self.Rload = 6.0
        self.Vout = 0.0
        self.IL = 0.0
        self.fault_time = 0.01
        self.fault_kind = 0
        self.register_variable(Float64("time", causality=Fmi3Causality.independent,
                                       variability=Fmi3Variability.continuous))
        self.register_variable(Float64("duty", start=0.0, causality=Fmi3Causality.input,
                                       variability=Fmi3Variability.continuous))
        self.register_variable(Float64("Rload", start=6.0, causality=Fmi3Causality.input,
                                       variability=Fmi3Variability.continuous))
        self.register_variable(Float64("fault_time", start=0.01, causality=Fmi3Causality.parameter,
                                       variability=Fmi3Variability.fixed))
        self.register_variable(Int32("fault_kind", start=0, causality=Fmi3Causality.parameter,
                                     variability=Fmi3Variability.fixed))
        self.register_variable(Float64("Vout", causality=Fmi3Causality.output, variability=Fmi3Variability.continuous))
        self.register_variable(Float64("IL", causality=Fmi3Causality.output, variability=Fmi3Variability.continuous))

    def do_step(self, current_time, step_size):
        if current_time + step_size > self.fault_time:
            if self.fault_kind == 1:
                return False
            if self.fault_kind == 2:
                raise RuntimeError("simulated solver breakdown")
            if self.fault_kind == 3:
                self.Vout = math.nan
                return True
            if self.fault_kind == 4:
                import ctypes

                ctypes.string_at(0)  # reads address 0: SIGSEGV, as a buggy C FMU would
            if self.fault_kind == 5:
                return Fmi3StepResult(terminateSimulation=True)
        target = 48.0 * self.duty
        self.Vout = target + (self.Vout - target) * math.exp(-step_size / 1e-4)
        self.IL = self.Vout / self.Rload
        return True
