"""The explicit NNPC in the reproduction: distillation per plant, the operating-region map, its
targets and its report section.

The reproduction calls :func:`in_pipeline` once per pipeline (a one-line hook in
:mod:`cosim.study.reproduce`): at one switching period it distills the pipeline's NNPC into an
explicit policy (:mod:`cosim.design.distillation`, saved as ``models/<tag>__nnpc-explicit.pt``),
returns the explicit controller to run beside the others in the paper's scenarios. The explicit NNPC
is measured over the operating envelope by the envelope map (:mod:`cosim.study.envelope`, the one map
definition), where :class:`~cosim.design.distillation.ShadowPolicy` runs the policy beside the online NNPC: the first-move error
|policy move - NNPC move| on the online NNPC's own states. :func:`target_rows` adds the explicit
NNPC's targets to the targets table and :func:`report_section` writes its part of ``REPORT.md``.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pandas as pd

from controllers.explicit_policy import load_policy, save_policy
from cosim.base.labels import period_label
from cosim.design.distillation import FULL_DISTILLATION, SMALL_DISTILLATION, distill
from cosim.design.experiments import explicit_nnpc
from cosim.design.vocabulary import (
    DEFAULT_IMPLEMENTATION,
    NNPC,
    NNPC_EXPLICIT,
    SWITCHING_PERIOD,
    pipeline_tag,
    transient_within_sample,
)
from cosim.study.claims import target_row

#: targets of the issue (explicit vs online NNPC, the cost; the envelope map's in cosim.study.envelope)
IAE_RATIO_TARGET = 1.05
OVERSHOOT_TARGET_PCT = 5.0
STEADY_STATE_TARGET_PCT = 0.2
MAC_TARGET = 300
#: the reproduction distills seed 0's NNPC only; scripts/explicit_every_seed.py (make every-seed) checks the same
#: targets on every identification seed (cosim.study.explicit_every_seed)
EVERY_SEED_NOTE = "seed 0's NNPC; every seed: explicit-every-seed.md (make every-seed)"


# ---------------------------------------------------------------------------------------------
# The reproduction's hook


def policy_path(out_dir: Path, tag: str) -> Path:
    return Path(out_dir) / "models" / f"{tag}__nnpc-explicit.pt"


def in_pipeline(pipeline, binding, model, pi, out_dir: Path, profile, seed: int,
                implementation: str = DEFAULT_IMPLEMENTATION, timings: dict | None = None, log=None) -> list:
    """The study's hook, once per pipeline: where the transient is shaped within samples (one switching period),
    distill the pipeline's NNPC (``model``) into an explicit policy and return it as a controller to run beside
    the others (an empty list at 1 ms)."""
    period = pipeline.control_period
    if transient_within_sample(period):
        return []
    tag = pipeline_tag(pipeline.plant_tag, period)
    settings = replace(SMALL_DISTILLATION if profile.quick else FULL_DISTILLATION, seed=seed)
    policy = distill(model, binding, period, settings, log=log, metadata={"pipeline": tag}, timings=timings)
    save_policy(policy, policy_path(out_dir, tag))
    return [explicit_nnpc(policy, NNPC_EXPLICIT, spec=binding.converter)]


# ---------------------------------------------------------------------------------------------
# Targets and report


def _fast_pipelines(metrics: pd.DataFrame, pipelines: list[str]) -> list[str]:
    fast = period_label(SWITCHING_PERIOD)
    present = set(metrics.loc[metrics["controller"] == NNPC_EXPLICIT, "pipeline"])
    return [p for p in pipelines if p.endswith(fast) and p in present]


def _ratios(metrics: pd.DataFrame, tag: str) -> pd.Series:
    m = metrics[metrics["pipeline"] == tag]
    a = m[m["controller"] == NNPC_EXPLICIT].set_index("scenario")["iae_Vs"]
    b = m[m["controller"] == NNPC].set_index("scenario")["iae_Vs"]
    return a / b


def target_rows(metrics: pd.DataFrame, pipelines: list[str], out_dir: Path | None) -> list[dict]:
    """The explicit NNPC's targets, as rows of :class:`cosim.study.targets.Targets` (target,
    measured, met, note): IAE, overshoot and steady-state error against the online NNPC per fast
    pipeline and the counted MACs per step (the timed C step and
    the measured Cortex-M4F cycles are benchmark rows: ``buck-cosim bench --only explicit``, ``--only embedded``)."""
    rows = []

    def add(target, measured, met, note="", value=None, limit=None):
        rows.append(target_row(target, measured, met, note, value=value, limit=limit))

    for tag in _fast_pipelines(metrics, pipelines):
        r = _ratios(metrics, tag)
        averaged = tag.split("__")[0].endswith("-averaged")  # the built-in averaged plant (binding-file pipelines
        # distil no policy); the issue sets the IAE target on the switched plants, kept as a row here
        add(f"NNPC-explicit IAE <= {IAE_RATIO_TARGET:.2f} x online NNPC IAE, every scenario, {tag}",
            "; ".join(f"{s}: {v:.3f}" for s, v in r.items()), bool((r <= IAE_RATIO_TARGET).all()),
            "beyond the issue's target (set for the switched plant): the online NNPC is nearly dead-beat on the "
            f"averaged plant, so its IAE is small; {EVERY_SEED_NOTE}" if averaged else EVERY_SEED_NOTE,
            value=float(r.max()) if len(r) else math.nan, limit=IAE_RATIO_TARGET)
        m = metrics[(metrics["pipeline"] == tag) & (metrics["controller"] == NNPC_EXPLICIT)]
        startup = m[m["scenario"] == "startup"]["overshoot_pct"]
        if len(startup):
            online = metrics[(metrics["pipeline"] == tag) & (metrics["controller"] == NNPC)
                             & (metrics["scenario"] == "startup")]["overshoot_pct"]
            add(f"NNPC-explicit start-up overshoot <= {OVERSHOOT_TARGET_PCT:g} %, {tag}", f"{startup.iloc[0]:.2f} %",
                float(startup.iloc[0]) <= OVERSHOOT_TARGET_PCT,
                f"online NNPC: {online.iloc[0]:.2f} %; {EVERY_SEED_NOTE}" if len(online) else EVERY_SEED_NOTE,
                value=float(startup.iloc[0]),
                limit=OVERSHOOT_TARGET_PCT)
        worst = m.loc[m["steady_state_error_pct"].abs().idxmax()]
        add(f"NNPC-explicit steady-state error <= {STEADY_STATE_TARGET_PCT:g} %, every scenario, {tag}",
            f"max |error| {abs(worst['steady_state_error_pct']):.3f} % ({worst['scenario']})",
            bool((m["steady_state_error_pct"].abs() <= STEADY_STATE_TARGET_PCT).all()), EVERY_SEED_NOTE,
            value=abs(float(worst["steady_state_error_pct"])), limit=STEADY_STATE_TARGET_PCT)
    for tag in _fast_pipelines(metrics, pipelines):
        path = policy_path(out_dir, tag) if out_dir is not None else None
        if path is None or not path.is_file():
            continue
        policy = load_policy(path)
        macs = policy.config.macs()
        add(f"NNPC-explicit <= {MAC_TARGET} multiply-accumulates per step (counted), {tag}",
            f"{macs} MACs, {sum(policy.config.hidden)} tanh ({policy.config.label})", macs <= MAC_TARGET,
            "C step time: benchmarks.md (group explicit); Cortex-M4F cycles, measured: group embedded", value=macs,
            limit=MAC_TARGET)
    return rows


def report_section(out_dir: Path, metrics: pd.DataFrame, pipelines: list[str]) -> list[str]:
    """The explicit NNPC's section of ``REPORT.md`` (Markdown lines; empty when it did not run)."""
    from cosim.base.markdown import markdown_table

    tags = _fast_pipelines(metrics, pipelines)
    if not tags:
        return []
    lines = ["## Explicit NNPC (a policy distilled from the online NNPC)", "",
             "The online NNPC plans a duty sequence per sample on its NN model (the real-time iteration, with the "
             "search over thousands of candidate sequences as its start-up fallback); the explicit NNPC is one "
             "forward pass of a small tanh network trained to return the online NNPC's first move, plus an integral "
             "term near the reference that makes it offset-free (`controllers/explicit_policy.py`, C twin "
             "`controllers/c/explicit_policy.c`). It is distilled per plant with DAgger on the plant FMU "
             "(`cosim/design/distillation.py`): the expert drives seeded random episodes first (references 3-20 V, "
             "loads 4-100 Ohm, start-ups from rest), then the policy drives more and more of them while the online "
             "NNPC's C twin, as it runs by default (the RTI), labels every visited state in shadow; the labels are "
             "aggregated and the policy retrained "
             "after each round. At 1 ms it is not distilled: the online NNPC's one-step optimisation already fits "
             "the budget there (benchmarks.md). The reproduction distills seed 0's NNPC only: the table below and the "
             "targets are that one policy's. The same targets for the NNPC of every identification seed, each "
             "distilled with this budget, are in [explicit-every-seed.md](explicit-every-seed.md), and with the "
             "search's labels instead in [explicit-every-seed-search-labels.md](explicit-every-seed-search-labels.md) "
             "(`make every-seed`, after `make reproduce`: about 40 s of distillation per plant and seed with the RTI's "
             "labels, 80 s with the search's, so not part of the reproduction).", ""]
    rows = []
    for tag in tags:
        m = metrics[metrics["pipeline"] == tag]
        ratios = _ratios(metrics, tag)
        for scenario, ratio in ratios.items():
            ex = m[(m["controller"] == NNPC_EXPLICIT) & (m["scenario"] == scenario)].iloc[0]
            on = m[(m["controller"] == NNPC) & (m["scenario"] == scenario)].iloc[0]
            rows.append({"pipeline": tag, "scenario": scenario, "ratio": ratio,
                         "os_on": on["overshoot_pct"], "os_ex": ex["overshoot_pct"],
                         "sse_ex": ex["steady_state_error_pct"], "settle_on": on["settling_time_ms"],
                         "settle_ex": ex["settling_time_ms"]})
    lines += markdown_table(pd.DataFrame(rows), ["pipeline", "scenario", "ratio", "os_on", "os_ex", "sse_ex",
                                                 "settle_on", "settle_ex"],
                            ["pipeline", "scenario", "IAE explicit / online", "overshoot online [%]",
                             "overshoot explicit [%]", "SS error explicit [%]", "settling online [ms]",
                             "settling explicit [ms]"])
    lines += ["", "**Distillation** (per plant; the DAgger rounds, how many labels, and the first-move error of the "
              "policy on the states it visited before it was retrained on them):", ""]
    rounds = []
    for tag in tags:
        path = policy_path(out_dir, tag)
        if not path.is_file():
            continue
        policy = load_policy(path)
        for r in policy.metadata.get("distillation", {}).get("history", []):
            rounds.append({"pipeline": tag, "network": policy.config.label, "round": r["round"],
                           "beta": r["beta"], "labels": r["labels"], "aggregate": r["aggregate_labels"],
                           "on_policy": r.get("first_move_rms_before_retraining", math.nan),
                           "validation": r["validation_rms_duty"]})
    if rounds:
        lines += markdown_table(pd.DataFrame(rounds), ["pipeline", "network", "round", "beta", "labels", "aggregate",
                                                       "on_policy", "validation"],
                                ["pipeline", "network", "round", "expert share beta", "new labels", "aggregate",
                                 "on-policy RMS error before retraining [duty]", "validation RMS [duty]"])
    lines += ["", "Over the operating envelope (references x loads x supplies) the explicit NNPC is measured with the "
              "other controllers in the section *Control quality over the operating envelope*, where it runs in shadow "
              "beside the online NNPC (the first-move error figure there).", ""]
    lines += [""]
    return lines
