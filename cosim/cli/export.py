"""Commands that take the loop out of the workbench and back: ``export-controller``, ``export-ssp``,
``run-ssp``, ``build-fmu``."""

from __future__ import annotations

from pathlib import Path

from cosim.base.errors import BuildError, ConfigError
from cosim.cli.options import (
    EXPORTED_PREDICTIVE,
    _add_controller_design_options,
    _add_fmi_version_option,
    _add_plant_options,
    _check_duty_limits,
    _plant_binding,
    cache_dir,
    input_file,
    optimizer_options,
    output_dir,
    output_file,
    parse_period,
)
from cosim.design.vocabulary import EXPORTABLE_CONTROLLERS, FLOAT32_CONTROLLERS, PAPER_PERIOD


def _design_controller(args, binding, period: float, work_dir: Path, policy_path: str | None = None):
    """The built-in controller ``args.controller`` designed for ``binding`` at ``period`` from the options of
    :func:`_add_controller_design_options` (tuned, trained or distilled on demand, cached in ``work_dir``)."""
    from cosim.design.controller_factory import make_controllers

    optimizer, rti_changes = optimizer_options(args)
    [controller] = make_controllers([args.controller], binding, period, work_dir,
                                    duty_limits=(args.duty_min, args.duty_max), kp=args.kp, ki=args.ki,
                                    model_path=args.model, samples=args.samples, seed=args.seed,
                                    progress=args.progress, policy_path=policy_path, optimizer=optimizer,
                                    rti_changes=rti_changes, offered=EXPORTED_PREDICTIVE)
    return controller


def _export_controller_fmu(controller, out: Path, precision: str = "float64", fmi_version: int = 2) -> tuple[Path, Path]:
    """Write ``controller`` as a controller FMU (FMI ``fmi_version``) at ``out`` from the ``precision`` build of its
    C twin: (binary FMU, source FMU); a configuration its C twin cannot hold is a ConfigError naming the controller."""
    from cosim.fmi.controller_export import export_controller

    try:
        return export_controller(controller, out, precision=precision, fmi_version=fmi_version)
    except ValueError as error:  # a configuration the C twins cannot hold
        raise ConfigError(f"{controller.name}: {error}") from None


def cmd_export_controller(args) -> int:
    out = output_file(args.out, (".fmu",))
    _check_duty_limits(args)
    if args.cortex_m4:
        from cosim.benchmark_harness.cortex_m4 import toolchain_problem

        if args.precision != "float32":
            raise ConfigError(f"--cortex-m4 {args.cortex_m4} needs --precision float32 (the object is the float32 "
                              "build)")
        if toolchain_problem():
            raise ConfigError(f"--cortex-m4 {args.cortex_m4}: {toolchain_problem()}")
        output_dir(args.cortex_m4)  # an unwritable folder before the FMU is designed, built and written
    if args.precision == "float32" and args.controller not in FLOAT32_CONTROLLERS:
        raise ConfigError(f"--precision float32: {args.controller} has no float32 controller FMU (the predictive "
                          "controller FMU computes in double; the online NNPC's float32 build runs on the Cortex-M4F: "
                          "docs/guide/embedded.md); expected one of "
                          f"{', '.join(FLOAT32_CONTROLLERS)}")
    work_dir = cache_dir(args.work_dir)
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
        print(f"the same controller for a Cortex-M4F (float32, -O2, hard float): {target} (how to link it: "
              "docs/guide/embedded.md)")
    return 0


def cmd_export_ssp(args) -> int:
    import re
    import tempfile

    from cosim.master import check_plant_supports
    from cosim.scenarios import load_scenario
    from cosim.ssp.package import export_ssp
    from cosim.timeline import plan_timeline

    out = output_file(args.out, (".ssp",))
    _check_duty_limits(args)
    if args.controller not in EXPORTABLE_CONTROLLERS:  # an FMU: the options that design a built-in one do not apply
        given = [f"--{name}" for name, value in (("kp", args.kp), ("ki", args.ki), ("model", args.model),
                                                 ("samples", args.samples), ("optimizer", args.optimizer))
                 if value is not None]
        given += ["--rti"] if args.rti else []
        given += ["--duty-min/--duty-max"] if (args.duty_min, args.duty_max) != (0.0, 1.0) else []
        if given:
            raise ConfigError(f"{', '.join(given)} design a built-in controller, but --controller {args.controller} "
                              f"is a controller FMU, which brings its own: drop {', '.join(given)}")
    binding = _plant_binding(args)
    scenario = load_scenario(args.scenario, binding.converter, warn=True)
    if args.fmi_version == 3 and binding.source is None:  # the built-in plant's FMI 3.0 edition
        from dataclasses import replace

        from plant_fmu import fmu_path

        binding = replace(binding, fmu_path=fmu_path(fmi_version=3))
    check_plant_supports(binding, scenario)  # before any tuning or training
    with tempfile.TemporaryDirectory(prefix="buck-cosim-export-ssp-") as tmp:
        if args.controller in EXPORTABLE_CONTROLLERS:
            period = args.control_period or PAPER_PERIOD
            plan_timeline(scenario, period, period)
            controller = _design_controller(args, binding, period, cache_dir(args.work_dir))
            fmu, _ = _export_controller_fmu(controller,
                                            Path(tmp) / f"{re.sub(r'[^A-Za-z0-9_]', '_', controller.name)}.fmu",
                                            fmi_version=args.fmi_version)
        else:
            from cosim.fmi.controller import controller_binding

            if Path(args.controller).suffix.lower() != ".fmu":
                raise ConfigError(f"--controller {args.controller} is invalid: expected "
                                  f"{', '.join(EXPORTABLE_CONTROLLERS)} or a controller FMU (.fmu) with the "
                                  "workbench's role names")
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


