"""Commands that run the loop and handle its files: ``scenarios``, ``run``, ``inspect``, ``export``,
``plot``, ``compare``."""

from __future__ import annotations

import sys
from pathlib import Path

from cosim.base.errors import ConfigError
from cosim.cli.options import (
    DEFAULT_RESULTS,
    SEED_MAX,
    _add_implementation_option,
    _add_optimizer_options,
    _add_pi_and_duty_options,
    _add_plant_options,
    _check_duty_limits,
    _plant_binding,
    bounded,
    optimizer_options,
    output_dir,
    output_file,
    parse_period,
    seed_value,
)
from cosim.design.data_collection import MIN_SAMPLES
from cosim.design.vocabulary import CONTROLLERS, ON_DEMAND_SAMPLES, PAPER_PERIOD

#: image formats plot does not write (it writes PNG and SVG): an --out ending in one is refused, not renamed
OTHER_IMAGE_FORMATS = (".pdf", ".eps", ".ps", ".jpg", ".jpeg", ".tif", ".tiff", ".gif", ".bmp", ".webp")


def cmd_scenarios(args) -> int:
    from cosim.scenarios import SHIPPED_DIR, shipped_scenarios

    binding = _plant_binding(args)
    print(f"Shipped scenarios ({SHIPPED_DIR}), resolved against {binding.converter.origin}:")
    for s in shipped_scenarios(binding.converter):
        events = ", ".join(f"{e.time * 1e3:g} ms: " + ", ".join(
            [f"{k}={v:g}" for k, v in e.changes.items()] + [f"{k}={v:g}" for k, v in e.parameters.items()])
            for e in s.events) or "none"
        print(f"  {s.name:<16} {s.description}  [duration {s.duration * 1e3:g} ms, settle {s.settle * 1e3:g} ms; "
              f"events: {events}]")
    return 0


