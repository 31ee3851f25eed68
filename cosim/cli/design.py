"""Commands that design controllers: ``collect-data``, ``train``, ``distill``, ``tune-pi``."""

from __future__ import annotations

import math
import sys
from pathlib import Path

from controllers.explicit_policy import INTEGRAL_GAIN_PER_SAMPLE, PolicyConfig
from cosim.base.errors import ConfigError
from cosim.cli.options import (
    DEFAULT_RESULTS,
    SEED_MAX,
    _add_plant_options,
    _plant_binding,
    bounded,
    cache_dir,
    input_file,
    output_file,
    parse_period,
    seed_value,
)
from cosim.design.data_collection import MAX_EXCITATION, MIN_SAMPLES
from cosim.design.vocabulary import (
    COLLECTION_REGIONS,
    DITHER_FAST,
    DITHER_SLOW,
    ENVELOPE_DITHER,
    OPTIMIZERS,
    PAPER_PERIOD,
    TRANSIENT_WITHIN_SAMPLE_PERIOD,
)

#: what a model or policy file written by train or distill may be named (torch's archive, by its usual endings)
MODEL_SUFFIXES = (".pt", ".pth")


def cmd_tune_pi(args) -> int:
    from cosim.base.files import atomic_write_text
    from cosim.design.pi_tuning import tune_pi

    output_file(args.out, (".json",), "the gains are written as JSON")
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
    from cosim.design.data_collection import collect, save_samples
    from cosim.design.experiments import collection_settings
    from cosim.master import check_set_up
    from cosim.scenarios import load_scenario

    output_file(args.out, (".parquet",), "the samples are written as Parquet, with their metadata")
    work_dir = cache_dir(args.work_dir)
    binding = _plant_binding(args)
    settings = collection_settings(args.control_period, args.samples, args.seed, args.excitation, args.region,
                                   spec=binding.converter)
    settings.check()  # all of it before the PI is tuned (seconds, or minutes on a slow external plant)
    # what the FMU refuses, even where the PI tuning is cached
    check_set_up(binding, [load_scenario("startup", binding.converter)])
    from cosim.design.controller_factory import tuned_pi  # scipy.optimize: after the checks

    pi = tuned_pi(binding, args.control_period, work_dir, args.progress)
    data = collect(binding, pi.controller(), settings, progress=args.progress)
    save_samples(data, Path(args.out))
    print(f"wrote {len(data)} samples ({', '.join(data.columns)}) to {args.out}")
    return 0


def cmd_train(args) -> int:
    from controllers.nn_config import NNConfig, TrainingSettings, extra_columns
    from cosim.results import is_parquet, read_parquet

    try:  # arguments first, before any file is read
        config = NNConfig(hidden=tuple(args.hidden), activation=args.activation, delays=args.delays,
                          extra_signals=tuple(args.extra or ()), residual=args.residual)
        settings = TrainingSettings(seed=args.seed, multi_step_horizon=args.multi_step_horizon,
                                    multi_step_iterations=args.multi_step_iterations,
                                    multi_step_stride=args.multi_step_stride)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    output_file(args.out, MODEL_SUFFIXES, "the model is written as a torch archive")
    needed = ["measured_inductor_current", "measured_output_voltage", "duty_cycle", *extra_columns(config)]

    def samples(name: str):
        source = input_file(name, "data file", "write one with buck-cosim collect-data")
        if not is_parquet(source):
            raise ConfigError(f"{source} is not a Parquet file{' (it is a CSV)' if source.suffix == '.csv' else ''}: "
                              "expected the samples .parquet that buck-cosim collect-data writes")
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
    from cosim.base.digests import file_sha256

    extra, contents = [], ({file_sha256(source): source} if args.extra_data else {})  # hashed only to compare
    for name in args.extra_data or ():
        other, more, more_meta = samples(name)
        first = contents.setdefault(file_sha256(other), other)
        if first != other:  # the held-out share of the data would be trained on: its RMSE would flatter the model
            raise ConfigError(f"--extra-data {other} holds the same samples as {first}: training on them twice "
                              "would train on the held-out share too (an optimistic held-out RMSE)")
        other_period = more_meta.get("control_period_s")
        if other_period is not None and not math.isclose(period, other_period, rel_tol=1e-9):
            raise ConfigError(f"{other} was collected at a control period of {other_period:.6g} s, "
                              f"{source} at {period:.6g} s: train on data of one rate")
        extra.append(more)
    from controllers.nn_model import load_model, save_model, train  # torch: after every check of the arguments

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
    from cosim.design.identification import write_identification_figure

    figure = write_identification_figure(model, frame, Path(args.out))
    print(f"wrote {args.out} and {figure} (learning curves, held-out predictions)")
    return 0


