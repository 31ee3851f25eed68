"""Figures like the paper's Figures 8-10: output voltage and inductor current, controllers overlaid.

PNG for reports and SVG for papers; the SVG is written without a date and with a fixed hash salt
so the same results give the same file.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from cosim.results import RunResult, atomic_write  # noqa: E402

plt.rcParams["svg.hashsalt"] = "buck-cosim"
COLORS = {"PI": "tab:blue", "NNPC": "tab:red", "MPC-oracle": "tab:green", "MPC-mismatched": "tab:purple"}


def _label(result: RunResult) -> str:
    return str(result.metadata.get("controller", {}).get("name", "controller"))


def scenario_figure(results: list[RunResult], title: str, zoom: tuple[float, float] | None = None):
    """Two stacked panels (output voltage, inductor current) against time in ms."""
    fig, (ax_v, ax_i) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True, constrained_layout=True)
    reference_drawn = False
    for result in results:
        frame = result.frame
        if zoom is not None:
            frame = frame[(frame["time"] >= zoom[0]) & (frame["time"] <= zoom[1])]
        t_ms = frame["time"].to_numpy() * 1e3
        name = _label(result)
        color = COLORS.get(name)
        if not reference_drawn:
            ax_v.plot(t_ms, frame["reference"], "k--", linewidth=1.0, label="reference")
            reference_drawn = True
        ax_v.plot(t_ms, frame["output_voltage"], color=color, linewidth=1.2, label=name)
        ax_i.plot(t_ms, frame["inductor_current"], color=color, linewidth=1.2, label=name)
    ax_v.set_ylabel("output voltage $v_o$ [V]")
    ax_i.set_ylabel("inductor current $i_L$ [A]")
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
        atomic_write(stem.with_suffix(".png"), lambda tmp: fig.savefig(tmp, format="png", dpi=150,
                                                                       metadata={"Software": None})),
        atomic_write(stem.with_suffix(".svg"), lambda tmp: fig.savefig(tmp, format="svg",
                                                                       metadata={"Date": None})),
    ]
    plt.close(fig)
    return paths


def plot_scenario(results: list[RunResult], stem: Path, title: str | None = None,
                  zoom: tuple[float, float] | None = None) -> list[Path]:
    """Figure of one scenario with every controller overlaid; returns the PNG and SVG paths."""
    if not results:
        raise ValueError("plot_scenario needs at least one run")
    meta = results[0].metadata
    if title is None:
        period = meta.get("rates", {}).get("control_period_s", float("nan"))
        shown = f"{period * 1e3:.4g} ms" if period >= 1e-3 else f"{period * 1e6:.4g} µs"
        title = (f"{meta.get('scenario', {}).get('description', '')}\n{meta.get('plant', {}).get('label', '')}, "
                 f"control period {shown}")
    return save_figure(scenario_figure(results, title, zoom), stem)
