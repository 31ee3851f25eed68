"""``results/REPORT.md``: tables, figures, the targets and a plain discussion, all from measured data.

Every number in the report comes from the runs of the same reproduction (``metrics_all.csv``)
or from the physics of the Table II parameters computed here; nothing is typed in by hand.
"""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from cosim.base.files import atomic_write, atomic_write_text
from cosim.base.labels import period_label, period_text
from cosim.results import package_versions
from cosim.study.experiments import horizon_settings
from cosim.study.pi_tuning import METHOD as PI_METHOD
from cosim.study.vocabulary import (
    DITHER_FAST,
    DITHER_SLOW,
    FAST_RATE_COMPRESSION,
    MISMATCH,
    MPC_NOMINAL,
    MPC_ORACLE,
    MPC_ORACLE_AVERAGED,
    MPC_ORACLE_SYNC,
    NNPC,
    NNPC_PAPER,
    PAPER_PERIOD,
    PI,
    SWITCHING_PERIOD,
    horizon_variant,
    is_seed_variant,
)
from plant_fmu.table_ii import TABLE_II


def lc_physics(resistance: float = TABLE_II.load_resistance) -> dict[str, float]:
    """Natural frequency, damping, overshoot and 2 % settling of the open-loop LC step (Table II)."""
    l, c = TABLE_II.inductance, TABLE_II.capacitance
    wn = 1 / math.sqrt(l * c)
    zeta = math.sqrt(l / c) / (2 * resistance)
    return {"f0_Hz": wn / (2 * math.pi), "zeta": zeta,
            "overshoot_pct": 100 * math.exp(-zeta * math.pi / math.sqrt(1 - zeta ** 2)),
            "settling_ms": 4 / (zeta * wn) * 1e3}


def _fmt(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and (math.isnan(value) or math.isinf(value))):
        return "n/a"
    if isinstance(value, str):
        return value
    if isinstance(value, (bool,)):
        return "yes" if value else "no"
    if abs(value) >= 1e4 or (abs(value) < 1e-3 and value != 0):
        return f"{value:.{digits}e}"
    return f"{value:.{digits}g}"


def _table(frame: pd.DataFrame, columns: list[str], headers: list[str] | None = None, digits: int = 3) -> list[str]:
    headers = headers or columns
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    for _, row in frame[columns].iterrows():
        lines.append("| " + " | ".join(_fmt(v, digits) if not isinstance(v, str) else v for v in row) + " |")
    return lines


def _ratio_table(metrics: pd.DataFrame, pipeline: str, numerator: str, denominator: str) -> pd.DataFrame:
    m = metrics[metrics["pipeline"] == pipeline]
    a = m[m["controller"] == numerator].set_index("scenario")["iae_Vs"]
    b = m[m["controller"] == denominator].set_index("scenario")["iae_Vs"]
    return (a / b).rename(f"{numerator}/{denominator}")


def _seed_study(metrics, pipeline) -> list[str]:
    """Names of the seed-study NNPCs of a pipeline ("NNPC (seed 1)", ...)."""
    names = metrics.loc[metrics["pipeline"] == pipeline, "controller"]
    return sorted(n for n in set(names) if is_seed_variant(n))


def _value(metrics, pipeline, controller, scenario, column):
    rows = metrics[(metrics["pipeline"] == pipeline) & (metrics["controller"] == controller)
                   & (metrics["scenario"] == scenario)]
    return float(rows[column].iloc[0]) if len(rows) else math.nan


def benchmark_p99(out_dir: Path) -> float | None:
    """NNPC p99 compute time at 1 ms from the benchmark table, if ``buck-cosim bench`` has run."""
    path = Path(out_dir) / "benchmarks.csv"
    if not path.is_file():
        return None
    try:
        table = pd.read_csv(path)
        row = table[table["benchmark"].str.startswith("controller compute per step, NNPC, 1 ms")]
        return float(row["p99"].iloc[0]) if len(row) else None
    except (OSError, ValueError, KeyError):
        return None


