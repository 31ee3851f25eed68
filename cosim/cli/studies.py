"""Commands that run studies on a dask cluster: ``reproduce``, ``study``, ``sweep``, ``frequency-response``."""

from __future__ import annotations

from pathlib import Path

from cosim.base.errors import ConfigError
from cosim.cli.options import (
    DEFAULT_RESULTS,
    SEED_MAX,
    _add_implementation_option,
    _add_optimizer_options,
    _add_plant_options,
    _plant_binding,
    bounded,
    optimizer_options,
    output_dir,
    parse_period,
    seed_value,
)
from cosim.design.vocabulary import CONTROLLERS, PAPER_PERIOD, PREDICTIVE_CONTROLLERS


def cmd_reproduce(args) -> int:
    output_dir(args.out)
    if args.control_period and not args.plant:
        raise ConfigError("--control-period applies to reproduce --plant only (the built-in study runs at 1 ms and "
                          "at one switching period)")
    if args.plant:  # refuse a bad binding, or a period its scenarios cannot use, before any work starts
        from cosim.batch import Batch
        from cosim.design.experiments import scenarios_for
        from cosim.fmi.binding_file import load_binding

        binding = load_binding(args.plant)
        binding.converter.circuit("reproduce --plant (its MPC baseline predicts with the nominal circuit)")
        for period in args.control_period or (PAPER_PERIOD,):
            scenarios = [s for s in scenarios_for(period, spec=binding.converter)
                         if s.required_roles() <= set(binding.roles)]
            Batch(binding, scenarios).check_rates(period)
    from cosim.study.reproduce import FULL, QUICK, reproduce  # the whole study (torch, scipy): after the checks

    reproduce(Path(args.out), workers=args.workers, resume=args.resume, seed=args.seed,
              implementation=args.implementation,
              profile=QUICK if args.quick else FULL, binding_file=args.plant,
              control_periods=tuple(args.control_period or ()), controller_files=tuple(args.controller or ()))
    return 0


def cmd_study(args) -> int:
    from cosim.study.converter_study import plan_study  # checks the binding, its spec and the rates before any work

    plan = plan_study(args.plant, tuple(args.control_period or ()), args.seeds, args.quick)
    output_dir(args.out)  # then the output folder (created only for a study that will run)
    from cosim.study.converter_study import run_study

    run_study(plan, Path(args.out), workers=args.workers, resume=args.resume, implementation=args.implementation)
    return 0


def cmd_sweep(args) -> int:
    from cosim.design.sweeps.spec import load_sweep
    from cosim.design.sweeps.sweep import raise_if_failed, run_sweep

    spec = load_sweep(args.spec)  # the file first: its mistakes before the folder is touched
    if args.scheduler_timeout is not None and not args.scheduler_timeout > 0:
        raise ConfigError(f"--scheduler-timeout {args.scheduler_timeout} s is invalid: expected > 0")
    outcome = run_sweep(spec, output_dir(args.out), scheduler=args.scheduler, workers=args.workers,
                        resume=args.resume, progress=args.progress, connect_timeout=args.scheduler_timeout)
    print(f"{outcome.planned} runs ({outcome.done_before} done earlier, {outcome.computed} now, {outcome.failed} "
          f"failed); summary: {outcome.out_dir / 'SWEEP.md'}")
    raise_if_failed(outcome)
    return 0


#: the controllers frequency-response measures (command-line keys, each also its sweep kind), and the predictive ones
RESPONSE_CONTROLLERS = ("pi", "pi-envelope", "current-mode", "type-iii", "nnpc", "nnpc-explicit", "mpc-oracle",
                        "mpc-nominal")
RESPONSE_PREDICTIVE = tuple(k for k in PREDICTIVE_CONTROLLERS if k in RESPONSE_CONTROLLERS)


