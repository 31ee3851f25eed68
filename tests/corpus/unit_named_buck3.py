"""An FMI 3.0 buck (pythonfmu3) whose variable names say nothing a name-based guess could use, but whose units do:
the duty in %, the supply and output in V, the load in Ohm, the inductor current in mA -- as tools that export
declared units make them. The physics of python_buck.py (buck_math.py, bundled with the FMU)."""

from buck_math import advance, output_voltage, substeps
from pythonfmu3 import Float64, Fmi3Causality, Fmi3Slave, Fmi3Variability


class UnitNamedBuck3(Fmi3Slave):
    author = "buck-cosim test corpus"
    description = "Averaged buck converter whose names are opaque and whose units are declared"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.command, self.rail, self.sink = 0.0, 48.0, 6.0  # [%], [V], [Ohm]
        self.terminal, self.winding = 0.0, 0.0  # [V], [mA]
        self.henry, self.farad = 220e-6, 10e-6
        self._il = self._vc = 0.0
        self.register_variable(Float64("time", causality=Fmi3Causality.independent,
                                       variability=Fmi3Variability.continuous))
        for name, unit in (("command", "%"), ("rail", "V"), ("sink", "Ohm")):
            self.register_variable(Float64(name, start=getattr(self, name), unit=unit, causality=Fmi3Causality.input,
                                           variability=Fmi3Variability.continuous))
        for name, unit in (("henry", "H"), ("farad", "F")):
            self.register_variable(Float64(name, start=getattr(self, name), unit=unit,
                                           causality=Fmi3Causality.parameter, variability=Fmi3Variability.fixed))
        for name, unit in (("terminal", "V"), ("winding", "mA")):
            self.register_variable(Float64(name, unit=unit, causality=Fmi3Causality.output,
                                           variability=Fmi3Variability.continuous))

    def do_step(self, current_time, step_size):
        n = substeps(step_size)
        for _ in range(n):
            self._il, self._vc = advance(self._il, self._vc, self.command / 100.0, self.rail, self.sink, self.henry,
                                         self.farad, 0.1, 0.02, step_size / n)
        self.terminal = output_voltage(self._il, self._vc, self.sink, 0.02)
        self.winding = 1000.0 * self._il
        return True