class Targets:
    """The issue's targets, each checked against the measured metrics."""

    def __init__(self, metrics: pd.DataFrame, elapsed: float, pipelines: list[str], out_dir: Path = Path(".")):
        self.rows: list[dict] = []
        m = metrics
        fast = period_label(SWITCHING_PERIOD)
        paper = period_label(PAPER_PERIOD)

        def add(target, measured, met, note=""):
            self.rows.append({"target": target, "measured": measured, "met": "yes" if met else "**no**",
                              "note": note})

        for mode in ("averaged", "switched"):
            tag = f"nominal-{mode}__{paper}"
            if tag in pipelines:
                r = _ratio_table(m, tag, NNPC, MPC_ORACLE)
                add(f"NNPC IAE <= 1.10 x oracle-MPC IAE, every scenario, 1 ms, {mode}",
                    "; ".join(f"{s}: {v:.3f}" for s, v in r.items()), bool((r <= 1.10).all()))
        nnpc = m[(m["controller"] == NNPC) & m["pipeline"].str.startswith("nominal")]
        if len(nnpc):
            worst = nnpc.loc[nnpc["steady_state_error_pct"].abs().idxmax()]
            add("NNPC steady-state error <= 0.2 % of the reference, every scenario (nominal plants, both rates)",
                f"max |error| {abs(worst['steady_state_error_pct']):.3f} % ({worst['scenario']}, {worst['pipeline']})",
                bool((nnpc["steady_state_error_pct"].abs() <= 0.2).all()))
        for mode in ("averaged", "switched"):
            tag = f"nominal-{mode}__{fast}"
            if tag in pipelines:
                overshoot = _value(m, tag, NNPC, "startup", "overshoot_pct")
                seeds = _seed_study(m, tag)
                note = ("NNPC identified from other seeds' data: " + "; ".join(
                    f"{name}: {_value(m, tag, name, 'startup', 'overshoot_pct'):.2f} %" for name in seeds)) if seeds else ""
                add(f"NNPC start-up overshoot <= 5 % at 1/fsw, {mode}", f"{overshoot:.2f} %", overshoot <= 5.0, note)
                r = _ratio_table(m, tag, NNPC, PI)
                note = ("other seeds, worst scenario: " + "; ".join(
                    f"{name}: {_ratio_table(m, tag, name, 'PI').max():.3f}" for name in seeds)) if seeds else ""
                add(f"NNPC IAE <= 0.6 x PI IAE at 1/fsw, {mode}", "; ".join(f"{s}: {v:.3f}" for s, v in r.items()),
                    bool((r <= 0.6).all()), note)
        for rate in (paper, fast):
            tag = f"mismatch-switched__{rate}"
            if tag in pipelines:
                r = _ratio_table(m, tag, NNPC, MPC_NOMINAL)
                add(f"Under mismatch: NNPC IAE <= 0.8 x nominal-model MPC IAE, {rate}",
                    "; ".join(f"{s}: {v:.3f}" for s, v in r.items()), bool((r <= 0.8).all()))
        slow = m[(m["controller"] == NNPC) & m["pipeline"].str.endswith(paper)]
        if len(slow):
            p99 = float(slow["controller_p99_us"].max())
            measured, met, note = f"worst run p99 {p99:.0f} us", p99 <= 100.0, \
                "per-run p99 over ~45 samples, two pipelines sharing the cores"
            bench = benchmark_p99(out_dir)
            if bench is not None:
                measured += f"; benchmark suite: p99 {bench:.0f} us"
                met = bench <= 100.0
                note = "met/not met from the benchmark (3000 samples, one process; results/benchmarks.md)"
            add("NNPC compute per step p99 <= 100 us at 1 ms", measured, met, note)
        add("Whole reproduction <= 120 s on 2 cores", f"{elapsed:.1f} s", elapsed <= 120.0)

    def frame(self) -> pd.DataFrame:
        return pd.DataFrame(self.rows)


