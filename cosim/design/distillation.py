"""Distilling the online NNPC into an explicit policy, with DAgger on the plant FMU.

Imitation by plain supervised learning (behaviour cloning) trains on the states the expert
visits; the learner's own small errors then take it to states the expert never saw, where it has
no data. DAgger (Ross, Gordon and Bagnell, AISTATS 2011) fixes that by letting the learner drive
and asking the expert what it would have done there:

* round 0 -- the online NNPC drives the plant FMU through seeded random episodes (references
  3-20 V, loads 4-100 Ohm log-uniform into DCM, held for random intervals, start-ups from rest
  and returns to 0 V); every sample is labelled with its own first move;
* round i >= 1 -- at each sample the expert's move is applied with probability beta^i, else the
  current policy's (seeded); every visited state is labelled with the online NNPC's first move
  *at that state*: the expert runs in shadow, its memory of the applied duty and its one-step
  prediction (hence its disturbance estimate) corrected to the duty actually applied;
* after each round the policy is retrained on all labels so far (the aggregate).

The expert is the online NNPC's C twin with the workbench's default optimizer, the RTI (microseconds per label at
13.33 us, the search's ~1 ms at its start-up fallbacks; ``expert_optimizer="search"`` for the search's labels,
why not by default: :func:`distill`), equal to the Python reference at every sample, so the budget is counted in
labels: rounds x episodes x samples.
Everything is seeded (episodes, mixing, training) and torch runs on one thread, so the same
inputs give the same policy file byte for byte.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Callable

import numpy as np

from controllers.base import Measurement
from controllers.explicit_policy import (
    ExplicitPolicy,
    ExplicitPolicyController,
    PolicyConfig,
    PolicyInputs,
    PolicyTrainingSettings,
    train_policy,
)
from controllers.nn_model import NNPlantModel
from cosim.base.errors import ConfigError
from cosim.converter_spec import ConverterSpec
from cosim.design import experiments
from cosim.design.data_collection import MIN_SAMPLES, CollectionSettings, random_scenario
from cosim.design.experiments import explicit_nnpc, implemented, nnpc, operating_point
from cosim.design.vocabulary import OPTIMIZERS
from cosim.fmi.binding import PlantBinding
from cosim.fmi.plant import open_plant
from cosim.master import run


@dataclass(frozen=True)
class DistillationSettings:
    """The DAgger budget and the episodes' ranges (labels = (rounds + 1) x episodes x samples)."""

    rounds: int = 6  # DAgger rounds after the behaviour-cloning round 0
    episodes: int = 8  # closed-loop episodes per round ((6 + 1) rounds x 8 x 600 samples = 33 600 labels; with
    # (4 + 1) x 6 = 18 000 the nominal plant's reference step down or the mismatch plant's load change ended at
    # 1.065-1.080 x the online NNPC's IAE, depending on the network)
    samples: int = 600  # control samples per episode (600 at 13.33 us: 8 ms)
    #: [V], uniform; None: the converter's envelope (its output_voltage_range; Table II: 3-20 V), see for_converter
    reference_range: tuple[float, float] | None = None
    load_range: tuple[float, float] | None = None  # [Ohm], log-uniform; None: its load_resistance_range (4-100 Ohm)
    hold_range: tuple[int, int] = (20, 100)  # control periods a level is held (short: many transients per label;
    # (40, 200) gave 8-16 % reference-step overshoot where this gives 3 %, nominal switched plant)
    rest_probability: float = 0.1  # chance that a new reference is 0 V (so start-ups recur)
    expert_mixing: float = 0.5  # beta: round i applies the expert's move with probability beta^i
    expert_optimizer: str | None = None  # the expert online NNPC's optimizer, one of cosim.study.vocabulary's
    # OPTIMIZERS, which labels the states; None: the workbench's default (DEFAULT_OPTIMIZER, the RTI; why: distill)
    seed: int = 0
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    training: PolicyTrainingSettings = field(default_factory=PolicyTrainingSettings)

    def check(self) -> None:
        if self.rounds < 0 or self.episodes < 1 or self.samples < MIN_SAMPLES:
            raise ConfigError(f"DAgger budget rounds = {self.rounds}, episodes = {self.episodes}, samples = "
                              f"{self.samples} is invalid: expected rounds >= 0, episodes >= 1, samples >= {MIN_SAMPLES}")
        if not 0 <= self.expert_mixing <= 1:
            raise ConfigError(f"expert mixing {self.expert_mixing} is invalid: expected 0 <= beta <= 1")
        if self.expert_optimizer is not None and self.expert_optimizer not in OPTIMIZERS:
            raise ConfigError(f"expert optimizer {self.expert_optimizer!r} is unknown: expected one of "
                              f"{', '.join(OPTIMIZERS)}")
        # the region and the supply come from the converter at distillation time (for_converter): stand-ins here
        replace(self.collection(0), reference_range=self.reference_range or (0.0, 1.0),
                load_range=self.load_range or (1.0, 2.0), input_voltage=1.0).check()

    def for_converter(self, spec: ConverterSpec) -> DistillationSettings:
        """These settings with the episodes' region the converter ``spec``'s envelope where they leave it out (the
        references over its output range, the loads over its load range): what a policy's design key holds."""
        purpose = "the explicit NNPC's distillation episodes"
        return replace(self, reference_range=self.reference_range or spec.operating_range("output_voltage", purpose),
                       load_range=self.load_range or spec.operating_range("load_resistance", purpose))

    def resolved(self) -> DistillationSettings:
        """These settings with the expert's optimizer named: None becomes the workbench's default now
        (:data:`cosim.design.experiments.DEFAULT_OPTIMIZER`, which the benchmark group reproduction-optimizer switches
        to time the reproduction with the search)."""
        return replace(self, expert_optimizer=self.expert_optimizer or experiments.DEFAULT_OPTIMIZER)

    @property
    def labels(self) -> int:
        return (self.rounds + 1) * self.episodes * self.samples

    def collection(self, seed: int, input_voltage: float | None = None) -> CollectionSettings:
        """One episode's random references and loads (``input_voltage`` [V]: its supply)."""
        return CollectionSettings(samples=self.samples, reference_range=self.reference_range,
                                  load_range=self.load_range, hold_range=self.hold_range, excitation=0.0,
                                  rest_probability=self.rest_probability, seed=seed, input_voltage=input_voltage)


