"""Figures like the paper's Figures 8-10: output voltage and inductor current, controllers overlaid.

PNG for reports and SVG for papers; the SVG is written without a date and with a fixed hash salt
so the same results give the same file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from cosim.base.files import atomic_write  # noqa: E402
from cosim.base.labels import period_text  # noqa: E402
from cosim.results import RunResult  # noqa: E402

plt.rcParams["svg.hashsalt"] = "buck-cosim"
#: controller name -> (colour, line style); controllers not named get matplotlib's colour cycle
Styles = Mapping[str, tuple[str, object]]
#: a run whose output ends this far from the reference (relative) does not set the axis limits
DIVERGED = 0.05
ZOOM_BEFORE, ZOOM_AFTER = 1e-3, 10e-3  # [s] the zoom window around a long run's main event




def scenario_figure(results: list[RunResult], title: str, zoom: tuple[float, float] | None = None,
                    period_means: bool = False, styles: Styles | None = None):
    """Two stacked panels (output voltage, inductor current) against time in ms.

    ``period_means``: draw the PWM-period means (the ``measured_*`` columns) instead of the
    instantaneous switched waveforms, whose ripple would hide the controllers behind each other.
    """
    v_column, i_column = ("measured_output_voltage", "measured_inductor_current") if period_means \
        else ("output_voltage", "inductor_current")
    fig, (ax_v, ax_i) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True, constrained_layout=True)
    reference_drawn = False
    limits_v, limits_i, clipped = [], [], []
    for result in results:
        frame = result.frame
        if zoom is not None:
            frame = frame[(frame["time"] >= zoom[0]) & (frame["time"] <= zoom[1])]
        t_ms = frame["time"].to_numpy() * 1e3
        name = result.info.controller
        color, style = (styles or {}).get(name, (None, "-"))
        if not reference_drawn:
            ax_v.plot(t_ms, frame["reference"], "k--", linewidth=1.0, label="reference")
            reference_drawn = True
        lines = [ax_v.plot(t_ms, frame[v_column], color=color, linestyle=style, linewidth=1.2, label=name)[0],
                 ax_i.plot(t_ms, frame[i_column], color=color, linestyle=style, linewidth=1.2, label=name)[0]]
        final_error = abs(frame[v_column].iloc[-1] - frame["reference"].iloc[-1])
        if final_error <= DIVERGED * max(abs(frame["reference"].iloc[-1]), 1.0):
            limits_v.append((frame[v_column].min(), frame[v_column].max()))
            limits_i.append((frame[i_column].min(), frame[i_column].max()))
        else:  # a run that never settles: faint, so it does not hide the others
            clipped.append(name)
            for line in lines:
                line.set_alpha(0.35)
                line.set_linewidth(0.8)
    # a diverging controller must not squash the others into a line: scale to the settled runs
    for ax, limits in ((ax_v, limits_v), (ax_i, limits_i)):
        if limits and clipped:
            low, high = min(l for l, _ in limits), max(h for _, h in limits)
            margin = 0.08 * (high - low or 1.0)
            ax.set_ylim(low - margin, high + margin)
    if clipped:
        title += f"\n(axes scaled to the settled runs; {', '.join(clipped)} {'leaves' if len(clipped) == 1 else 'leave'} the plot)"
    mean = "\n(PWM-period mean)" if period_means else ""  # two short lines: the panels' labels must not overlap
    ax_v.set_ylabel(f"output voltage $v_o$ [V]{mean}")
    ax_i.set_ylabel(f"inductor current $i_L$ [A]{mean}")
    ax_i.set_xlabel("time [ms]")
    ax_v.set_title(title, fontsize=10)
    for ax in (ax_v, ax_i):
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    return fig


def save_figure(fig, stem: Path) -> list[Path]:
    """Write ``<stem>.png`` (150 dpi) and ``<stem>.svg`` atomically; close the figure."""
    stem = Path(stem)
    paths = [
        atomic_write(stem.with_suffix(".png"), lambda tmp: fig.savefig(tmp, format="png", dpi=110,
                                                                       metadata={"Software": None})),
        atomic_write(stem.with_suffix(".svg"), lambda tmp: fig.savefig(tmp, format="svg",
                                                                       metadata={"Date": None})),
    ]
    plt.close(fig)
    return paths


def default_zoom(result: RunResult) -> tuple[float, float] | None:
    """Around the scenario's main event when the run is long: from 1 ms before it to 10 ms after
    (a 1 ms loop has settled by then); short runs (the fast-rate ones) are shown whole."""
    t0 = result.info.metrics_start
    end = float(result.frame["time"].iloc[-1])
    if end - t0 <= ZOOM_AFTER:
        return None
    return max(0.0, t0 - ZOOM_BEFORE), min(end, t0 + ZOOM_AFTER)


def plot_scenario(results: list[RunResult], stem: Path, title: str | None = None,
                  zoom: tuple[float, float] | None = None, styles: Styles | None = None) -> list[Path]:
    """Figure of one scenario with every controller overlaid; returns the PNG and SVG paths.

    Switched plants are drawn as PWM-period means (the ripple is 0.55 A / 91 mV peak to peak and
    would hide the controllers behind one another); long runs are zoomed on their event.
    """
    if not results:
        raise ValueError("plot_scenario needs at least one run")
    info = results[0].info
    zoom = zoom if zoom is not None else default_zoom(results[0])
    if title is None:
        title = f"{info.description}\n{info.plant}, control period {period_text(info.control_period)}"
    return save_figure(scenario_figure(results, title, zoom, period_means=info.plant_mode == "switched",
                                       styles=styles), stem)
