"""Figures like the paper's Figures 8-10: output voltage, inductor current and duty cycle, controllers
overlaid, the whole run beside the transient with its overshoot, settling band and settling time marked.

PNG for reports and SVG for papers; the SVG is written without a date and with a fixed hash salt
so the same results give the same file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from cosim.base.files import atomic_write  # noqa: E402
from cosim.base.labels import period_text  # noqa: E402
from cosim.results import RunResult  # noqa: E402

plt.rcParams["svg.hashsalt"] = "buck-cosim"
#: controller name -> (colour, line style); controllers not named get :data:`OTHER_COLOURS`
Styles = Mapping[str, tuple[str, object]]
#: colours of controllers without a style (a user's own): none is a built-in controller's
#: (cosim.design.vocabulary.CONTROLLER_STYLES), and none repeats a colour the figure already shows
OTHER_COLOURS = ("black", "magenta", "gold", "teal", "navy", "lime", "maroon", "darkorange", "slateblue")
#: their line style: dash-dot-dot, unlike every built-in controller's
OTHER_LINE_STYLE = (0, (6, 1.5, 1, 1.5, 1, 1.5))
#: a run whose output ends this far from the reference (relative) does not set the axis limits
DIVERGED = 0.05




#: the transient column spans this multiple of the slowest run's settling time ...
ZOOM_SETTLING_FACTOR = 1.5
#: ... and at least this many control periods (a run that settles within a sample still shows a few)
ZOOM_MIN_SAMPLES = 5
#: shown before the event, as a share of the transient column's span (the level the step starts from)
ZOOM_LEAD = 0.1
MEAN_NOTE = ("bold: PWM-period mean (what the controller reads); faint: instantaneous -- the metrics' signal "
             "(overshoot, settling, peak current, ripple)")


def figure_styles(names, styles: Styles | None) -> dict[str, tuple[str, object]]:
    """Colour and line style of each controller of one figure: its own (``styles``), else the next of
    :data:`OTHER_COLOURS` not shown by another controller of the figure, dash-dot-dot -- so a user's controller
    is never drawn in the PI's blue, nor two of them alike."""
    styles = styles or {}
    shown = {styles[name][0] for name in names if name in styles}
    free = [c for c in OTHER_COLOURS if c not in shown] or list(OTHER_COLOURS)
    chosen, others = {}, 0
    for name in names:
        if name in styles:
            chosen[name] = styles[name]
        elif name not in chosen:
            chosen[name] = (free[others % len(free)], OTHER_LINE_STYLE)
            others += 1
    return chosen


def transient_window(results: list[RunResult], metrics: list[dict]) -> tuple[float, float]:
    """Where the transient happens [s]: from shortly before the metrics window starts (the event)
    to :data:`ZOOM_SETTLING_FACTOR` x the slowest settling time after it, of the runs that settle (at
    least :data:`ZOOM_MIN_SAMPLES` control periods; a fifth of the window if none settles)."""
    info = results[0].info
    t0 = info.metrics_start
    end = max(float(r.frame["time"].iloc[-1]) for r in results if len(r.frame))
    finite = [m["settling_time_ms"] * 1e-3 for m in metrics if np.isfinite(m["settling_time_ms"])]
    span = ZOOM_SETTLING_FACTOR * max(finite) if finite else 0.2 * (end - t0)  # runs that never settle: not here
    span = min(max(span, ZOOM_MIN_SAMPLES * info.control_period), end - t0)
    return max(0.0, t0 - ZOOM_LEAD * span), t0 + span


