"""Run results: one pandas DataFrame per run, typed facts about it, and its metadata; CSV and Parquet.

A :class:`RunResult` holds the table (columns of :data:`cosim.recorder.SCHEMA`), a
:class:`RunInfo` with the typed facts metrics, plots and tables read (scenario timing, controller,
rates, duty limits, plant and its mode), whether the run completed (and why not), and the
descriptions that make the run repeatable (scenario, controller settings, plant binding, seed,
package versions). :attr:`RunResult.metadata` derives the JSON metadata from all of these on
export; :func:`read_run` parses it back.

Files written for a run ``<stem>`` (each written to a temporary name and renamed, so a crash never
leaves a half-written file behind):

* ``<stem>.parquet`` -- the table; run metadata (JSON) in the schema metadata under ``buck_cosim``
  and ``PANDAS_ATTRS`` (so ``pandas.read_parquet`` returns it as ``DataFrame.attrs``), each
  column's unit and description in its field metadata under ``unit`` and ``description``;
* ``<stem>.csv`` + ``<stem>.json`` -- the same table as text, metadata in the JSON sidecar;
* ``<stem>.timing.csv`` -- wall-clock columns (controller compute time), kept apart so the two
  tables above are byte-identical when the same command runs twice.

A streamed run (:class:`RunStream`) writes ``<stem>.parquet`` in chunks, its metadata in the
Parquet footer and the JSON sidecar, and ``<stem>.timing.parquet``. :func:`read_run` reads every
form back into the same frame and metadata, ``complete`` and ``error`` included.
"""

from __future__ import annotations

import functools
import json
import math
import os
import platform
from dataclasses import dataclass, field
from importlib import metadata as importlib_metadata
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from cosim.base.digests import file_sha256
from cosim.base.errors import ConfigError
from cosim.base.files import atomic_write, atomic_write_json, json_text, temporary_name
from cosim.fmi.binding import parameter_values
from cosim.recorder import BOOLEAN_COLUMNS, COLUMNS, DESCRIPTIONS, UNITS, WALLCLOCK_COLUMNS

METADATA_KEY = b"buck_cosim"
PANDAS_ATTRS_KEY = b"PANDAS_ATTRS"  # where pandas.read_parquet looks for DataFrame.attrs
RUN_FORMAT = "buck-cosim run 1"
PACKAGES = ("buck-cosim", "fmpy", "numpy", "scipy", "pandas", "pyarrow", "torch", "matplotlib")


@dataclass(frozen=True)
class RunInfo:
    """The typed facts of a run that metrics, plots and tables read (SI units)."""

    scenario: str
    description: str
    metrics_start: float  # [s] where the metrics window starts
    controller: str
    control_period: float  # [s]
    record_period: float  # [s]
    duty_limits: tuple[float, float]
    plant: str  # the plant's label
    plant_mode: str | None  # "averaged" or "switched" for the built-in FMU, None for an external one
    interface: str  # "co-simulation" or "model-exchange"

    @classmethod
    def from_metadata(cls, meta: dict) -> "RunInfo":
        """Parse the facts out of run metadata written by :attr:`RunResult.metadata`."""
        scenario, controller, plant = meta.get("scenario", {}), meta.get("controller", {}), meta.get("plant", {})
        rates = meta.get("rates", {})
        low, high = controller.get("duty_limits", (0.0, 1.0))
        return cls(scenario=scenario.get("name", ""), description=scenario.get("description", ""),
                   metrics_start=float(scenario.get("metrics_start_s", 0.0)),
                   controller=str(controller.get("name", "controller")),
                   control_period=float(rates.get("control_period_s", math.nan)),
                   record_period=float(rates.get("record_period_s", math.nan)),
                   duty_limits=(float(low), float(high)), plant=plant.get("label", ""),
                   plant_mode=plant_mode_of(plant), interface=plant.get("interface", ""))


def plant_mode_of(plant_description: dict) -> str | None:
    """The built-in FMU's mode from a plant description (its ``plant_mode`` parameter), else None."""
    if plant_description.get("binding_file"):
        return None
    code = plant_description.get("parameters", {}).get("plant_mode")
    return {0: "averaged", 1: "switched"}.get(code)


