"""Run scenario sets and write what they produce: run tables, a metrics table and figures.

Shared by ``buck-cosim run`` and the paper reproduction. Each run is written as soon as it
finishes (atomically), so an interrupted batch keeps every completed run; a failed or
interrupted run is written too, with ``complete = false`` in its metadata.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterable

import pandas as pd

from controllers.base import Controller
from cosim.base.errors import ConfigError, RunInterrupted
from cosim.base.files import atomic_write
from cosim.base.labels import period_label, slug
from cosim.data_domain import checked_metadata
from cosim.fmi.binding import PlantBinding
from cosim.fmi.plant import open_plant
from cosim.master import RunFailed, check_plant_supports, check_rates, check_set_up, run_checked
from cosim.metrics import METRIC_COLUMNS, WALLCLOCK_METRICS, metrics_table
from cosim.results import RunResult, write_parquet, write_run
from cosim.scenarios import Scenario

if TYPE_CHECKING:  # matplotlib (1 s to import) loads when a figure is drawn, so a refused batch answers at once
    from cosim.plots import Styles


def run_stem(scenario: Scenario, controller: Controller, plant_tag: str) -> str:
    """File stem of a run: ``<scenario>__<controller slug>__<plant tag>__<period label>``."""
    return f"{scenario.name}__{slug(controller.name)}__{plant_tag}__{period_label(controller.sample_period)}"


def figure_stem(scenario: Scenario, binding: PlantBinding, control_period: float) -> str:
    """File stem of a scenario's figure: ``<scenario>__<plant tag>__<period label>``."""
    return f"{scenario.name}__{binding.tag}__{period_label(control_period)}"


@dataclass(frozen=True)
class Batch:
    """A plant and the scenarios to run on it, checked against each other once, when made
    (every scenario's events need roles the binding has), so a batch refuses before any run."""

    binding: PlantBinding
    scenarios: tuple[Scenario, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "scenarios", tuple(self.scenarios))
        named: dict[str, Scenario] = {}
        for scenario in self.scenarios:  # the files of a run are named after its scenario: two of one name would clash
            other = named.setdefault(scenario.name, scenario)
            if other is not scenario:
                where = scenario.source or scenario.name
                raise ConfigError(
                    f"scenario {where} is given twice" if where == (other.source or other.name) else
                    f"{scenario.place('name')}: scenario name {scenario.name!r} is the name of {other.place('name')} "
                    "too: the runs' files are named after it, so one would overwrite the other -- rename one")
            check_plant_supports(self.binding, scenario)

    def check_plant(self, interface: str | None = None) -> None:
        """Refuse, before any work, what the plant FMU itself refuses: the binding's parameters or a scenario's
        first inputs at its set-up, a value of a scenario's parameter events (:func:`cosim.master.preflight`)."""
        check_set_up(self.binding, self.scenarios, interface)

    def check_rates(self, control_period: float, record_period: float | None = None,
                    interface: str | None = None) -> None:
        """Refuse, before any work, periods that no run of the batch could use (too many instants, too few controller
        samples, a grid a fixed-step FMU cannot follow): :func:`cosim.master.check_rates`."""
        check_rates(self.binding, self.scenarios, control_period, record_period, interface)


@dataclass
class BatchOutput:
    results: list[RunResult]
    metrics: pd.DataFrame
    files: list[Path]