def cmd_frequency_response(args) -> int:
    from cosim.design.cluster import dask_client
    from cosim.design.controller_factory import check_optimizer_options
    from cosim.design.frequency_response import ResponseSettings, measure, write_outputs
    from cosim.design.sweeps.spec import ControllerEntry

    binding = _plant_binding(args)
    spec = binding.converter  # the operating point and the rate not given: the plant's converter's
    purpose = "the frequency response's operating point (or give --reference, --load, --input-voltage)"
    reference, load, supply = (given if given is not None else spec.require(key, purpose)
                               for given, key in ((args.reference, "output_voltage"), (args.load, "load_resistance"),
                                                  (args.input_voltage, "input_voltage")))
    if args.control_period is None:
        args.control_period = 1.0 / spec.require("switching_frequency",
                                                 "the frequency response's rate (or give --control-period)")
    settings = ResponseSettings(injection=args.injection, low=args.low, high=args.high, points=args.points,
                                amplitude=args.amplitude, reference=reference, load=load, input_voltage=supply,
                                settle=args.settle)
    settings.check(args.control_period)  # every setting before the cluster or a design
    out = output_dir(args.out)
    names = args.controller or ["pi"]
    for name in names:
        if name not in RESPONSE_CONTROLLERS:
            raise ConfigError(f"--controller {name} is invalid: expected one of {', '.join(RESPONSE_CONTROLLERS)}")
    optimizer, rti_changes = optimizer_options(args)
    check_optimizer_options(names, args.control_period, (0.0, 1.0), optimizer, rti_changes, RESPONSE_PREDICTIVE)
    tables = []
    with dask_client(None, args.workers) as client:
        for name in names:
            planning = {"optimizer": optimizer, "rti": tuple(rti_changes.items())} \
                if name in PREDICTIVE_CONTROLLERS else {}
            entry = ControllerEntry(kind=name, name=CONTROLLERS[name], place=f"--controller {name}", **planning)
            table = measure(binding, entry, args.control_period, settings, out / CONTROLLERS[name], client=client,
                            implementation=args.implementation, progress=args.progress)
            tables.append(table)
            summary = table.attrs["summary"]
            measured, model = summary.get("measured"), summary.get("closed_form")
            if measured:
                print(f"{entry.name}: measured crossover {measured['crossover_hz'] or float('nan'):.0f} Hz, phase margin "
                      f"{measured['phase_margin_deg'] or float('nan'):.1f} deg, gain margin "
                      f"{measured['gain_margin_db'] or float('nan'):.1f} dB"
                      + (f"; closed form {model['crossover_hz']:.0f} Hz, {model['phase_margin_deg']:.1f} deg, "
                         f"{model['gain_margin_db']:.1f} dB" if model else ""))
            agreement = summary.get("agreement_up_to_fsw_over_5")
            if agreement:
                print(f"{entry.name}: against the averaged small-signal closed form up to {agreement['up_to_hz']:.0f} Hz: "
                      f"{agreement['max_magnitude_error_db']:.2f} dB, {agreement['max_phase_error_deg']:.2f} deg at most")
    files = write_outputs(tables, out)
    print(f"wrote {', '.join(str(f) for f in files)}")
    return 0


def add_reproduce_parser(sub) -> None:
    p = sub.add_parser("reproduce", help="reproduce the paper end to end into results/ (the main job)",
                       description="For the nominal averaged, nominal switched and mismatch-study plants at 1 ms "
                                   "and at one switching period (13.3 us): tune the PI, collect 10 000 samples, "
                                   "train the NN plant models, run the paper's scenarios with PI, NNPC and the "
                                   "MPC baselines, and write data, models, runs, metrics, figures and "
                                   "REPORT.md under OUT.")
    p.add_argument("--out", default=str(DEFAULT_RESULTS), metavar="DIR", help="output folder (default: results)")
    p.add_argument("--workers", type=bounded(int, 1), default=2,
                   help="worker processes of the local dask cluster the jobs run on (default: 2)")
    p.add_argument("--resume", action="store_true",
                   help="keep pipelines an interrupted reproduction finished, and their tuned gains")
    p.add_argument("--quick", action="store_true",
                   help="tiny sizes for a smoke test (400 samples, two scenarios): checks the pipeline, not the paper")
    p.add_argument("--plant", metavar="BINDING.toml",
                   help="run the same pipeline (PI tuning, data, NN training, PI/NNPC/MPC-nominal runs) on an "
                        "external FMU instead of the built-in plants")
    p.add_argument("--control-period", action="append", type=parse_period, metavar="SECONDS",
                   help="with --plant: control period(s) to run (repeatable; default 1e-3)")
    p.add_argument("--seed", type=seed_value, default=0, help=f"base random seed, 0 .. {SEED_MAX} (default: 0)")
    p.add_argument("--controller", action="append", metavar="FMU|BINDING.toml",
                   help="a controller FMU (export-controller's, or any with the role names) or a controller-binding "
                        "file, run next to the built-in controllers in every pipeline at its sample period "
                        "(repeatable); its runs are in metrics/ and the figures under its name")
    _add_implementation_option(p)
    p.set_defaults(func=cmd_reproduce)


