"""The paper's Table II: the nominal 48 V -> 12 V buck converter that the built-in plant FMU models.

This is the one place in Python that holds these numbers; everything else imports
:data:`TABLE_II` (scenario defaults, the study's nominal circuit, PI tuning, reports, tests).
The FMU carries them too, as the start values of ``modelDescription.xml`` and the defaults in
``buck_model.c`` -- the FMU must be usable on its own -- and ``tests/test_plant_fmu.py`` checks
that both agree with this module.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ConverterRatings:
    """Nominal operating point and components of a buck converter (SI units)."""

    input_voltage: float  # Vs [V]
    output_voltage: float  # Vo [V], the regulated reference
    load_resistance: float  # R [Ohm]
    switching_frequency: float  # f_sw [Hz]
    inductance: float  # L [H]
    capacitance: float  # C [F]

    @property
    def switching_period(self) -> float:
        """1 / f_sw [s]."""
        return 1.0 / self.switching_frequency


#: Table II of the paper (Saadatmand, Shamsi, Ferdowsi)
TABLE_II = ConverterRatings(input_voltage=48.0, output_voltage=12.0, load_resistance=6.0,
                            switching_frequency=75e3, inductance=220e-6, capacitance=10e-6)
