"""``buck-cosim``: the workbench's command line.

Every user mistake ends in one line ``error: ...`` on stderr and a non-zero exit code:
2 bad input or configuration, 3 a plant or controller fault during a run, 4 the FMU build
failed, 130 interrupted (Ctrl-C or SIGTERM). Completed runs are kept on disk in every case.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path

from cosim.base.errors import ConfigError, WorkbenchError
from cosim.fmi.binding import PLANT_MODE_CODES
from cosim.study.vocabulary import (
    CONTROLLERS,
    DITHER_FAST,
    DITHER_SLOW,
    PAPER_PERIOD,
    PLANT_VARIANTS,
    SENSORS,
    TRANSIENT_WITHIN_SAMPLE_PERIOD,
)

DEFAULT_RESULTS = Path("results")


class OneLineParser(argparse.ArgumentParser):
    """Usage mistakes end in one line on stderr (exit code 2), like every other user error."""

    def error(self, message: str):
        self.exit(2, f"error: {self.prog}: {message} (see {self.prog} --help)\n")


def output_dir(text: str | None) -> Path | None:
    """A folder results go to: refused at once if it cannot be one (not after hours of work)."""
    if text is None:
        return None
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"output folder {path} is an existing file: expected a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ConfigError(f"cannot create output folder {path}: {error.strerror}") from None
    if not os.access(path, os.W_OK):
        raise ConfigError(f"output folder {path} is not writable")
    return path


def output_file(text: str | None) -> Path | None:
    """A file a result goes to: its folder must be creatable and writable, and it must not be a folder."""
    if text is None:
        return None
    path = Path(text)
    if path.is_dir():
        raise ConfigError(f"output file {path} is a folder: expected a file name")
    output_dir(str(path.parent))
    return path


def parse_period(text: str) -> float:
    """A period in seconds: ``1e-3``, ``0.001`` or a fraction such as ``1/75e3``."""
    try:
        if "/" in text:
            numerator, denominator = text.split("/", 1)
            value = float(numerator) / float(denominator)
        else:
            value = float(text)
    except (ValueError, ZeroDivisionError):
        raise argparse.ArgumentTypeError(f"{text!r} is not a period in seconds (e.g. 1e-3 or 1/75e3)") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"period {text} s is invalid: expected a finite value > 0")
    return value


# ---------------------------------------------------------------------------------------------
# Commands


def cmd_scenarios(args) -> int:
    from cosim.scenarios import SHIPPED_DIR, shipped_scenarios

    print(f"Shipped scenarios ({SHIPPED_DIR}):")
    for s in shipped_scenarios():
        events = ", ".join(f"{e.time * 1e3:g} ms: " + ", ".join(f"{k}={v:g}" for k, v in e.changes.items())
                           for e in s.events) or "none"
        print(f"  {s.name:<16} {s.description}  [duration {s.duration * 1e3:g} ms, settle {s.settle * 1e3:g} ms; "
              f"events: {events}]")
    return 0


def _plant_binding(args):
    if getattr(args, "plant", None):
        from cosim.fmi.binding_file import load_binding

        return load_binding(args.plant)
    from cosim.study.experiments import plant_binding

    return plant_binding(args.variant, args.mode, args.sensor)


def cmd_run(args) -> int:
    from cosim.batch import Batch, run_batch, write_metrics
    from cosim.scenarios import PAPER_SCENARIOS, load_scenario
    from cosim.study.controller_factory import make_controllers
    from cosim.study.experiments import implemented
    from cosim.study.vocabulary import CONTROLLER_STYLES

    if not (0.0 <= args.duty_min < args.duty_max <= 1.0):
        raise ConfigError(f"duty limits ({args.duty_min}, {args.duty_max}) are invalid: expected 0 <= min < max <= 1")
    out_dir = output_dir(args.out)
    batch = Batch(_plant_binding(args), [load_scenario(s) for s in (args.scenarios or PAPER_SCENARIOS)])
    # the batch is checked: now the (possibly long) tuning and training
    controllers = make_controllers(args.controller, batch.binding, args.control_period, out_dir,
                                   duty_limits=(args.duty_min, args.duty_max), kp=args.kp, ki=args.ki,
                                   model_path=args.model, samples=args.samples, seed=args.seed,
                                   progress=args.progress)
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

    print(describe_fmu(args.fmu))
    if args.draft_binding:
        from cosim.fmi.binding_file import write_draft_binding

        path = write_draft_binding(args.fmu, args.draft_binding)
        print(f"wrote a draft binding to {path}: the roles are guesses, check every one before use")
    return 0


def cmd_export(args) -> int:
    from cosim.base.files import atomic_write
    from cosim.results import read_run, write_parquet

    source = Path(args.run_file)
    if not source.is_file():
        raise ConfigError(f"run file {source} does not exist")
    try:
        result = read_run(source)
    except (ValueError, OSError) as error:
        raise ConfigError(f"{source}: cannot read run ({error})") from None
    out_dir = output_dir(args.out) if args.out else source.parent
    frame = result.frame.drop(columns=["controller_compute_time"], errors="ignore")
    if args.to == "csv":
        import json

        target = out_dir / f"{source.stem}.csv"
        atomic_write(target, lambda tmp: frame.to_csv(tmp, index=False))
        atomic_write(target.with_suffix(".json"),
                     lambda tmp: tmp.write_text(json.dumps(result.metadata, indent=2, sort_keys=True) + "\n"))
    else:
        target = write_parquet(frame, result.metadata, out_dir / f"{source.stem}.parquet")
    print(f"wrote {target}")
    return 0


def cmd_build_fmu(args) -> int:
    from plant_fmu import export_fmus, fmu_path, source_fmu_path

    if args.output:
        binary, source = export_fmus(output_dir(args.output), force=args.force)
    else:
        binary, source = fmu_path(force=args.force), source_fmu_path(force=args.force)
    print(f"co-simulation + model exchange FMU: {binary}")
    print(f"source FMU (compile with any FMI 2.0 tool): {source}")
    return 0


def cmd_tune_pi(args) -> int:
    from cosim.base.files import atomic_write_text
    from cosim.study.pi_tuning import tune_pi

    output_file(args.out)
    binding = _plant_binding(args)
    tuning = tune_pi(binding, args.control_period, progress=args.progress)
    print(f"Kp = {tuning.kp:.6g} 1/V, Ki = {tuning.ki:.6g} 1/(V s) at Ts = {args.control_period * 1e6:.4g} us "
          f"(cost {tuning.cost:.4g} V^2 s, worst overshoot {tuning.worst_overshoot_pct:.3g} %, "
          f"{tuning.evaluations} simulations)")
    if args.out:
        atomic_write_text(Path(args.out), tuning.to_json() + "\n")
        print(f"wrote {args.out}")
    return 0


def cmd_collect(args) -> int:
    from cosim.study.controller_factory import tuned_pi
    from cosim.study.data_collection import collect, save_samples
    from cosim.study.experiments import collection_settings

    output_file(args.out)
    work_dir = output_dir(args.work_dir)
    binding = _plant_binding(args)
    pi = tuned_pi(binding, args.control_period, work_dir, args.progress)
    settings = collection_settings(args.control_period, args.samples, args.seed, args.excitation)
    data = collect(binding, pi.controller(), settings, progress=args.progress)
    save_samples(data, Path(args.out))
    print(f"wrote {len(data)} samples ({', '.join(data.columns)}) to {args.out}")
    return 0


def cmd_train(args) -> int:
    from controllers.nn_model import NNConfig, TrainingSettings, extra_columns, save_model, train
    from cosim.results import read_parquet

    try:  # arguments first, before any file is read
        config = NNConfig(hidden=tuple(args.hidden), activation=args.activation, delays=args.delays,
                          extra_signals=tuple(args.extra or ()), residual=args.residual)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    output_file(args.out)
    source = Path(args.data)
    if not source.is_file():
        raise ConfigError(f"data file {source} does not exist (write one with buck-cosim collect-data)")
    try:
        frame, metadata = read_parquet(source)
    except Exception as error:
        raise ConfigError(f"{source}: cannot read samples ({str(error).splitlines()[0]})") from None
    needed = ["measured_inductor_current", "measured_output_voltage", "duty_cycle", *extra_columns(config)]
    missing = [c for c in needed if c not in frame.columns]
    if missing:
        raise ConfigError(f"{source} lacks column(s) {', '.join(missing)} needed by {config.label}")
    try:
        model = train(frame, config, TrainingSettings(seed=args.seed), progress=args.progress,
                      metadata={"control_period_s": metadata.get("control_period_s"), "plant": metadata.get("plant"),
                                "data_file": str(source), "seed": args.seed})
    except ValueError as error:
        raise ConfigError(f"{source}: {error}") from None
    save_model(model, Path(args.out))
    rmse = model.metadata["held_out_rmse"]
    print(f"{config.label}: held-out one-step RMSE {rmse['one_step_rmse_voltage_V'] * 1e3:.2f} mV, "
          f"{rmse['one_step_rmse_current_A'] * 1e3:.2f} mA; 10-step {rmse.get('10_step_rmse_voltage_V', float('nan')) * 1e3:.2f} mV")
    print(f"wrote {args.out}")
    return 0


def cmd_reproduce(args) -> int:
    from cosim.study.reproduce import reproduce

    if args.workers < 1:
        raise ConfigError(f"--workers {args.workers} is invalid: expected >= 1")
    output_dir(args.out)
    from cosim.study.reproduce import FULL, QUICK

    if args.plant:
        from cosim.fmi.binding_file import load_binding

        load_binding(args.plant)  # refuse a bad binding before any work starts
    reproduce(Path(args.out), workers=args.workers, resume=args.resume, seed=args.seed,
              implementation=args.implementation,
              profile=QUICK if args.quick else FULL, binding_file=args.plant,
              control_periods=tuple(args.control_period or ()))
    return 0


def cmd_sweep(args) -> int:
    from cosim.study.sweeps.spec import load_sweep
    from cosim.study.sweeps.sweep import raise_if_failed, run_sweep

    spec = load_sweep(args.spec)  # the file first: its mistakes before the folder is touched
    if args.scheduler_timeout is not None and not args.scheduler_timeout > 0:
        raise ConfigError(f"--scheduler-timeout {args.scheduler_timeout} s is invalid: expected > 0")
    outcome = run_sweep(spec, output_dir(args.out), scheduler=args.scheduler, workers=args.workers,
                        resume=args.resume, progress=args.progress, connect_timeout=args.scheduler_timeout)
    print(f"{outcome.planned} runs ({outcome.done_before} done earlier, {outcome.computed} now, {outcome.failed} "
          f"failed); summary: {outcome.out_dir / 'SWEEP.md'}")
    raise_if_failed(outcome)
    return 0


def cmd_bench(args) -> int:
    from cosim.benchmarks import BENCHMARKS, run_benchmarks

    unknown = [name for name in args.only or [] if name not in BENCHMARKS]
    if unknown:
        raise ConfigError(f"unknown benchmark(s) {', '.join(unknown)}: expected {', '.join(BENCHMARKS)}")
    output_dir(args.out)
    command = "buck-cosim bench" + "".join(f" --only {n}" for n in args.only or [])
    md_path, csv_path = run_benchmarks(Path(args.out), quick=args.quick, only=args.only, command=command)
    print(md_path.read_text())
    print(f"wrote {md_path} and {csv_path}")
    return 0


# ---------------------------------------------------------------------------------------------
# Parser


def _add_plant_options(parser) -> None:
    parser.add_argument("--mode", choices=list(PLANT_MODE_CODES), default="averaged",
                        help="built-in plant: averaged model (eq. 3, with DCM) or switched (PWM, ideal switch and "
                             "diode) (default: averaged)")
    parser.add_argument("--variant", choices=list(PLANT_VARIANTS), default="nominal",
                        help="built-in plant parameters: Table II, or L +20 %%, C -20 %% with parasitics "
                             "(default: nominal)")
    parser.add_argument("--sensor", choices=list(SENSORS), default="average",
                        help="what controllers measure: the mean over the last PWM period (default), or a point "
                             "sample at mid off-time with centre-aligned PWM")
    parser.add_argument("--plant", metavar="BINDING.toml",
                        help="drive an external FMU through a plant-binding file instead of the built-in plant "
                             "(--mode/--variant/--sensor then do not apply; see README)")
    parser.add_argument("--interface", choices=["cs", "me"], default=None,
                        help="FMI interface: cs = co-simulation (fmi2DoStep), me = model exchange with fmpy's CVode "
                             "(default: the binding's choice, else co-simulation)")


def _add_implementation_option(parser) -> None:
    parser.add_argument("--implementation", choices=["c", "python"], default="c",
                        help="run the PI and predictive controllers as their C twins (controllers/c: the same duty "
                             "at every sample, several times faster) or as the Python references (default: c)")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="buck-cosim",
        description="FMU co-simulation workbench for a 48 V -> 12 V buck converter: PI, NNPC and MPC controllers "
                    "driving an FMI 2.0 plant through fmpy. Units: seconds, volts, amperes, ohms.")
    parser.add_argument("--no-progress", dest="progress", action="store_false",
                        help="hide progress bars (shown by default on long runs)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("scenarios", help="list the shipped scenarios",
                       description="List the shipped scenario files (TOML) with their events.")
    p.set_defaults(func=cmd_scenarios)

    p = sub.add_parser("run", help="run scenarios with controllers; write tables, metrics and figures",
                       description="Run scenarios in closed loop on the plant FMU. Writes per-run Parquet/CSV "
                                   "(+ JSON metadata) under OUT/runs, a metrics table under OUT/metrics and one "
                                   "figure per scenario (PNG + SVG) under OUT/figures.")
    p.add_argument("scenarios", nargs="*", metavar="SCENARIO",
                   help="shipped scenario name or path to a scenario TOML file (default: the paper's four)")
    p.add_argument("--controller", action="append",
                   choices=list(CONTROLLERS),
                   help="controller(s) to run; repeat to overlay several (default: pi). nnpc trains its network "
                        "on demand (data collected with the tuned PI) unless --model is given")
    _add_plant_options(p)
    p.add_argument("--control-period", type=parse_period, default=PAPER_PERIOD, metavar="SECONDS",
                   help="controller sample period in s, e.g. 1e-3 (the paper) or 1/75e3 (one switching period) "
                        "(default: 1e-3)")
    p.add_argument("--record-period", type=parse_period, default=1e-5, metavar="SECONDS",
                   help="recording step in s; need not divide the control period (default: 1e-5)")
    p.add_argument("--kp", type=float, help="PI proportional gain [1/V] (default: tuned automatically)")
    p.add_argument("--ki", type=float, help="PI integral gain [1/(V s)] (default: tuned automatically)")
    p.add_argument("--duty-min", type=float, default=0.0, help="lower duty limit (default: 0)")
    p.add_argument("--duty-max", type=float, default=1.0, help="upper duty limit (default: 1)")
    p.add_argument("--model", metavar="MODEL.pt", help="trained NN plant model for nnpc (default: train on demand)")
    p.add_argument("--samples", type=int, default=10_000, help="samples collected when nnpc trains on demand")
    p.add_argument("--seed", type=int, default=0, help="random seed for data collection and training (default: 0)")
    p.add_argument("--out", default=str(DEFAULT_RESULTS / "runs-cli"), metavar="DIR",
                   help="output folder (default: results/runs-cli)")
    p.add_argument("--no-figures", action="store_true", help="skip the figures")
    _add_implementation_option(p)
    p.add_argument("--stream", action="store_true",
                   help="for long runs: write rows to Parquet while running, in bounded memory (no CSV, metrics "
                        "or figures)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("collect-data", help="collect NN training data with the tuned PI (paper Section IV)",
                       description="Drive the plant with the tuned PI under random references and loads held for "
                                   "random intervals; write one row per control sample (iL, vo, d, ...) as Parquet.")
    _add_plant_options(p)
    p.add_argument("--control-period", type=parse_period, default=PAPER_PERIOD, metavar="SECONDS",
                   help="sample period in s (default: 1e-3)")
    p.add_argument("--samples", type=int, default=10_000, help="number of samples (default: 10000, the paper's)")
    p.add_argument("--excitation", type=float, default=None,
                   help=f"standard deviation of the duty dither added to the PI (default: {DITHER_SLOW} at control "
                        f"periods >= {TRANSIENT_WITHIN_SAMPLE_PERIOD * 1e3:g} ms, {DITHER_FAST} faster; 0 = plain PI)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.add_argument("--work-dir", default=str(DEFAULT_RESULTS / "runs-cli"), metavar="DIR",
                   help="where tuned PI gains are cached (default: results/runs-cli)")
    p.add_argument("--out", required=True, metavar="DATA.parquet", help="output file")
    p.set_defaults(func=cmd_collect)

    p = sub.add_parser("train", help="train an NN plant model from collected data",
                       description="Fit [iL, vo, d](k-1..k-D) (+ extra signals) -> [iL, vo](k) with torch; report "
                                   "held-out one-step and 10-step RMSE; save with weights only.")
    p.add_argument("data", help="samples written by collect-data (.parquet)")
    p.add_argument("--hidden", type=int, nargs="+", default=[7], help="hidden layer sizes (default: 7, the paper's)")
    p.add_argument("--activation", default="tanh", help="tanh (default), relu or sigmoid")
    p.add_argument("--delays", type=int, default=1, help="past samples of [iL, vo, d] fed in (default: 1)")
    p.add_argument("--extra", action="append", choices=["load_conductance", "load_current", "input_voltage"],
                   help="extra measured input at k-1 (repeatable)")
    p.add_argument("--residual", action="store_true", help="learn the change over one sample (skip connection)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.add_argument("--out", required=True, metavar="MODEL.pt", help="output model file")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("inspect", help="describe any FMU (and draft a binding file for it)",
                       description="Check an FMU archive and print its FMI version, interfaces, platforms and "
                                   "variables (causality, variability, unit, start value).")
    p.add_argument("fmu", help="path to a .fmu file")
    p.add_argument("--draft-binding", metavar="OUT.toml",
                   help="also write a draft plant-binding file, roles guessed from names and units")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("export", help="convert a run file between Parquet and CSV",
                       description="Read a run (.parquet, or .csv with its .json sidecar) and write it in the "
                                   "other format, metadata included.")
    p.add_argument("run_file", help="a run's .parquet or .csv file")
    p.add_argument("--to", choices=["csv", "parquet"], required=True, help="target format")
    p.add_argument("--out", metavar="DIR", help="output folder (default: beside the input)")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("build-fmu", help="compile BuckConverter.fmu from its C sources with fmpy",
                       description="Build the plant FMU (model exchange + co-simulation) with fmpy's CMake "
                                   "compile; cached by a hash of the sources. Also writes a source-only FMU.")
    p.add_argument("--output", metavar="DIR", help="copy BuckConverter.fmu and BuckConverter-source.fmu here")
    p.add_argument("--force", action="store_true", help="rebuild even if a cached build exists")
    p.set_defaults(func=cmd_build_fmu)

    p = sub.add_parser("tune-pi", help="tune the PI for a plant and control period",
                       description="Tune Kp, Ki by the repeatable method in cosim/study/pi_tuning.py.")
    _add_plant_options(p)
    p.add_argument("--control-period", type=parse_period, default=PAPER_PERIOD, metavar="SECONDS",
                   help="controller sample period in s (default: 1e-3)")
    p.add_argument("--out", metavar="FILE.json", help="write the gains as JSON")
    p.set_defaults(func=cmd_tune_pi)

    p = sub.add_parser("reproduce", help="reproduce the paper end to end into results/ (the main job)",
                       description="For the nominal averaged, nominal switched and mismatch-study plants at 1 ms "
                                   "and at one switching period (13.3 us): tune the PI, collect 10 000 samples, "
                                   "train the NN plant models, run the paper's scenarios with PI, NNPC and the "
                                   "MPC baselines, and write data, models, runs, metrics, figures and "
                                   "REPORT.md under OUT.")
    p.add_argument("--out", default=str(DEFAULT_RESULTS), metavar="DIR", help="output folder (default: results)")
    p.add_argument("--workers", type=int, default=2,
                   help="worker processes of the local dask cluster the pipelines run on (default: 2)")
    p.add_argument("--resume", action="store_true",
                   help="keep pipelines an interrupted reproduction finished, and their tuned gains")
    p.add_argument("--quick", action="store_true",
                   help="tiny sizes for a smoke test (400 samples, two scenarios): checks the pipeline, not the paper")
    p.add_argument("--plant", metavar="BINDING.toml",
                   help="run the same pipeline (PI tuning, data, NN training, PI/NNPC/MPC-nominal runs) on an "
                        "external FMU instead of the built-in plants")
    p.add_argument("--control-period", action="append", type=parse_period, metavar="SECONDS",
                   help="with --plant: control period(s) to run (repeatable; default 1e-3)")
    p.add_argument("--seed", type=int, default=0, help="base random seed (default: 0)")
    _add_implementation_option(p)
    p.set_defaults(func=cmd_reproduce)

    p = sub.add_parser("sweep", help="a parameter sweep or Monte Carlo tolerance study on dask -> dataset + SWEEP.md",
                       description="Run every unit of a sweep file (grids and distributions of FMU parameters and of "
                                   "the scenarios' supply and load) with controllers designed once on the nominal "
                                   "plant, on a local dask cluster or an existing one. Writes a partitioned Parquet "
                                   "dataset (one row per run: values, status, metrics) under DIR/dataset, the "
                                   "summary DIR/SWEEP.md (yield against the file's [spec], distributions, most "
                                   "influential parameter, worst case) with figures, and DIR/timings.json (wall "
                                   "clock). Values in the sweep file are SI: s, V, A, Ohm, H, F, Hz (README, "
                                   "'Sweeps and Monte Carlo'). Exit 2 on a mistake, before any work; 3 if some "
                                   "runs failed (each is a row saying why); 130 if interrupted (--resume finishes).")
    p.add_argument("spec", metavar="SPEC.toml", help="sweep file, or the name of a shipped study (e.g. tolerance)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder for the dataset and the summary")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="use the running dask cluster at tcp://HOST:PORT (started with `dask scheduler` and "
                        "`dask worker tcp://HOST:PORT`; every worker needs buck-cosim and a platform the FMU has a "
                        "binary for) instead of a local cluster")
    p.add_argument("--workers", type=int, metavar="N",
                   help="worker processes of the local cluster, one thread each (default: one per core)")
    p.add_argument("--resume", action="store_true",
                   help="finish an interrupted sweep in DIR: runs with a row in the dataset are not run again")
    p.add_argument("--scheduler-timeout", type=float, metavar="SECONDS", default=None,
                   help="how long to try to reach --scheduler, in s (default: 10)")
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser("bench", help="run the benchmark suite; write results/benchmarks.md and .csv",
                       description="Measure plant, master and controller costs as medians, p99 and same-run "
                                   "ratios; write benchmarks.md and benchmarks.csv.")
    p.add_argument("--quick", action="store_true",
                   help="run each benchmark once on a tiny size (smoke test; writes benchmarks-quick.*)")
    p.add_argument("--only", action="append", metavar="NAME", help="run only this benchmark (repeatable)")
    p.add_argument("--out", default=str(DEFAULT_RESULTS), metavar="DIR", help="output folder (default: results)")
    p.set_defaults(func=cmd_bench)
    return parser


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "controller", "unset") is None:
        args.controller = ["pi"]
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        return args.func(args) or 0
    except WorkbenchError as error:
        print(f"error: {' '.join(str(error).split())}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt:
        print("error: interrupted; completed results were kept", file=sys.stderr)
        return 130
    except OSError as error:  # a file system refusal (disk full, permissions): one line, not a traceback
        where = f"{error.filename}: " if error.filename else ""
        print(f"error: {where}{error.strerror or error}", file=sys.stderr)
        return 2
    except Exception as error:
        from plant_fmu import PlantBuildError

        if isinstance(error, PlantBuildError):
            print(f"error: {str(error).splitlines()[0]}", file=sys.stderr)
            return 4
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