@dataclass
class RunResult:
    """A run's table (one row per recorded instant), its facts, its ending and its descriptions."""

    frame: pd.DataFrame
    info: RunInfo
    complete: bool
    error: str | None = None
    #: everything else that makes the run repeatable: JSON-ready descriptions of the scenario,
    #: controller, plant, rates, seed, versions, and what the caller added (e.g. the pipeline)
    details: dict = field(default_factory=dict)
    rows: int | None = None  # rows written when the table was streamed to a file (the frame is empty)
    streamed: bool = False  # the rows were written to a file while running (RunStream)
    streamed_to: str | None = None

    @property
    def metadata(self) -> dict:
        """The JSON metadata written beside the table (derived: the details plus the ending)."""
        meta = {**self.details, "complete": self.complete, "error": self.error,
                "rows": self.rows if self.rows is not None else len(self.frame)}
        if self.streamed:
            meta["streamed"] = True
        if self.streamed_to is not None:
            meta["streamed_to"] = self.streamed_to
        return meta

    @classmethod
    def from_table(cls, data: np.ndarray, info: RunInfo, details: dict, complete: bool,
                   error: str | None = None) -> "RunResult":
        return cls(frame=frame_of(data), info=info, complete=complete, error=error, details=details)

    @classmethod
    def from_metadata(cls, frame: pd.DataFrame, metadata: dict) -> "RunResult":
        details = {k: v for k, v in metadata.items() if k not in ("complete", "error", "rows", "streamed",
                                                                   "streamed_to")}
        rows = metadata.get("rows")
        streamed = bool(metadata.get("streamed", False))
        return cls(frame=frame, info=RunInfo.from_metadata(metadata), complete=bool(metadata.get("complete", False)),
                   error=metadata.get("error"), details=details, rows=rows if streamed else None, streamed=streamed,
                   streamed_to=metadata.get("streamed_to"))


def frame_of(data: np.ndarray) -> pd.DataFrame:
    """A recorded table (rows, len(COLUMNS)) as a DataFrame with the schema's columns and types."""
    frame = pd.DataFrame(data, columns=list(COLUMNS), copy=False)
    for column in BOOLEAN_COLUMNS:
        frame[column] = frame[column].astype(bool)
    return frame


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


def controller_description(controller) -> dict:
    """The controller's ``describe()``, or -- for a user's controller that gives none (a subclass of the
    :class:`controllers.base.Controller` protocol inherits a ``describe`` that returns None) -- what the workbench
    knows of it: its class, name, sample period and duty limits."""
    described = controller.describe() if callable(getattr(controller, "describe", None)) else None
    if isinstance(described, dict):
        return described
    return {"type": type(controller).__name__, "name": getattr(controller, "name", type(controller).__name__),
            "sample_period_s": getattr(controller, "sample_period", None),
            "duty_limits": list(getattr(controller, "duty_limits", (0.0, 1.0)))}


def run_details(*, scenario, controller, plant, control_period: float, record_period: float,
                seed: int | None, extra: dict | None = None) -> dict:
    """Everything needed to understand and repeat a run (no wall-clock fields: runs compare byte for byte)."""
    md = plant.model_description
    meta = {
        "format": RUN_FORMAT,
        "scenario": scenario.describe(),
        "controller": controller_description(controller),
        "plant": {
            **plant.binding.describe(),
            "interface": plant.interface,
            "model_name": md.modelName,
            "guid": md.guid,
            "fmu_file": Path(plant.binding.fmu_path).name,
            "fmu_sha256": file_sha256(plant.binding.fmu_path),  # which FMU, whatever its name (design keys use it)
            "parameter_values": parameter_values(plant.binding.parameters, md),  # e.g. switching_frequency, pwm_carrier
        },
        "rates": {"control_period_s": control_period, "record_period_s": record_period},
        "seed": seed,
        "versions": package_versions(),
        "platform": {"machine": platform.machine(), "system": platform.system()},
        "units": dict(UNITS),
        "descriptions": dict(DESCRIPTIONS),
    }
    if extra:
        meta.update(extra)
    return json_ready(meta)


def json_ready(value):
    """Round-trip through JSON so metadata written and read back compare equal (non-finite
    numbers become null: the files are strict JSON)."""
    return json.loads(json_text(value, indent=None))


# ---------------------------------------------------------------------------------------------
# Export and import


def _deterministic_part(frame: pd.DataFrame) -> pd.DataFrame:
    return frame.drop(columns=[c for c in WALLCLOCK_COLUMNS if c in frame.columns])


def write_parquet(frame: pd.DataFrame, metadata: dict, path: Path, units: dict | None = None,
                  descriptions: dict | None = None) -> Path:
    """Write a frame with metadata and units (and descriptions) per field inside one Parquet file.

    The metadata is stored twice in the schema: as JSON under ``buck_cosim`` (what
    :func:`read_parquet` and other Arrow readers read) and under ``PANDAS_ATTRS``, where
    ``pandas.read_parquet`` finds it and returns it as ``DataFrame.attrs``."""
    units = units if units is not None else metadata.get("units", {})
    descriptions = descriptions if descriptions is not None else metadata.get("descriptions", {})
    table = pa.Table.from_pandas(frame, preserve_index=False)
    fields = []
    for f in table.schema:
        about = {key: text[f.name] for key, text in (("unit", units), ("description", descriptions)) if f.name in text}
        fields.append(f.with_metadata(about) if about else f)
    text = json_text(metadata, indent=None).encode()
    schema = pa.schema(fields, metadata={**(table.schema.metadata or {}), METADATA_KEY: text, PANDAS_ATTRS_KEY: text})
    table = table.cast(schema)
    return atomic_write(path, lambda tmp: pq.write_table(table, tmp))