def write_report(out_dir: Path, outputs, metrics: pd.DataFrame, elapsed: float, *, profile, seed: int,
                 workers: int) -> Path:
    pipelines = [o.pipeline.tag for o in outputs]
    targets = Targets(metrics, elapsed, pipelines, out_dir)
    target_frame = targets.frame()
    atomic_write(out_dir / "targets.csv", lambda tmp: target_frame.to_csv(tmp, index=False))
    physics = lc_physics()
    paper, fast = period_label(PAPER_PERIOD), period_label(SWITCHING_PERIOD)
    lines = [
        "# Reproduction report: NNPC for a 48 V -> 12 V buck converter",
        "",
        "Generated by `make reproduce` (`buck-cosim reproduce`) -- do not edit by hand. "
        f"Wall time {elapsed:.1f} s on {workers} worker process(es), seed {seed}.",
    ]
    if profile.quick:
        lines += ["", "**Quick profile (CI smoke test): tiny data sets and shortened runs; the numbers mean nothing.**"]
    lines += ["", "## Summary", ""] + _summary(metrics, pipelines, physics, targets) + [""]
    lines += ["## Targets", "", "Each target of the project's issue, checked against this reproduction "
              "(also in `targets.csv`).", ""]
    lines += _table(target_frame, ["target", "measured", "met", "note"])
    lines += ["", "## Setup", ""] + _setup(physics) + [""]
    lines += ["## PI gains (tuned per plant and rate)", "", f"Method: {PI_METHOD}.", ""]
    pi_rows = pd.DataFrame([{"pipeline": o.pipeline.tag, "Kp [1/V]": o.pi["kp"], "Ki [1/(V s)]": o.pi["ki"],
                             "worst overshoot [%]": o.pi["worst_overshoot_pct"], "simulations": o.pi["evaluations"]}
                            for o in outputs])
    lines += _table(pi_rows, list(pi_rows.columns), digits=4)
    lines += ["", "## NN identification", "",
              "10 000 samples per plant and rate (the paper's 3 x 10 000 matrix of iL, vc, d, plus the load "
              "conductance), collected with the tuned PI and seeded random references and loads; the last 20 % "
              "is held out. RMSEs on that held-out tail: one step, and 10 steps open loop with the recorded "
              "duties.", ""]
    nn_rows = []
    for o in outputs:
        for name, meta in o.models.items():
            rmse = meta.get("held_out_rmse", {})
            nn_rows.append({"pipeline": o.pipeline.tag, "model": name, "network": meta.get("architecture"),
                            "1-step vo [mV]": rmse.get("one_step_rmse_voltage_V", math.nan) * 1e3,
                            "1-step iL [mA]": rmse.get("one_step_rmse_current_A", math.nan) * 1e3,
                            "10-step vo [mV]": rmse.get("10_step_rmse_voltage_V", math.nan) * 1e3,
                            "10-step iL [mA]": rmse.get("10_step_rmse_current_A", math.nan) * 1e3,
                            "training [s]": o.timings.get(f"training_{name}_s", math.nan)})
    lines += _table(pd.DataFrame(nn_rows), list(nn_rows[0]), digits=3) if nn_rows else []
    columns = ["scenario", "controller", "rise_time_ms", "overshoot_pct", "undershoot_pct", "settling_time_ms",
               "steady_state_error_pct", "iae_Vs", "peak_inductor_current_A", "controller_p50_us",
               "controller_p99_us"]
    headers = ["scenario", "controller", "rise [ms]", "overshoot [%]", "undershoot [%]", "settling 2% [ms]",
               "SS error [%]", "IAE [V s]", "peak iL [A]", "ctrl p50 [us]", "ctrl p99 [us]"]
    for rate, title in ((paper, f"Results at the paper's rate ({period_text(PAPER_PERIOD)})"),
                        (fast, f"Results at one switching period ({period_text(SWITCHING_PERIOD)})")):
        lines += ["", f"## {title}", ""]
        for o in outputs:
            if period_label(o.pipeline.control_period) != rate:
                continue
            tag = o.pipeline.tag
            lines += [f"### {o.pipeline.plant_tag}", ""]
            lines += _table(metrics[metrics["pipeline"] == tag], columns, headers)
            lines += [""]
            for scenario in sorted(set(metrics.loc[metrics["pipeline"] == tag, "scenario"]),
                                   key=lambda s: list(metrics["scenario"]).index(s)):
                lines.append(f"![{scenario}, {tag}](figures/{scenario}__{o.pipeline.plant_tag}__{rate}.png)")
            lines.append("")
    lines += ["## Ablations", ""] + _ablations(metrics) + [""]
    lines += ["## Discussion", ""] + _discussion(metrics, pipelines, physics) + [""]
    lines += ["## Reproducing", "", "```", "make reproduce        # everything above, from a fresh clone",
              "make bench            # the benchmark table (results/benchmarks.md)", "```", "",
              "Package versions: " + ", ".join(f"{k} {v}" for k, v in package_versions().items()) + ".", "",
              "Per-pipeline wall times [s]:", ""]
    timing_rows = pd.DataFrame([{"pipeline": o.pipeline.tag, **{k: v for k, v in o.timings.items()}} for o in outputs])
    lines += _table(timing_rows, list(timing_rows.columns), digits=3)
    return atomic_write_text(out_dir / "REPORT.md", "\n".join(lines) + "\n")


