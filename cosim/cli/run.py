"""Commands that run the loop and handle its files: ``scenarios``, ``run``, ``inspect``, ``export``."""

from __future__ import annotations

from cosim.base.errors import ConfigError
from cosim.cli.options import (
    DEFAULT_RESULTS,
    SEED_MAX,
    _add_implementation_option,
    _add_pi_and_duty_options,
    _add_plant_options,
    _check_duty_limits,
    _plant_binding,
    bounded,
    input_file,
    output_dir,
    output_file,
    parse_period,
    seed_value,
)
from cosim.study.data_collection import MIN_SAMPLES
from cosim.study.vocabulary import CONTROLLERS, PAPER_PERIOD


def cmd_scenarios(args) -> int:
    from cosim.scenarios import SHIPPED_DIR, shipped_scenarios

    print(f"Shipped scenarios ({SHIPPED_DIR}):")
    for s in shipped_scenarios():
        events = ", ".join(f"{e.time * 1e3:g} ms: " + ", ".join(f"{k}={v:g}" for k, v in e.changes.items())
                           for e in s.events) or "none"
        print(f"  {s.name:<16} {s.description}  [duration {s.duration * 1e3:g} ms, settle {s.settle * 1e3:g} ms; "
              f"events: {events}]")
    return 0


def cmd_run(args) -> int:
    from cosim.batch import Batch, run_batch, write_metrics
    from cosim.scenarios import PAPER_SCENARIOS, load_scenario
    from cosim.study.controller_factory import make_controllers
    from cosim.study.experiments import implemented
    from cosim.study.vocabulary import CONTROLLER_STYLES

    _check_duty_limits(args)
    out_dir = output_dir(args.out)
    args.controller = args.controller or ["pi"]
    batch = Batch(_plant_binding(args), [load_scenario(s) for s in (args.scenarios or PAPER_SCENARIOS)])
    batch.check_rates(args.control_period, args.record_period)
    # the batch is checked: now the (possibly long) tuning and training
    controllers = make_controllers(args.controller, batch.binding, args.control_period, out_dir,
                                   duty_limits=(args.duty_min, args.duty_max), kp=args.kp, ki=args.ki,
                                   model_path=args.model, samples=args.samples, seed=args.seed,
                                   progress=args.progress, policy_path=args.policy)
    controllers = [implemented(c, args.implementation) for c in controllers]
    output = run_batch(batch, controllers, out_dir, styles=CONTROLLER_STYLES, interface=args.interface,
                       record_period=args.record_period, seed=args.seed, figures=not args.no_figures,
                       progress=args.progress, stream=args.stream)
    if args.stream:
        for result in output.results:
            print(f"streamed {result.rows} rows to {result.streamed_to}")
        return 0
    files = write_metrics(output.metrics, out_dir / "metrics" / f"metrics__{batch.binding.tag}")
    columns = ["scenario", "controller", "rise_time_ms", "overshoot_pct", "settling_time_ms",
               "steady_state_error_pct", "iae_Vs", "controller_p99_us"]
    print(output.metrics[columns].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    print(f"wrote {len(output.files) + len(files)} files under {out_dir}/")
    return 0


def cmd_inspect(args) -> int:
    from cosim.fmi.inspect import describe_fmu

    output_file(args.draft_binding)  # a folder or an unwritable place is refused before anything is read
    print(describe_fmu(args.fmu))
    if args.draft_binding:
        from cosim.fmi.binding_file import write_draft_binding

        path = write_draft_binding(args.fmu, args.draft_binding)
        print(f"wrote a draft binding to {path}: the roles are guesses, check every one before use")
    return 0


def cmd_export(args) -> int:
    from cosim.base.files import atomic_write, atomic_write_json
    from cosim.results import read_run, write_parquet

    source = input_file(args.run_file, "run file")
    try:
        result = read_run(source)
    except (ValueError, OSError) as error:
        raise ConfigError(f"{source}: cannot read run ({error})") from None
    out_dir = output_dir(args.out) if args.out else source.parent
    frame = result.frame.drop(columns=["controller_compute_time"], errors="ignore")
    if args.to == "csv":
        target = out_dir / f"{source.stem}.csv"
        atomic_write(target, lambda tmp: frame.to_csv(tmp, index=False))
        atomic_write_json(target.with_suffix(".json"), result.metadata)
    else:
        target = write_parquet(frame, result.metadata, out_dir / f"{source.stem}.parquet")
    print(f"wrote {target}")
    return 0


def add_scenarios_parser(sub) -> None:
    p = sub.add_parser("scenarios", help="list the shipped scenarios",
                       description="List the shipped scenario files (TOML) with their events.")
    p.set_defaults(func=cmd_scenarios)


def add_run_parser(sub) -> None:
    p = sub.add_parser("run", help="run scenarios with controllers; write tables, metrics and figures",
                       description="Run scenarios in closed loop on the plant FMU. Writes per-run Parquet/CSV "
                                   "(+ JSON metadata) under OUT/runs, a metrics table under OUT/metrics and one "
                                   "figure per scenario (PNG + SVG) under OUT/figures.")
    p.add_argument("scenarios", nargs="*", metavar="SCENARIO",
                   help="shipped scenario name or path to a scenario TOML file (default: the paper's four)")
    p.add_argument("--controller", action="append", metavar="NAME|FMU|BINDING.toml",
                   help=f"controller(s) to run; repeat to overlay several (default: pi): {', '.join(CONTROLLERS)}, "
                        "a controller FMU with the workbench's role names (buck-cosim export-controller), or a "
                        "controller-binding file for any other controller FMU (it runs at its own sample period). "
                        "nnpc trains its network on demand (data collected with the tuned PI) unless --model")
    _add_plant_options(p)
    p.add_argument("--control-period", type=parse_period, default=PAPER_PERIOD, metavar="SECONDS",
                   help="controller sample period in s, e.g. 1e-3 (the paper) or 1/75e3 (one switching period) "
                        "(default: 1e-3)")
    p.add_argument("--record-period", type=parse_period, default=1e-5, metavar="SECONDS",
                   help="recording step in s; need not divide the control period (default: 1e-5)")
    _add_pi_and_duty_options(p, gains_default="tuned automatically")
    p.add_argument("--model", metavar="MODEL.pt", help="trained NN plant model for nnpc (default: train on demand)")
    p.add_argument("--policy", metavar="POLICY.pt",
                   help="distilled policy for nnpc-explicit (buck-cosim distill; default: distilled on demand from "
                        "the nnpc network, about a minute at 13.33 us)")
    p.add_argument("--samples", type=bounded(int, MIN_SAMPLES), default=10_000,
                   help=f"samples collected when nnpc trains on demand (>= {MIN_SAMPLES}; default: 10000)")
    p.add_argument("--seed", type=seed_value, default=0,
                   help=f"random seed for data collection and training, 0 .. {SEED_MAX} (default: 0)")
    p.add_argument("--out", default=str(DEFAULT_RESULTS / "runs-cli"), metavar="DIR",
                   help="output folder (default: results/runs-cli)")
    p.add_argument("--no-figures", action="store_true", help="skip the figures")
    _add_implementation_option(p)
    p.add_argument("--stream", action="store_true",
                   help="for long runs: write rows to Parquet while running, in bounded memory (no CSV, metrics "
                        "or figures)")
    p.set_defaults(func=cmd_run)


def add_inspect_parser(sub) -> None:
    p = sub.add_parser("inspect", help="describe any FMU (and draft a binding file for it)",
                       description="Check an FMU archive and print its FMI version, interfaces, platforms and "
                                   "variables (causality, variability, unit, start value).")
    p.add_argument("fmu", help="path to a .fmu file")
    p.add_argument("--draft-binding", metavar="OUT.toml",
                   help="also write a draft plant-binding file, roles guessed from names and units")
    p.set_defaults(func=cmd_inspect)


def add_export_parser(sub) -> None:
    p = sub.add_parser("export", help="convert a run file between Parquet and CSV",
                       description="Read a run (.parquet, or .csv with its .json sidecar) and write it in the "
                                   "other format, metadata included.")
    p.add_argument("run_file", help="a run's .parquet or .csv file")
    p.add_argument("--to", choices=["csv", "parquet"], required=True, help="target format")
    p.add_argument("--out", metavar="DIR", help="output folder (default: beside the input)")
    p.set_defaults(func=cmd_export)
