"""Run results: one pandas DataFrame per run plus its metadata, exported to CSV and Parquet.

Files written for a run ``<stem>`` (each written to a temporary name and renamed, so a crash never
leaves a half-written file behind):

* ``<stem>.parquet`` -- the table; run metadata (JSON) in the schema metadata under ``buck_cosim``
  and each column's unit in its field metadata under ``unit``;
* ``<stem>.csv`` + ``<stem>.json`` -- the same table as text, metadata in the JSON sidecar;
* ``<stem>.timing.csv`` -- wall-clock columns (controller compute time), kept apart so the two
  tables above are byte-identical when the same command runs twice.

:func:`read_run` reads either form back into the same frame.
"""

from __future__ import annotations

import functools
import json
import os
import platform
from dataclasses import dataclass
from importlib import metadata as importlib_metadata
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from cosim.base.files import atomic_write, atomic_write_text, temporary_name

COLUMNS = (
    "time",
    "reference",
    "output_voltage",
    "inductor_current",
    "measured_output_voltage",
    "measured_inductor_current",
    "load_current",
    "measured_load_current",
    "duty_cycle",
    "load_resistance",
    "input_voltage",
    "control_sample",
    "controller_compute_time",
)
UNITS = {
    "time": "s",
    "reference": "V",
    "output_voltage": "V",
    "inductor_current": "A",
    "measured_output_voltage": "V (what the controller's sensor reads)",
    "measured_inductor_current": "A (what the controller's sensor reads)",
    "load_current": "A",
    "measured_load_current": "A (what the controller's sensor reads)",
    "duty_cycle": "1",
    "load_resistance": "Ohm",
    "input_voltage": "V",
    "control_sample": "bool (a controller sample at this instant)",
    "controller_compute_time": "s (wall clock, NaN between samples)",
}
WALLCLOCK_COLUMNS = ("controller_compute_time",)
METADATA_KEY = b"buck_cosim"
PACKAGES = ("buck-cosim", "fmpy", "numpy", "scipy", "pandas", "pyarrow", "torch", "matplotlib")


@dataclass
class RunResult:
    """A run's table (one row per recorded instant) and its metadata."""

    frame: pd.DataFrame
    metadata: dict

    @property
    def complete(self) -> bool:
        return bool(self.metadata.get("complete", False))

    @classmethod
    def from_array(cls, data: np.ndarray, metadata: dict, complete: bool, error: str | None = None) -> "RunResult":
        frame = pd.DataFrame(np.array(data, copy=True), columns=list(COLUMNS))
        frame["control_sample"] = frame["control_sample"].astype(bool)
        meta = dict(metadata)
        meta["complete"] = complete
        meta["error"] = error
        meta["rows"] = len(frame)
        return cls(frame=frame, metadata=meta)


