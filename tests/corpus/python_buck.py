"""A buck converter written with pythonfmu, as an outside author would: its own names and units.

Averaged model with winding resistance and capacitor ESR, duty in percent, inductor current in
mA, co-simulation only. Each step is solved exactly (2x2 matrix exponential) in sub-steps of at
most 10 us; a negative inductor current is clipped to zero (the diode) after each sub-step
(buck_math.py, bundled with the FMU; python_buck3.py is its FMI 3.0 twin).
"""

from buck_math import advance, output_voltage, substeps
from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real


class PyBuck(Fmi2Slave):
    author = "buck-cosim test corpus"
    description = "Averaged buck converter with losses (duty in %, current in mA)"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.D = 0.0  # duty cycle [%]
        self.Vin = 48.0  # [V]
        self.Rload = 6.0  # [Ohm]
        self.L = 220e-6
        self.C = 10e-6
        self.rL = 0.1  # winding resistance [Ohm]
        self.rC = 0.02  # capacitor ESR [Ohm]
        self.Vout = 0.0
        self.IL_mA = 0.0
        self.Iout = 0.0
        self._il = 0.0
        self._vc = 0.0
        for name in ("D", "Vin", "Rload"):
            self.register_variable(Real(name, causality=Fmi2Causality.input))
        for name in ("L", "C", "rL", "rC"):
            self.register_variable(Real(name, causality=Fmi2Causality.parameter, variability=Fmi2Variability.fixed))
        for name in ("Vout", "IL_mA", "Iout"):
            self.register_variable(Real(name, causality=Fmi2Causality.output))

    def do_step(self, current_time, step_size):
        n = substeps(step_size)
        for _ in range(n):
            self._il, self._vc = advance(self._il, self._vc, self.D / 100.0, self.Vin, self.Rload, self.L, self.C,
                                         self.rL, self.rC, step_size / n)
        self.Vout = output_voltage(self._il, self._vc, self.Rload, self.rC)
        self.IL_mA = 1000.0 * self._il
        self.Iout = self.Vout / self.Rload
        return True
