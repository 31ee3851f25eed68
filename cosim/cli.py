"""``buck-cosim``: the workbench's command line.

Every user mistake ends in one line ``error: ...`` on stderr and a non-zero exit code:
2 bad input or configuration, 3 a plant or controller fault during a run, 4 the FMU build
failed, 130 interrupted (Ctrl-C or SIGTERM). Completed runs are kept on disk in every case.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
from pathlib import Path

from controllers.explicit_policy import INTEGRAL_GAIN_PER_SAMPLE, PolicyConfig
from cosim.base.errors import BuildError, ConfigError, WorkbenchError
from cosim.fmi.binding import PLANT_MODE_CODES
from cosim.study.data_collection import MAX_EXCITATION, MIN_SAMPLES
from cosim.study.vocabulary import (
    CONTROLLERS,
    DITHER_FAST,
    DITHER_SLOW,
    FLOAT32_CONTROLLERS,
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


def input_file(text: str, what: str, hint: str = "") -> Path:
    """A file to read: refused at once, in one line, if it is missing or a folder."""
    path = Path(text)
    if path.is_dir():
        raise ConfigError(f"{what} {path} is a folder: expected a file")
    if not path.is_file():
        raise ConfigError(f"{what} {path} does not exist" + (f" ({hint})" if hint else ""))
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


#: seeds are 32-bit: numpy's and torch's generators take them, and so does any tool a user repeats a run with
SEED_MAX = 2**32 - 1


def seed_value(text: str) -> int:
    """A random seed: a whole number 0 .. 2**32 - 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a seed: expected a whole number 0 .. {SEED_MAX}") from None
    if not 0 <= value <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"seed {text} is out of range: expected a whole number 0 .. {SEED_MAX}")
    return value


def bounded(kind=float, low: float | None = None, high: float | None = None, *, below_high: bool = False,
            unit: str = ""):
    """An argparse type: a finite number (``kind`` int or float) with ``low <= value`` and
    ``value <= high`` (``value < high`` with ``below_high``); NaN and infinities are refused."""
    name = "whole number" if kind is int else "finite number"
    limits = [f">= {low:g}" if low is not None else "", (f"< {high:g}" if below_high else f"<= {high:g}")
              if high is not None else ""]
    expected = f"a {name} {' and '.join(x for x in limits if x)}".strip() + (f" {unit}" if unit else "")

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is invalid: expected {expected}") from None
        ok = math.isfinite(value) and (low is None or value >= low) and \
            (high is None or (value < high if below_high else value <= high))
        if not ok:
            raise argparse.ArgumentTypeError(f"{text} is invalid: expected {expected}")
        return value

    return parse


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
    from dataclasses import replace

    if getattr(args, "plant", None):
        from cosim.fmi.binding_file import load_binding

        binding = load_binding(args.plant)
    else:
        from cosim.study.experiments import plant_binding

        binding = plant_binding(args.variant, args.mode, args.sensor)
    isolate = getattr(args, "isolate", None)
    binding = binding if isolate is None else replace(binding, isolate=isolate)
    limits = {key: value for key, value in (("step_timeout", getattr(args, "step_timeout", None)),
                                            ("memory_limit", getattr(args, "memory_limit", None))) if value is not None}
    if limits and not binding.isolate:
        option = "--" + next(iter(limits)).replace("_", "-")
        raise ConfigError(f"{option} needs an isolated plant (--isolate, or a binding file's default): the workbench "
                          "cannot stop an FMU running in its own process")
    return replace(binding, **limits) if limits else binding


def _check_duty_limits(args) -> None:
    """Refuse --duty-min/--duty-max unless 0 <= min < max <= 1, before any other work."""
    if not (0.0 <= args.duty_min < args.duty_max <= 1.0):
        raise ConfigError(f"duty limits ({args.duty_min}, {args.duty_max}) are invalid: expected 0 <= min < max <= 1")


def _design_controller(args, binding, period: float, work_dir: Path, policy_path: str | None = None):
    """The built-in controller ``args.controller`` designed for ``binding`` at ``period`` from the options of
    :func:`_add_controller_design_options` (tuned, trained or distilled on demand, cached in ``work_dir``)."""
    from cosim.study.controller_factory import make_controllers

    [controller] = make_controllers([args.controller], binding, period, work_dir,
                                    duty_limits=(args.duty_min, args.duty_max), kp=args.kp, ki=args.ki,
                                    model_path=args.model, samples=args.samples, seed=args.seed,
                                    progress=args.progress, policy_path=policy_path)
    return controller


def _export_controller_fmu(controller, out: Path, precision: str = "float64", fmi_version: int = 2) -> tuple[Path, Path]:
    """Write ``controller`` as a controller FMU (FMI ``fmi_version``) at ``out`` from the ``precision`` build of its
    C twin: (binary FMU, source FMU); a configuration its C twin cannot hold is a ConfigError naming the controller."""
    from cosim.fmi.controller_export import export_controller

    try:
        return export_controller(controller, out, precision=precision, fmi_version=fmi_version)
    except ValueError as error:  # a configuration the C twins cannot hold
        raise ConfigError(f"{controller.name}: {error}") from None


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