def add_study_parser(sub) -> None:
    from cosim.study.converter_study import DEFAULT_SEEDS, QUICK_SEEDS, QUICK_STUDY_BUDGET_S, STUDY_BUDGET_S

    p = sub.add_parser("study", help="the whole study for your converter: PI, NNPC, MPC and classical baselines on "
                                     "a bound plant FMU, with its report",
                       description="The study make reproduce runs for the paper's converter, run for the converter "
                                   "a binding file describes (its [converter] table): at each control period the "
                                   "spec names, tune the PI at the nominal point, identify the NNPC from data over "
                                   "the spec's ranges (one network per identification seed), run the paper's "
                                   "scenarios resolved against the spec with PI, NNPC, the paper's NNPC and the MPC "
                                   "on the nominal circuit; at one switching period also the explicit NNPC, the "
                                   "current-mode controller and the Type-III, and the envelope map over the spec's "
                                   "ranges. Writes data, models, runs, metrics, figures, envelope/, targets.csv, "
                                   "REPORT.md and timings.md under OUT. Budget on 2 cores: "
                                   f"{STUDY_BUDGET_S / 60:g} min ({QUICK_STUDY_BUDGET_S / 60:g} min with --quick).")
    p.add_argument("--plant", required=True, metavar="BINDING.toml",
                   help="binding file of the plant FMU, with a [converter] table that gives the nominal circuit "
                        "(L, C, f_sw) and the control periods")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--control-period", action="append", type=parse_period, metavar="SECONDS",
                   help="control period(s) in s to study (repeatable; default: the spec's control_periods)")
    p.add_argument("--seeds", type=bounded(int, 1, 20), default=None,
                   help=f"identification seeds, 1 .. 20 (default: {DEFAULT_SEEDS}, {QUICK_SEEDS} with --quick)")
    p.add_argument("--quick", action="store_true",
                   help="a first look: 2 seeds, 4 000 identification samples, a small distillation")
    p.add_argument("--workers", type=bounded(int, 1), default=2,
                   help="worker processes of the local dask cluster the jobs run on (default: 2)")
    p.add_argument("--resume", action="store_true", help="keep the jobs an interrupted study finished")
    _add_implementation_option(p)
    p.set_defaults(func=cmd_study)


def add_sweep_parser(sub) -> None:
    p = sub.add_parser("sweep", help="a parameter sweep or Monte Carlo tolerance study on dask -> dataset + SWEEP.md",
                       description="Run every unit of a sweep file (grids and distributions of FMU parameters and of "
                                   "the scenarios' supply and load) with controllers designed once on the nominal "
                                   "plant, on a local dask cluster or an existing one. Writes a partitioned Parquet "
                                   "dataset (one row per run: values, status, metrics) under DIR/dataset, the "
                                   "summary DIR/SWEEP.md (yield against the file's [spec], distributions, most "
                                   "influential parameter, worst case) with figures, and DIR/timings.json (wall "
                                   "clock). Values in the sweep file are SI: s, V, A, Ohm, H, F, Hz "
                                   "(docs/guide/sweeps.md). Exit 2 on a mistake, before any work; 3 if some "
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


def add_frequency_response_parser(sub) -> None:
    p = sub.add_parser("frequency-response", help="loop gain, margins or output impedance by injection on the plant FMU",
                       description="Measure a controller's loop in closed loop on the plant FMU by injecting a small "
                                   "sine -- at the duty (loop gain T = -U/D, crossover, phase and gain margins), at "
                                   "the reference (closed-loop Vo/R) or at the load (output impedance -Vo/Io) -- and "
                                   "correlating at the injection frequency, one run per frequency on the sweep "
                                   "engine (a local dask cluster). Beside each point: the averaged small-signal "
                                   "closed form (PI, current-mode, Type-III). Writes DIR/frequency_response.csv, "
                                   ".json (margins) and .png (Bode plot, margins marked).")
    p.add_argument("--controller", action="append", metavar="NAME",
                   help=f"{', '.join(RESPONSE_CONTROLLERS)} (repeatable; default: pi)")
    _add_optimizer_options(p, RESPONSE_PREDICTIVE)
    p.add_argument("--injection", choices=["duty", "reference", "load"], default="duty",
                   help="where the sine goes in (default: duty)")
    p.add_argument("--control-period", type=parse_period, default=None, metavar="SECONDS",
                   help="controller sample period in s (default: one switching period of the plant's converter, "
                        "1/75e3 for the built-in plant)")
    p.add_argument("--low", type=float, default=100.0, metavar="HZ", help="lowest frequency [Hz] (default: 100)")
    p.add_argument("--high", type=float, default=30e3, metavar="HZ", help="highest frequency [Hz] (default: 30e3)")
    p.add_argument("--points", type=int, default=24, metavar="N", help="log-spaced frequencies (default: 24)")
    p.add_argument("--amplitude", type=float, default=None,
                   help="injection amplitude: duty [1] (default 0.01), reference [V] (0.1), load [relative "
                        "conductance change] (0.05)")
    p.add_argument("--reference", type=float, default=None, metavar="V",
                   help="operating point: reference [V] (default: the converter's nominal output, 12 V built-in)")
    p.add_argument("--load", type=float, default=None, metavar="OHM",
                   help="operating point: load [Ohm] (default: the converter's nominal load, 6 Ohm built-in)")
    p.add_argument("--input-voltage", type=float, default=None, metavar="V",
                   help="operating point: supply [V] (default: the converter's nominal supply, 48 V built-in)")
    p.add_argument("--settle", type=float, default=15e-3, metavar="SECONDS",
                   help="closed loop from rest before the injection starts [s] (default: 0.015)")
    p.add_argument("--workers", type=bounded(int, 1), metavar="N", help="local dask workers (default: one per core)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    _add_plant_options(p)
    _add_implementation_option(p)
    p.set_defaults(func=cmd_frequency_response)
