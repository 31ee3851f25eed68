"""Like for like: the current-mode controller with and without the one-sample computation delay (issue 25).

The classical baselines carry the computation delay of a microcontroller (the duty computed from the
sample at t_k is applied at t_(k+1)); the NNPC applies its duty in the sample it computes it. This
command designs the current-mode controller both ways by the same method
(:func:`cosim.design.classical_design.design_current_mode` and ``design_current_mode_no_delay``) and runs
both at the nominal point (the paper's four scenarios, time-compressed at 1/fsw) and on the envelope map
(on the sweep engine, :func:`cosim.study.envelope.run_entries`)::

    python -m cosim.study.fairness --out DIR [--workers 2] [--no-map]

It writes ``DIR/nominal.csv`` and ``DIR/map.csv`` and prints the crossovers, the nominal runs and the shares.
The reproduction maps the delay-free design as the row ``CMC (no delay)`` (``tuning/current-mode-no-delay__*``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd


def designs():
    """The two current-mode designs on the nominal switched plant at 1/fsw: (with the delay, without)."""
    from cosim.design.classical_design import design_current_mode, design_current_mode_no_delay, targets_for
    from cosim.design.controller_factory import true_parameters
    from cosim.design.plants import plant_binding
    from cosim.design.vocabulary import CURRENT_MODE, CURRENT_MODE_NO_DELAY, SWITCHING_PERIOD

    binding = plant_binding("nominal", "switched")
    parameters, targets = true_parameters(binding), targets_for(binding, SWITCHING_PERIOD)
    return (design_current_mode(parameters, targets, CURRENT_MODE),
            design_current_mode_no_delay(parameters, targets, CURRENT_MODE_NO_DELAY))


def nominal(controllers) -> pd.DataFrame:
    """The paper's four scenarios at 12 V / 6 Ohm / 48 V on the switched plant for each controller (C twins)."""
    from cosim.design.experiments import implemented, scenarios_for
    from cosim.design.plants import plant_binding
    from cosim.design.vocabulary import SWITCHING_PERIOD
    from cosim.master import simulate
    from cosim.metrics import run_metrics

    binding = plant_binding("nominal", "switched")
    rows = []
    for controller in controllers:
        for scenario in scenarios_for(SWITCHING_PERIOD, spec=binding.converter):
            m = run_metrics(simulate(binding, implemented(controller), scenario, record_period=1e-5))
            rows.append({"controller": controller.name, "scenario": scenario.name, "iae_Vs": m["iae_Vs"],
                         "overshoot_pct": m["overshoot_pct"], "settling_time_ms": m["settling_time_ms"]})
    return pd.DataFrame(rows)


def main(argv=None) -> None:
    from cosim.design.classical_design import write_design
    from cosim.design.sweeps.spec import ControllerEntry
    from cosim.study import envelope

    parser = argparse.ArgumentParser(prog="python -m cosim.study.fairness", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--no-map", action="store_true")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    pair = designs()
    for d in pair:
        loops = "; ".join(f"{k} {v['crossover_hz']:.0f} Hz, PM {v['phase_margin_deg']:.1f} deg, GM "
                          f"{v['gain_margin_db']:.1f} dB" for k, v in d.loops.items())
        print(f"{d.controller.name}: {loops}")
    runs = nominal([d.controller for d in pair])
    runs.to_csv(args.out / "nominal.csv", index=False, float_format="%.6g")
    print(runs.to_string(index=False))
    if args.no_map:
        return
    entries = []
    for d in pair:
        path = write_design(d, args.out / f"{d.controller.name.replace(' ', '-').replace('(', '').replace(')', '')}.json")
        entries.append(ControllerEntry("current-mode", d.controller.name, design=path))
    steps = envelope.run_entries(entries, args.out / "sweep", workers=args.workers)
    steps.to_csv(args.out / "map.csv", index=False, float_format="%.8g")
    points = envelope.point_results(steps)
    light = points["load_Ohm"] >= 40
    for name, p in points.groupby("controller", sort=False):
        print(f"{name}: {100 * p['meets'].mean():.0f} % of the map (loads < 40 Ohm "
              f"{100 * p[~light.loc[p.index]]['meets'].mean():.0f} %, >= 40 Ohm "
              f"{100 * p[light.loc[p.index]]['meets'].mean():.0f} %); {envelope._failure_causes(points, name)}")


if __name__ == "__main__":
    main()
