"""A deliberately faulty plant (pythonfmu): at fault_time it fails in the way fault_kind selects.

fault_kind: 0 none, 1 do_step reports failure (fmi2Discard), 2 do_step raises (fmi2Error),
3 the output turns NaN, 4 do_step dereferences a null pointer (the process dies of SIGSEGV), 5 do_step never
returns (a hang), 6 every do_step keeps another 64 MB (memory without bound; it stops itself at 4 GB so a test
whose watchdog failed cannot take the machine). Until then it is a first-order stand-in: Vout follows D * Vin
with a 0.1 ms time constant; IL = Vout / Rload.
"""

import math

from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Integer, Real


class FaultyBuck(Fmi2Slave):
    author = "buck-cosim test corpus"
    description = "A plant that fails on purpose"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.duty = 0.0
        self.Rload = 6.0
        self.Vout = 0.0
        self.IL = 0.0
        self.fault_time = 0.01
        self.fault_kind = 0
        self._hoard = []
        self.register_variable(Real("duty", causality=Fmi2Causality.input))
        self.register_variable(Real("Rload", causality=Fmi2Causality.input))
        self.register_variable(Real("fault_time", causality=Fmi2Causality.parameter, variability=Fmi2Variability.fixed))
        self.register_variable(Integer("fault_kind", causality=Fmi2Causality.parameter,
                                       variability=Fmi2Variability.fixed))
        self.register_variable(Real("Vout", causality=Fmi2Causality.output))
        self.register_variable(Real("IL", causality=Fmi2Causality.output))

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
                import time

                while True:  # an FMU's solver that never converges, a deadlock: the call does not return
                    time.sleep(1.0)
            if self.fault_kind == 6:
                if len(self._hoard) >= 64:
                    raise MemoryError("the test FMU's own 4 GB safety stop")
                self._hoard.append(b"x" * (64 << 20))  # touched pages: resident memory
        target = 48.0 * self.duty
        self.Vout = target + (self.Vout - target) * math.exp(-step_size / 1e-4)
        self.IL = self.Vout / self.Rload
        return True