def scenario_figure(results: list[RunResult], title: str, zoom: tuple[float, float] | None = None,
                    period_means: bool = False, styles: Styles | None = None):
    """The run figure: output voltage, inductor current and duty cycle against time in ms, the
    controllers overlaid; the left column shows the run (or ``zoom``), the right one the transient
    (:func:`transient_window`) with the 2 % settling band, each run's overshoot peak and settling
    time marked (the legend gives their values, from :func:`cosim.metrics.run_metrics`).

    ``period_means``: draw the PWM-period means (the ``measured_*`` columns) bold and the
    instantaneous switched waveforms faint behind them -- the metrics are computed on the
    instantaneous ones, and the figure says so.
    """
    from cosim.metrics import SETTLING_BAND, run_metrics

    metrics = [run_metrics(r) for r in results]
    window = transient_window(results, metrics)
    chosen = figure_styles([r.info.controller for r in results], styles)
    fig, axes = plt.subplots(3, 2, figsize=(12, 8.5), sharex="col", constrained_layout=True,
                             gridspec_kw={"width_ratios": [1.6, 1.0], "height_ratios": [1.25, 1.0, 0.7]})
    columns = (("full", zoom), ("transient", window))
    signals = (("output_voltage", "measured_output_voltage"), ("inductor_current", "measured_inductor_current"))
    v_column = "measured_output_voltage" if period_means else "output_voltage"
    clipped = [r.info.controller for r in results if len(r.frame) and  # runs ending off the reference
               abs(r.frame[v_column].iloc[-1] - r.frame["reference"].iloc[-1])
               > DIVERGED * max(abs(r.frame["reference"].iloc[-1]), 1.0)]
    end = max(float(r.frame["time"].iloc[-1]) for r in results if len(r.frame))
    for col, (kind, view) in enumerate(columns):
        ax_v, ax_i, ax_d = axes[:, col]
        limits_v, limits_i, duties = [], [], []
        view = view if view is not None else (0.0, end)
        for k, (result, m) in enumerate(zip(results, metrics)):
            frame = result.frame
            if view is not None:
                frame = frame[(frame["time"] >= view[0]) & (frame["time"] <= view[1])]
            if not len(frame):
                continue
            t_ms = frame["time"].to_numpy() * 1e3
            name = result.info.controller
            color, style = chosen[name]
            if k == 0:
                ax_v.plot(t_ms, frame["reference"], "k--", linewidth=1.0, label="reference")
                r_final = float(result.frame["reference"].iloc[-1])
                band = SETTLING_BAND * abs(r_final)
                ax_v.axhspan(r_final - band, r_final + band, color="0.85", alpha=0.6, linewidth=0,
                             label=f"{SETTLING_BAND * 100:g} % settling band")
            label = name
            if col == 1:
                settles = f"{m['settling_time_ms']:.3g} ms" if np.isfinite(m["settling_time_ms"]) else "never"
                label = f"{name}: overshoot {m['overshoot_pct']:.3g} %, settling {settles}"
            lines = []
            # the current's legend names the peak currents (its marks), not the voltage's metrics
            for ax, (instant, mean), text in zip((ax_v, ax_i), signals, (label, "_nolegend_")):
                if period_means:
                    lines.append(ax.plot(t_ms, frame[instant], color=color, linestyle="-", linewidth=0.6,
                                         alpha=0.3)[0])
                    lines.append(ax.plot(t_ms, frame[mean], color=color, linestyle=style, linewidth=1.4,
                                         label=text)[0])
                else:
                    lines.append(ax.plot(t_ms, frame[instant], color=color, linestyle=style, linewidth=1.3,
                                         label=text)[0])
            duties.append((float(frame["duty_cycle"].min()), float(frame["duty_cycle"].max())))
            lines.append(ax_d.plot(t_ms, frame["duty_cycle"], color=color, linestyle=style, linewidth=1.1,
                                   drawstyle="steps-post", label=name)[0])
            if name not in clipped:
                limits_v.append((frame[signals[0][period_means]].min(), frame["output_voltage"].max()))
                limits_i.append((frame[signals[1][period_means]].min(), frame["inductor_current"].max()))
            else:  # a run that never settles: faint, so it does not hide the others
                for line in lines:
                    line.set_alpha(0.35)
                    line.set_linewidth(0.8)
            if col == 1:
                _mark_transient(ax_v, ax_i, result, m, color, view)
        for ax, limits in ((ax_v, limits_v), (ax_i, limits_i)):
            if limits and clipped:  # scale to the settled runs: a diverging one must not squash them
                low, high = min(l for l, _ in limits), max(h for _, h in limits)
                margin = 0.08 * (high - low or 1.0)
                ax.set_ylim(low - margin, high + margin)
        if duties:  # the duties' own range (a 0.21 -> 0.25 step stays visible), within 0..1
            low, high = min(d for d, _ in duties), max(d for _, d in duties)
            margin = max(0.1 * (high - low), 0.02)
            ax_d.set_ylim(max(low - margin, -0.03), min(high + margin, 1.03))
        ax_d.set_xlim(view[0] * 1e3, view[1] * 1e3)  # the data's span: no marker stretches it
        ax_d.set_xlabel("time [ms]")
        for ax in (ax_v, ax_i, ax_d):
            ax.grid(True, alpha=0.3)
        if col == 1:  # beside the transient, not over it: its legends name every controller's metrics
            ax_v.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, borderaxespad=0.0)
            if ax_i.get_legend_handles_labels()[0]:
                ax_i.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, borderaxespad=0.0)
        else:
            ax_v.legend(loc="best", fontsize=7)
        if col == 0:
            ax_v.set_ylabel("output voltage $v_o$ [V]")
            ax_i.set_ylabel("inductor current $i_L$ [A]")
            ax_d.set_ylabel("duty cycle [1]")
            ax_d.legend(loc="best", fontsize=7)
        else:
            ax_v.set_title(f"transient: {window[0] * 1e3:.3g} - {window[1] * 1e3:.3g} ms", fontsize=9)
    if clipped:
        title += f"\n(axes scaled to the settled runs; {', '.join(clipped)} " \
                 f"{'leaves' if len(clipped) == 1 else 'leave'} the plot)"
    if period_means:
        title += f"\n{MEAN_NOTE}"
    fig.suptitle(title, fontsize=10)
    return fig