#: the reproduction's budget (33 600 labels per plant) and the small one of the tests
FULL_DISTILLATION = DistillationSettings()
SMALL_DISTILLATION = DistillationSettings(rounds=2, episodes=2, samples=300)


class ShadowExpert:
    """The online NNPC's C twin labelling states it does not drive: after its move it is told the
    duty actually applied, so its next history, its warm start and its disturbance estimate are
    those of the visited trajectory."""

    def __init__(self, expert):
        from controllers.native import NativePredictiveController

        if not isinstance(expert, NativePredictiveController):
            raise TypeError("the DAgger expert must be the online NNPC's C twin (NativePredictiveController)")
        self.expert = expert
        self.name, self.sample_period, self.duty_limits = expert.name, expert.sample_period, expert.duty_limits
        self._horizon = expert.config.horizon.horizon

    def reset(self) -> None:
        self.expert.reset()

    def label(self, m: Measurement) -> float:
        """The online NNPC's first move at this sample (its state then assumes that move is applied)."""
        return self.expert.step(m)

    def applied(self, duty: float, label: float) -> None:
        """The duty applied in fact: correct the expert's memory of it and its one-step prediction."""
        if duty == label:
            return
        state = self.expert.state
        sequence = np.array(state.warm[:self._horizon], dtype=float)
        sequence[0] = duty
        _, first = self.expert.cost(sequence)
        state.predicted[0] = first[0] - state.bias[0]
        state.predicted[1] = first[1] - state.bias[1]
        state.previous_duty = duty