def run_batch(batch: Batch, controllers: Iterable[Controller], out_dir: Path, *, interface: str | None = None,
              record_period: float | None = None, seed: int | None = None, figures: bool = True,
              styles: Styles | None = None, progress: bool = False, extra_metadata: dict | None = None,
              on_run: Callable[[RunResult], None] | None = None, stream: bool = False) -> BatchOutput:
    """Run every controller on every scenario of ``batch`` with one reused plant instance; write
    runs, metrics and figures under ``out_dir``.

    Files are named ``<scenario>__<controller>__<plant tag>__<period label>`` (the plant tag is
    :attr:`PlantBinding.tag`); ``styles`` gives figure colours and line styles per controller name.

    ``record_period`` [s]: as :func:`cosim.master.run` takes it (None: 10 us, or a fixed-step FMU's nearest).
    ``stream``: write each run's rows to Parquet while it runs (bounded memory for long runs); no
    CSV, metrics or figures then -- the returned results carry metadata only.
    """
    out_dir = Path(out_dir)
    binding = batch.binding
    plant_tag = binding.tag
    controllers = list(controllers)
    results: list[RunResult] = []
    stems: dict[str, str] = {}
    for controller in controllers:  # the runs' files are named after the controllers' slugs: two alike would clash
        other = stems.get(slug(controller.name))
        if other is not None:
            raise ConfigError(f"controller {controller.name} is given twice" if other == controller.name else
                              f"controllers {other!r} and {controller.name!r} would write the same run files "
                              f"({slug(controller.name)}): name them apart")
        stems[slug(controller.name)] = controller.name
    files: list[Path] = []
    with open_plant(binding, interface=interface) as plant:
        for scenario in batch.scenarios:
            per_scenario: list[RunResult] = []
            for controller in controllers:
                stem = run_stem(scenario, controller, plant_tag)
                target = out_dir / "runs" / f"{stem}.parquet" if stream else None
                try:
                    result = run_checked(plant, controller, scenario, record_period=record_period, seed=seed,
                                         progress=progress, stream_to=target,
                                         extra_metadata=checked_metadata(controller, scenario, extra_metadata))
                except (RunFailed, RunInterrupted) as error:
                    if error.partial is not None and not stream:  # a streamed run wrote its rows already
                        files.extend(write_run(error.partial, out_dir / "runs", stem).values())
                    raise
                if stream:
                    files.append(target)
                else:
                    files.extend(write_run(result, out_dir / "runs", stem).values())
                per_scenario.append(result)
                if on_run is not None:
                    on_run(result)
            results.extend(per_scenario)
            if figures and not stream:
                from cosim.plots import plot_scenario

                files.extend(plot_scenario(per_scenario, out_dir / "figures" / figure_stem(scenario, binding,
                                                                                           controllers[0].sample_period),
                                           styles=styles))
    table = metrics_table(results) if not stream else pd.DataFrame()
    if len(table):
        table.insert(2, "plant_tag", plant_tag)
    return BatchOutput(results=results, metrics=table, files=files)


def with_earlier_metrics(table: pd.DataFrame, path_stem: Path) -> pd.DataFrame:
    """``table`` after the rows of an earlier metrics table at ``path_stem`` (:func:`write_metrics`' files) that it
    does not replace -- a run of the same scenario, controller and control period replaces its row -- so a folder
    that several commands ran into keeps one table of all its runs (a second ``run`` into the same ``--out`` used to
    leave only its own rows beside the first one's run files). No earlier table: ``table`` itself."""
    path_stem = Path(path_stem)
    stored, timing = path_stem.with_suffix(".csv"), path_stem.with_name(f"{path_stem.name}.timing.csv")
    if not stored.is_file():
        return table
    key = ["scenario", "controller", "control_period_us"]
    text = {"keep_default_na": False, "na_values": [""]}  # only an empty cell is missing (a controller named NA is not)
    earlier = pd.read_csv(stored, **text)
    if timing.is_file():
        clocks = pd.read_csv(timing, **text)
        extra = [c for c in WALLCLOCK_METRICS if c in clocks.columns and c not in earlier.columns]
        if len(clocks) == len(earlier) and extra:  # written together, row for row
            earlier = pd.concat([earlier, clocks[extra]], axis=1)
    if not set(key) <= set(earlier.columns):
        return table
    new = pd.MultiIndex.from_frame(table[key])
    kept = earlier[~pd.MultiIndex.from_frame(earlier[key]).isin(new)]
    return pd.concat([kept, table], ignore_index=True)[list(dict.fromkeys([*earlier.columns, *table.columns]))]


def write_metrics(table: pd.DataFrame, path_stem: Path) -> list[Path]:
    """Write a metrics table atomically: ``<stem>.csv`` and ``.parquet`` with every metric that is
    not a wall-clock measurement (byte-identical when the same runs are repeated), and
    ``<stem>.timing.csv`` with the wall-clock ones (controller compute time) beside the columns
    that identify each row."""
    path_stem = Path(path_stem)
    deterministic = table.drop(columns=[c for c in WALLCLOCK_METRICS if c in table.columns])
    identity = [c for c in table.columns if c not in METRIC_COLUMNS]
    timing = table[identity + [c for c in WALLCLOCK_METRICS if c in table.columns]]
    return [
        atomic_write(path_stem.with_suffix(".csv"), lambda tmp: deterministic.to_csv(tmp, index=False)),
        write_parquet(deterministic, {"description": "metrics per scenario and controller; see cosim/metrics.py"},
                      path_stem.with_suffix(".parquet"), units={}),
        atomic_write(path_stem.with_name(f"{path_stem.name}.timing.csv"), lambda tmp: timing.to_csv(tmp, index=False)),
    ]