def _add_fmi_version_option(p, whose: str) -> None:
    p.add_argument("--fmi-version", type=int, choices=(2, 3), default=2, metavar="{2,3}",
                   help=f"{whose} FMI version: 2 (FMI 2.0, the default) or 3 (FMI 3.0)")


def cmd_export_controller(args) -> int:
    out = output_file(args.out)
    if out.suffix.lower() != ".fmu":
        raise ConfigError(f"--out {out} is invalid: expected a file name ending in .fmu")
    _check_duty_limits(args)
    if args.cortex_m4:
        from cosim.benchmark_harness.cortex_m4 import toolchain_problem

        if args.precision != "float32":
            raise ConfigError(f"--cortex-m4 {args.cortex_m4} needs --precision float32 (the object is the float32 "
                              "build)")
        if toolchain_problem():
            raise ConfigError(f"--cortex-m4 {args.cortex_m4}: {toolchain_problem()}")
    if args.precision == "float32" and args.controller not in FLOAT32_CONTROLLERS:
        raise ConfigError(f"--precision float32: {args.controller} has no float32 build (the predictive "
                          "controller's optimizer, controllers/c/predictive.c, computes in double); expected one of "
                          f"{', '.join(FLOAT32_CONTROLLERS)}")
    work_dir = output_dir(args.work_dir)
    controller = _design_controller(args, _plant_binding(args), args.control_period, work_dir, args.policy)
    binary, source = _export_controller_fmu(controller, out, args.precision, args.fmi_version)
    version = f"FMI {args.fmi_version}.0"
    build = "" if args.precision == "float64" else f" ({args.precision} build of the C twin)"
    print(f"{controller.name} sampled every {controller.sample_period:.6g} s as an {version} co-simulation FMU{build}: "
          f"{binary}")
    print(f"source FMU (compile with any {version} tool): {source}")
    if args.cortex_m4:
        from cosim.benchmark_harness.cortex_m4 import EmbeddedError, export_object

        try:
            target = export_object(controller, output_dir(args.cortex_m4))
        except EmbeddedError as error:
            raise BuildError(f"--cortex-m4 {args.cortex_m4}: {str(error).splitlines()[0]}") from None
        print(f"the same controller for a Cortex-M4F (float32, -O2, hard float): {target} (link it with newlib's "
              "libm: see the README's 'On a microcontroller')")
    return 0


def cmd_export_ssp(args) -> int:
    import re
    import tempfile

    from cosim.master import check_plant_supports
    from cosim.scenarios import load_scenario
    from cosim.ssp.package import export_ssp
    from cosim.timeline import plan_timeline

    out = output_file(args.out)
    if out.suffix.lower() != ".ssp":
        raise ConfigError(f"--out {out} is invalid: expected a file name ending in .ssp")
    _check_duty_limits(args)
    scenario = load_scenario(args.scenario)
    binding = _plant_binding(args)
    if args.fmi_version == 3 and binding.source is None:  # the built-in plant's FMI 3.0 edition
        from dataclasses import replace

        from plant_fmu import fmu_path

        binding = replace(binding, fmu_path=fmu_path(fmi_version=3))
    check_plant_supports(binding, scenario)  # before any tuning or training
    with tempfile.TemporaryDirectory(prefix="buck-cosim-export-ssp-") as tmp:
        if args.controller in CONTROLLERS:
            period = args.control_period or PAPER_PERIOD
            plan_timeline(scenario, period, period)
            controller = _design_controller(args, binding, period, output_dir(args.work_dir))
            fmu, _ = _export_controller_fmu(controller,
                                            Path(tmp) / f"{re.sub(r'[^A-Za-z0-9_]', '_', controller.name)}.fmu",
                                            args.fmi_version)
        else:
            from cosim.fmi.controller import controller_binding

            if Path(args.controller).suffix.lower() != ".fmu":
                raise ConfigError(f"--controller {args.controller} is invalid: expected {', '.join(CONTROLLERS)} or a "
                                  "controller FMU (.fmu) with the workbench's role names")
            from cosim.fmi.archive import check_fmu
            from cosim.ssp.package import controller_sample_period

            fmu = controller_binding(args.controller).fmu_path
            own = controller_sample_period(check_fmu(fmu))
            if args.control_period and abs(own - args.control_period) > 1e-9 * args.control_period:
                raise ConfigError(f"controller FMU {args.controller} samples every {own:.6g} s, not the "
                                  f"--control-period {args.control_period:.6g} s given")
        loop = export_ssp(scenario, binding, Path(fmu), out, step=args.communication_step)
    print(f"wrote {out}: scenario {scenario.name}, controller {Path(loop.components['controller'].source).stem} "
          f"every {loop.control_period:.6g} s, plant {loop.plant_label}; stop time {loop.stop_time:.6g} s, "
          f"communication step {loop.step:.6g} s (plant time: the scenario's t = 0 at {loop.settle:.6g} s)")
    return 0


