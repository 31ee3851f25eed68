"""``DIR/SWEEP.md``, ``DIR/yield.csv`` and ``DIR/figures/``: what a sweep found, from its dataset.

* **Yield**: the share of runs meeting every threshold of the sweep file's ``[spec]`` (a failed
  run, or a metric that is not a number -- a run that never settles -- fails), per controller and
  scenario, and per *unit* (a grid point and random draw: one production unit) over all scenarios,
  with a 95 % Wilson score interval (the sample count decides how sure the yield is).
* **Distributions** of overshoot, 2 % settling time, IAE and steady-state error per controller
  (box plots: median, quartiles, whiskers at 1.5 IQR, the spec as a dashed line).
* **The most influential parameter** of each metric: the swept quantity with the largest Spearman
  rank correlation |rho| with it (monotonic, not only linear, dependence), and a scatter of the
  metric against it -- only where the correlation is significant (p < :data:`SIGNIFICANCE`) and the
  metric varies by more than its :data:`MAGNITUDE_FLOOR` over the runs; otherwise "none" (a rank
  correlation of -1 on a steady-state error of 1e-10 % is numerical noise, not an influence).
* **The worst case** per controller and scenario with its parameters: the run furthest outside the
  spec (largest metric / threshold), or the largest IAE without a spec.

Nothing here depends on the wall clock, so the same dataset always gives the same files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from cosim.base.files import atomic_write, atomic_write_text
from cosim.base.labels import period_text
from cosim.base.markdown import markdown_table
from cosim.design.sweeps.dataset import DATASET_DIR, METRIC_UNITS, TIMING_DIR
from cosim.design.sweeps.spec import SweepSpec, Threshold
from cosim.design.sweeps.worker import FAILED, OK
from cosim.design.vocabulary import CONTROLLER_STYLES

#: the metrics a tolerance study is about (the issue's list), with their axis labels
HEADLINE = {"overshoot_pct": "overshoot [%]", "settling_time_ms": "2 % settling time [ms]",
            "iae_Vs": "IAE [V s]", "steady_state_error_pct": "steady-state error [%]"}
WORST_METRICS = ("overshoot_pct", "undershoot_pct", "settling_time_ms", "steady_state_error_pct", "iae_Vs",
                 "peak_inductor_current_A")
ALL_SCENARIOS = "all scenarios (per unit)"
MARKERS = ("o", "s", "^", "D", "v", "P")
#: fixed margins of the 2 x 2 panel figures (a layout engine costs more than the rest of the summary), wide
#: enough for the tick labels and axis labels of :data:`HEADLINE` (tests/test_first_contact.py measures them)
PANEL_MARGINS = {"left": 0.085, "right": 0.985, "bottom": 0.08, "top": 0.93, "wspace": 0.26, "hspace": 0.28}
#: a parameter is "most influential" only if its Spearman correlation has a p-value below this ...
SIGNIFICANCE = 0.01
#: ... and the metric spans more than this over the runs (max - min, in the metric's unit): below it, a
#: perfect rank correlation is rounding in the solver, not an effect an engineer would act on
MAGNITUDE_FLOOR = {"overshoot_pct": 0.01, "settling_time_ms": 0.01, "iae_Vs": 1e-7, "steady_state_error_pct": 1e-3}
NO_INFLUENCE = "none"
#: how the figures show each headline metric: (factor, axis label) -- IAE in mV s keeps its tick labels short
DISPLAY = {"overshoot_pct": (1.0, "overshoot [%]"), "settling_time_ms": (1.0, "2 % settling time [ms]"),
           "iae_Vs": (1e3, "IAE [mV s]"), "steady_state_error_pct": (1.0, "steady-state error [%]")}
Z95 = 1.959963984540054


def wilson_interval(successes: int, total: int, z: float = Z95) -> tuple[float, float]:
    """The 95 % Wilson score interval of a proportion (sound at 0 % and 100 % and for small samples)."""
    if total == 0:
        return math.nan, math.nan
    p = successes / total
    centre = (p + z * z / (2 * total)) / (1 + z * z / total)
    half = z * math.sqrt(p * (1 - p) / total + z * z / (4 * total * total)) / (1 + z * z / total)
    # rounded: at 0 % and 100 % one bound is exact, not 1e-17 away from it
    return max(0.0, round(centre - half, 12)), min(1.0, round(centre + half, 12))


def meets(rows: pd.DataFrame, threshold: Threshold) -> pd.Series:
    """Per row: the threshold is met (a failed run or a NaN metric does not meet it)."""
    values = rows[threshold.metric].astype(float)
    if threshold.signed:
        values = values.abs()
    ok = (rows["status"] == OK) & values.notna() & (values <= threshold.limit)
    return ok.astype(bool)


def spec_mask(rows: pd.DataFrame, thresholds) -> pd.Series:
    mask = rows["status"] == OK
    for threshold in thresholds:
        mask &= meets(rows, threshold)
    return mask.astype(bool)


def pass_column(metric: str) -> str:
    """The yield table's column of the share of runs [%] meeting the threshold on ``metric``:
    ``pass_overshoot_pct`` (not ``pass_overshoot_pct_pct``), ``pass_settling_time_ms_pct``."""
    return f"pass_{metric.removesuffix('_pct')}_pct"


def _md(text: str) -> str:
    """Text for a Markdown table cell (a ``|`` would end the cell)."""
    return text.replace("|", "\\|")


def threshold_label(threshold: Threshold) -> str:
    """``overshoot <= 5 %``, ``|steady-state error| <= 0.5 %`` for figures."""
    name = HEADLINE.get(threshold.metric, threshold.metric).split(" [")[0]
    name = f"|{name}|" if threshold.signed else name
    return f"{name} <= {threshold.limit:g} {METRIC_UNITS.get(threshold.metric, '')}".strip()


def display_unit(unit: str, values) -> tuple[float, str]:
    """A readable unit for an axis: (factor to multiply by, label), e.g. H -> uH, F -> uF, Hz -> kHz."""
    finite = np.asarray([v for v in values if isinstance(v, (int, float)) and math.isfinite(v)], dtype=float)
    size = float(np.max(np.abs(finite))) if len(finite) else 1.0
    if unit in ("H", "F", "Ohm", "V", "A", "s") and size:
        for factor, prefix in ((1.0, ""), (1e3, "m"), (1e6, "u"), (1e9, "n")):
            if size * factor >= 1.0:
                return factor, f"{prefix}{unit}"
        return 1e9, f"n{unit}"
    if unit == "Hz" and size >= 1e3:
        return 1e-3, "kHz"
    return 1.0, unit


@dataclass
class SweepSummary:
    """What the report needs from a summary (paths relative to the sweep folder)."""

    out_dir: Path
    yield_table: pd.DataFrame
    counts: dict
    figures: dict[str, str] = field(default_factory=dict)  # name -> path relative to out_dir
    thresholds: tuple[Threshold, ...] = ()
    influence: pd.DataFrame | None = None
    units: int = 0  # grid points x samples
    axes: list[str] = field(default_factory=list)  # "parameters.inductance: uniform, nominal x [0.8, 1.2]"
    control_period: float = 0.0  # [s]
    seed: int = 0


class _Summary:
    def __init__(self, spec: SweepSpec, plan, recipes, rows: pd.DataFrame, out_dir: Path, sweep_id: str):
        self.spec, self.plan, self.recipes, self.out_dir, self.sweep_id = spec, plan, recipes, Path(out_dir), sweep_id
        self.rows = rows
        self.controllers = [r.name for r in recipes]
        self.scenarios = [s.name for s in spec.scenarios]
        self.axes = [(i.axis.name, i.unit, i.axis) for i in plan.axes]
        self.axis_names = [a for a, _, _ in self.axes if rows[a].nunique() > 1] if len(rows) else []

    # ------------------------------------------------------------------ tables
    def yield_table(self) -> pd.DataFrame:
        if not self.spec.thresholds:
            return pd.DataFrame()
        rows = self.rows.assign(meets=spec_mask(self.rows, self.spec.thresholds))
        records = []
        for controller in self.controllers:
            mine = rows[rows["controller"] == controller]
            groups = [(s, mine[mine["scenario"] == s]) for s in self.scenarios]
            units = mine.groupby(["point", "sample"])["meets"].all()
            groups.append((ALL_SCENARIOS, None))
            for scenario, group in groups:
                if group is None:
                    total, good = len(units), int(units.sum())
                else:
                    total, good = len(group), int(group["meets"].sum())
                low, high = wilson_interval(good, total)
                record = {"controller": controller, "scenario": scenario, "runs": total, "meet_spec": good,
                          "yield_pct": 100 * good / total if total else math.nan,
                          "ci95_low_pct": 100 * low, "ci95_high_pct": 100 * high}
                for threshold in self.spec.thresholds:
                    if group is None:
                        passed = mine.assign(m=meets(mine, threshold)).groupby(["point", "sample"])["m"].all()
                        share = passed.mean() if len(passed) else math.nan
                    else:
                        share = meets(group, threshold).mean() if len(group) else math.nan
                    record[pass_column(threshold.metric)] = 100 * share
                record["failed_runs"] = int((mine["status"] == FAILED).sum()) if group is None else \
                    int((group["status"] == FAILED).sum())
                records.append(record)
        return pd.DataFrame(records)

    def distribution_table(self) -> pd.DataFrame:
        records = []
        for scenario in self.scenarios:
            for controller in self.controllers:
                group = self.rows[(self.rows["scenario"] == scenario) & (self.rows["controller"] == controller)
                                  & (self.rows["status"] == OK)]
                for metric in HEADLINE:
                    values = group[metric].astype(float)
                    finite = values.dropna()
                    worst = (finite.abs().max() if metric == "steady_state_error_pct" else finite.max()) \
                        if len(finite) else math.nan
                    records.append({"scenario": scenario, "controller": controller, "metric": HEADLINE[metric],
                                    "median": finite.median() if len(finite) else math.nan,
                                    "p5": finite.quantile(0.05) if len(finite) else math.nan,
                                    "p95": finite.quantile(0.95) if len(finite) else math.nan,
                                    "worst": worst, "not a number": int(values.isna().sum())})
        return pd.DataFrame(records)

    def influence_table(self) -> pd.DataFrame:
        """Per scenario, controller and headline metric: the swept quantity with the largest |Spearman
        rho| that is significant and moves the metric by more than its floor (module docstring), with
        rho, its p-value and the metric's span; ``axis`` is :data:`NO_INFLUENCE` when none qualifies
        (``reason`` says why)."""
        from scipy.stats import spearmanr

        records = []
        for scenario in self.scenarios:
            for controller in self.controllers:
                group = self.rows[(self.rows["scenario"] == scenario) & (self.rows["controller"] == controller)
                                  & (self.rows["status"] == OK)]
                for metric in HEADLINE:
                    values = group[metric].astype(float).dropna()
                    span = float(values.max() - values.min()) if len(values) else math.nan
                    best, rho, p_value = None, math.nan, math.nan
                    for axis in self.axis_names:
                        pair = group[[axis, metric]].astype(float).dropna()
                        if len(pair) < 3 or pair[axis].nunique() < 2 or pair[metric].nunique() < 2:
                            continue
                        r, p = spearmanr(pair[axis], pair[metric])
                        r, p = float(r), float(p)
                        if math.isfinite(r) and (best is None or abs(r) > abs(rho)):
                            best, rho, p_value = axis, r, p
                    reason = ""
                    if best is None:
                        reason = "the metric or no swept quantity varies"
                    elif not span > MAGNITUDE_FLOOR[metric]:
                        reason = f"the metric spans {span:.2g} only (floor {MAGNITUDE_FLOOR[metric]:g})"
                    elif not p_value < SIGNIFICANCE:
                        reason = f"not significant (p = {p_value:.2g} >= {SIGNIFICANCE:g})"
                    records.append({"scenario": scenario, "controller": controller, "metric": metric,
                                    "axis": NO_INFLUENCE if reason else best, "spearman_rho": rho,
                                    "p_value": p_value, "span": span, "strongest": best or "n/a", "reason": reason})
        return pd.DataFrame(records)

    def worst_cases(self) -> pd.DataFrame:
        records = []
        for scenario in self.scenarios:
            for controller in self.controllers:
                group = self.rows[(self.rows["scenario"] == scenario) & (self.rows["controller"] == controller)]
                if not len(group):
                    continue
                score = self._badness(group)
                worst = group.loc[score.sort_values(ascending=False, kind="mergesort").index[0]]
                record = {"scenario": scenario, "controller": controller, "run_id": worst["run_id"],
                          "status": worst["status"]}
                for axis, _, _ in self.axes:
                    record[axis] = worst[axis]
                for metric in WORST_METRICS:
                    record[metric] = worst[metric]
                record["violates"] = _md(", ".join(t.text() for t in self.spec.thresholds
                                                   if not meets(group.loc[[worst.name]], t).iloc[0]) or "none")
                records.append(record)
        return pd.DataFrame(records)

    def _badness(self, group: pd.DataFrame) -> pd.Series:
        """Largest metric / threshold per run (inf for a failed run or a NaN metric); IAE breaks ties."""
        iae = group["iae_Vs"].astype(float).fillna(np.inf)
        if not self.spec.thresholds:
            return iae.where(group["status"] == OK, np.inf)
        ratios = []
        for t in self.spec.thresholds:
            values = group[t.metric].astype(float)
            values = values.abs() if t.signed else values
            ratios.append((values / t.limit if t.limit > 0 else values.where(values <= 0, np.inf)).fillna(np.inf))
        score = pd.concat(ratios, axis=1).max(axis=1).where(group["status"] == OK, np.inf)
        return score + 1e-12 * iae.clip(upper=1e6).rank(pct=True)

    # ------------------------------------------------------------------ figures
    def _style(self, controller: str, index: int):
        """The controller's colour: its own, else one no other controller of the sweep shows (cosim.plots)."""
        from cosim.plots import figure_styles

        return figure_styles(self.controllers, CONTROLLER_STYLES)[controller][0]

    def figures(self, vector: bool = True) -> dict[str, str]:
        from cosim.plots import plt, save_figure

        def save(fig, stem: Path) -> None:
            if vector:
                save_figure(fig, stem)  # PNG + SVG
            else:
                atomic_write(stem.with_name(f"{stem.name}.png"),  # every dot of the name kept, as save_figure does
                             lambda tmp: fig.savefig(tmp, format="png", dpi=110, metadata={"Software": None}))
                plt.close(fig)

        folder = self.out_dir / "figures"
        made = {}
        period = period_text(self.spec.control_period)
        influence = self.influence_table()
        for scenario in self.scenarios:
            group = self.rows[(self.rows["scenario"] == scenario) & (self.rows["status"] == OK)]
            fig, axes = plt.subplots(2, 2, figsize=(10, 7.5))
            fig.subplots_adjust(**PANEL_MARGINS)
            for ax, metric in zip(axes.flat, HEADLINE):
                scale, label = DISPLAY[metric]
                data, names = [], []
                for controller in self.controllers:
                    values = group.loc[group["controller"] == controller, metric].astype(float)
                    data.append(values.dropna().to_numpy() * scale)
                    missing = int(values.isna().sum())
                    names.append(controller + (f"\n({missing} never)" if missing else ""))
                parts = ax.boxplot([d if len(d) else [np.nan] for d in data], patch_artist=True, widths=0.6,
                                   flierprops={"markersize": 3, "alpha": 0.5})
                ax.set_xticks(range(1, len(names) + 1), names)
                for i, box in enumerate(parts["boxes"]):
                    box.set_facecolor(self._style(self.controllers[i], i))
                    box.set_alpha(0.45)
                for t in self.spec.thresholds:
                    if t.metric == metric:
                        ax.axhline(t.limit * scale, color="crimson", linestyle="--", linewidth=1.1,
                                   label=f"spec: {threshold_label(t)}")
                        if t.signed:
                            ax.axhline(-t.limit * scale, color="crimson", linestyle="--", linewidth=1.1)
                        ax.legend(loc="best", fontsize=8)
                ax.set_ylabel(label)
                ax.grid(True, axis="y", alpha=0.3)
            fig.suptitle(f"{self.spec.name}: {scenario} at {period}, {self._units()} units per controller "
                         "(box: quartiles; whiskers: 1.5 IQR)", fontsize=10)
            save(fig, folder / f"distributions__{scenario}")
            made[f"distributions__{scenario}"] = f"figures/distributions__{scenario}.png"

            if self.axis_names:
                fig, axes = plt.subplots(2, 2, figsize=(10, 7.5))
                fig.subplots_adjust(**PANEL_MARGINS)
                for ax, metric in zip(axes.flat, HEADLINE):
                    scale, label = DISPLAY[metric]
                    mine = influence[(influence["scenario"] == scenario) & (influence["metric"] == metric)]
                    strength = {a: mine.loc[mine["axis"] == a, "spearman_rho"].abs().sum() for a in self.axis_names}
                    axis = max(self.axis_names, key=lambda a: (strength[a], -self.axis_names.index(a)))
                    significant = strength[axis] > 0
                    unit = dict((a, u) for a, u, _ in self.axes)[axis]
                    factor, shown = display_unit(unit, group[axis].tolist())
                    for i, controller in enumerate(self.controllers):
                        sub = group[group["controller"] == controller]
                        rho = mine.loc[(mine["controller"] == controller) & (mine["axis"] == axis), "spearman_rho"]
                        tag = f" (rho {rho.iloc[0]:+.2f})" if len(rho) else ""
                        ax.scatter(sub[axis].astype(float) * factor, sub[metric].astype(float) * scale, s=12,
                                   alpha=0.6, color=self._style(controller, i), marker=MARKERS[i % len(MARKERS)],
                                   label=controller + tag)  # shapes too: controllers often coincide
                    for t in self.spec.thresholds:
                        if t.metric == metric:
                            ax.axhline(t.limit * scale, color="crimson", linestyle="--", linewidth=1.1,
                                       label=f"spec: {threshold_label(t)}")
                    ax.set_xlabel((f"{axis} [{shown}]" if shown else axis)
                                  + ("" if significant else " (no significant influence)"))
                    ax.set_ylabel(label)
                    ax.grid(True, alpha=0.3)
                    ax.legend(loc="best", fontsize=7)
                fig.suptitle(f"{self.spec.name}: {scenario}, each metric against its most influential parameter "
                             f"(largest significant |Spearman rho|, p < {SIGNIFICANCE:g})", fontsize=10)
                save(fig, folder / f"influence__{scenario}")
                made[f"influence__{scenario}"] = f"figures/influence__{scenario}.png"

        table = self.yield_table()
        if len(table):
            width_in = max(7.0, 1.6 * (len(self.scenarios) + 1) * len(self.controllers) / 2 + 1.6)
            fig, ax = plt.subplots(figsize=(width_in, 4.4))
            fig.subplots_adjust(left=0.8 / width_in, right=1 - 1.5 / width_in, bottom=0.14, top=0.86)
            groups = [*self.scenarios, ALL_SCENARIOS]
            width = 0.8 / max(1, len(self.controllers))
            for i, controller in enumerate(self.controllers):
                mine = table[table["controller"] == controller].set_index("scenario").reindex(groups)
                x = np.arange(len(groups)) + (i - (len(self.controllers) - 1) / 2) * width
                y = mine["yield_pct"].to_numpy()
                error = np.clip(np.vstack([y - mine["ci95_low_pct"].to_numpy(),
                                           mine["ci95_high_pct"].to_numpy() - y]), 0.0, None)
                ax.bar(x, y, width, color=self._style(controller, i), alpha=0.75, label=controller, yerr=error,
                       capsize=3, error_kw={"linewidth": 0.9})
                for xi, yi in zip(x, y):  # the value on every bar: a 0 % bar is otherwise invisible
                    if math.isfinite(yi):
                        ax.text(xi, min(yi, 100.0) + 1.5, f"{yi:.0f}", ha="center", va="bottom", fontsize=7)
            ax.set_xticks(np.arange(len(groups)), [g.replace(" (per unit)", "\n(per unit)") for g in groups])
            ax.set_ylim(0, 112)
            ax.set_ylabel("yield: runs meeting the spec [%]")
            ax.set_title(f"{self.spec.name}: yield at {period} ({self._units()} units; bars: 95 % Wilson interval)\n"
                         f"spec: {'; '.join(threshold_label(t) for t in self.spec.thresholds)}", fontsize=9)
            ax.grid(True, axis="y", alpha=0.3)
            ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
            save(fig, folder / "yield")
            made["yield"] = "figures/yield.png"
        return made

    def _units(self) -> int:
        return self.plan.spec.grid_points * self.spec.samples

    # ------------------------------------------------------------------ SWEEP.md
    def markdown(self, figures: dict[str, str], yield_table, distributions, influence, worst) -> str:
        spec, plan = self.spec, self.plan
        statuses = self.rows["status"].value_counts()
        ok, failed = int(statuses.get(OK, 0)), int(statuses.get(FAILED, 0))
        lines = [f"# Sweep `{spec.name}`" + (f": {spec.description}" if spec.description else ""), "",
                 f"Generated by `buck-cosim sweep` -- do not edit by hand. Sweep id `{self.sweep_id}`; "
                 f"{len(self.rows)} runs = {spec.grid_points} grid point(s) x {spec.samples} sample(s) x "
                 f"{len(self.scenarios)} scenario(s) x {len(self.controllers)} controller(s); seed {spec.seed}. "
                 f"{ok} complete, {failed} failed. One row per run in [`{DATASET_DIR}/`]({DATASET_DIR}/) (wall-clock "
                 f"figures apart, in `{TIMING_DIR}/` and `timings.json`).", "",
                 "## What was swept", "",
                 f"- **Plant**: {plan.binding.label} ({_origin(plan.binding)}); control period "
                 f"{period_text(spec.control_period)}, recording every {spec.record_period * 1e6:g} us; "
                 f"controllers as {'C twins' if spec.implementation == 'c' else 'Python references'}.",
                 "- **Scenarios**: " + "; ".join(f"`{s.name}` ({s.description})" for s in spec.scenarios) + ".",
                 "- **Controllers**, designed once on the nominal plant (no axis applied) and run unchanged on "
                 "every unit:"]
        for recipe in self.recipes:
            s = recipe.settings
            if recipe.kind == "pi":
                how = f"Kp = {s['kp_per_V']:.4g} 1/V, Ki = {s['ki_per_V_s']:.4g} 1/(V s) ({s['tuning']['method']})"
            elif recipe.kind == "fmu":
                how = (f"{s['origin']} (SHA-256 {recipe.blob_digest[:12]}), sampled every "
                       f"{period_text(recipe.control_period)}, run as it is")
            elif recipe.kind.startswith("nnpc"):
                rmse = s.get("held_out_one_step_rmse_V")
                how = f"network {s['network']}, {s['origin']}" + (f"; held-out one-step RMSE {rmse * 1e3:.2f} mV"
                                                                   if rmse is not None else "")
            else:
                c = s["circuit"]
                how = (f"circuit model L {c['inductance'] * 1e6:.4g} uH, C {c['capacitance'] * 1e6:.4g} uF, "
                       f"DCR {c['inductor_resistance']:g} Ohm, ESR {c['capacitor_esr']:g} Ohm")
            lines.append(f"  - *{recipe.name}* ({recipe.kind}): {how}.")
        axis_rows = []
        for info in plan.axes:
            a = info.axis
            if a.group == "operating_point" or info.nominal is None:
                nominal = "the scenario's" if a.group == "operating_point" else "n/a"
            else:
                factor, label = display_unit(info.unit, [info.nominal])
                nominal = f"{info.nominal * factor:.4g} {label}".strip()
            axis_rows.append({"axis": a.key, "swept as": a.describe(info.unit), "nominal": nominal,
                              "unit": info.unit or "-"})
        if axis_rows:
            lines += ["", *markdown_table(pd.DataFrame(axis_rows), ["axis", "swept as", "nominal", "unit"])]
        lines += ["", "Each random axis draws from its own stream (seed and axis name); every controller and "
                      "scenario sees the same units."]

        lines += ["", "## Yield", ""]
        if len(yield_table):
            lines += [f"Spec: {'; '.join(t.text() for t in spec.thresholds)}. A failed run, or a metric that is not a "
                      "number (a run that never settles), does not meet it. *All scenarios (per unit)*: the share of "
                      "units (grid point and draw) that meet the spec in every scenario. 95 % CI: Wilson score "
                      "interval.", ""]
            columns = ["controller", "scenario", "runs", "meet_spec", "yield_pct", "ci95_low_pct", "ci95_high_pct",
                       *[pass_column(t.metric) for t in spec.thresholds], "failed_runs"]
            headers = ["controller", "scenario", "runs", "meet spec", "yield [%]", "CI low [%]", "CI high [%]",
                       *[_md(f"{t.text()} [%]") for t in spec.thresholds], "failed"]
            lines += markdown_table(yield_table, columns, headers, digits=3)
            if "yield" in figures:
                lines += ["", f"![yield]({figures['yield']})"]
        else:
            lines.append("No `[spec]` in the sweep file, so no yield: add thresholds such as `overshoot_pct = 5.0`.")

        lines += ["", "## Distributions", "",
                  "Over the complete runs; *not a number*: runs whose metric is undefined (settling: the output is "
                  "outside the 2 % band at the end).", ""]
        lines += markdown_table(distributions, ["scenario", "controller", "metric", "median", "p5", "p95", "worst",
                                                "not a number"], digits=4)
        for scenario in self.scenarios:
            if f"distributions__{scenario}" in figures:
                lines += ["", f"![distributions, {scenario}]({figures[f'distributions__{scenario}']})"]

        lines += ["", "## Most influential parameter", "",
                  "Per metric, the swept quantity with the largest |Spearman rank correlation| over the complete "
                  f"runs (+1: the metric grows with it), if it is significant (p < {SIGNIFICANCE:g}) and the metric "
                  "spans more than a floor (overshoot and steady-state error 0.01 / 0.001 %, settling 0.01 ms, IAE "
                  "1e-7 V s); otherwise *none* and why -- a perfect rank correlation on a metric that moves by "
                  "1e-10 % is rounding, not an influence.", ""]
        if len(influence) and self.axis_names:
            shown = influence.assign(metric=influence["metric"].map(HEADLINE),
                                     why=[_md(r) for r in influence["reason"]])
            lines += markdown_table(shown, ["scenario", "controller", "metric", "axis", "spearman_rho", "p_value",
                                            "strongest", "why"],
                                    ["scenario", "controller", "metric", "most influential", "Spearman rho", "p",
                                     "largest correlation", "if none: why"], digits=3)
            for scenario in self.scenarios:
                if f"influence__{scenario}" in figures:
                    lines += ["", f"![influence, {scenario}]({figures[f'influence__{scenario}']})"]
        else:
            lines.append("Nothing varies, so nothing to rank.")

        lines += ["", "## Worst case", "",
                  "Per controller and scenario, the run furthest outside the spec (largest metric / threshold; a "
                  "failed run is worst) -- or the largest IAE without a spec -- with its parameters.", ""]
        if len(worst):
            value_columns = [a for a, _, _ in self.axes]
            shown, value_headers = worst.copy(), []
            for axis, unit, _ in self.axes:  # in readable units: uH, uF, mOhm
                factor, label = display_unit(unit, self.rows[axis].tolist())
                shown[axis] = shown[axis].astype(float) * factor
                value_headers.append(f"{axis} [{label}]" if label else axis)
            columns = ["scenario", "controller", "run_id", "status", *value_columns, *WORST_METRICS, "violates"]
            headers = ["scenario", "controller", "run id", "status", *value_headers,
                       *[f"{m} [{METRIC_UNITS.get(m, '')}]" for m in WORST_METRICS], "violates"]
            lines += markdown_table(shown, columns, headers, digits=4)

        failed_rows = self.rows[self.rows["status"] == FAILED]
        lines += ["", "## Failed runs", ""]
        if len(failed_rows):
            lines += [f"{len(failed_rows)} run(s) failed; each is a row with status `failed` and its cause in `error`"
                      + (" (the first 20 below)." if len(failed_rows) > 20 else "."), ""]
            shown = failed_rows.head(20).assign(error=lambda f: f["error"].map(lambda e: _md(str(e))))
            lines += markdown_table(shown, ["controller", "scenario", "run_id", "error"])
        else:
            lines.append("None.")
        lines += ["", "## Reading the dataset", "", "```python", "import pyarrow.dataset as ds",
                  f"rows = ds.dataset(\"{DATASET_DIR}\", format=\"parquet\", partitioning=\"hive\").to_table().to_pandas()",
                  "# one row per run: run_id, point, sample, the swept values, status, error, metrics;",
                  "# controller and scenario come from the folder names", "```"]
        return "\n".join(lines) + "\n"


