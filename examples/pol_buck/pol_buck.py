"""A point-of-load buck converter as a third-party tool might export it: written with pythonfmu, its own variable
names, no declared units, co-simulation only -- the workbench's second converter (docs/tutorials/own-plant.md).

Averaged model (CCM and DCM: the inductor current is held at zero while the diode blocks) with winding resistance
and capacitor ESR. Over each step the linear part is solved exactly (the matrix exponential of the augmented system),
in sub-steps of at most 2 us; a negative inductor current is clipped to zero after each. Nominal: 24 V -> 5 V at
2 Ohm, L = 47 uH, C = 27 uF, 100 kHz (the switching frequency only names the converter here: the model is averaged).
"""

import numpy as np
from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real
from scipy.linalg import expm


class PolBuck(Fmi2Slave):
    author = "buck-cosim examples"
    description = "Averaged point-of-load buck 24 V -> 5 V (no units declared)"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.d_cmd = 0.0  # duty cycle, 0..1
        self.VBAT = 24.0  # supply
        self.RL_ohm = 2.0  # load
        self.Lf = 47e-6
        self.Cf = 27e-6
        self.R_dcr = 0.02  # winding resistance
        self.R_esr = 0.005  # capacitor ESR
        self.FSW = 100e3
        self.VOUT = 0.0
        self.I_L = 0.0
        self.I_OUT = 0.0
        self._state = np.zeros(2)  # inductor current, capacitor voltage
        for name in ("d_cmd", "VBAT", "RL_ohm"):
            self.register_variable(Real(name, causality=Fmi2Causality.input))
        for name in ("Lf", "Cf", "R_dcr", "R_esr", "FSW"):
            self.register_variable(Real(name, causality=Fmi2Causality.parameter, variability=Fmi2Variability.fixed))
        for name in ("VOUT", "I_L", "I_OUT"):
            self.register_variable(Real(name, causality=Fmi2Causality.output))

    def _transition(self, h: float) -> np.ndarray:
        """exp(h M) of the augmented system d/dt [iL, vC, 1] = M [iL, vC, 1] at the present inputs."""
        k = self.RL_ohm / (self.RL_ohm + self.R_esr)
        switch_node = min(max(self.d_cmd, 0.0), 1.0) * self.VBAT
        m = np.array([[-(self.R_dcr + k * self.R_esr) / self.Lf, -k / self.Lf, switch_node / self.Lf],
                      [k / self.Cf, -1.0 / ((self.RL_ohm + self.R_esr) * self.Cf), 0.0],
                      [0.0, 0.0, 0.0]])
        return expm(m * h)

    def do_step(self, current_time, step_size):
        n = max(1, int(np.ceil(step_size / 2e-6 - 1e-9)))
        phi = self._transition(step_size / n)
        state = np.append(self._state, 1.0)
        for _ in range(n):
            state = phi @ state
            state[0] = max(state[0], 0.0)  # the diode blocks a negative inductor current
        self._state = state[:2]
        il, vc = self._state
        self.VOUT = self.RL_ohm / (self.RL_ohm + self.R_esr) * (vc + self.R_esr * il)
        self.I_L = il
        self.I_OUT = self.VOUT / self.RL_ohm
        return True
