"""A converter study's ``REPORT.md``, ``targets.csv`` and summary figure, from its metrics and design files.

Every number comes from the study's own runs (``metrics/metrics_all.csv``), its pipelines' summaries and the design
files it wrote; the converter's values come from its spec (:mod:`cosim.converter_spec`) -- nothing of the paper's
converter appears unless the spec is the paper's. A comparison is stated only where it holds for every
identification seed, otherwise it is said to be within the seed-to-seed spread (:mod:`cosim.study.claims`).

The targets (the ones the paper's converter reaches in the reproduction):

* the PI meets its design constraints at the spec's nominal point: start-up overshoot <= 5 % and
  |steady-state error| <= 0.5 %, at every control period;
* at one switching period, the NNPC's IAE is below the PI's in every scenario for every seed, and at most 1.10 x
  the nominal-model MPC's at the median seed (1.5 x at the worst seed), in every scenario;
* no run of an NNPC leaves the ranges of its identification data.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pandas as pd

from cosim.base.files import atomic_write, atomic_write_text
from cosim.base.labels import period_text
from cosim.base.markdown import markdown_table
from cosim.design.vocabulary import (
    CONTROLLER_STYLES,
    CURRENT_MODE,
    MPC_NOMINAL,
    NNPC,
    NNPC_EXPLICIT,
    NNPC_PAPER,
    PI,
    TYPE_III,
)
from cosim.study.claims import TARGET_COLUMNS, comparison, per_scenario_text, spread, target_row
from cosim.study.summaries import seed_controllers, seed_ratio_spreads, value

#: the PI's design constraints at the nominal point (the tuning's: cosim.design.pi_tuning)
PI_OVERSHOOT_LIMIT_PCT, PI_STEADY_STATE_LIMIT_PCT = 5.0, 0.5
#: NNPC IAE / nominal-model MPC IAE at one switching period: at the median seed, and at the worst seed
MPC_RATIO_MEDIAN_LIMIT, MPC_RATIO_WORST_LIMIT = 1.10, 1.5
#: the order of the controllers in tables and the figure
ORDER = (PI, NNPC, NNPC_PAPER, MPC_NOMINAL, NNPC_EXPLICIT, CURRENT_MODE, TYPE_III)


#: the nominal circuit's parasitics as the report names them
PARASITICS = (("inductor_resistance", "inductor resistance", "Ohm"), ("switch_on_resistance", "switch on-resistance",
                                                                       "Ohm"),
              ("diode_forward_voltage", "diode drop", "V"), ("capacitor_esr", "capacitor ESR", "Ohm"))


def _spec_table(spec) -> list[str]:
    def rng(key, unit):
        values = getattr(spec, f"{key}_range")
        return f"{values[0]:g}-{values[1]:g} {unit}" if values else "not given"

    rows = [("nominal supply", f"{spec.input_voltage:g} V", rng("input_voltage", "V")),
            ("nominal output (reference)", f"{spec.output_voltage:g} V", rng("output_voltage", "V")),
            ("nominal load", f"{spec.load_resistance:g} Ohm", rng("load_resistance", "Ohm"))]
    lines = ["| quantity | nominal | range (the operating envelope) |", "|---|---|---|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    circuit = []
    if spec.inductance is not None:
        circuit.append(f"L = {spec.inductance * 1e6:g} uH")
    if spec.capacitance is not None:
        circuit.append(f"C = {spec.capacitance * 1e6:g} uF")
    if spec.switching_frequency is not None:
        circuit.append(f"f_sw = {spec.switching_frequency / 1e3:g} kHz")
    circuit += [f"{name} {getattr(spec, key):g} {unit}" for key, name, unit in PARASITICS if getattr(spec, key)]
    limits = [f"duty {spec.duty_limits[0]:g}-{spec.duty_limits[1]:g}" if spec.duty_limits else "",
              f"inductor current {spec.inductor_current_limit:g} A" if spec.inductor_current_limit else ""]
    lines += ["", f"Nominal circuit: {', '.join(circuit) or 'not given'}. Limits: "
              f"{', '.join(x for x in limits if x) or 'none given'}. Control periods: "
              f"{', '.join(period_text(p) for p in (spec.control_periods or ())) or 'not named'}."]
    return lines


def _domain_leaves(out_dir: Path, tags: list[str]) -> list[str]:
    """Runs of the study whose network's data domain the scenario leaves (their run metadata says so)."""
    found = []
    for path in sorted((out_dir / "runs").glob("*.json")):
        if not any(path.stem.endswith(f"__{tag}") for tag in tags):
            continue
        outside = json.loads(path.read_text(encoding="utf-8")).get("outside_data_domain")  # the run's metadata
        if outside:
            found.append(f"{path.stem}: " + "; ".join(f"{o['signal']} {o['value']:g} outside {o['range']}"
                                                       for o in outside))
    return found