def _origin(binding) -> str:
    """The plant by its file's name (not a path, so the summary reads the same on every machine)."""
    if binding.source is not None:
        return f"binding file {Path(binding.source).name}"
    return f"FMU {Path(binding.fmu_path).name}"


def summarise(spec: SweepSpec, plan, recipes, rows: pd.DataFrame, out_dir: Path, sweep_id: str,
              vector: bool = True) -> SweepSummary:
    """Write ``SWEEP.md``, ``yield.csv`` and the figures (PNG, and SVG if ``vector``) from the
    planned runs' rows."""
    out_dir = Path(out_dir)
    summary = _Summary(spec, plan, recipes, rows, out_dir, sweep_id)
    yield_table = summary.yield_table()
    distributions = summary.distribution_table()
    influence = summary.influence_table()
    worst = summary.worst_cases()
    figures = summary.figures(vector) if len(rows) else {}
    if len(yield_table):
        atomic_write(out_dir / "yield.csv", lambda tmp: yield_table.to_csv(tmp, index=False))
    atomic_write_text(out_dir / "SWEEP.md", summary.markdown(figures, yield_table, distributions, influence, worst))
    statuses = rows["status"].value_counts() if len(rows) else pd.Series(dtype=int)
    counts = {"runs": len(rows), "ok": int(statuses.get(OK, 0)), "failed": int(statuses.get(FAILED, 0))}
    axes = [f"{i.axis.name}: {i.axis.describe(i.unit)}" for i in plan.axes]
    return SweepSummary(out_dir, yield_table, counts, figures, spec.thresholds, influence,
                        spec.grid_points * spec.samples, axes, spec.control_period, spec.seed)