def cmd_distill(args) -> int:
    from dataclasses import replace

    from controllers.explicit_policy import save_policy
    from controllers.nn_model import load_model
    from cosim.design.distillation import FULL_DISTILLATION, distill

    try:  # arguments first, before any file is read or any work starts
        policy_config = PolicyConfig(hidden=tuple(args.hidden), integral_gain=args.integral_gain,
                                     integral_band=args.integral_band)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    settings = replace(FULL_DISTILLATION, rounds=args.rounds, episodes=args.episodes, samples=args.samples,
                       seed=args.seed, policy=policy_config,
                       expert_optimizer=args.expert_optimizer)
    settings.check()
    output_file(args.out, MODEL_SUFFIXES, "the policy is written as a torch archive")
    source = input_file(args.model, "model file", "train one with buck-cosim train")
    model = load_model(source, expect_period=args.control_period)
    period = args.control_period or model.metadata.get("control_period_s")
    if period is None:
        raise ConfigError(f"model file {source} names no control period: give --control-period")
    binding = _plant_binding(args)
    if not binding.has("inductor_current"):
        raise ConfigError(f"the NNPC needs the inductor_current role, which {binding.origin} does not bind")
    from cosim.design.experiments import implemented, nnpc

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


def add_collect_data_parser(sub) -> None:
    p = sub.add_parser("collect-data", help="collect NN training data with the tuned PI (paper Section IV)",
                       description="Drive the plant with the tuned PI under random references and loads (and, over "
                                   "the envelope, supplies) held for random intervals, its duty dithered; write one "
                                   "row per control sample (iL, vo, d, ...) as Parquet. The region, over the "
                                   "plant's converter spec (a binding file's [converter] table; Table II for the "
                                   "built-in plant): 'paper' -- the paper's experiment scaled to it (references 0 V "
                                   "to the top of its output range, loads from its smallest to 5/3 x its nominal load "
                                   "at its nominal supply; Table II: 0-20 V, 4-10 Ohm at 48 V), a white dither; "
                                   "'envelope' -- references, loads and supplies over its ranges (Table II: 3-20 V, "
                                   "4-100 Ohm, 36-60 V; a plant binding without an input_voltage role keeps its "
                                   "supply), an amplitude-modulated random binary dither. Default: the workbench's recipe, "
                                   "'paper' at control periods >= 1 ms, 'envelope' faster (train such data with "
                                   "--extra load_conductance input_voltage).")
    _add_plant_options(p)
    p.add_argument("--control-period", type=parse_period, default=PAPER_PERIOD, metavar="SECONDS",
                   help="sample period in s (default: 1e-3)")
    p.add_argument("--samples", type=bounded(int, MIN_SAMPLES), default=10_000,
                   help=f"number of samples (>= {MIN_SAMPLES}; default: 10000, the paper's)")
    p.add_argument("--excitation", type=bounded(float, 0.0, MAX_EXCITATION, below_high=True), default=None,
                   help=f"the duty dither added to the PI: the white dither's standard deviation in the paper region "
                        f"(default: {DITHER_SLOW} at control periods >= {TRANSIENT_WITHIN_SAMPLE_PERIOD * 1e3:g} ms, "
                        f"{DITHER_FAST} faster), the binary dither's largest level over the envelope (default: "
                        f"{ENVELOPE_DITHER}); 0 = plain PI")
    p.add_argument("--region", choices=COLLECTION_REGIONS, default=None,
                   help="where the references, loads and supplies are drawn (default: 'paper' at control periods "
                        f">= {TRANSIENT_WITHIN_SAMPLE_PERIOD * 1e3:g} ms, 'envelope' faster)")
    p.add_argument("--seed", type=seed_value, default=0, help=f"random seed, 0 .. {SEED_MAX} (default: 0)")
    p.add_argument("--work-dir", default=str(DEFAULT_RESULTS / "runs-cli"), metavar="DIR",
                   help="where tuned PI gains are cached, created only when they are (default: results/runs-cli, "
                        "relative to the current folder)")
    p.add_argument("--out", required=True, metavar="DATA.parquet",
                   help="the samples file to write: Parquet with the collection's metadata (the name must end in .parquet)")
    p.set_defaults(func=cmd_collect)