def is_parquet(path: Path) -> bool:
    """Does the file begin with Parquet's magic bytes (``PAR1``)? (pyarrow's own refusal of another file speaks of
    its footer, not of what was expected.)"""
    try:
        with open(path, "rb") as file:
            return file.read(4) == b"PAR1"
    except OSError:
        return False


def read_parquet(path: Path) -> tuple[pd.DataFrame, dict]:
    """A Parquet file's table and the workbench metadata: from the schema, or from the file
    footer where a streamed run stores it (the metadata is known only when the stream closes)."""
    table = pq.read_table(path)
    raw = (table.schema.metadata or {}).get(METADATA_KEY)
    if raw is None:
        raw = (pq.read_metadata(path).metadata or {}).get(METADATA_KEY)
    return table.to_pandas(), json.loads(raw) if raw else {}


def write_run(result: RunResult, directory: Path, stem: str) -> dict[str, Path]:
    """Write ``<stem>.parquet``, ``<stem>.csv``, ``<stem>.json`` and ``<stem>.timing.csv`` atomically. A ``stem``
    given with one of those endings (``"startup.parquet"``) stands for the run without it (not
    ``startup.parquet.parquet``)."""
    directory = Path(directory)
    for ending in (".parquet", ".csv", ".json"):
        stem = stem.removesuffix(ending)
    metadata = result.metadata
    table = _deterministic_part(result.frame)
    timing = result.frame[["time", *[c for c in WALLCLOCK_COLUMNS if c in result.frame.columns]]]
    paths = {
        "parquet": write_parquet(table, metadata, directory / f"{stem}.parquet"),
        "csv": atomic_write(directory / f"{stem}.csv", lambda tmp: table.to_csv(tmp, index=False)),
        "json": atomic_write_json(directory / f"{stem}.json", metadata),
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
        frame = frame_of(data)
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
        """Finish both files with ``metadata`` (``rows`` and ``streamed`` are added)."""
        if self._writers is None:  # nothing was recorded: still leave a valid, empty table
            self.write(np.empty((0, len(COLUMNS))))
        meta = {**metadata, "rows": self.rows, "streamed": True}
        self._writers[0].add_key_value_metadata({METADATA_KEY: json_text(meta, indent=None).encode()})
        for writer in self._writers:
            writer.close()
        os.replace(self._tmp, self.path)
        os.replace(self._tmp_timing, self._timing_path)
        atomic_write_json(self.path.with_suffix(".json"), meta)
        return self.path


def read_run_file(path: str | Path) -> RunResult:
    """:func:`read_run` of a file a user names, checked first: a folder, a missing file, another suffix, a CSV
    without its JSON metadata beside it, a file that is not a table or not a workbench run are each one
    :class:`ConfigError` line naming the file (``plot``, ``compare`` and ``export`` read runs this way)."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"run file {path} is a folder: expected a run's .parquet or .csv (e.g. "
                          f"{path}/runs/<run>.parquet)")
    if not path.is_file():
        raise ConfigError(f"run file {path} does not exist")
    if path.suffix not in (".parquet", ".csv"):
        raise ConfigError(f"run file {path} is not a run: expected a .parquet, or a .csv with its .json")
    if path.suffix == ".csv" and _is_metrics_table(path):
        raise ConfigError(f"{path} is a metrics table (one row of metrics per run), not a run: give the runs' own "
                          "files (runs/<run>.parquet, or a .csv with its .json)")
    if path.suffix == ".parquet" and not is_parquet(path):
        raise ConfigError(f"run file {path} is not a Parquet file: expected a run's .parquet as write_run writes it")
    if path.suffix == ".csv" and not path.with_suffix(".json").is_file():
        raise ConfigError(f"run file {path} has no {path.with_suffix('.json').name} beside it (the run's "
                          "metadata: scenario, controller, rates)")
    try:
        result = read_run(path)
    except Exception as error:  # not a table, or not one of ours
        raise ConfigError(f"{path}: cannot read run ({str(error).splitlines()[0] if str(error) else error})") \
            from None
    missing = [c for c in ("time", "reference", "output_voltage", "duty_cycle") if c not in result.frame.columns]
    if missing or not result.details.get("format"):
        raise ConfigError(f"{path}: not a workbench run (" + (f"no column {', '.join(missing)}" if missing else
                                                              "no run metadata") + ")")
    return result


def _is_metrics_table(path: Path) -> bool:
    """Is the CSV a metrics table (``metrics/metrics__*.csv``: a scenario and controller per row, no time column)?"""
    try:
        with open(path, encoding="utf-8") as file:
            header = file.readline().strip().split(",")
    except (OSError, UnicodeDecodeError):
        return False
    return "time" not in header and {"scenario", "controller", "iae_Vs"} <= set(header)


def read_run(path: Path) -> RunResult:
    """Read a run written by :func:`write_run` or :class:`RunStream` from its ``.parquet`` or ``.csv`` file."""
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
    return RunResult.from_metadata(frame, metadata)


__all__ = ["RunResult", "RunInfo", "COLUMNS", "UNITS", "write_run", "read_run", "write_parquet", "read_parquet",
           "run_details", "package_versions", "json_ready"]
