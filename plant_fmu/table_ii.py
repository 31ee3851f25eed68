"""The paper's Table II as the built-in plant's converter spec: the nominal 48 V -> 12 V buck converter the
built-in plant FMU models, its operating envelope and rates.

This is the one place in Python that holds these numbers, and the built-in binding
(:func:`cosim.fmi.binding.builtin_binding`) the one module that reads them: every design takes the converter spec of
the plant it designs for (:mod:`cosim.converter_spec`), and the paper study names this one as
``cosim.study.vocabulary.PAPER_SPEC``. The FMU carries the circuit too, as the start values of
``modelDescription.xml`` and the defaults in ``buck_model.c`` -- the FMU must be usable on its own -- and
``tests/test_plant_fmu.py`` checks that both agree with this module.
"""

from __future__ import annotations

from cosim.converter_spec import ConverterSpec

#: Table II of the paper (Saadatmand, Shamsi, Ferdowsi): 48 V -> 12 V at 6 Ohm, 220 uH, 10 uF, 75 kHz; the envelope
#: the study maps and identifies over (supplies 36-60 V, references 3-20 V, loads 4-100 Ohm); the paper's 1 ms and one
#: switching period; the current-mode baseline's 8 A inductor-current limit
TABLE_II = ConverterSpec(
    label="Table II buck (48 V -> 12 V)",
    input_voltage=48.0, output_voltage=12.0, load_resistance=6.0,
    input_voltage_range=(36.0, 60.0), output_voltage_range=(3.0, 20.0), load_resistance_range=(4.0, 100.0),
    control_periods=(1e-3, 1 / 75e3), inductor_current_limit=8.0,
    inductance=220e-6, capacitance=10e-6, switching_frequency=75e3,
    origin="the built-in plant's spec (Table II)",
)