def add_export_controller_parser(sub) -> None:
    p = sub.add_parser("export-controller", help="a controller as an FMI 2.0 (or 3.0) co-simulation FMU (C99)",
                       description="Write the workbench's PI, predictive controller (NNPC, MPC) or explicit NNPC as "
                                   "an FMI 2.0 (--fmi-version 3: FMI 3.0) co-simulation FMU built from the hand-written C99 twins of "
                                   "controllers/c and a generated header of data (gains, the horizon settings and the "
                                   "network's weights, or the policy's weights), plus its source FMU. Its variables "
                                   "carry the workbench's role names (reference, measured_output_voltage, measured_inductor_current, "
                                   "measured_load_current, input_voltage -> duty_cycle; parameter sample_period "
                                   "[s]); run it with 'buck-cosim run --controller NAME.fmu'.")
    p.add_argument("controller", choices=list(EXPORTABLE_CONTROLLERS), help="which controller")
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
                        "DIR/controller.o (+ buckc_controller.h, buckc.h, buckc_tanhf.h), the object a firmware links "
                        "(needs gcc-arm-none-eabi and libnewlib-arm-none-eabi)")
    _add_fmi_version_option(p, "the controller FMU's")
    _add_controller_design_options(p)
    _add_plant_options(p)
    p.set_defaults(func=cmd_export_controller)


def add_export_ssp_parser(sub) -> None:
    p = sub.add_parser("export-ssp", help="the closed loop as an SSP 1.0 archive (scenario, controller, plant FMUs)",
                       description="Write the closed loop of SCENARIO as an SSP 1.0 archive: the scenario as a "
                                   "signal-source FMU, the controller FMU, the plant FMU, their connections, the "
                                   "parameter values (.ssv), units and a default experiment (stop time, a "
                                   "communication step on every control sample and event). Time in the archive is "
                                   "plant time: the scenario's t = 0 at the end of its settle interval. Run it with "
                                   "'buck-cosim run-ssp', fmpy or libcosim.")
    p.add_argument("scenario", metavar="SCENARIO", help="shipped scenario name or path to a scenario TOML file")
    p.add_argument("--controller", required=True, metavar="NAME|FMU",
                   help=f"{', '.join(EXPORTABLE_CONTROLLERS)} (exported as with export-controller) or a controller FMU "
                        "with the workbench's role names")
    p.add_argument("--control-period", type=parse_period, default=None, metavar="SECONDS",
                   help="controller sample period in s (default: 1e-3; a controller FMU's own period)")
    p.add_argument("--communication-step", type=parse_period, default=None, metavar="SECONDS",
                   help="the engines' communication step in s; must divide the control period and land on every "
                        "event (default: 1e-5, the workbench's recording period; a fixed-step plant FMU's own step, "
                        "the only one it takes)")
    p.add_argument("--out", required=True, metavar="LOOP.ssp", help="the archive to write")
    p.add_argument("--model", metavar="MODEL.pt", help="trained NN plant model for nnpc (default: trained on demand)")
    p.add_argument("--fmi-version", type=int, choices=(2, 3), default=2, metavar="{2,3}",
                   help="3: the built-in controller, the scenario source and the built-in plant as FMI 3.0 FMUs (a "
                        "--plant binding file keeps its FMU); only --engine workbench runs such an archive "
                        "(default: 2)")
    _add_controller_design_options(p)
    _add_plant_options(p)
    p.set_defaults(func=cmd_export_ssp)


def add_run_ssp_parser(sub) -> None:
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


def add_build_fmu_parser(sub) -> None:
    p = sub.add_parser("build-fmu", help="compile BuckConverter.fmu (FMI 2.0 or 3.0) from its C sources with fmpy",
                       description="Build the plant FMU (model exchange + co-simulation) with fmpy's CMake "
                                   "compile; cached by a hash of the sources. Also writes a source-only FMU. "
                                   "--fmi-version 3 builds the FMI 3.0 edition: the same model code behind the "
                                   "FMI 3.0 glue (it computes the same values as the FMI 2.0 one).")
    p.add_argument("--output", metavar="DIR", help="copy BuckConverter.fmu and BuckConverter-source.fmu here")
    p.add_argument("--force", action="store_true", help="rebuild even if a cached build exists")
    _add_fmi_version_option(p, "the plant FMU's")
    p.set_defaults(func=cmd_build_fmu)