def study_targets(out_dir: Path, spec, periods: list[float], tags: dict[float, str],
                  metrics: pd.DataFrame) -> pd.DataFrame:
    """The study's targets (see the module's docstring), one row each, measured on ``metrics``."""
    rows = []
    for period in periods:
        tag = tags[period]
        overshoot = value(metrics, tag, PI, "startup", "overshoot_pct")
        error = value(metrics, tag, PI, "startup", "steady_state_error_pct")
        if not math.isnan(overshoot):
            rows.append(target_row(
                f"PI start-up at the nominal point, {period_text(period, ascii_only=True)}: overshoot <= "
                f"{PI_OVERSHOOT_LIMIT_PCT:g} % and |steady-state error| <= {PI_STEADY_STATE_LIMIT_PCT:g} %",
                f"overshoot {overshoot:.2f} %, steady-state error {error:+.3f} %",
                overshoot <= PI_OVERSHOOT_LIMIT_PCT and abs(error) <= PI_STEADY_STATE_LIMIT_PCT,
                value=overshoot, limit=PI_OVERSHOOT_LIMIT_PCT))
        if not spec.samples_once_per_pwm_period(period):
            continue
        seeds = seed_controllers(metrics, tag)
        against_pi = seed_ratio_spreads(metrics, tag, PI)
        if against_pi:
            worst_scenario = max(against_pi, key=lambda s: against_pi[s].maximum)
            worst = against_pi[worst_scenario].maximum
            rows.append(target_row(
                f"NNPC IAE < PI IAE at one switching period, every scenario and seed ({len(seeds)} seeds)",
                f"worst NNPC / PI {worst:.3f} ({worst_scenario}, seed {against_pi[worst_scenario].worst_seed()})",
                all(s.count == len(seeds) and s.maximum < 1.0 for s in against_pi.values()), value=worst, limit=1.0))
        against_mpc = seed_ratio_spreads(metrics, tag, MPC_NOMINAL)
        if against_mpc:
            median_scenario = max(against_mpc, key=lambda s: against_mpc[s].median)
            worst_scenario = max(against_mpc, key=lambda s: against_mpc[s].maximum)
            median, worst = against_mpc[median_scenario].median, against_mpc[worst_scenario].maximum
            rows.append(target_row(
                f"NNPC IAE <= {MPC_RATIO_MEDIAN_LIMIT:.2f} x nominal-model MPC IAE at one switching period, median "
                "seed, every scenario", f"{median:.3f} ({median_scenario})",
                median <= MPC_RATIO_MEDIAN_LIMIT, "; ".join(f"{s}: {v.text('.3f')}" for s, v in against_mpc.items()),
                value=median, limit=MPC_RATIO_MEDIAN_LIMIT))
            rows.append(target_row(
                f"NNPC IAE <= {MPC_RATIO_WORST_LIMIT:.2f} x nominal-model MPC IAE at one switching period, worst "
                "seed, every scenario", f"{worst:.3f} ({worst_scenario}, seed "
                                        f"{against_mpc[worst_scenario].worst_seed()})",
                worst <= MPC_RATIO_WORST_LIMIT, value=worst, limit=MPC_RATIO_WORST_LIMIT))
    leaves = _domain_leaves(out_dir, list(tags.values()))
    rows.append(target_row("No NNPC run leaves its identification data's ranges (supply, load conductance, reference)",
                           f"{len(leaves)} run(s) outside", not leaves, "; ".join(leaves[:3])))
    return pd.DataFrame(rows, columns=TARGET_COLUMNS)