def report_section(summary: SweepSummary, folder: str) -> list[str]:
    """The report's section on a tolerance study: what it swept, its yield table and figures, and
    which threshold decides each controller's yield (links relative to the report, in ``folder``)."""
    lines = ["## Tolerance study", "",
             f"The 1 ms controllers of the nominal switched pipeline, unchanged, on {summary.units} production "
             f"units of the switched converter (seed {summary.seed}): " + "; ".join(summary.axes) + ". "
             f"{summary.counts['ok']} of {summary.counts['runs']} runs complete. Spec: "
             + "; ".join(threshold_label(t) for t in summary.thresholds)
             + f". Distributions, the most influential parameter and the worst units: [SWEEP.md]({folder}/SWEEP.md).",
             ""]
    table = summary.yield_table
    if not len(table):
        return lines
    shown = table.assign(ci=[f"{lo:.0f} ... {hi:.0f}" for lo, hi in zip(table["ci95_low_pct"], table["ci95_high_pct"])])
    pass_columns = [pass_column(t.metric) for t in summary.thresholds]
    lines += markdown_table(shown, ["controller", "scenario", "runs", "yield_pct", "ci", *pass_columns],
                            ["controller", "scenario", "units", "yield [%]", "95 % CI [%]",
                             *[_md(f"{threshold_label(t)} [%]") for t in summary.thresholds]], digits=3)
    lines.append("")
    deciding = []
    for controller, group in table[table["scenario"] == ALL_SCENARIOS].groupby("controller", sort=False):
        row = group.iloc[0]
        worst = min(summary.thresholds, key=lambda t: row[pass_column(t.metric)])
        deciding.append(f"{controller}: {row['yield_pct']:.0f} % of the units meet the spec in every scenario; the "
                        f"limiting threshold is {threshold_label(worst)} ({row[pass_column(worst.metric)]:.0f} % "
                        "pass it)")
    lines += ["- " + line + "." for line in deciding]
    for name in ("yield", *[k for k in summary.figures if k.startswith("distributions__")]):
        if name in summary.figures:
            lines += ["", f"![{name.replace('__', ', ')}]({folder}/{summary.figures[name]})"]
    return lines