def _setup(physics: dict) -> list[str]:
    slow, fast = horizon_settings(PAPER_PERIOD), horizon_settings(SWITCHING_PERIOD)
    t = TABLE_II
    return [
        "- **Plant**: the project's BuckConverter FMU (FMI 2.0, co-simulation, exact piecewise steps), "
        f"Table II: Vs {t.input_voltage:g} V, L {t.inductance * 1e6:g} uH, C {t.capacitance * 1e6:g} uF, "
        f"R {t.load_resistance:g} Ohm, f_sw {t.switching_frequency / 1e3:g} kHz; *averaged* (eq. 3 with DCM) and "
        "*switched* (ideal switch and diode, sawtooth PWM). The *mismatch* plant has L +20 % "
        f"({MISMATCH.inductance * 1e6:.0f} uH), C -20 % ({MISMATCH.capacitance * 1e6:.0f} uF), DCR "
        f"{MISMATCH.inductor_resistance} Ohm, switch {MISMATCH.switch_on_resistance} Ohm, diode "
        f"{MISMATCH.diode_forward_voltage} V, ESR {MISMATCH.capacitor_esr} Ohm.",
        f"- **LC physics** (6 Ohm): f0 = {physics['f0_Hz']:.0f} Hz, damping {physics['zeta']:.2f}, open-loop step "
        f"overshoot {physics['overshoot_pct']:.1f} %, 2 % settling {physics['settling_ms']:.2f} ms -- faster than "
        "the paper's 1 ms sample.",
        "- **Sensing**: controllers read the means of vo, iL and the load current io over the last PWM period "
        "(an averaging ADC; the FMU computes them exactly); a point sample would alias the 91 mV ripple "
        "into a DC error. All three are sampled alike, so the load estimate vo/io is exact between load "
        "steps; a load step at a sample instant is seen one sample later, which dominates the 1 ms one-step "
        "current RMSE of the switched plants below.",
        "- **Rates**: the paper's 1 ms, and one switching period (13.33 us), where the scenarios are "
        f"time-compressed ({FAST_RATE_COMPRESSION.describe()}) since every controller settles "
        "within about a millisecond.",
        "- **NNPC**: receding horizon with the paper's cost (eq. 23, discounted sum eq. 16, gamma "
        f"{slow.discount}); horizon {slow.horizon} sample at 1 ms (the LC transient is over within one "
        f"sample; an N = 3 ablation is below), {fast.horizon} samples (one LC period) at 13.33 us with "
        f"move blocking {fast.blocks}; offset-free via a filtered state-disturbance estimate "
        f"(alpha {slow.bias_filter}). *NNPC-paper* uses the paper's 3-7-2 network; *NNPC* adds the load "
        "conductance io/vo as a fourth input (still 7 hidden neurons).",
        "- **MPC baselines** share the optimizer and predict with the plant's exact circuit model: on the "
        "averaged plant eq. 3 discretised with the matrix exponential, on the switched plant the switched "
        "circuit solved exactly per PWM period (sawtooth timing, parasitics) and seen through the averaging "
        "sensor. *MPC-oracle* has the plant's parameters; *MPC-mismatched* uses the mismatch plant's "
        "parameters on the nominal plant, and *MPC-nominal* the nominal parameters on the mismatch plant.",
    ]