@functools.lru_cache(maxsize=1)
def _package_versions() -> tuple[tuple[str, str], ...]:
    versions = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            versions[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return tuple(versions.items())


def package_versions() -> dict[str, str]:
    """Versions of Python and the packages that shape results (looked up once per process)."""
    return dict(_package_versions())


def run_metadata(*, scenario, controller, plant, control_period: float, record_period: float,
                 seed: int | None, extra: dict | None = None) -> dict:
    """Everything needed to understand and repeat a run (no wall-clock fields: runs compare byte for byte)."""
    md = plant.model_description
    meta = {
        "format": "buck-cosim run 1",
        "scenario": scenario.describe(),
        "controller": controller.describe(),
        "plant": {
            **plant.binding.describe(),
            "interface": plant.interface,
            "model_name": md.modelName,
            "guid": md.guid,
            "fmu_file": Path(plant.binding.fmu_path).name,
        },
        "rates": {"control_period_s": control_period, "record_period_s": record_period},
        "seed": seed,
        "versions": package_versions(),
        "platform": {"machine": platform.machine(), "system": platform.system()},
        "units": dict(UNITS),
    }
    if extra:
        meta.update(extra)
    return _json_ready(meta)


def _json_ready(value):
    """Round-trip through JSON so metadata written and read back compare equal."""
    return json.loads(json.dumps(value, default=_jsonable, sort_keys=True))


def _jsonable(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (set, tuple)):
        return list(value)
    return str(value)


# ---------------------------------------------------------------------------------------------
# Export and import


def _deterministic_part(frame: pd.DataFrame) -> pd.DataFrame:
    return frame.drop(columns=[c for c in WALLCLOCK_COLUMNS if c in frame.columns])


def write_parquet(frame: pd.DataFrame, metadata: dict, path: Path, units: dict | None = None) -> Path:
    """Write a frame with metadata (schema) and units (per field) inside one Parquet file."""
    units = units or metadata.get("units", {})
    table = pa.Table.from_pandas(frame, preserve_index=False)
    fields = [f.with_metadata({"unit": units[f.name]}) if f.name in units else f for f in table.schema]
    schema = pa.schema(fields, metadata={**(table.schema.metadata or {}),
                                         METADATA_KEY: json.dumps(metadata, sort_keys=True).encode()})
    table = table.cast(schema)
    return atomic_write(path, lambda tmp: pq.write_table(table, tmp))


def read_parquet(path: Path) -> tuple[pd.DataFrame, dict]:
    table = pq.read_table(path)
    raw = (table.schema.metadata or {}).get(METADATA_KEY)
    return table.to_pandas(), json.loads(raw) if raw else {}


def write_run(result: RunResult, directory: Path, stem: str) -> dict[str, Path]:
    """Write ``<stem>.parquet``, ``<stem>.csv``, ``<stem>.json`` and ``<stem>.timing.csv`` atomically."""
    directory = Path(directory)
    table = _deterministic_part(result.frame)
    timing = result.frame[["time", *[c for c in WALLCLOCK_COLUMNS if c in result.frame.columns]]]
    paths = {
        "parquet": write_parquet(table, result.metadata, directory / f"{stem}.parquet"),
        "csv": atomic_write(directory / f"{stem}.csv", lambda tmp: table.to_csv(tmp, index=False)),
        "json": atomic_write_text(directory / f"{stem}.json", json.dumps(result.metadata, indent=2, sort_keys=True) + "\n"),
        "timing": atomic_write(directory / f"{stem}.timing.csv", lambda tmp: timing.to_csv(tmp, index=False)),
    }
    return paths


class RunStream:
    """Writes a run's rows to Parquet in chunks as they come, for runs too long to hold in memory.

    ``<stem>.parquet`` (deterministic columns) and ``<stem>.timing.parquet`` (wall clock) grow
    under temporary names; :meth:`close` stores the final metadata (complete or not) in the
    Parquet footer and a JSON sidecar, and renames both into place.
    """

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._timing_path = self.path.with_name(f"{self.path.stem}.timing.parquet")
        self._tmp = temporary_name(self.path)
        self._tmp_timing = temporary_name(self._timing_path)
        self._writers = None
        self.rows = 0

    @staticmethod
    def _tables(data: np.ndarray) -> tuple[pa.Table, pa.Table]:
        frame = RunResult.from_array(data, {}, complete=False).frame
        return (pa.Table.from_pandas(_deterministic_part(frame), preserve_index=False),
                pa.Table.from_pandas(frame[["time", *WALLCLOCK_COLUMNS]], preserve_index=False))

    def write(self, data: np.ndarray) -> None:
        main, timing = self._tables(data)
        if self._writers is None:
            self._writers = (pq.ParquetWriter(self._tmp, main.schema), pq.ParquetWriter(self._tmp_timing, timing.schema))
        if len(data):
            self._writers[0].write_table(main)
            self._writers[1].write_table(timing)
            self.rows += len(data)

    def close(self, metadata: dict) -> Path:
        if self._writers is None:  # nothing was recorded: still leave a valid, empty table
            self.write(np.empty((0, len(COLUMNS))))
        meta = {**metadata, "rows": self.rows, "streamed": True}
        self._writers[0].add_key_value_metadata({METADATA_KEY: json.dumps(meta, sort_keys=True).encode()})
        for writer in self._writers:
            writer.close()
        os.replace(self._tmp, self.path)
        os.replace(self._tmp_timing, self._timing_path)
        atomic_write_text(self.path.with_suffix(".json"), json.dumps(meta, indent=2, sort_keys=True) + "\n")
        return self.path


def read_run(path: Path) -> RunResult:
    """Read a run written by :func:`write_run` from its ``.parquet`` or ``.csv`` file."""
    path = Path(path)
    if path.suffix == ".parquet":
        frame, metadata = read_parquet(path)
    elif path.suffix == ".csv":
        frame = pd.read_csv(path)
        metadata = json.loads(path.with_suffix(".json").read_text(encoding="utf-8"))
    else:
        raise ValueError(f"{path}: expected a .parquet or .csv run file")
    timing_path = path.with_name(f"{path.stem}.timing.csv")
    timing_parquet = path.with_name(f"{path.stem}.timing.parquet")
    timing = pd.read_csv(timing_path) if timing_path.is_file() else \
        pq.read_table(timing_parquet).to_pandas() if timing_parquet.is_file() else None
    if timing is not None:
        for column in WALLCLOCK_COLUMNS:
            if column in timing:
                frame[column] = timing[column].to_numpy()
    frame = frame[[c for c in COLUMNS if c in frame.columns] + [c for c in frame.columns if c not in COLUMNS]]
    return RunResult(frame=frame, metadata=metadata)


__all__ = ["RunResult", "COLUMNS", "UNITS", "write_run", "read_run", "write_parquet", "read_parquet",
           "run_metadata", "package_versions"]