class DaggerEpisode:
    """One episode's controller: the expert labels every sample; the expert's or the learner's move
    is applied (the expert's with probability ``beta``, seeded); inputs and labels are kept."""

    def __init__(self, expert: ShadowExpert, learner, beta: float, seed: int, nominal_load: float):
        self.expert, self.learner, self.beta, self.seed = expert, learner, beta, seed
        self.name, self.sample_period, self.duty_limits = "DAgger", expert.sample_period, expert.duty_limits
        self.inputs = PolicyInputs(nominal_load)
        self.features: list[list[float]] = []
        self.labels: list[float] = []
        self.applied_policy = 0
        self.reset()

    def reset(self) -> None:
        self.expert.reset()
        self.inputs.reset()
        if self.learner is not None:
            self.learner.reset()
        self._rng = np.random.default_rng(self.seed)

    def step(self, m: Measurement) -> float:
        x = self.inputs.features(m)
        label = self.expert.label(m)
        duty = label
        if self.learner is not None:
            own = self.learner.step(m)
            if self._rng.random() >= self.beta:
                duty = own
                self.applied_policy += 1
            self.learner.inputs.previous_duty = duty
        self.expert.applied(duty, label)
        self.inputs.advance(m, x, duty)
        self.features.append(x)
        self.labels.append(label)
        return duty

    def describe(self) -> dict:
        return {"type": "DAgger episode", "beta": self.beta, "seed": self.seed}


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def distill(model: NNPlantModel, binding: PlantBinding, control_period: float,
            settings: DistillationSettings = FULL_DISTILLATION, *, log: Callable[[str], None] | None = _log,
            progress: bool = False, metadata: dict | None = None,
            timings: dict[str, float] | None = None) -> ExplicitPolicy:
    """Distill the online NNPC on ``model`` into an explicit policy, with DAgger on ``binding``'s
    plant at ``control_period`` [s]. ``log`` gets one line per round (None: silent); ``progress``
    shows a bar over the episodes. ``timings`` (wall-clock, never in the policy file) gets the seconds of the
    policy's trainings (``distillation_training_s``) and of all the rest (``distillation_episodes_s``: the labelled
    episodes -- the plant, the expert and the learner -- and their set-up)."""
    settings.check()  # torch trains on one thread (train_policy), and nothing else here uses it
    settings = settings.resolved().for_converter(binding.converter)  # the metadata names the optimizer and region
    # by default the labels come from the online NNPC as it runs, the RTI (with the search as its fallback at
    # start-ups): on every identification seed and plant its policies met the explicit NNPC's targets as often as or
    # more often than the search's, whose labels had been kept for their plans' cost (the RTI's cost > 1 % more than
    # the search's at 3-7.5 % of these episodes' samples, right at the steps) -- worst-scenario IAE / online median
    # 1.016 vs 1.043 (nominal switched), 1.014 vs 1.028 (mismatch), start-up overshoot 6.74 vs 8.22 % and
    # 0.90 vs 4.09 %: results/explicit-every-seed.md and -search-labels.md (make every-seed) -- in half the time
    spec = binding.converter
    online = nnpc(model, control_period, optimizer=settings.expert_optimizer, spec=spec)
    expert = ShadowExpert(implemented(online, "c"))
    point = operating_point(spec)
    nominal_load = point["nominal_load"]
    features = np.empty((0, 7))
    labels = np.empty(0)
    policy: ExplicitPolicy | None = None
    rounds = []
    bar = None
    started_at, training_seconds = time.perf_counter(), 0.0
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=(settings.rounds + 1) * settings.episodes, desc="DAgger episodes", unit="episode",
                   leave=False)
    try:
        with open_plant(binding) as plant:
            for round_index in range(settings.rounds + 1):
                beta = 1.0 if round_index == 0 else settings.expert_mixing ** round_index
                learner = None if policy is None else explicit_nnpc(policy, spec=spec)
                new_x, new_y, applied = [], [], 0
                for episode in range(settings.episodes):
                    seed = settings.seed + 1000 * round_index + episode
                    scenario = random_scenario(settings.collection(seed, point["nominal_input_voltage"]),
                                               control_period)
                    loop = DaggerEpisode(expert, learner, beta, seed, nominal_load)
                    run(plant, loop, scenario, record_period=control_period, seed=seed)
                    new_x += loop.features
                    new_y += loop.labels
                    applied += loop.applied_policy
                    if bar is not None:
                        bar.update(1)
                x_round, y_round = np.array(new_x), np.array(new_y)
                record = {"round": round_index, "beta": beta, "labels": len(y_round),
                          "policy_share": applied / len(y_round)}
                if policy is not None:  # the current policy on the states it (partly) visited itself
                    error = np.clip(policy.evaluate(x_round), *policy.duty_limits) - y_round
                    record["first_move_rms_before_retraining"] = float(np.sqrt(np.mean(error ** 2)))
                features = np.vstack([features, x_round])
                labels = np.concatenate([labels, y_round])
                training = replace(settings.training, seed=settings.training.seed + round_index)
                started = time.perf_counter()
                policy = train_policy(features, labels, control_period, settings.policy, training,
                                      online.duty_limits, initial=policy)
                training_seconds += time.perf_counter() - started
                record["aggregate_labels"] = len(labels)
                record["validation_rms_duty"] = policy.metadata["training"]["validation_rms_duty"]
                rounds.append(record)
                if log is not None:
                    before = record.get("first_move_rms_before_retraining")
                    log(f"  DAgger round {round_index}/{settings.rounds}: {len(y_round)} labels (policy applied at "
                        f"{100 * record['policy_share']:.0f} %), aggregate {len(labels)}"
                        + (f", on-policy first-move RMS before retraining {before:.4f}" if before is not None else "")
                        + f", validation RMS {record['validation_rms_duty']:.4f}")
    finally:
        if bar is not None:
            bar.close()
        if timings is not None:
            timings.update(distillation_episodes_s=time.perf_counter() - started_at - training_seconds,
                           distillation_training_s=training_seconds)
    policy.metadata = {**(metadata or {}), **policy.metadata, "control_period_s": control_period,
                       "expert_model": expert_fingerprint(model),
                       "plant": binding.label, "expert": online.describe()["predictor"],
                       "distillation": {**settings_dict(settings), "labels": int(len(labels)), "history": rounds}}
    return policy


