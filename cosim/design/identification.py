"""How the workbench identifies its NNPC: PI data, simulation-error training, NNPC-in-the-loop data.

One recipe, used by the reproduction and by ``buck-cosim run --controller nnpc`` alike
(:func:`identify`):

1. **PI data** -- the paper's identification experiment (:mod:`cosim.design.data_collection`):
   the tuned PI under seeded random references and loads, with a duty dither;
2. **one-step training** -- the paper's loss, full-batch L-BFGS (:func:`controllers.nn_model.train`);
3. **simulation-error training** -- from that solution, the error of the network rolled out over
   the predictive controller's horizon with the recorded duties (at 1 ms the horizon is one
   sample, so this stage is the one-step one);
4. **closed-loop rounds** (optional, ``Recipe.rounds``; none by default): collect data with the
   NNPC itself in the loop (its full-duty and braking moves, which the PI never makes) under new
   random references and loads, and refine stage 3 on the PI and NNPC data together
   (:func:`closed_loop_round`).

Every stage is seeded; the same seed gives the same weights. :class:`Identified` keeps each
stage's model, so the reproduction measures what each one buys (its ablation table). Why no
closed-loop round by default: measured on five seeds, a round of 3000 samples changed the worst
start-up overshoot and IAE ratios by less than their spread over seeds (switched plant: 1.6 ->
2.4 %, 1.09 -> 1.07) and a round of 1000 made them worse (4.4 %, and 1.45 x the oracle on one
seed's load change on the averaged plant), while each round costs as much as the rest of the
identification; the reproduction keeps one round as an ablation variant.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from controllers.nn_config import NNConfig, TrainingSettings
from controllers.predictors import data_domain, domain_text
from cosim.converter_spec import ConverterSpec
from cosim.design.data_collection import CollectionSettings, collect
from cosim.design.design_cache import DesignKey, design_key
from cosim.design.experiments import collection_settings, horizon_settings, implemented, network_region, nnpc
from cosim.design.vocabulary import (
    CLOSED_LOOP_DITHER,
    CLOSED_LOOP_ITERATIONS,
    CLOSED_LOOP_SAMPLES,
    CLOSED_LOOP_SEED_OFFSET,
    DEFAULT_IMPLEMENTATION,
    MULTI_STEP_ITERATIONS,
    MULTI_STEP_STRIDE,
    ONE_STEP_ITERATIONS,
)
from cosim.fmi.binding import PlantBinding

if TYPE_CHECKING:  # torch loads with the NN model's module (seconds): only where a network is trained
    from controllers.nn_model import NNPlantModel

#: the stages an :class:`Identified` keeps, in order
ONE_STEP, MULTI_STEP, CLOSED_LOOP = "one-step", "multi-step", "closed-loop"


def training_settings(control_period: float, seed: int, iterations: int = MULTI_STEP_ITERATIONS,
                      spec: ConverterSpec | None = None) -> TrainingSettings:
    """Training per rate: the simulation-error stage spans the predictive controller's horizon on ``spec``'s
    converter (None: the paper study's; one sample at 1 ms, where it is the one-step loss)."""
    horizon = horizon_settings(control_period, spec=spec).horizon
    if horizon == 1:  # the one-step training of the paper, as before
        return TrainingSettings(seed=seed)
    return TrainingSettings(seed=seed, max_iterations=ONE_STEP_ITERATIONS, multi_step_horizon=horizon,
                            multi_step_stride=MULTI_STEP_STRIDE, multi_step_iterations=iterations)


@dataclass(frozen=True)
class Recipe:
    samples: int = 10_000  # PI data (the paper's 10 000)
    rounds: int = 0  # NNPC-in-the-loop rounds after the simulation-error stage
    closed_loop_samples: int = CLOSED_LOOP_SAMPLES  # per round
    closed_loop_dither: float = CLOSED_LOOP_DITHER  # duty dither on the NNPC in those rounds
    closed_loop_iterations: int = CLOSED_LOOP_ITERATIONS  # of the refinement after each round, at most
    implementation: str = DEFAULT_IMPLEMENTATION  # the NNPC in the rounds: its C twin (same duties, faster) or Python
    multi_step_iterations: int = MULTI_STEP_ITERATIONS  # at most, per simulation-error stage


def network_design(name: str, binding: PlantBinding, control_period: float, config: NNConfig, seed: int,
                   samples: int, *, recipe: Recipe | None = None, training: TrainingSettings | None = None,
                   pi_key: str | None = None) -> DesignKey:
    """The design key of a network ``name`` identified on ``binding`` at ``control_period`` [s]: by
    :func:`identify` with ``recipe`` (the workbench's NNPC), else by one ``train`` with ``training``
    on the PI data (the paper's network); ``samples`` of PI data collected with ``seed`` by the PI
    whose design key is ``pi_key`` (:mod:`cosim.design.design_cache`)."""
    collection = collection_settings(control_period, samples, seed, region=network_region(name, control_period),
                                     spec=binding.converter)
    if recipe is not None:
        training = training_settings(control_period, seed, recipe.multi_step_iterations, binding.converter)
    settings = {"network": asdict(config), "collection": asdict(collection),
                "training": asdict(training or TrainingSettings(seed=seed)),
                "recipe": asdict(recipe) if recipe is not None else None}
    return design_key(f"nn-model:{name}", binding, control_period, seed=seed, settings=settings,
                      depends_on={"pi": pi_key})


@dataclass
class Identified:
    model: NNPlantModel  # the final model
    data: pd.DataFrame  # the PI data
    stages: dict[str, NNPlantModel] = field(default_factory=dict)  # ONE_STEP, MULTI_STEP, CLOSED_LOOP 1, ...
    closed_loop: list[pd.DataFrame] = field(default_factory=list)


def identify(binding: PlantBinding, pi_controller, control_period: float, config: NNConfig, seed: int,
             recipe: Recipe = Recipe(), metadata: dict | None = None, data: pd.DataFrame | None = None,
             progress: bool = False, collection: CollectionSettings | None = None) -> Identified:
    """The workbench's identification of ``config`` on ``binding`` (module docstring), seeded.

    ``data``: PI data collected already, with ``collection`` (default: ``collection_settings(period, samples,
    seed)``, the rate's recipe); the model's metadata records those settings.
    """
    from controllers.nn_model import train

    settings = collection if collection is not None else collection_settings(control_period, recipe.samples, seed,
                                                                                spec=binding.converter)
    if data is None:
        data = collect(binding, pi_controller, settings, progress=progress)
    training = training_settings(control_period, seed, recipe.multi_step_iterations, binding.converter)
    rounds = recipe.rounds
    meta = {"control_period_s": control_period, "plant": binding.label, "seed": seed,
            "collection": asdict(settings), **(metadata or {})}

    def described(model: NNPlantModel, stage: str, extra: list) -> NNPlantModel:
        model.metadata["identification"] = {
            "stage": stage, "closed_loop_rounds": len(extra),
            "closed_loop_samples": int(sum(len(f) for f in extra)),
            "closed_loop_dither": recipe.closed_loop_dither if extra else None}
        return model

    stages: dict[str, NNPlantModel] = {}
    one_step = train(data, config, replace(training, multi_step_horizon=1), metadata=meta, progress=progress)
    stages[ONE_STEP] = described(one_step, ONE_STEP, [])
    model = one_step
    if training.multi_step_horizon > 1 and training.multi_step_iterations > 0:
        model = described(train(data, config, training, metadata=meta, progress=progress, initial=one_step),
                          MULTI_STEP, [])
        model.metadata["training"]["history"] = one_step.metadata["training"]["history"]  # both learning curves
        stages[MULTI_STEP] = model
    identified = Identified(model=model, data=data, stages=stages)
    for _ in range(rounds):
        identified = closed_loop_round(identified, binding, control_period, config, seed, recipe, meta, progress)
    return identified


def closed_loop_round(identified: Identified, binding: PlantBinding, control_period: float, config: NNConfig,
                      seed: int, recipe: Recipe = Recipe(), metadata: dict | None = None,
                      progress: bool = False) -> Identified:
    """One NNPC-in-the-loop round on top of ``identified``: collect ``recipe.closed_loop_samples``
    with its NNPC driving the plant (seeded dither, new random references and loads), refine the
    simulation-error stage on the PI and every round's data; returns the extended identification."""
    from controllers.nn_model import train

    r = len(identified.closed_loop) + 1
    training = training_settings(control_period, seed, recipe.multi_step_iterations, binding.converter)
    loop = implemented(nnpc(identified.model, control_period, spec=binding.converter), recipe.implementation)
    closed = collection_settings(control_period, recipe.closed_loop_samples, seed + CLOSED_LOOP_SEED_OFFSET * r,
                                 excitation=recipe.closed_loop_dither, spec=binding.converter)
    extra = [*identified.closed_loop, collect(binding, loop, closed, progress=progress)]
    refine = replace(training, multi_step_iterations=min(training.multi_step_iterations, recipe.closed_loop_iterations))
    meta = dict(metadata if metadata is not None else
                {k: v for k, v in identified.model.metadata.items() if k not in ("config", "training", "held_out_rmse")})
    model = train(identified.data, config, refine, metadata=meta, progress=progress, extra_frames=extra,
                  initial=identified.model)
    model.metadata["identification"] = {"stage": f"{CLOSED_LOOP} {r}", "closed_loop_rounds": r,
                                        "closed_loop_samples": int(sum(len(f) for f in extra)),
                                        "closed_loop_dither": recipe.closed_loop_dither}
    return Identified(model=model, data=identified.data, stages={**identified.stages, f"{CLOSED_LOOP} {r}": model},
                      closed_loop=extra)


# ---------------------------------------------------------------------------------------------
# The identification figure (like the MATLAB NNPC block's plant-identification window)

#: held-out samples drawn in the predicted-vs-measured panels (the start of the held-out tail)
FIGURE_SAMPLES = 400


def figure_path(model_path: Path) -> Path:
    """Where a model's identification figure goes: ``<model>.identification.png`` beside it."""
    model_path = Path(model_path)
    return model_path.with_name(f"{model_path.stem}.identification.png")


def write_identification_figure(model: NNPlantModel, data: pd.DataFrame, model_path: Path) -> Path:
    """:func:`identification_figure` beside the model's file (:func:`figure_path`). PNG only (the
    reproduction commits no SVG); the same model and data give the same bytes."""
    from cosim.base.files import atomic_write
    from cosim.plots import plt

    fig = identification_figure(model, data)
    path = figure_path(model_path)
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=100, metadata={"Software": None}))
    plt.close(fig)
    return path