def _iae_table(metrics: pd.DataFrame, tag: str) -> list[str]:
    """IAE [mV s] per scenario (rows) and controller (columns, seed 0), with the NNPC's spread over the seeds."""
    m = metrics[metrics["pipeline"] == tag]
    scenarios = list(dict.fromkeys(m["scenario"]))
    present = [c for c in ORDER if c in set(m["controller"])]
    seeds = seed_controllers(metrics, tag)
    header = ["scenario", *(f"{c} IAE [mV s]" for c in present)]
    if len(seeds) > 1:
        header.append(f"NNPC over {len(seeds)} seeds: median (min-max)")
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for scenario in scenarios:
        cells = [scenario] + [f"{value(metrics, tag, c, scenario, 'iae_Vs') * 1e3:.4g}" for c in present]
        if len(seeds) > 1:
            cells.append(spread({seed: value(metrics, tag, name, scenario, "iae_Vs") * 1e3
                                 for seed, name in seeds.items()}).text(".4g"))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _transient_table(metrics: pd.DataFrame, tag: str) -> list[str]:
    m = metrics[(metrics["pipeline"] == tag) & metrics["controller"].isin(ORDER)].copy()
    m["order"] = m["controller"].map({c: i for i, c in enumerate(ORDER)})
    m = m.sort_values(["scenario", "order"], kind="stable")
    m["iae_mVs"] = m["iae_Vs"] * 1e3
    return markdown_table(m, ["scenario", "controller", "overshoot_pct", "settling_time_ms", "steady_state_error_pct",
                              "iae_mVs"],
                          ["scenario", "controller", "overshoot [%]", "settling (2 %) [ms]", "steady-state error [%]",
                           "IAE [mV s]"])


def _classical_designs(out_dir: Path, tag: str) -> list[str]:
    lines = []
    for kind, name in (("current-mode", CURRENT_MODE), ("type-iii", TYPE_III)):
        path = out_dir / "tuning" / f"{kind}__{tag}.json"
        if not path.is_file():
            continue
        design = json.loads(path.read_text(encoding="utf-8"))
        loops = "; ".join(f"{loop}: crossover {v['crossover_hz']:.0f} Hz, phase margin {v['phase_margin_deg']:.1f} deg"
                          for loop, v in design["loops"].items())
        lines.append(f"- **{name}** (`tuning/{path.name}`), designed on the nominal circuit: {loops}.")
    return lines


def _domain_text(model: dict) -> str:
    c = model.get("collection") or {}
    parts = []
    if c.get("input_voltage_range"):
        parts.append("supplies {:g}-{:g} V".format(*c["input_voltage_range"]))
    elif c.get("input_voltage") is not None:
        parts.append(f"supply {c['input_voltage']:g} V")
    if c.get("load_range"):
        parts.append("loads {:g}-{:g} Ohm".format(*c["load_range"]))
    if c.get("reference_range"):
        parts.append("references {:g}-{:g} V".format(*c["reference_range"]))
    return ", ".join(parts) or "not recorded"