def _ablation(text: str, rows: pd.DataFrame, columns: dict[str, str]) -> list[str]:
    """One ablation: its explanation and its table (metric column -> heading), or nothing without rows."""
    if not len(rows):
        return []
    return [text, "", *_table(rows, list(columns), list(columns.values())), ""]


def _ablations(metrics: pd.DataFrame) -> list[str]:
    paper, fast = period_label(PAPER_PERIOD), period_label(SWITCHING_PERIOD)

    def runs(tag, controllers):
        return metrics[(metrics["pipeline"] == tag) & metrics["controller"].isin(controllers)].copy()

    lines = _ablation(
        "**Horizon at 1 ms** (nominal switched plant): the NNPC with one step of prediction against three. The LC "
        "transient is over within a sample, so the first move -- the only one applied -- is the same.",
        runs(f"nominal-switched__{paper}", [NNPC, horizon_variant(NNPC, 3)]),
        {"scenario": "scenario", "controller": "controller", "iae_Vs": "IAE [V s]", "overshoot_pct": "overshoot [%]",
         "settling_time_ms": "settling [ms]", "controller_p50_us": "ctrl p50 [us]"})
    tag = f"nominal-switched__{fast}"
    lines += _ablation(
        "**Model and sensor at 13.33 us** (nominal switched plant, oracle parameters): *MPC-oracle* predicts the "
        "averaging sensor's reading (mean over the last PWM period) with the switched circuit solved per PWM "
        "period; *(averaged model)* predicts the same reading with eq. 3, blind to the sensor's half-sample lag "
        "and to the sawtooth putting the on-time at the start of the period, so the aggressive optimum of eq. 23 "
        "overshoots; *(sync. sample)* reads a point sample at mid off-time with centre-aligned PWM, predicted "
        "exactly too, but regulates the ripple crest and leaves a DC error of about half the 91 mV ripple.",
        runs(tag, [MPC_ORACLE, MPC_ORACLE_AVERAGED, MPC_ORACLE_SYNC]),
        {"scenario": "scenario", "controller": "controller", "iae_Vs": "IAE [V s]", "overshoot_pct": "overshoot [%]",
         "steady_state_error_pct": "SS error [%]"})
    seeds = _seed_study(metrics, tag)
    if seeds:
        rows = runs(tag, [NNPC, *seeds])
        pi = runs(tag, [PI]).set_index("scenario")["iae_Vs"]
        rows["iae_over_pi"] = rows["iae_Vs"].to_numpy() / pi.reindex(rows["scenario"]).to_numpy()
        lines += _ablation(
            "**Seed sensitivity at 13.33 us** (nominal switched plant): the NNPC identified again from data "
            "collected and a network trained with other seeds (same tuned PI, same settings). The spread is the "
            "uncertainty of the NNPC numbers above; the MPC baselines have none.",
            rows, {"scenario": "scenario", "controller": "controller", "iae_Vs": "IAE [V s]",
                   "iae_over_pi": "IAE / PI IAE", "overshoot_pct": "overshoot [%]",
                   "steady_state_error_pct": "SS error [%]"})
    return lines