def add_train_parser(sub) -> None:
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
    p.add_argument("--out", required=True, metavar="MODEL.pt",
                   help="the model file to write: a torch archive (the name must end in .pt or .pth)")
    p.set_defaults(func=cmd_train)


def add_distill_parser(sub) -> None:
    p = sub.add_parser("distill", help="distill the NNPC into an explicit policy network (DAgger on the plant FMU)",
                       description="Train a small policy network to return the online NNPC's first move: DAgger on "
                                   "the plant FMU -- the current policy drives seeded random episodes (references "
                                   "and loads over the plant's converter envelope, Table II: 3-20 V, 4-100 Ohm; "
                                   "start-ups from rest), the NNPC's C twin labels every "
                                   "visited state, labels are aggregated and the policy retrained, for a few rounds. "
                                   "The policy adds an integral term near the reference (offset-free) and saturates "
                                   "to the duty limits; run it with --controller nnpc-explicit --policy POLICY.pt or "
                                   "export it with export-controller nnpc-explicit.")
    p.add_argument("--model", required=True, metavar="NNPC.pt", help="the NNPC's NN plant model (buck-cosim train)")
    p.add_argument("--control-period", type=parse_period, metavar="SECONDS",
                   help="sample period in s, e.g. 1/75e3 (default: the model's); the model must have been trained "
                        "at it")
    p.add_argument("--out", required=True, metavar="POLICY.pt",
                   help="the policy file to write: a torch archive (the name must end in .pt or .pth)")
    p.add_argument("--rounds", type=bounded(int, 0, 50), default=6,
                   help="DAgger rounds after the first, expert-driven one (default: %(default)s, as make reproduce)")
    p.add_argument("--episodes", type=bounded(int, 1, 1000), default=8,
                   help="closed-loop episodes per round (default: %(default)s)")
    p.add_argument("--samples", type=bounded(int, MIN_SAMPLES, 10**6), default=600,
                   help="control samples per episode (default: %(default)s, 8 ms at 13.33 us); each costs one NNPC "
                        "label and one plant step")
    p.add_argument("--hidden", type=bounded(int, 1, 32), nargs="+", default=list(PolicyConfig.hidden),
                   help=f"tanh units per hidden layer of the policy (default: {' '.join(map(str, PolicyConfig.hidden))}"
                        f"; 7 inputs, so {PolicyConfig().macs()} MACs per step)")
    p.add_argument("--integral-gain", type=bounded(float, 0.0), default=None,
                   help=f"Ki of the offset-free integral term [1/(V s)] (default: {INTEGRAL_GAIN_PER_SAMPLE:.4g} / the "
                        "control period: 200 at 13.33 us, 2.67 at 1 ms)")
    p.add_argument("--integral-band", type=bounded(float, 0.0, 1.0), default=PolicyConfig.integral_band,
                   help="integrate only while |reference - vo| <= band x reference [1] (default: %(default)g)")
    p.add_argument("--expert-optimizer", choices=OPTIMIZERS, default=None,
                   help="the optimizer of the online NNPC whose first moves label the states (default: the "
                        "workbench's, the RTI, as make reproduce: microseconds per label at 13.33 us; search: about "
                        "1 ms; their policies side by side on every seed: results/explicit-every-seed.md and "
                        "explicit-every-seed-search-labels.md)")
    p.add_argument("--seed", type=seed_value, default=0, help=f"random seed, 0 .. {SEED_MAX} (default: 0)")
    _add_plant_options(p)
    p.set_defaults(func=cmd_distill)


def add_tune_pi_parser(sub) -> None:
    p = sub.add_parser("tune-pi", help="tune the PI for a plant and control period",
                       description="Tune Kp, Ki by the repeatable method in cosim/design/pi_tuning.py.")
    _add_plant_options(p)
    p.add_argument("--control-period", type=parse_period, default=PAPER_PERIOD, metavar="SECONDS",
                   help="controller sample period in s (default: 1e-3)")
    p.add_argument("--out", metavar="FILE.json", help="write the gains as JSON (the name must end in .json)")
    p.set_defaults(func=cmd_tune_pi)