def _mark_transient(ax_v, ax_i, result: RunResult, m: dict, color, view: tuple[float, float]) -> None:
    """The metrics on the transient column: the overshoot peak (on the instantaneous output voltage, as
    :func:`cosim.metrics.signal_metrics` measures it), the settling instant, the peak inductor current -- each where
    it falls inside the column's ``view`` [s] (a peak after it is given in the legend, not drawn off the data)."""
    frame = result.frame
    t0 = result.info.metrics_start
    after = frame[frame["time"] >= t0 - 1e-12]
    shown = view[1] + 1e-12  # [s] the column's end
    if not len(after):
        return
    y = after["output_voltage"].to_numpy()
    r_final = float(after["reference"].iloc[-1])
    direction = 1.0 if r_final >= y[0] else -1.0
    if np.isfinite(m["overshoot_pct"]) and m["overshoot_pct"] > 0 and \
            after["time"].iloc[k := int(np.argmax(direction * (y - r_final)))] <= shown:
        ax_v.plot(after["time"].iloc[k] * 1e3, y[k], marker="v" if direction > 0 else "^", color=color,
                  markersize=7, markeredgecolor="k", markeredgewidth=0.5, linestyle="none")
    if np.isfinite(m["settling_time_ms"]) and m["settling_time_ms"] > 0 and t0 + m["settling_time_ms"] * 1e-3 <= shown:
        ax_v.axvline(t0 * 1e3 + m["settling_time_ms"], color=color, linestyle=":", linewidth=1.2)
    current = after["inductor_current"].to_numpy()
    if np.isfinite(current).any() and after["time"].iloc[k := int(np.nanargmax(current))] <= shown:
        ax_i.plot(after["time"].iloc[k] * 1e3, current[k], marker="v", color=color, markersize=6,
                  markeredgecolor="k", markeredgewidth=0.5, linestyle="none",
                  label=f"{result.info.controller}: peak {m['peak_inductor_current_A']:.3g} A")


def save_figure(fig, stem: Path) -> list[Path]:
    """Write ``<stem>.png`` (110 dpi) and ``<stem>.svg`` atomically; close the figure. A ``stem`` ending in .png or
    .svg stands for the pair; any other dot is part of the name (``startup_13.33us`` gives ``startup_13.33us.png``,
    not ``startup_13.png``)."""
    stem = Path(stem)
    if stem.suffix.lower() in (".png", ".svg"):
        stem = stem.with_suffix("")
    paths = [
        atomic_write(stem.with_name(f"{stem.name}.png"), lambda tmp: fig.savefig(tmp, format="png", dpi=110,
                                                                                 metadata={"Software": None})),
        atomic_write(stem.with_name(f"{stem.name}.svg"), lambda tmp: fig.savefig(tmp, format="svg",
                                                                                 metadata={"Date": None})),
    ]
    plt.close(fig)
    return paths


def plot_scenario(results: list[RunResult], stem: Path, title: str | None = None,
                  zoom: tuple[float, float] | None = None, styles: Styles | None = None) -> list[Path]:
    """Figure of one scenario with every controller overlaid; returns the PNG and SVG paths.

    Switched plants are drawn as PWM-period means (the ripple is 0.55 A / 91 mV peak to peak and
    would hide the controllers behind one another) over the faint instantaneous waveforms the
    metrics use; the left column shows the whole run (or ``zoom``), the right column the transient with
    its metrics marked (:func:`scenario_figure`).
    """
    if not results:
        raise ValueError("plot_scenario needs at least one run")
    info = results[0].info
    if title is None:
        title = f"{info.description}\n{info.plant}, control period {period_text(info.control_period)}"
    return save_figure(scenario_figure(results, title, zoom, period_means=info.plant_mode == "switched",
                                       styles=styles), stem)