def _summary(metrics, pipelines, physics, targets) -> list[str]:
    paper, fast = period_label(PAPER_PERIOD), period_label(SWITCHING_PERIOD)
    lines = []
    tag = f"nominal-switched__{paper}"
    if tag in pipelines:
        os_pi = _value(metrics, tag, PI, "startup", "overshoot_pct")
        os_nn = _value(metrics, tag, NNPC, "startup", "overshoot_pct")
        r_pi = _ratio_table(metrics, tag, NNPC, PI)
        r_or = _ratio_table(metrics, tag, NNPC, MPC_ORACLE)
        lines.append(
            f"- **At 1 ms the LC transient is over before the next sample** ({physics['settling_ms']:.2f} ms). "
            f"No controller can shape it: a predictive controller moves the output in one sample and the "
            f"ringing inside that sample shows as {os_nn:.0f} % start-up overshoot (NNPC; the open-loop "
            f"value is {physics['overshoot_pct']:.0f} %), while the tuned PI approaches in smaller steps "
            f"({os_pi:.1f} %). NNPC IAE / PI IAE on the switched plant: "
            + ", ".join(f"{s} {v:.2f}" for s, v in r_pi.items())
            + "; NNPC / oracle MPC: " + ", ".join(f"{s} {v:.3f}" for s, v in r_or.items()) + ".")
    tag = f"nominal-switched__{fast}"
    if tag in pipelines:
        r_pi = _ratio_table(metrics, tag, NNPC, PI)
        r_or = _ratio_table(metrics, tag, NNPC, MPC_ORACLE)
        os_nn = _value(metrics, tag, NNPC, "startup", "overshoot_pct")
        seeds = _seed_study(metrics, tag)
        spread = (" (NNPCs identified from other seeds' data: " + ", ".join(
            f"{_value(metrics, tag, name, 'startup', 'overshoot_pct'):.1f} %" for name in seeds) + ")") if seeds else ""
        lines.append(
            "- **At one switching period the controllers can shape the transient**: NNPC IAE / PI IAE = "
            + ", ".join(f"{s} {v:.2f}" for s, v in r_pi.items())
            + f"; start-up overshoot {os_nn:.1f} %{spread}; NNPC / oracle MPC = "
            + ", ".join(f"{s} {v:.2f}" for s, v in r_or.items()) + ".")
    paper_nn = metrics[metrics["controller"] == NNPC_PAPER]
    if len(paper_nn):
        slow = paper_nn[paper_nn["pipeline"].str.endswith(paper)]
        quick = paper_nn[paper_nn["pipeline"].str.endswith(fast)]
        lines.append(
            "- **The paper's 3-7-2 network** (no load information) works at 1 ms (worst steady-state error "
            f"{slow['steady_state_error_pct'].abs().max():.2f} %) but not at 13.33 us (worst steady-state "
            f"error {quick['steady_state_error_pct'].abs().max():.1f} %): within one switching period the output "
            "voltage moves by (iL - io) Ts / C, and without the load the network cannot know io.")
    tag = f"nominal-switched__{fast}"
    sync = metrics[(metrics["pipeline"] == tag) & (metrics["controller"] == MPC_ORACLE_SYNC)]
    if len(sync):
        averaged = _value(metrics, tag, MPC_ORACLE, "startup", "overshoot_pct")
        synchronous = _value(metrics, tag, MPC_ORACLE_SYNC, "startup", "overshoot_pct")
        learned = _value(metrics, tag, NNPC, "startup", "overshoot_pct")
        blind = _value(metrics, tag, MPC_ORACLE_AVERAGED, "startup", "overshoot_pct")
        lines.append(
            f"- **On the switched plant at 13.33 us the model must contain the sensor**: the oracle MPC, which "
            f"predicts the averaging sensor's reading with the switched circuit, overshoots {averaged:.1f} % at "
            f"start-up; with eq. 3 instead (blind to the half-sample lag of the period mean) {blind:.1f} %; with "
            f"a synchronous mid-off-time sample {synchronous:.1f} %, at the price of a ripple-size DC error "
            f"({sync['steady_state_error_pct'].abs().max():.2f} %). The NNPC, which reads the averaged "
            f"measurement and sees two past samples, overshoots {learned:.1f} %.")
    tag = f"mismatch-switched__{fast}"
    if tag in pipelines:
        r = _ratio_table(metrics, tag, NNPC, MPC_NOMINAL)
        lines.append("- **Model mismatch** (L +20 %, C -20 %, parasitics): NNPC IAE / nominal-model MPC IAE at "
                     "13.33 us = " + ", ".join(f"{s} {v:.2f}" for s, v in r.items())
                     + ". The disturbance estimate makes the nominal-model MPC offset-free, so mismatch costs it "
                       "transient quality, not accuracy.")
    missed = [row["target"] for row in targets.rows if row["met"] != "yes"]
    lines.append(f"- **Targets**: {len(targets.rows) - len(missed)} of {len(targets.rows)} met"
                 + (" (not met: " + "; ".join(missed) + ")." if missed else "."))
    return lines