def cmd_run(args) -> int:
    from cosim.batch import Batch, run_batch, with_earlier_metrics, write_metrics
    from cosim.scenarios import PAPER_SCENARIOS, load_scenario

    _check_duty_limits(args)
    optimizer, rti_changes = optimizer_options(args)
    out_dir = output_dir(args.out)
    args.controller = args.controller or ["pi"]
    binding = _plant_binding(args)
    scenarios = [load_scenario(s, binding.converter, warn=True) for s in (args.scenarios or PAPER_SCENARIOS)]
    batch = Batch(binding, scenarios)
    batch.check_rates(args.control_period, args.record_period, args.interface)  # None: 10 us or a fixed step's
    batch.check_plant(args.interface)
    # the batch is checked: now the (possibly long) tuning and training. Imported here, not above: torch takes
    # seconds to load, and a refused scenario, binding or rate is answered without it
    from cosim.design.controller_factory import make_controllers
    from cosim.design.experiments import implemented
    from cosim.study.vocabulary import STUDY_STYLES

    controllers = make_controllers(args.controller, batch.binding, args.control_period, out_dir,
                                   duty_limits=(args.duty_min, args.duty_max), kp=args.kp, ki=args.ki,
                                   model_path=args.model, samples=args.samples, seed=args.seed,
                                   progress=args.progress, policy_path=args.policy, optimizer=optimizer,
                                   rti_changes=rti_changes)
    controllers = [implemented(c, args.implementation) for c in controllers]
    output = run_batch(batch, controllers, out_dir, styles=STUDY_STYLES, interface=args.interface,
                       record_period=args.record_period, seed=args.seed, figures=not args.no_figures,
                       progress=args.progress, stream=args.stream)
    if args.stream:
        for result in output.results:
            print(f"streamed {result.rows} rows to {result.streamed_to}")
        return 0
    stem = out_dir / "metrics" / f"metrics__{batch.binding.tag}"
    files = write_metrics(with_earlier_metrics(output.metrics, stem), stem)  # the folder's earlier runs kept
    columns = ["scenario", "controller", "rise_time_ms", "overshoot_pct", "settling_time_ms",
               "steady_state_error_pct", "iae_Vs", "controller_p99_us"]
    print(output.metrics[columns].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    print(f"wrote {len(output.files) + len(files)} files under {out_dir}/")
    _warn_implausible(output, batch.binding)
    return 0


def _warn_implausible(output, binding) -> None:
    """One warning line on stderr if runs look implausible (:func:`cosim.metrics.implausible_runs`)."""
    from cosim.metrics import implausible_runs

    found = implausible_runs(output.results, output.metrics)
    if not found:
        return
    hint = ("check the binding's roles and scales (fmu_value = scale * workbench_value + offset; a duty in percent "
            f"needs scale = 100) in {binding.source}" if binding.source is not None else
            "check the controller's gains and limits")
    print(f"warning: implausible runs on {binding.label}: {'; '.join(found)} -- {hint}", file=sys.stderr)


def cmd_inspect(args) -> int:
    from cosim.fmi.inspect import describe_fmu

    # a folder, an unwritable place, a name for another format or an existing file is refused before anything is read
    draft = output_file(args.draft_binding, (".toml",), "a plant-binding file is TOML", option="--draft-binding")
    if draft is not None and draft.exists():
        raise ConfigError(f"--draft-binding {draft} exists: a draft never replaces a file (a binding edited by hand "
                          "would be lost): remove it or give another name")
    if Path(args.fmu).suffix.lower() == ".toml":  # a binding file: its FMU, and the binding checked against it
        from cosim.fmi.binding_file import load_binding
        from cosim.master import check_set_up
        from cosim.scenarios import set_up_scenario

        if args.draft_binding:
            raise ConfigError(f"--draft-binding drafts a binding for an FMU; {args.fmu} is a binding already")
        binding = load_binding(args.fmu)  # every check, and a warning line if units contradict roles
        check_set_up(binding, [set_up_scenario(binding)])  # its parameters on the FMU, set up as a run's
        print(describe_fmu(binding.fmu_path))
        roles = [f"{role} -> {m.variable}" + (f" x {m.scale:g}" if m.scale != 1 else "")
                 + (f" + {m.offset:g}" if m.offset else "") for role, m in binding.roles.items()]
        print(f"\nbinding {args.fmu}: {', '.join(roles)}")
        return 0
    print(describe_fmu(args.fmu))
    if args.draft_binding:
        from cosim.fmi.archive import check_fmu
        from cosim.fmi.binding_file import guess_roles, unitless_guesses, write_draft_binding

        path = write_draft_binding(args.fmu, args.draft_binding)
        print(f"wrote a draft binding to {path}: the roles are guesses, check every one before use")
        by_unit = [f"{role} = {name}" + (f" (scale {scale:g})" if scale != 1 else "")
                   for role, (name, scale, reason) in guess_roles(check_fmu(args.fmu).model_description).items()
                   if not reason.startswith("name")]
        if by_unit:
            print(f"guessed from the declared units alone (no name matched): {', '.join(by_unit)}")
        unitless = unitless_guesses(args.fmu)
        if unitless:
            print(f"warning: {path}: the FMU declares no unit for {', '.join(unitless)}: the draft assumes a duty "
                  "0..1, volts, amperes and ohms -- a duty in percent needs scale = 100, a current in mA "
                  "scale = 1000", file=sys.stderr)
    return 0


def cmd_export(args) -> int:
    from cosim.base.files import atomic_write, atomic_write_json
    from cosim.results import read_run_file, write_parquet

    source = Path(args.run_file)
    result = read_run_file(source)
    out_dir = output_dir(args.out) if args.out else source.parent
    if (out_dir / f"{source.stem}.{args.to}").resolve() == source.resolve():  # it would replace what it reads
        raise ConfigError(f"export {source} --to {args.to} would write {source} itself (and replace it): give --out DIR "
                          "for a copy, or the other format")
    frame = result.frame.drop(columns=["controller_compute_time"], errors="ignore")
    if args.to == "csv":
        target = out_dir / f"{source.stem}.csv"
        atomic_write(target, lambda tmp: frame.to_csv(tmp, index=False))
        atomic_write_json(target.with_suffix(".json"), result.metadata)
    else:
        target = write_parquet(frame, result.metadata, out_dir / f"{source.stem}.parquet")
    print(f"wrote {target}")
    return 0


def cmd_plot(args) -> int:
    from cosim.compare import overlay
    from cosim.study.vocabulary import STUDY_STYLES

    out = output_file(args.out)
    if out.suffix.lower() in OTHER_IMAGE_FORMATS:
        raise ConfigError(f"--out {out} is invalid: plot writes PNG and SVG (FIG.png and FIG.svg), not "
                          f"{out.suffix[1:].upper()}: give FIG, FIG.png or FIG.svg")
    files = overlay(args.runs, out, title=args.title, styles=STUDY_STYLES)
    print(f"wrote {' and '.join(str(f) for f in files)}")
    return 0


def cmd_compare(args) -> int:
    from cosim.base.files import atomic_write
    from cosim.compare import comparison_table, overlay
    from cosim.metrics import WALLCLOCK_METRICS
    from cosim.study.vocabulary import STUDY_STYLES

    out_dir = output_dir(args.out)
    table = comparison_table(args.runs)  # every file read and checked before anything is written
    files = overlay(args.runs, out_dir / "compare", title=args.title, styles=STUDY_STYLES)
    deterministic = table.drop(columns=[c for c in WALLCLOCK_METRICS if c in table.columns])
    files.append(atomic_write(out_dir / "compare.csv", lambda tmp: deterministic.to_csv(tmp, index=False)))
    columns = ["run", "scenario", "rise_time_ms", "overshoot_pct", "settling_time_ms", "steady_state_error_pct",
               "iae_Vs", "peak_inductor_current_A", "output_voltage_ripple_mV", "inductor_current_ripple_A"]
    print(table[columns].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    print(f"wrote {', '.join(str(f) for f in files)}")
    return 0


def add_scenarios_parser(sub) -> None:
    p = sub.add_parser("scenarios", help="list the shipped scenarios",
                       description="List the shipped scenario files (TOML) with their events, resolved against a "
                                   "plant's converter spec (the shipped scenarios are templates: the start-up to the "
                                   "nominal output, the load step to 5/6 of the nominal load, ...): the built-in "
                                   "plant's Table II, or a binding file's [converter] table with --plant.")
    _add_plant_options(p)
    p.set_defaults(func=cmd_scenarios)


def add_run_parser(sub) -> None:
    p = sub.add_parser("run", help="run scenarios with controllers; write tables, metrics and figures",
                       description="Run scenarios in closed loop on the plant FMU. Writes per-run Parquet/CSV "
                                   "(+ JSON metadata) under OUT/runs, a metrics table under OUT/metrics and one "
                                   "figure per scenario (PNG + SVG) under OUT/figures.")
    p.add_argument("scenarios", nargs="*", metavar="SCENARIO",
                   help="shipped scenario name or path to a scenario TOML file (default: the paper's four); the "
                        "shipped ones are templates resolved against the plant's converter spec (a binding file's "
                        "[converter] table; Table II for the built-in plant): start-up to its nominal output, load "
                        "step to 5/6 of its nominal load, ...")
    p.add_argument("--controller", action="append", metavar="NAME|FMU|BINDING.toml|MODULE:CLASS",
                   help=f"controller(s) to run; repeat to overlay several (default: pi): {', '.join(CONTROLLERS)}, "
                        "a controller FMU with the workbench's role names (buck-cosim export-controller; named "
                        "'<file stem> (FMU)'), a controller-binding file for any other controller FMU, or your own "
                        "Python controller as module:Class or path/to/file.py:Class (docs/guide/python-controller.md); "
                        "FMUs and Python controllers run at their own sample period. nnpc trains its network on "
                        "demand (data collected with the tuned PI) unless --model")
    _add_plant_options(p)
    p.add_argument("--control-period", type=parse_period, default=PAPER_PERIOD, metavar="SECONDS",
                   help="controller sample period in s, e.g. 1e-3 (the paper) or 1/75e3 (one switching period) "
                        "(default: 1e-3)")
    p.add_argument("--record-period", type=parse_period, default=None, metavar="SECONDS",
                   help="recording step in s; need not divide the control period, except on a fixed-step FMU, whose "
                        "step it must be a multiple of (default: 1e-5, on a fixed-step FMU the nearest multiple of its "
                        "step)")
    _add_pi_and_duty_options(p, gains_default="tuned automatically")
    _add_optimizer_options(p)
    p.add_argument("--model", metavar="MODEL.pt", help="trained NN plant model for nnpc (default: train on demand)")
    p.add_argument("--policy", metavar="POLICY.pt",
                   help="distilled policy for nnpc-explicit (buck-cosim distill; default: distilled on demand from "
                        "the nnpc network, about a minute at 13.33 us)")
    p.add_argument("--samples", type=bounded(int, MIN_SAMPLES), default=None,
                   help=f"samples of PI data an NNPC's network is identified from when trained on demand"
                        f" (>= {MIN_SAMPLES}; default: {ON_DEMAND_SAMPLES}); refused where none is")
    p.add_argument("--seed", type=seed_value, default=0,
                   help=f"random seed for data collection and training, 0 .. {SEED_MAX} (default: 0)")
    p.add_argument("--out", default=str(DEFAULT_RESULTS / "runs-cli"), metavar="DIR",
                   help="output folder (default: results/runs-cli, relative to the current folder)")
    p.add_argument("--no-figures", action="store_true", help="skip the figures")
    _add_implementation_option(p)
    p.add_argument("--stream", action="store_true",
                   help="for long runs: write rows to Parquet while running, in bounded memory (no CSV, metrics "
                        "or figures)")
    p.set_defaults(func=cmd_run)


def add_inspect_parser(sub) -> None:
    p = sub.add_parser("inspect", help="describe any FMU (and draft a binding file for it)",
                       description="Check an FMU archive and print its FMI version, interfaces, platforms and "
                                   "variables (causality, variability, unit, start value). Given a plant-binding "
                                   "file, describe its FMU and check the binding against it (a warning line if a "
                                   "unit the FMU declares contradicts a role or its scale).")
    p.add_argument("fmu", metavar="FMU|BINDING.toml", help="path to a .fmu file, or a plant-binding file")
    p.add_argument("--draft-binding", metavar="OUT.toml",
                   help="also write a draft plant-binding file, roles guessed from names and units (a new .toml "
                        "file: an existing one is never replaced)")
    p.set_defaults(func=cmd_inspect)


def add_export_parser(sub) -> None:
    p = sub.add_parser("export", help="convert a run file between Parquet and CSV",
                       description="Read a run (.parquet, or .csv with its .json sidecar) and write it in the "
                                   "other format, metadata included.")
    p.add_argument("run_file", help="a run's .parquet or .csv file")
    p.add_argument("--to", choices=["csv", "parquet"], required=True, help="target format")
    p.add_argument("--out", metavar="DIR", help="output folder (default: beside the input)")
    p.set_defaults(func=cmd_export)


def add_plot_parser(sub) -> None:
    p = sub.add_parser("plot", help="overlay runs from any folders in one figure (CSV or Parquet runs)",
                       description="Draw runs written by run, reproduce, a sweep's traces or a Python controller's "
                                   "write_run (each a .parquet, or a .csv with its .json) overlaid in the run figure: "
                                   "output voltage, inductor current and duty cycle, the whole run beside the "
                                   "transient with overshoot, settling band and settling time marked. Runs that share "
                                   "a controller name are labelled with their folder. Writes FIG.png and FIG.svg.")
    p.add_argument("runs", nargs="+", metavar="RUN", help="run files (.parquet, or .csv with its .json beside it)")
    p.add_argument("--out", required=True, metavar="FIG",
                   help="the figure to write: FIG.png and FIG.svg (FIG.png or FIG.svg stands for the pair)")
    p.add_argument("--title", help="figure title (default: the scenarios and plants)")
    p.set_defaults(func=cmd_plot)


def add_compare_parser(sub) -> None:
    p = sub.add_parser("compare", help="overlay runs from any folders and compare their metrics",
                       description="Like plot, and the runs' metrics side by side: printed, and written with the "
                                   "figure to DIR (compare.png, compare.svg, compare.csv: one row per run, its label "
                                   "and file, every metric of cosim/metrics.py but the wall-clock ones).")
    p.add_argument("runs", nargs="+", metavar="RUN", help="run files (.parquet, or .csv with its .json beside it)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--title", help="figure title (default: the scenarios and plants)")
    p.set_defaults(func=cmd_compare)