def identification_figure(model: NNPlantModel, data: pd.DataFrame):
    """The learning curves (training and validation loss, standardised, at every L-BFGS check of the
    one-step and the simulation-error stage) and the one-step predictions against the measured iL
    and vo on the held-out tail of ``data`` (the samples ``train`` held out: its last
    ``test_fraction``), with the held-out RMSE. Three stacked axes: loss, iL, vo."""
    import numpy as np

    from controllers.nn_model import build_dataset
    from cosim.plots import plt

    training = model.metadata.get("training", {})
    test_fraction = training.get("test_fraction", TrainingSettings().test_fraction)
    held_out = data.iloc[int(round(len(data) * (1 - test_fraction))):]
    fig, (ax_loss, ax_i, ax_v) = plt.subplots(3, 1, figsize=(8, 9), constrained_layout=True,
                                              gridspec_kw={"height_ratios": [1.1, 1, 1]})
    offset = 0
    stages = (("one-step", training.get("history") or []),
              (f"simulation error over {((training.get('multi_step') or {}).get('horizon'))} steps",
               (training.get("multi_step") or {}).get("history") or []))
    for k, (stage, history) in enumerate(stages):
        if not history:
            continue
        h = np.asarray(history, dtype=float)
        ax_loss.semilogy(h[:, 0] + offset, h[:, 1], color=f"C{2 * k}", label=f"{stage}: training")
        ax_loss.semilogy(h[:, 0] + offset, h[:, 2], color=f"C{2 * k + 1}", linestyle="--",
                         label=f"{stage}: validation")
        offset += float(h[-1, 0])
    ax_loss.set_xlabel("L-BFGS iteration")
    ax_loss.set_ylabel("loss (standardised MSE)")
    ax_loss.grid(True, which="both", alpha=0.3)
    if ax_loss.lines:
        ax_loss.legend(fontsize=8)
    rmse = model.metadata.get("held_out_rmse", {})
    domain = data_domain(model.metadata)
    ax_loss.set_title(f"{model.config.label}\nidentified on {model.metadata.get('plant', '?')}"
                      + (f"\ndata: {domain_text(domain)}" if domain else "")
                      + f"\nheld-out one-step RMSE {rmse.get('one_step_rmse_current_A', float('nan')) * 1e3:.3g} mA, "
                      f"{rmse.get('one_step_rmse_voltage_V', float('nan')) * 1e3:.3g} mV", fontsize=9)
    if len(held_out) > model.config.delays + 1:
        x, y = build_dataset(held_out, model.config)
        predicted = model.predict(x)
        shown = slice(0, FIGURE_SAMPLES)
        time = held_out["time"].to_numpy()[model.config.delays:] * 1e3 if "time" in held_out \
            else np.arange(len(y)) + len(data) - len(held_out) + model.config.delays
        for ax, j, name, unit in ((ax_i, 0, "inductor current $i_L$", "A"), (ax_v, 1, "output voltage $v_o$", "V")):
            ax.plot(time[shown], y[shown, j], color="k", linewidth=1.2, label="measured (held out)")
            ax.plot(time[shown], predicted[shown, j], color="C1", linestyle="--", linewidth=1.0,
                    label="one-step prediction")
            ax.set_ylabel(f"{name} [{unit}]")
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=8, loc="best")
        ax_v.set_xlabel("time [ms]" if "time" in held_out else "sample")
        ax_i.set_title(f"held-out samples {len(data) - len(held_out)} .. {len(data) - 1} (first "
                       f"{min(FIGURE_SAMPLES, len(y))} shown), never used in training", fontsize=9)
    return fig
