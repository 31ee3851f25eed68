"""A buck converter written with pythonfmu, as an outside author would: its own names and units.

Averaged model with winding resistance and capacitor ESR, duty in percent, inductor current in
mA, co-simulation only. Each step is solved exactly (2x2 matrix exponential) in sub-steps of at
most 10 us; a negative inductor current is clipped to zero (the diode) after each sub-step.
"""

import math

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

    def _advance(self, h):
        r, rc = self.Rload, self.rC
        k = r / (r + rc)
        a11, a12 = -(self.rL + k * rc) / self.L, -k / self.L
        a21, a22 = k / self.C, -1.0 / ((r + rc) * self.C)
        b0 = min(max(self.D / 100.0, 0.0), 1.0) * self.Vin / self.L
        det = a11 * a22 - a12 * a21
        eq0, eq1 = -a22 * b0 / det, a21 * b0 / det
        s = 0.5 * (a11 + a22)
        m11 = 0.5 * (a11 - a22)
        delta = m11 * m11 + a12 * a21
        if delta < 0:
            w = math.sqrt(-delta)
            c, g = math.cos(w * h), math.sin(w * h) / w
        elif delta > 0:
            w = math.sqrt(delta)
            c, g = math.cosh(w * h), math.sinh(w * h) / w
        else:
            c, g = 1.0, h
        e = math.exp(s * h)
        d0, d1 = self._il - eq0, self._vc - eq1
        self._il = eq0 + e * (c * d0 + g * (m11 * d0 + a12 * d1))
        self._vc = eq1 + e * (c * d1 + g * (a21 * d0 - m11 * d1))
        self._il = max(self._il, 0.0)

    def do_step(self, current_time, step_size):
        n = max(1, math.ceil(step_size / 10e-6 - 1e-9))
        for _ in range(n):
            self._advance(step_size / n)
        k = self.Rload / (self.Rload + self.rC)
        self.Vout = k * (self._vc + self.rC * self._il)
        self.IL_mA = 1000.0 * self._il
        self.Iout = self.Vout / self.Rload
        return True
