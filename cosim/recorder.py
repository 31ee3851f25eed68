"""The recorded table of a run: one schema of (column, unit, source) and the recorder that fills it.

:data:`SCHEMA` is the single definition of a run's columns: their order, their units and where
each value comes from --

* ``master:<field>`` -- a value the master knows at the instant (time, reference, the duty in
  effect, load, supply, whether it is a control sample, the controller's compute time);
* ``plant:<role>`` -- a plant output role, e.g. ``plant:output_voltage``; a ``|`` gives the role
  used when the first is not bound (what a sensor reads defaults to the plain output), and a
  role bound by neither records NaN.

:data:`COLUMNS`, :data:`UNITS`, :data:`DESCRIPTIONS` and :data:`WALLCLOCK_COLUMNS` are derived from it. The master
hands the recorder one tuple per row: its values in the order of :data:`MASTER_FIELDS`, then the
plant's outputs in the order of the plant's output roles (one append of a tuple of floats per row:
the cheapest thing the hot loop can do, and invisible to the garbage collector); the recorder
assembles the columns by name at the end of the run or of each streamed chunk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Column:
    name: str
    unit: str  # SI unit ("1": dimensionless, "": none, e.g. a flag)
    source: str  # "master:<field>" or "plant:<role>[|<fallback role>]"
    description: str  # what the column holds, in words
    wallclock: bool = False  # a wall-clock quantity: kept out of the byte-comparable tables

    @property
    def kind(self) -> str:
        return self.source.split(":", 1)[0]

    @property
    def keys(self) -> tuple[str, ...]:
        """The master field, or the plant roles in order of preference."""
        return tuple(self.source.split(":", 1)[1].split("|"))


SENSOR = "what the controller's sensor reads"
SCHEMA: tuple[Column, ...] = (
    Column("time", "s", "master:time", "scenario time (0 at the end of the settle interval)"),
    Column("reference", "V", "master:reference", "output-voltage reference in effect"),
    Column("output_voltage", "V", "plant:output_voltage", "output voltage vo (the plant's output_voltage role)"),
    Column("inductor_current", "A", "plant:inductor_current", "inductor current iL"),
    Column("measured_output_voltage", "V", "plant:measured_output_voltage|output_voltage",
           f"output voltage, {SENSOR}"),
    Column("measured_inductor_current", "A", "plant:measured_inductor_current|inductor_current",
           f"inductor current, {SENSOR}"),
    Column("load_current", "A", "plant:load_current", "load current io"),
    Column("measured_load_current", "A", "plant:measured_load_current|load_current", f"load current, {SENSOR}"),
    Column("duty_cycle", "1", "master:duty_cycle", "duty cycle applied to the plant, held between controller samples"),
    Column("load_resistance", "Ohm", "master:load_resistance", "load resistance R the scenario sets"),
    Column("input_voltage", "V", "master:input_voltage", "supply voltage Vs the scenario sets"),
    Column("control_sample", "", "master:control_sample", "true where a controller sample falls on this instant"),
    Column("controller_compute_time", "s", "master:controller_compute_time",
           "controller compute time of the sample, wall clock (NaN between samples)", wallclock=True),
)
COLUMNS = tuple(c.name for c in SCHEMA)
UNITS = {c.name: c.unit for c in SCHEMA}
DESCRIPTIONS = {c.name: c.description for c in SCHEMA}
WALLCLOCK_COLUMNS = tuple(c.name for c in SCHEMA if c.wallclock)
#: the order in which the master passes its values for a row
MASTER_FIELDS = tuple(c.keys[0] for c in SCHEMA if c.kind == "master")
BOOLEAN_COLUMNS = ("control_sample",)


class Recorder:
    """Collects a run's rows: ``record((*master values, *plant outputs))`` per row."""

    def __init__(self, output_roles: tuple[str, ...]):
        self.output_roles = tuple(output_roles)
        self._rows: list[tuple] = []
        self.record = self._rows.append  # the hot loop binds it once
        self.width = len(MASTER_FIELDS) + len(self.output_roles)
        # per column, its index in [master values | plant outputs | NaN]: one gather builds the table
        nan_index = len(MASTER_FIELDS) + len(self.output_roles)
        order = []
        for column in SCHEMA:
            if column.kind == "master":
                order.append(MASTER_FIELDS.index(column.keys[0]))
            else:
                bound = [self.output_roles.index(r) for r in column.keys if r in self.output_roles]
                order.append(len(MASTER_FIELDS) + bound[0] if bound else nan_index)
        self._order = np.array(order)

    def __len__(self) -> int:
        return len(self._rows)

    def table(self) -> np.ndarray:
        """The rows recorded so far as an array (rows, len(COLUMNS)) in schema order."""
        n = len(self._rows)
        rows = np.array(self._rows, dtype=float).reshape(n, self.width)
        return np.hstack([rows, np.full((n, 1), np.nan)])[:, self._order]

    def take(self) -> np.ndarray:
        """:meth:`table`, then forget the rows (streaming writes them in chunks)."""
        table = self.table()
        self._rows.clear()
        return table