def cmd_run_ssp(args) -> int:
    from cosim.batch import write_metrics
    from cosim.master import RunFailed
    from cosim.metrics import metrics_table
    from cosim.results import write_run
    from cosim.ssp.engines import prepare, run_ssp, run_stem

    source = input_file(args.ssp, "SSP file", "write one with buck-cosim export-ssp")
    loop, step = prepare(source, args.engine, args.communication_step)  # everything checked before any output
    out_dir = output_dir(args.out)
    stem = run_stem(loop, args.engine)
    try:
        result = run_ssp(source, args.engine, step)
    except RunFailed as error:
        write_run(error.partial, out_dir / "runs", stem)
        raise
    files = list(write_run(result, out_dir / "runs", stem).values())
    table = metrics_table([result])
    table.insert(2, "engine", args.engine)
    files += write_metrics(table, out_dir / "metrics" / f"metrics__{stem}")
    columns = ["scenario", "controller", "engine", "rise_time_ms", "overshoot_pct", "settling_time_ms",
               "steady_state_error_pct", "iae_Vs"]
    print(table[columns].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    print(f"engine {args.engine}, communication step {step:.6g} s: wrote {len(files)} files under {out_dir}/")
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


def cmd_build_fmu(args) -> int:
    from plant_fmu import export_fmus, fmu_path, source_fmu_path

    version = args.fmi_version
    if args.output:
        binary, source = export_fmus(output_dir(args.output), force=args.force, fmi_version=version)
    else:
        binary, source = (fmu_path(force=args.force, fmi_version=version),
                          source_fmu_path(force=args.force, fmi_version=version))
    print(f"FMI {version}.0 co-simulation + model exchange FMU: {binary}")
    print(f"source FMU (compile with any FMI {version}.0 tool): {source}")
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
    settings = collection_settings(args.control_period, args.samples, args.seed, args.excitation)
    settings.check()  # all of it before the PI is tuned (seconds, or minutes on a slow external plant)
    binding = _plant_binding(args)
    pi = tuned_pi(binding, args.control_period, work_dir, args.progress)
    data = collect(binding, pi.controller(), settings, progress=args.progress)
    save_samples(data, Path(args.out))
    print(f"wrote {len(data)} samples ({', '.join(data.columns)}) to {args.out}")
    return 0


def cmd_train(args) -> int:
    from controllers.nn_model import NNConfig, TrainingSettings, extra_columns, load_model, save_model, train
    from cosim.results import read_parquet

    try:  # arguments first, before any file is read
        config = NNConfig(hidden=tuple(args.hidden), activation=args.activation, delays=args.delays,
                          extra_signals=tuple(args.extra or ()), residual=args.residual)
        settings = TrainingSettings(seed=args.seed, multi_step_horizon=args.multi_step_horizon,
                                    multi_step_iterations=args.multi_step_iterations,
                                    multi_step_stride=args.multi_step_stride)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    output_file(args.out)
    needed = ["measured_inductor_current", "measured_output_voltage", "duty_cycle", *extra_columns(config)]

    def samples(name: str):
        source = input_file(name, "data file", "write one with buck-cosim collect-data")
        try:
            frame, metadata = read_parquet(source)
        except Exception as error:
            raise ConfigError(f"{source}: cannot read samples ({str(error).splitlines()[0]})") from None
        missing = [c for c in needed if c not in frame.columns]
        if missing:
            raise ConfigError(f"{source} lacks column(s) {', '.join(missing)} needed by {config.label}")
        return source, frame, metadata

    source, frame, metadata = samples(args.data)
    period = metadata.get("control_period_s")
    if args.control_period is not None:
        if period is not None and not math.isclose(period, args.control_period, rel_tol=1e-9):
            raise ConfigError(f"{source} was collected at a control period of {period:.6g} s, not the "
                              f"--control-period {args.control_period:.6g} s given")
        period = args.control_period
    if period is None:
        raise ConfigError(f"{source} has no workbench metadata naming its control period (not written by "
                          "buck-cosim collect-data?): give the period the samples were taken at with --control-period")
    extra = []
    for name in args.extra_data or ():
        other, more, more_meta = samples(name)
        other_period = more_meta.get("control_period_s")
        if other_period is not None and not math.isclose(period, other_period, rel_tol=1e-9):
            raise ConfigError(f"{other} was collected at a control period of {other_period:.6g} s, "
                              f"{source} at {period:.6g} s: train on data of one rate")
        extra.append(more)
    initial = load_model(Path(args.init), expect_period=period, expect_config=config) if args.init else None
    try:
        model = train(frame, config, settings, progress=args.progress, extra_frames=extra, initial=initial,
                      metadata={"control_period_s": period, "plant": metadata.get("plant"),
                                "data_file": str(source), "extra_data_files": [str(n) for n in args.extra_data or ()],
                                "seed": args.seed})
        save_model(model, Path(args.out))
    except ValueError as error:
        raise ConfigError(f"{source}: {error}") from None
    rmse = model.metadata["held_out_rmse"]
    print(f"{config.label}: held-out one-step RMSE {rmse['one_step_rmse_voltage_V'] * 1e3:.2f} mV, "
          f"{rmse['one_step_rmse_current_A'] * 1e3:.2f} mA; 10-step (recorded duties and load) "
          f"{rmse.get('10_step_rmse_voltage_V', float('nan')) * 1e3:.2f} mV")
    print(f"wrote {args.out}")
    return 0


def cmd_distill(args) -> int:
    from dataclasses import replace

    from controllers.explicit_policy import save_policy
    from controllers.nn_model import load_model
    from cosim.study.distillation import FULL_DISTILLATION, distill

    try:  # arguments first, before any file is read or any work starts
        policy_config = PolicyConfig(hidden=tuple(args.hidden), integral_gain=args.integral_gain,
                                     integral_band=args.integral_band)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    settings = replace(FULL_DISTILLATION, rounds=args.rounds, episodes=args.episodes, samples=args.samples,
                       seed=args.seed, policy=policy_config)
    settings.check()
    output_file(args.out)
    source = input_file(args.model, "model file", "train one with buck-cosim train")
    model = load_model(source, expect_period=args.control_period)
    period = args.control_period or model.metadata.get("control_period_s")
    if period is None:
        raise ConfigError(f"model file {source} names no control period: give --control-period")
    binding = _plant_binding(args)
    if not binding.has("inductor_current"):
        raise ConfigError(f"the NNPC needs the inductor_current role, which {binding.origin} does not bind")
    from cosim.study.experiments import implemented, nnpc

    implemented(nnpc(model, period))  # refuses a network the C twin cannot hold, before any work
    print(f"distilling the NNPC of {source} on {binding.label} at {period * 1e6:.4g} us: {settings.rounds + 1} "
          f"rounds x {settings.episodes} episodes x {settings.samples} samples = {settings.labels} labels",
          file=sys.stderr)
    policy = distill(model, binding, period, settings, progress=args.progress,
                     metadata={"expert_file": str(source)})
    save_policy(policy, Path(args.out))
    training = policy.metadata["training"]
    last = policy.metadata["distillation"]["history"][-1]  # the last round's on-policy error
    distillation = policy.metadata["distillation"]
    print(f"{policy_config.label} policy ({policy_config.macs()} MACs per step): {len(distillation['history'])} "
          f"DAgger rounds, {distillation['labels']} labels; validation RMS first-move error "
          f"{training['validation_rms_duty']:.4f}"
          + (f", last round on-policy before retraining {last['first_move_rms_before_retraining']:.4f}"
             if "first_move_rms_before_retraining" in last else ""))
    print(f"wrote {args.out}")
    return 0


def cmd_reproduce(args) -> int:
    from cosim.study.reproduce import FULL, QUICK, reproduce

    output_dir(args.out)
    if args.control_period and not args.plant:
        raise ConfigError("--control-period applies to reproduce --plant only (the built-in study runs at 1 ms and "
                          "at one switching period)")
    if args.plant:  # refuse a bad binding, or a period its scenarios cannot use, before any work starts
        from cosim.batch import Batch
        from cosim.fmi.binding_file import load_binding
        from cosim.study.experiments import scenarios_for

        binding = load_binding(args.plant)
        for period in args.control_period or (PAPER_PERIOD,):
            scenarios = [s for s in scenarios_for(period) if s.required_roles() <= set(binding.roles)]
            Batch(binding, scenarios).check_rates(period, 1e-5)
    reproduce(Path(args.out), workers=args.workers, resume=args.resume, seed=args.seed,
              implementation=args.implementation,
              profile=QUICK if args.quick else FULL, binding_file=args.plant,
              control_periods=tuple(args.control_period or ()), controller_files=tuple(args.controller or ()))
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


def cmd_frequency_response(args) -> int:
    from cosim.study.cluster import dask_client
    from cosim.study.frequency_response import ResponseSettings, measure, write_outputs
    from cosim.study.sweeps.spec import ControllerEntry

    settings = ResponseSettings(injection=args.injection, low=args.low, high=args.high, points=args.points,
                                amplitude=args.amplitude, reference=args.reference, load=args.load,
                                input_voltage=args.input_voltage, settle=args.settle)
    settings.check(args.control_period)  # every setting before the cluster or a design
    binding = _plant_binding(args)
    out = output_dir(args.out)
    kinds = {"pi": "pi", "pi-envelope": "pi-envelope", "current-mode": "current-mode", "type-iii": "type-iii",
             "nnpc": "nnpc", "nnpc-explicit": "nnpc-explicit", "mpc-oracle": "mpc-oracle",
             "mpc-nominal": "mpc-nominal"}
    tables = []
    with dask_client(None, args.workers) as client:
        for name in args.controller or ["pi"]:
            if name not in kinds:
                raise ConfigError(f"--controller {name} is invalid: expected one of {', '.join(kinds)}")
            entry = ControllerEntry(kind=kinds[name], name=CONTROLLERS[name], place=f"--controller {name}")
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


def cmd_bench(args) -> int:
    from cosim.benchmarks import BENCHMARKS, run_benchmarks

    unknown = [name for name in args.only or [] if name not in BENCHMARKS]
    if unknown:
        raise ConfigError(f"unknown benchmark(s) {', '.join(unknown)}: expected {', '.join(BENCHMARKS)}")
    output_dir(args.out)
    command = "buck-cosim bench" + "".join(f" --only {n}" for n in args.only or [])
    models = Path(args.models) if args.models else None
    if models is not None and not models.is_dir():
        raise ConfigError(f"--models {args.models}: no such folder (expected the models folder of a reproduction)")
    md_path, csv_path = run_benchmarks(Path(args.out), quick=args.quick, only=args.only, command=command,
                                       models_dir=models)
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
    isolation = parser.add_mutually_exclusive_group()
    isolation.add_argument("--isolate", dest="isolate", action="store_true", default=None,
                           help="step the plant FMU in a child process: a crash inside it ends the run with an error "
                                "(exit 3, rows kept) instead of the workbench (default for binding-file plants; costs "
                                "one pipe round trip per step, see benchmarks.md)")
    isolation.add_argument("--no-isolate", dest="isolate", action="store_false",
                           help="step the plant FMU in this process (default for the built-in plant)")
    parser.add_argument("--step-timeout", type=bounded(float, 1e-3, unit="s"), default=None, metavar="SECONDS",
                        help="isolated plant: a step that takes longer (wall time) is stopped and the run fails "
                             "(exit 3) (default: the binding file's step_timeout, else 30 s + 1000 x the step's "
                             "simulated length)")
    parser.add_argument("--memory-limit", type=bounded(float, 1.0, unit="MB"), default=None, metavar="MB",
                        help="isolated plant: its process is stopped (the run fails, exit 3) above this resident "
                             "memory (default: the binding file's memory_limit, else half the machine's)")
    parser.add_argument("--interface", choices=["cs", "me"], default=None,
                        help="FMI interface: cs = co-simulation (fmi2DoStep), me = model exchange with fmpy's CVode "
                             "(default: the binding's choice, else co-simulation)")


def _add_implementation_option(parser) -> None:
    parser.add_argument("--implementation", choices=["c", "python"], default="c",
                        help="run the PI and predictive controllers as their C twins (controllers/c: the same duty "
                             "at every sample, several times faster) or as the Python references (default: c)")


def _add_pi_and_duty_options(parser, gains_default: str) -> None:
    """--kp/--ki (the PI's gains; ``gains_default`` says what happens without them) and --duty-min/--duty-max (every
    built-in controller's duty limits), checked together by :func:`_check_duty_limits`."""
    parser.add_argument("--kp", type=bounded(float, 0.0),
                        help=f"PI proportional gain [1/V] (default: {gains_default})")
    parser.add_argument("--ki", type=bounded(float, 0.0),
                        help=f"PI integral gain [1/(V s)] (default: {gains_default})")
    parser.add_argument("--duty-min", type=bounded(float, 0.0, 1.0), default=0.0,
                        help="lower duty limit [1] (default: 0)")
    parser.add_argument("--duty-max", type=bounded(float, 0.0, 1.0), default=1.0,
                        help="upper duty limit [1] (default: 1)")


def _add_controller_design_options(parser) -> None:
    """What export-controller and export-ssp need to design a built-in controller on the plant (read by
    :func:`_design_controller`): the PI's gains and the duty limits, the samples and seed of an NN plant model
    trained on demand, and the folder the tuned gains and trained networks are cached in."""
    _add_pi_and_duty_options(parser, gains_default="tuned on the plant")
    parser.add_argument("--samples", type=bounded(int, MIN_SAMPLES), default=10_000,
                        help=f"samples collected when nnpc trains on demand (>= {MIN_SAMPLES}; default: 10000)")
    parser.add_argument("--seed", type=seed_value, default=0, help=f"random seed, 0 .. {SEED_MAX} (default: 0)")
    parser.add_argument("--work-dir", default=str(DEFAULT_RESULTS / "runs-cli"), metavar="DIR",
                        help="where tuned gains and trained networks are cached (default: results/runs-cli)")


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

    p = sub.add_parser("collect-data", help="collect NN training data with the tuned PI (paper Section IV)",
                       description="Drive the plant with the tuned PI under random references and loads held for "
                                   "random intervals; write one row per control sample (iL, vo, d, ...) as Parquet.")
    _add_plant_options(p)
    p.add_argument("--control-period", type=parse_period, default=PAPER_PERIOD, metavar="SECONDS",
                   help="sample period in s (default: 1e-3)")
    p.add_argument("--samples", type=bounded(int, MIN_SAMPLES), default=10_000,
                   help=f"number of samples (>= {MIN_SAMPLES}; default: 10000, the paper's)")
    p.add_argument("--excitation", type=bounded(float, 0.0, MAX_EXCITATION, below_high=True), default=None,
                   help=f"standard deviation of the duty dither added to the PI (default: {DITHER_SLOW} at control "
                        f"periods >= {TRANSIENT_WITHIN_SAMPLE_PERIOD * 1e3:g} ms, {DITHER_FAST} faster; 0 = plain PI)")
    p.add_argument("--seed", type=seed_value, default=0, help=f"random seed, 0 .. {SEED_MAX} (default: 0)")
    p.add_argument("--work-dir", default=str(DEFAULT_RESULTS / "runs-cli"), metavar="DIR",
                   help="where tuned PI gains are cached (default: results/runs-cli)")
    p.add_argument("--out", required=True, metavar="DATA.parquet", help="output file")
    p.set_defaults(func=cmd_collect)

    p = sub.add_parser("train", help="train an NN plant model from collected data",
                       description="Fit [iL, vo, d](k-1..k-D) (+ extra signals) -> [iL, vo](k) with torch; report "
                                   "held-out one-step and 10-step RMSE; save with weights only.")
    p.add_argument("data", help="samples written by collect-data (.parquet)")
    p.add_argument("--hidden", type=bounded(int, 1), nargs="+", default=[7],
                   help="hidden layer sizes (default: 7, the paper's)")
    p.add_argument("--activation", default="tanh", help="tanh (default), relu or sigmoid")
    p.add_argument("--delays", type=bounded(int, 1), default=1, help="past samples of [iL, vo, d] fed in (default: 1)")
    p.add_argument("--extra", action="append", choices=["load_conductance", "load_current", "input_voltage"],
                   help="extra measured input at k-1 (repeatable)")
    p.add_argument("--residual", action="store_true", help="learn the change over one sample (skip connection)")
    p.add_argument("--control-period", type=parse_period, metavar="SECONDS",
                   help="the period the samples were taken at, in s -- needed only for data without the workbench's "
                        "metadata (collect-data writes it); the model is then refused at any other period")
    p.add_argument("--multi-step-horizon", type=bounded(int, 1), default=1, metavar="SAMPLES",
                   help="after one-step training, minimise the simulation error over this many control samples "
                        "(the network rolled out with the recorded duties and extra inputs, its predictions fed "
                        "back); use the predictive controller's horizon, e.g. 23 at 13.33 us (default: 1 = one-step "
                        "training only)")
    p.add_argument("--multi-step-iterations", type=bounded(int, 0), default=400, metavar="N",
                   help="L-BFGS iterations of that stage, at most (early stopping on held-back windows; default: 400)")
    p.add_argument("--multi-step-stride", type=bounded(int, 1), default=1, metavar="SAMPLES",
                   help="one simulation window every this many samples (neighbours share all but one step; 6 "
                        "costs a sixth; default: 1)")
    p.add_argument("--extra-data", action="append", metavar="DATA.parquet",
                   help="more training records, e.g. collected with the NNPC in the loop (repeatable; used for "
                        "training only, the held-out tail stays that of DATA)")
    p.add_argument("--init", metavar="MODEL.pt",
                   help="refine this model (same network): keep its normalisation, skip the one-step stage")
    p.add_argument("--seed", type=seed_value, default=0, help=f"random seed, 0 .. {SEED_MAX} (default: 0)")
    p.add_argument("--out", required=True, metavar="MODEL.pt", help="output model file")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("distill", help="distill the NNPC into an explicit policy network (DAgger on the plant FMU)",
                       description="Train a small policy network to return the online NNPC's first move: DAgger on "
                                   "the plant FMU -- the current policy drives seeded random episodes (references "
                                   "3-20 V, loads 4-100 Ohm, start-ups from rest), the NNPC's C twin labels every "
                                   "visited state, labels are aggregated and the policy retrained, for a few rounds. "
                                   "The policy adds an integral term near the reference (offset-free) and saturates "
                                   "to the duty limits; run it with --controller nnpc-explicit --policy POLICY.pt or "
                                   "export it with export-controller nnpc-explicit.")
    p.add_argument("--model", required=True, metavar="NNPC.pt", help="the NNPC's NN plant model (buck-cosim train)")
    p.add_argument("--control-period", type=parse_period, metavar="SECONDS",
                   help="sample period in s, e.g. 1/75e3 (default: the model's); the model must have been trained "
                        "at it")
    p.add_argument("--out", required=True, metavar="POLICY.pt", help="the policy file to write")
    p.add_argument("--rounds", type=bounded(int, 0, 50), default=6,
                   help="DAgger rounds after the first, expert-driven one (default: %(default)s, as make reproduce)")
    p.add_argument("--episodes", type=bounded(int, 1, 1000), default=8,
                   help="closed-loop episodes per round (default: %(default)s)")
    p.add_argument("--samples", type=bounded(int, MIN_SAMPLES, 10**6), default=600,
                   help="control samples per episode (default: %(default)s, 8 ms at 13.33 us); each costs one NNPC "
                        "label, about 1 ms at 13.33 us")
    p.add_argument("--hidden", type=bounded(int, 1, 32), nargs="+", default=list(PolicyConfig.hidden),
                   help=f"tanh units per hidden layer of the policy (default: {' '.join(map(str, PolicyConfig.hidden))}"
                        f"; 7 inputs, so {PolicyConfig().macs()} MACs per step)")
    p.add_argument("--integral-gain", type=bounded(float, 0.0), default=None,
                   help=f"Ki of the offset-free integral term [1/(V s)] (default: {INTEGRAL_GAIN_PER_SAMPLE:.4g} / the "
                        "control period: 200 at 13.33 us, 2.67 at 1 ms)")
    p.add_argument("--integral-band", type=bounded(float, 0.0, 1.0), default=PolicyConfig.integral_band,
                   help="integrate only while |reference - vo| <= band x reference [1] (default: %(default)g)")
    p.add_argument("--seed", type=seed_value, default=0, help=f"random seed, 0 .. {SEED_MAX} (default: 0)")
    _add_plant_options(p)
    p.set_defaults(func=cmd_distill)

    p = sub.add_parser("export-controller", help="a controller as an FMI 2.0 (or 3.0) co-simulation FMU (C99)",
                       description="Write the workbench's PI, predictive controller (NNPC, MPC) or explicit NNPC as "
                                   "an FMI 2.0 (--fmi-version 3: FMI 3.0) co-simulation FMU built from the hand-written C99 twins of "
                                   "controllers/c and a generated header of data (gains, the horizon settings and the "
                                   "network's weights, or the policy's weights), plus its source FMU. Its variables "
                                   "carry the workbench's role names (reference, measured_output_voltage, measured_inductor_current, "
                                   "measured_load_current, input_voltage -> duty_cycle; parameter sample_period "
                                   "[s]); run it with 'buck-cosim run --controller NAME.fmu'.")
    p.add_argument("controller", choices=list(CONTROLLERS), help="which controller")
    p.add_argument("--control-period", type=parse_period, default=PAPER_PERIOD, metavar="SECONDS",
                   help="sample period in s, e.g. 1e-3 or 1/75e3 (default: 1e-3); the predictive settings are the "
                        "workbench's at that rate")
    p.add_argument("--out", required=True, metavar="NAME.fmu", help="the FMU to write (NAME-source.fmu beside it)")
    p.add_argument("--model", metavar="MODEL.pt", help="trained NN plant model for nnpc (default: trained on demand "
                                                     "on the plant below)")
    p.add_argument("--policy", metavar="POLICY.pt",
                   help="distilled policy for nnpc-explicit (buck-cosim distill; default: distilled on demand)")
    p.add_argument("--precision", choices=("float64", "float32"), default="float64",
                   help="the arithmetic of the C twin the FMU is built from: float64 (double, default) or float32 "
                        f"(single precision, as on a Cortex-M4F; {', '.join(FLOAT32_CONTROLLERS)} only). The FMU's "
                        "variables stay fmi2Real; a float32 FMU rounds its inputs to float at each sample")
    p.add_argument("--cortex-m4", metavar="DIR",
                   help="with --precision float32: also cross-compile the controller for a Cortex-M4F into "
                        "DIR/controller.o (+ buckc_controller.h, buckc.h), the object a firmware links "
                        "(needs gcc-arm-none-eabi and libnewlib-arm-none-eabi)")
    _add_fmi_version_option(p, "the controller FMU's")
    _add_controller_design_options(p)
    _add_plant_options(p)
    p.set_defaults(func=cmd_export_controller)

    p = sub.add_parser("export-ssp", help="the closed loop as an SSP 1.0 archive (scenario, controller, plant FMUs)",
                       description="Write the closed loop of SCENARIO as an SSP 1.0 archive: the scenario as a "
                                   "signal-source FMU, the controller FMU, the plant FMU, their connections, the "
                                   "parameter values (.ssv), units and a default experiment (stop time, a "
                                   "communication step on every control sample and event). Time in the archive is "
                                   "plant time: the scenario's t = 0 at the end of its settle interval. Run it with "
                                   "'buck-cosim run-ssp', fmpy or libcosim.")
    p.add_argument("scenario", metavar="SCENARIO", help="shipped scenario name or path to a scenario TOML file")
    p.add_argument("--controller", required=True, metavar="NAME|FMU",
                   help=f"{', '.join(CONTROLLERS)} (exported as with export-controller) or a controller FMU with the "
                        "workbench's role names")
    p.add_argument("--control-period", type=parse_period, default=None, metavar="SECONDS",
                   help="controller sample period in s (default: 1e-3; a controller FMU's own period)")
    p.add_argument("--communication-step", type=parse_period, default=None, metavar="SECONDS",
                   help="the engines' communication step in s; must divide the control period and land on every "
                        "event (default: 1e-5, the workbench's recording period)")
    p.add_argument("--out", required=True, metavar="LOOP.ssp", help="the archive to write")
    p.add_argument("--model", metavar="MODEL.pt", help="trained NN plant model for nnpc (default: trained on demand)")
    p.add_argument("--fmi-version", type=int, choices=(2, 3), default=2, metavar="{2,3}",
                   help="3: the built-in controller, the scenario source and the built-in plant as FMI 3.0 FMUs (a "
                        "--plant binding file keeps its FMU); only --engine workbench runs such an archive "
                        "(default: 2)")
    _add_controller_design_options(p)
    _add_plant_options(p)
    p.set_defaults(func=cmd_export_ssp)

    p = sub.add_parser("run-ssp", help="run an SSP of the loop with the workbench, fmpy or libcosim",
                       description="Run an archive written by export-ssp with the workbench's master (reading the "
                                   "SSP), fmpy's SSP simulation (fixed-step Jacobi) or libcosim (libcosimpy, "
                                   "fixed-step Jacobi), and write the result as a workbench run table (OUT/runs: "
                                   "the columns of 'run', metadata naming the engine; controller_compute_time is "
                                   "NaN for fmpy and libcosim) and its metrics (OUT/metrics).")
    p.add_argument("ssp", metavar="LOOP.ssp", help="an archive written by buck-cosim export-ssp")
    p.add_argument("--engine", choices=["workbench", "fmpy", "libcosim"], required=True,
                   help="co-simulation engine (fmpy and libcosim run FMI 2.0 components only)")
    p.add_argument("--communication-step", type=parse_period, default=None, metavar="SECONDS",
                   help="communication step in s (default: the archive's); must divide the control period and land "
                        "on every event")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.set_defaults(func=cmd_run_ssp)

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

    p = sub.add_parser("build-fmu", help="compile BuckConverter.fmu (FMI 2.0 or 3.0) from its C sources with fmpy",
                       description="Build the plant FMU (model exchange + co-simulation) with fmpy's CMake "
                                   "compile; cached by a hash of the sources. Also writes a source-only FMU. "
                                   "--fmi-version 3 builds the FMI 3.0 edition: the same model code behind the "
                                   "FMI 3.0 glue (it computes the same values as the FMI 2.0 one).")
    p.add_argument("--output", metavar="DIR", help="copy BuckConverter.fmu and BuckConverter-source.fmu here")
    p.add_argument("--force", action="store_true", help="rebuild even if a cached build exists")
    _add_fmi_version_option(p, "the plant FMU's")
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

    p = sub.add_parser("frequency-response", help="loop gain, margins or output impedance by injection on the plant FMU",
                       description="Measure a controller's loop in closed loop on the plant FMU by injecting a small "
                                   "sine -- at the duty (loop gain T = -U/D, crossover, phase and gain margins), at "
                                   "the reference (closed-loop Vo/R) or at the load (output impedance -Vo/Io) -- and "
                                   "correlating at the injection frequency, one run per frequency on the sweep "
                                   "engine (a local dask cluster). Beside each point: the averaged small-signal "
                                   "closed form (PI, current-mode, Type-III). Writes DIR/frequency_response.csv, "
                                   ".json (margins) and .png (Bode plot, margins marked).")
    p.add_argument("--controller", action="append", metavar="NAME",
                   help="pi, pi-envelope, current-mode, type-iii, nnpc, nnpc-explicit, mpc-oracle, mpc-nominal "
                        "(repeatable; default: pi)")
    p.add_argument("--injection", choices=["duty", "reference", "load"], default="duty",
                   help="where the sine goes in (default: duty)")
    p.add_argument("--control-period", type=parse_period, default=1 / 75e3, metavar="SECONDS",
                   help="controller sample period in s (default: 1/75e3)")
    p.add_argument("--low", type=float, default=100.0, metavar="HZ", help="lowest frequency [Hz] (default: 100)")
    p.add_argument("--high", type=float, default=30e3, metavar="HZ", help="highest frequency [Hz] (default: 30e3)")
    p.add_argument("--points", type=int, default=24, metavar="N", help="log-spaced frequencies (default: 24)")
    p.add_argument("--amplitude", type=float, default=None,
                   help="injection amplitude: duty [1] (default 0.01), reference [V] (0.1), load [relative "
                        "conductance change] (0.05)")
    p.add_argument("--reference", type=float, default=12.0, metavar="V", help="operating point: reference [V]")
    p.add_argument("--load", type=float, default=6.0, metavar="OHM", help="operating point: load [Ohm]")
    p.add_argument("--input-voltage", type=float, default=48.0, metavar="V", help="operating point: supply [V]")
    p.add_argument("--settle", type=float, default=15e-3, metavar="SECONDS",
                   help="closed loop from rest before the injection starts [s] (default: 0.015)")
    p.add_argument("--workers", type=int, metavar="N", help="local dask workers (default: one per core)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    _add_plant_options(p)
    _add_implementation_option(p)
    p.set_defaults(func=cmd_frequency_response)

    p = sub.add_parser("bench", help="run the benchmark suite; write results/benchmarks.md and .csv",
                       description="Measure plant, master and controller costs as medians, p99 and same-run "
                                   "ratios; write benchmarks.md and benchmarks.csv.")
    p.add_argument("--quick", action="store_true",
                   help="run each benchmark once on a tiny size (smoke test; writes benchmarks-quick.*)")
    p.add_argument("--only", action="append", metavar="NAME", help="run only this benchmark (repeatable)")
    p.add_argument("--out", default=str(DEFAULT_RESULTS), metavar="DIR", help="output folder (default: results)")
    p.add_argument("--models", metavar="DIR", default=None,
                   help="the reproduction's trained models to time (default: OUT/models, beside the tables written)")
    p.set_defaults(func=cmd_bench)
    return parser


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        return args.func(args) or 0
    except WorkbenchError as error:
        print(f"error: {' '.join(str(error).split())}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt:
        print("error: interrupted; files already complete were kept and none is half-written", file=sys.stderr)
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
