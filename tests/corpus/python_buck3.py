"""The FMI 3.0 twin of python_buck.py, written with pythonfmu3 under other names, as another outside author
would: the same averaged buck with losses (buck_math.py, bundled with the FMU), duty in percent, inductor
current in mA, co-simulation only.

It also carries what FMI 3.0 adds and the workbench must cope with: an Int32 and a Boolean parameter, a
Float64 array parameter (``loss_table``, never bound: an array cannot play a role) and an array output.
"""

import numpy as np
from buck_math import advance, output_voltage, substeps
from pythonfmu3 import Boolean, Dimension, Float64, Fmi3Causality, Fmi3Slave, Fmi3Variability, Int32


class PyBuck3(Fmi3Slave):
    author = "buck-cosim test corpus"
    description = "Averaged buck converter with losses, FMI 3.0 (duty in %, current in mA)"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.duty_pct = 0.0
        self.v_supply = 48.0  # [V]
        self.r_load = 6.0  # [Ohm]
        self.inductance_H = 220e-6
        self.capacitance_F = 10e-6
        self.r_winding = 0.1  # [Ohm]
        self.r_esr = 0.02  # [Ohm]
        self.max_substep_us = 10  # Int32 [us]
        self.diode = True  # Boolean: block reverse current
        self.loss_table = np.array([0.0, 0.1, 0.2])  # an array parameter nobody binds
        self.v_out = 0.0
        self.i_l_mA = 0.0
        self.i_out = 0.0
        self.states = np.zeros(2)  # an array output (iL, vC)
        self._il = 0.0
        self._vc = 0.0
        self.register_variable(Float64("time", causality=Fmi3Causality.independent,
                                       variability=Fmi3Variability.continuous))
        for name, start in (("duty_pct", 0.0), ("v_supply", 48.0), ("r_load", 6.0)):
            self.register_variable(Float64(name, start=start, causality=Fmi3Causality.input,
                                           variability=Fmi3Variability.continuous))
        for name, start in (("inductance_H", 220e-6), ("capacitance_F", 10e-6), ("r_winding", 0.1), ("r_esr", 0.02)):
            self.register_variable(Float64(name, start=start, causality=Fmi3Causality.parameter,
                                           variability=Fmi3Variability.fixed))
        self.register_variable(Int32("max_substep_us", start=10, causality=Fmi3Causality.parameter,
                                     variability=Fmi3Variability.fixed))
        self.register_variable(Boolean("diode", start=True, causality=Fmi3Causality.parameter,
                                       variability=Fmi3Variability.fixed))
        self.register_variable(Float64("loss_table", start=self.loss_table, causality=Fmi3Causality.parameter,
                                       variability=Fmi3Variability.fixed, dimensions=[Dimension(start="3")]))
        for name in ("v_out", "i_l_mA", "i_out"):
            self.register_variable(Float64(name, causality=Fmi3Causality.output,
                                           variability=Fmi3Variability.continuous))
        self.register_variable(Float64("states", causality=Fmi3Causality.output, variability=Fmi3Variability.continuous,
                                       dimensions=[Dimension(start="2")]))

    def do_step(self, current_time, step_size):
        n = substeps(step_size, self.max_substep_us * 1e-6)
        for _ in range(n):
            il, self._vc = advance(self._il, self._vc, self.duty_pct / 100.0, self.v_supply, self.r_load,
                                   self.inductance_H, self.capacitance_F, self.r_winding, self.r_esr, step_size / n)
            self._il = il if self.diode else il  # the clip is in advance(); the flag is a Boolean to bind, not used
        self.v_out = output_voltage(self._il, self._vc, self.r_load, self.r_esr)
        self.i_l_mA = 1000.0 * self._il
        self.i_out = self.v_out / self.r_load
        self.states = np.array([self._il, self._vc])
        return True