def summary_figure(metrics: pd.DataFrame, tags: dict[float, str], out_dir: Path) -> Path | None:
    """``figures/iae_by_scenario.png``: each controller's IAE per scenario at each rate (log scale), the NNPC's
    seeds as a range bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from cosim.plots import figure_styles, save_figure

    periods = list(tags)
    fig, axes = plt.subplots(1, len(periods), figsize=(6.2 * len(periods), 4.2), squeeze=False)
    for ax, period in zip(axes[0], periods):
        tag = tags[period]
        m = metrics[metrics["pipeline"] == tag]
        scenarios = list(dict.fromkeys(m["scenario"]))
        present = [c for c in ORDER if c in set(m["controller"])]
        width = 0.8 / max(1, len(present))
        x = np.arange(len(scenarios))
        seeds = seed_controllers(metrics, tag)
        for k, controller in enumerate(present):
            heights = [value(metrics, tag, controller, s, "iae_Vs") * 1e3 for s in scenarios]
            color, _ = figure_styles(present, CONTROLLER_STYLES)[controller]
            bars = ax.bar(x + (k - (len(present) - 1) / 2) * width, heights, width, label=controller, color=color,
                          edgecolor="black", linewidth=0.4)
            if controller == NNPC and len(seeds) > 1:
                spread = [[value(metrics, tag, n, s, "iae_Vs") * 1e3 for n in seeds.values()] for s in scenarios]
                low = [h - min(v) for h, v in zip(heights, spread)]
                high = [max(v) - h for h, v in zip(heights, spread)]
                ax.errorbar([b.get_x() + b.get_width() / 2 for b in bars], heights, yerr=[low, high], fmt="none",
                            ecolor="black", capsize=2, linewidth=0.8)
        ax.set_yscale("log")
        ax.set_xticks(x, [s.replace("_", " ") for s in scenarios])
        ax.set_ylabel("IAE [mV s] (log scale)")
        ax.set_title(f"{period_text(period)}" + (f" (NNPC bar: seed 0, whisker: {len(seeds)} seeds)"
                                                 if len(seeds) > 1 else ""))
        ax.grid(axis="y", which="both", alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    paths = save_figure(fig, out_dir / "figures" / "iae_by_scenario")
    plt.close(fig)
    return next(p for p in paths if p.suffix == ".png")


def _map_section(steps: pd.DataFrame | None) -> list[str]:
    """The envelope map's section: each controller's share of the grid meeting the spec (overall and per supply), its
    IAE per step, the NNPC's share over the seeds."""
    if steps is None or not len(steps):
        return []
    from cosim.study import envelope

    table = envelope.shares(steps)
    per_supply = envelope.shares(steps, by_supply=True).pivot(index="controller", columns="input_voltage_V",
                                                              values="share_pct")
    table = table.join(per_supply, on="controller")
    iae = steps.groupby("controller", sort=False)["iae_Vs"].agg(["median", "max"]).reindex(table["controller"])
    table["iae_median"], table["iae_worst"] = 1e3 * iae["median"].to_numpy(), 1e3 * iae["max"].to_numpy()
    supplies = list(per_supply.columns)
    references, loads = sorted(set(steps["reference_V"])), sorted(set(steps["load_Ohm"]))
    lines = ["## The envelope map", "",
             f"At each of {len(references) * len(loads) * len(supplies)} points -- references "
             f"{', '.join(f'{v:g}' for v in references)} V x loads {', '.join(f'{v:.3g}' for v in loads)} Ohm x "
             f"supplies {', '.join(f'{v:g}' for v in supplies)} V, over the spec's ranges -- a reference step "
             "0.8 r -> r and a load step 1.25 R -> R from the steady state, at one sample per PWM period; a point "
             f"meets the spec when both steps overshoot <= {envelope.OVERSHOOT_TARGET_PCT:g} % (of the step) and "
             f"settle (2 %) within {envelope.SETTLING_TARGET_MS:g} ms. Tables: `envelope/map.csv` (every run), "
             "`envelope/points.csv`, `envelope/shares.csv`.", ""]
    lines += markdown_table(table, ["controller", "share_pct", *supplies, "iae_median", "iae_worst"],
                            ["controller", "share of the grid [%]", *(f"at {v:g} V [%]" for v in supplies),
                             "IAE median [mV s]", "IAE worst [mV s]"])
    spread = envelope.nnpc_share_spread(steps)
    if spread.count > 1:
        lines += ["", f"The online NNPC's share over the {spread.count} identification seeds: "
                      f"{spread.text('.0f', ' %')} (median (min-max))."]
    return lines + ["", "![envelope map](figures/envelope_map.png)", ""]