def settings_dict(settings: DistillationSettings) -> dict:
    """The settings as the policy file's metadata stores them (JSON-ready)."""
    data = asdict(settings)
    data["policy"]["hidden"] = list(settings.policy.hidden)
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in data.items()}


def expert_fingerprint(model: NNPlantModel) -> str:
    """A short SHA-256 of the expert network's folded weights (which NNPC a policy imitates)."""
    import hashlib

    digest = hashlib.sha256()
    for array in (*model._weights, *model._biases):
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()[:16]


def first_move_errors(policy: ExplicitPolicy, features: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    """RMS, mean absolute and largest |policy move - expert move| (the policy clipped to its limits)."""
    error = np.clip(policy.evaluate(features), *policy.duty_limits) - labels
    return {"rms": float(np.sqrt(np.mean(error ** 2))), "mean_abs": float(np.mean(np.abs(error))),
            "max_abs": float(np.max(np.abs(error))) if len(error) else math.nan}


__all__ = ["DistillationSettings", "FULL_DISTILLATION", "SMALL_DISTILLATION", "ShadowExpert", "DaggerEpisode",
           "distill", "expert_fingerprint", "first_move_errors", "settings_dict"]


class ShadowPolicy:
    """The online NNPC driving the plant with the explicit policy beside it, fed the NNPC's applied
    duty: the policy's move is recorded at every sample from scenario time ``start`` [s] on (first-move
    error)."""

    def __init__(self, online, policy: ExplicitPolicyController, start: float):
        self.online, self.policy, self.start = online, policy, start
        self.name, self.sample_period, self.duty_limits = online.name, online.sample_period, online.duty_limits
        self.errors: list[float] = []

    def reset(self) -> None:
        self.online.reset()
        self.policy.reset()
        self.errors = []  # per run: a sweep worker reuses the controller

    def step(self, m: Measurement) -> float:
        duty = self.online.step(m)
        own = self.policy.step(m)
        self.policy.inputs.previous_duty = duty
        if m.time >= self.start - 1e-12:
            self.errors.append(own - duty)
        return duty

    def run_results(self) -> dict[str, float]:
        """The first-move error |policy - NNPC| over the run (the sweep worker adds it to the run's row)."""
        error = np.abs(np.array(self.errors)) if self.errors else np.array([math.nan])
        return {"first_move_rms": float(np.sqrt(np.mean(error ** 2))), "first_move_max": float(np.max(error)),
                "first_move_samples": float(len(self.errors))}

    def describe(self) -> dict:
        return self.online.describe()
