"""The sweep's results on disk: a partitioned Parquet dataset, written part by part as tasks finish.

Layout under the output folder::

    sweep.json                                   the sweep: id, spec, controllers as designed, plan
    dataset/controller=<name>/scenario=<name>/part-<key>.parquet   one row per run (below)
    timing/part-<key>.timing.parquet             wall clock per run: duration, controller p50/p99, worker
    traces/<run id>.parquet                      every run's full table (keep_traces = true only)

A row holds the run id, the grid point and sample indices, every swept value (in the FMU's or the
scenario's unit, kept in the field metadata), ``status`` (``ok`` or ``failed``), ``error`` (the
cause, or null) and every metric that is not wall clock (:mod:`cosim.metrics`); ``controller`` and
``scenario`` are the partition keys (hive style: ``pyarrow.dataset.dataset(DIR / "dataset",
partitioning="hive")`` reads it, and so do pandas, polars, DuckDB and Spark). The wall-clock
figures live in ``timing/`` beside it, joined on ``run_id``, so a repeated sweep writes
byte-identical parts. Each part is written to a temporary name and renamed (a reader, or an
interrupted sweep, never sees half a part); a part's name hashes its runs' ids.
"""

from __future__ import annotations

import json
from pathlib import Path
from urllib.parse import quote

import pandas as pd
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from cosim.base.files import atomic_write, atomic_write_text
from cosim.design.sweeps.worker import DETERMINISTIC_METRICS
from cosim.results import write_parquet

DATASET_DIR = "dataset"
TIMING_DIR = "timing"
TRACES_DIR = "traces"
MANIFEST = "sweep.json"
PARTITIONS = pa.schema([("controller", pa.string()), ("scenario", pa.string())])
METRIC_UNITS = {"rise_time_ms": "ms", "overshoot_pct": "%", "undershoot_pct": "%", "settling_time_ms": "ms",
                "steady_state_error_V": "V", "steady_state_error_pct": "%", "iae_Vs": "V s", "ise_V2s": "V^2 s",
                "itae_Vs2": "V s^2", "peak_inductor_current_A": "A", "output_voltage_ripple_mV": "mV",
                "inductor_current_ripple_A": "A", "duty_saturation_ms": "ms",
                "controller_p50_us": "us", "controller_p99_us": "us"}


def row_schema(axes: list[tuple[str, str, bool]], extra: tuple[pa.Field, ...] = ()) -> pa.Schema:
    """The rows' columns: ``axes`` is (name, unit, integer) per swept quantity; ``extra``: columns a
    measuring controller reports per run (the frequency response's correlations), after the metrics."""
    fields = [pa.field("run_id", pa.string()), pa.field("point", pa.int64()), pa.field("sample", pa.int64())]
    for name, unit, integer in axes:
        fields.append(pa.field(name, pa.int64() if integer else pa.float64(), metadata={"unit": unit}))
    fields += [pa.field("status", pa.string()), pa.field("error", pa.string())]
    fields += [pa.field(m, pa.float64(), metadata={"unit": METRIC_UNITS.get(m, "")}) for m in DETERMINISTIC_METRICS]
    return pa.schema(fields + list(extra))


#: the wall-clock and machine figures of each run, apart from the dataset: its wall time, the controller's compute
#: time, the worker, which of that worker process's runs it was (1, 2, ...) and the worker's resident memory after it
#: (a soak shows growth per worker, `buck-cosim bench --only soak`)
TIMING_SCHEMA = pa.schema([pa.field("run_id", pa.string()), pa.field("wall_time_s", pa.float64()),
                          pa.field("controller_p50_us", pa.float64()), pa.field("controller_p99_us", pa.float64()),
                          pa.field("worker", pa.string()), pa.field("worker_run", pa.int64()),
                          pa.field("worker_rss_mb", pa.float64())])


def part_path(out_dir: Path, controller: str, scenario: str, key: str) -> Path:
    return (Path(out_dir) / DATASET_DIR / f"controller={quote(controller, safe='')}"
            / f"scenario={quote(scenario, safe='')}" / f"part-{key}.parquet")


def write_part(out_dir: Path, controller: str, scenario: str, key: str, rows: list[dict], schema: pa.Schema) -> Path:
    """One task's rows as one part, atomically."""
    table = pa.Table.from_pylist(rows, schema=schema)
    return atomic_write(part_path(out_dir, controller, scenario, key), lambda tmp: pq.write_table(table, tmp))


def write_timing(out_dir: Path, key: str, rows: list[dict]) -> Path:
    table = pa.Table.from_pylist(rows, schema=TIMING_SCHEMA)
    return atomic_write(Path(out_dir) / TIMING_DIR / f"part-{key}.timing.parquet", lambda tmp: pq.write_table(table, tmp))


def write_trace(out_dir: Path, run_id: str, frame: pd.DataFrame, metadata: dict) -> Path:
    return write_parquet(frame, metadata, Path(out_dir) / TRACES_DIR / f"{run_id}.parquet")


def read_rows(out_dir: Path, schema: pa.Schema | None = None) -> pd.DataFrame:
    """Every row written so far (controller and scenario as columns), one per run id; without any,
    an empty frame with ``schema``'s columns."""
    root = Path(out_dir) / DATASET_DIR
    if not root.is_dir() or not any(root.rglob("part-*.parquet")):
        if schema is None:
            return pd.DataFrame(columns=["run_id", "status", "controller", "scenario"])
        return pa.schema([*schema, *PARTITIONS]).empty_table().to_pandas()
    dataset = ds.dataset(root, format="parquet", partitioning=ds.partitioning(PARTITIONS, flavor="hive"))
    frame = dataset.to_table().to_pandas()
    return frame.drop_duplicates("run_id", keep="first").reset_index(drop=True)


def read_timing(out_dir: Path) -> pd.DataFrame:
    root = Path(out_dir) / TIMING_DIR
    parts = sorted(root.glob("part-*.timing.parquet")) if root.is_dir() else []
    if not parts:
        return pd.DataFrame(columns=TIMING_SCHEMA.names)
    return pa.concat_tables([pq.read_table(p) for p in parts]).to_pandas().drop_duplicates("run_id", keep="last")


def done_run_ids(out_dir: Path) -> set[str]:
    """Ids of the runs that have a row (complete or failed): ``--resume`` does not run them again."""
    root = Path(out_dir) / DATASET_DIR
    if not root.is_dir():
        return set()
    ids: set[str] = set()
    for part in root.rglob("part-*.parquet"):
        ids.update(pq.read_table(part, columns=["run_id"]).column("run_id").to_pylist())
    return ids


def has_rows(out_dir: Path) -> bool:
    root = Path(out_dir) / DATASET_DIR
    return root.is_dir() and any(root.rglob("part-*.parquet"))


def read_manifest(out_dir: Path) -> dict | None:
    path = Path(out_dir) / MANIFEST
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def write_manifest(out_dir: Path, manifest: dict) -> Path:
    return atomic_write_text(Path(out_dir) / MANIFEST, json.dumps(manifest, indent=2, sort_keys=True) + "\n")


__all__ = ["read_rows", "read_timing", "done_run_ids", "write_part", "write_timing", "write_trace", "row_schema",
           "part_path", "DATASET_DIR", "TIMING_DIR", "TRACES_DIR", "MANIFEST"]