def write_converter_report(out_dir: Path, binding, plan, outputs, metrics: pd.DataFrame,
                           map_steps: pd.DataFrame | None = None) -> Path:
    """``REPORT.md`` and ``targets.csv`` of a converter study (``plan``: :class:`~cosim.study.converter_study.StudyPlan`,
    ``outputs``: its jobs' :class:`~cosim.study.reproduce.PipelineOutput` in plan order; ``map_steps``: its envelope
    map's steps table, if it ran one)."""
    out_dir = Path(out_dir)
    spec = binding.converter
    periods = list(plan.control_periods)
    tags = {p.control_period: p.tag for p in plan.pipelines}
    pipelines = {o.pipeline.tag: o for o in outputs if o.key == o.pipeline.tag}
    targets = study_targets(out_dir, spec, periods, tags, metrics)
    atomic_write(out_dir / "targets.csv", lambda tmp: targets.to_csv(tmp, index=False))
    figure = summary_figure(metrics, tags, out_dir)
    name = spec.label or binding.label
    met = int((targets["met"] == "yes").sum())
    lines = [f"# Study of {name}", "",
             f"Generated by `buck-cosim study --plant {Path(plan.binding_file).name}`"
             + (" --quick" if plan.quick else "") + f" for the plant of `{Path(plan.binding_file).name}` "
             f"({binding.label}); every number below comes from this study's runs (`metrics/metrics_all.csv`), its "
             "design files (`tuning/`) and its networks (`models/`). Wall-clock figures are in "
             "[timings.md](timings.md).", "",
             "## The converter", ""]
    lines += _spec_table(spec)
    lines += ["", "## Targets", "",
              f"{met} of {len(targets)} met. The NNPC's targets hold only if they hold for every identification seed "
              f"({len(plan.seeds)} seeds: the measured value is the worst seed's, or the median seed's where the "
              "target names it).", ""]
    lines += markdown_table(targets, TARGET_COLUMNS)
    lines += ["", "Controllers: PI (tuned on this plant at the nominal point); NNPC (the workbench's network, "
              "identified from PI data over the spec's ranges); NNPC-paper (the paper's 3-7-2 network, one-step "
              "training); MPC-nominal (the same optimizer on the averaged model of the spec's nominal circuit, with "
              "a disturbance estimate); at one switching period also NNPC-explicit (the NNPC distilled into an "
              "explicit policy), CMC (cascaded average-current-mode control) and Type-III (voltage mode), both "
              "designed on the nominal circuit with one sample of computation delay.", ""]
    if figure is not None:
        lines += [f"![IAE per scenario and controller](figures/{figure.name})", ""]
    for period in periods:
        tag = tags[period]
        output = pipelines.get(tag)
        lines += [f"## {period_text(period)} (`{tag}`)", ""]
        if output is not None:
            pi = output.pi
            lines += [f"PI: Kp = {pi['kp']:.6g} 1/V, Ki = {pi['ki']:.6g} 1/(V s), tuned by {pi['evaluations']} "
                      f"simulations of this plant ({pi['method']}).", ""]
            model = output.models.get("nnpc", {})
            rmse = model.get("held_out_rmse", {})
            lines += [f"NNPC network {model.get('architecture', '')}: identified from {model.get('collection', {}).get('samples', 'n/a')} "
                      f"samples over {_domain_text(model)}; held-out vo RMSE one step "
                      f"{rmse.get('one_step_rmse_voltage_V', math.nan) * 1e3:.1f} mV, 10 steps "
                      f"{rmse.get('10_step_rmse_voltage_V', math.nan) * 1e3:.0f} mV (seed 0).", ""]
        lines += _iae_table(metrics, tag) + [""]
        for denominator, words in ((PI, "the PI"), (MPC_NOMINAL, "the nominal-model MPC")):
            spreads = seed_ratio_spreads(metrics, tag, denominator)
            if spreads:
                lines += [comparison(spreads, "The NNPC", words) + f" (NNPC / {denominator} IAE, median (min-max) "
                          "over the seeds: " + per_scenario_text(spreads, ".3f") + ").", ""]
        lines += ["Transients (seed 0):", ""] + _transient_table(metrics, tag) + [""]
        designs = _classical_designs(out_dir, tag)
        if designs:
            lines += designs + [""]
        figures = [f"[{s}](figures/{s}__{tag}.png)" for s in dict.fromkeys(metrics.loc[metrics["pipeline"] == tag,
                                                                                         "scenario"])
                   if (out_dir / "figures" / f"{s}__{tag}.png").is_file()]
        if figures:
            lines += ["Figures: " + ", ".join(figures) + ".", ""]
    lines += _map_section(map_steps)
    return atomic_write_text(out_dir / "REPORT.md", "\n".join(lines) + "\n")