def _discussion(metrics, pipelines, physics) -> list[str]:
    text = [
        "**Which of the paper's claims hold, and at which rate.** The paper claims that the NNPC 'optimally "
        "regulates' the converter while the PI shows 'voltage and current oscillations' in start-up, load "
        "change and reference changes (Figs. 8-10), and that NNPC 'performs much better' than PI.",
        "",
        f"*At 1 ms* the claim reduces to sample-rate arithmetic. The LC filter rings at {physics['f0_Hz']:.0f} Hz "
        f"with damping {physics['zeta']:.2f} and settles within {physics['settling_ms']:.2f} ms, so at every 1 ms "
        "sample the plant is already at the steady state of the duty it was given. A controller that knows "
        "the plant (oracle MPC, or an accurately trained NNPC) sets the right duty at once -- a dead-beat "
        "response -- and the oscillation the paper shows inside a millisecond is the open-loop ringing that "
        "no 1 ms controller can damp. A PI tuned for that rate is a few samples slower (IAE several times "
        "higher in start-up and reference steps) but avoids the intra-sample overshoot by moving in smaller "
        "steps; load changes are the same for every controller, because the output recovers by itself "
        "before the next sample. The NNPC matches the oracle MPC closely once it knows the load.",
        "",
        "*At one switching period* the controllers act inside the LC transient, and the comparison the paper "
        "intended becomes meaningful: the predictive controllers shape the start-up and the reference steps "
        "and beat the PI, whose integral action must stay slow to keep the resonance stable. The NN's "
        "accuracy now matters over a whole LC period of prediction, and the paper's three inputs are not "
        "enough: the load decides how fast the capacitor charges within 13 us.",
        "",
        "**Model mismatch.** The paper's argument for the NNPC is that an MPC needs an accurate model. With "
        "an offset-free formulation (the same disturbance estimate for every predictor), a 20 % L/C error "
        "and parasitics do not produce steady-state error in the nominal-model MPC; they cost transient "
        "quality, and an NN trained on the real plant recovers it only as far as its own prediction error "
        "allows. The mismatch tables above give the numbers for each rate.",
        "",
        "**Limits of this reproduction.** The NNPC's quality depends on the identification data (seeded; "
        f"the PI-driven random references and loads of the paper, with a duty dither -- sigma {DITHER_SLOW} at 1 ms, "
        f"{DITHER_FAST} at 13.33 us -- and repeated start-ups from rest) and on training; results for other seeds and "
        "dither levels differ, at 13.33 us by several per cent of overshoot (the seed-sensitivity table "
        "above), because the network's multi-step predictions (see the 10-step RMSEs) are poor wherever the "
        "data is thin. The MPC baselines have no such dependence. Compute times are Python/numpy on a shared 2-core machine: "
        "the predictive controllers at 13.33 us are far from real time.",
    ]
    return text
