"""A PI voltage controller written with pythonfmu, as an outside author would: its own names, the
duty in percent, the period as a parameter. Same law as controllers/pi.py (backward-Euler
integral, conditional-integration anti-windup): the duty at a sample is computed from that
instant's inputs when it is read (a getter: direct feedthrough), and the integral is committed by
do_step."""

from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real


class PythonPI(Fmi2Slave):
    author = "buck-cosim test corpus"
    description = "PI voltage loop (duty in %), sampled every Ts"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.Vref = 0.0  # [V]
        self.Vmeas = 0.0  # [V]
        self.Kp = 0.0015  # [1/V]
        self.Ki = 15.6  # [1/(V s)]
        self.Ts = 1e-3  # [s]
        self.Dmax = 100.0  # [%]
        self._integral = 0.0
        self.register_variable(Real("Vref", causality=Fmi2Causality.input))
        self.register_variable(Real("Vmeas", causality=Fmi2Causality.input))
        for name in ("Kp", "Ki", "Ts", "Dmax"):
            self.register_variable(Real(name, causality=Fmi2Causality.parameter, variability=Fmi2Variability.fixed))
        self.register_variable(Real("Dpct", causality=Fmi2Causality.output, getter=lambda: self._law()[0]))

    def _law(self):
        error = self.Vref - self.Vmeas
        integral = self._integral + self.Ki * self.Ts * error
        unclamped = self.Kp * error + integral
        high = self.Dmax / 100.0
        duty = min(max(unclamped, 0.0), high)
        pushing = (unclamped > high and error > 0) or (unclamped < 0.0 and error < 0)
        return duty * 100.0, (self._integral if pushing else integral)

    def do_step(self, current_time, step_size):
        self._integral = self._law()[1]  # the sample at current_time is committed
        return True
