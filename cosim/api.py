"""The design steps as a Python API: collect identification data, identify the NNPC's network, tune the PI, design the
classical controllers and distill the explicit NNPC -- each for a plant binding at the operating points of a converter
spec (:mod:`cosim.converter_spec`), never the paper's unless the spec is the paper's.

Every function takes ``binding`` (:func:`cosim.builtin_binding`, :func:`cosim.load_binding`) and ``spec``: None means
the binding's own converter spec (a binding file's ``[converter]`` table; Table II for the built-in plant), a
:class:`~cosim.converter_spec.ConverterSpec` replaces it for this design. A value a design needs and the spec does not
give is refused with a one-line :class:`~cosim.base.errors.ConfigError` naming the key. Units: seconds, volts,
amperes, ohms; duty as a fraction 0..1.

This module is an entry point like the command line: it calls the study's design modules and nothing below imports
it. Example (``docs/guide/design-api.md``, executed by the tests)::

    from cosim import builtin_binding
    from cosim.api import collect_data, tune_pi

    plant = builtin_binding("averaged")
    pi = tune_pi(plant, 1e-3, quick=True)                  # at the spec's nominal point and supply
    data = collect_data(plant, 1e-3, pi.controller(), samples=600)
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from cosim.converter_spec import ConverterSpec
from cosim.fmi.binding import PlantBinding


def with_spec(binding: PlantBinding, spec: ConverterSpec | None) -> PlantBinding:
    """``binding`` designed for ``spec`` (None: its own converter spec)."""
    return binding if spec is None else replace(binding, spec=spec)


def tune_pi(binding: PlantBinding, control_period: float, *, spec: ConverterSpec | None = None,
            quick: bool = False, progress: bool = False):
    """The PI tuned on the plant at ``control_period`` [s]: minimum ISE of the spec's start-up and reference steps (the
    shipped templates at its nominal output, load and supply) with overshoot <= 5 % and |steady-state error| <= 0.5 %
    (:mod:`cosim.design.pi_tuning`). ``quick``: a 2 x 2 grid and 6 Nelder-Mead evaluations (examples and tests).
    Returns a :class:`~cosim.design.pi_tuning.PITuning` (``kp`` [1/V], ``ki`` [1/(V s)], ``controller()``)."""
    from cosim.design.pi_tuning import tune_pi as tune

    return tune(with_spec(binding, spec), control_period, quick=quick, progress=progress)


def collection_settings(binding: PlantBinding, control_period: float, *, spec: ConverterSpec | None = None,
                        samples: int = 10_000, seed: int = 0, region: str | None = None):
    """The identification experiment's settings over the spec's operating points: ``region`` ``"paper"`` (the paper's
    experiment scaled to the spec) or ``"envelope"`` (its whole envelope; None: the rate's default, the paper's at
    1 ms, the envelope at faster rates). Refused, naming the key, where the spec gives no ranges."""
    from cosim.design.experiments import collection_settings as settings

    return settings(control_period, samples, seed, region=region, spec=with_spec(binding, spec).converter)


def collect_data(binding: PlantBinding, control_period: float, controller, *, spec: ConverterSpec | None = None,
                 samples: int = 10_000, seed: int = 0, region: str | None = None, out: str | Path | None = None,
                 progress: bool = False):
    """Run the identification experiment (paper Section IV) with ``controller`` (e.g. ``tune_pi(...).controller()``)
    over :func:`collection_settings`: a pandas table, one row per control sample (iL, vo, duty, reference, load,
    supply, load conductance), its metadata in ``attrs["metadata"]``; written as Parquet to ``out`` if given."""
    from cosim.design.data_collection import collect, save_samples

    bound = with_spec(binding, spec)
    data = collect(bound, controller, collection_settings(bound, control_period, samples=samples, seed=seed,
                                                          region=region), progress=progress)
    if out is not None:
        save_samples(data, Path(out))
    return data


def identify_network(binding: PlantBinding, control_period: float, pi_controller, *,
                     spec: ConverterSpec | None = None, samples: int = 10_000, seed: int = 0, progress: bool = False):
    """The NNPC's network identified on the plant at ``control_period`` [s] by the workbench's recipe
    (:mod:`cosim.design.identification`: data collected with ``pi_controller`` over the spec's operating points, then
    one-step and simulation-error training). Returns the :class:`~controllers.nn_model.NNPlantModel`; its metadata
    records the data's ranges (``collection``) and the converter, which the NNPC starts from and a run outside them
    warns about."""
    from cosim.design.experiments import nn_configs
    from cosim.design.identification import Recipe, identify

    bound = with_spec(binding, spec)
    config = nn_configs(control_period)["nnpc"]
    return identify(bound, pi_controller, control_period, config, seed, Recipe(samples=samples),
                    metadata={"converter": bound.converter.describe()}, progress=progress).model


def nnpc(model, control_period: float, binding: PlantBinding, *, spec: ConverterSpec | None = None):
    """The NNPC on ``model`` for the plant's converter (it starts from the spec's nominal load and supply)."""
    from cosim.design.experiments import nnpc as make

    return make(model, control_period, spec=with_spec(binding, spec).converter)


def design_classical(binding: PlantBinding, *, spec: ConverterSpec | None = None) -> dict:
    """The current-mode and Type-III controllers designed on the spec's nominal circuit at its nominal point, one
    sample per PWM period (1 / its switching frequency), checked at its envelope's corners
    (:mod:`cosim.design.classical_design`). Returns ``{"current-mode": Design, "type-iii": Design}``; each design's
    ``controller`` runs, ``describe()`` gives its margins and ``meets()`` whether they meet the targets."""
    from controllers.predictors import CircuitParameters
    from cosim.design.classical_design import design_current_mode, design_type_iii, targets_for
    from cosim.design.vocabulary import CURRENT_MODE, TYPE_III

    bound = with_spec(binding, spec)
    converter = bound.converter
    parameters = CircuitParameters(**converter.circuit("the classical designs (the nominal circuit)"))
    period = 1.0 / converter.require("switching_frequency", "the classical designs (one sample per PWM period)")
    targets = targets_for(bound, period)
    return {"current-mode": design_current_mode(parameters, targets, CURRENT_MODE),
            "type-iii": design_type_iii(parameters, targets, TYPE_III)}


def distill_policy(model, binding: PlantBinding, control_period: float, *, spec: ConverterSpec | None = None,
                   settings=None, progress: bool = False):
    """The explicit NNPC: a policy network distilled from the online NNPC on ``model`` by DAgger on the plant, its
    episodes' references and loads over the spec's envelope (:mod:`cosim.design.distillation`; ``settings``: a
    :class:`~cosim.design.distillation.DistillationSettings`, default the reproduction's budget)."""
    from cosim.design.distillation import FULL_DISTILLATION, distill

    return distill(model, with_spec(binding, spec), control_period, settings or FULL_DISTILLATION, log=None,
                   progress=progress)


__all__ = ["collect_data", "collection_settings", "design_classical", "distill_policy", "identify_network", "nnpc",
           "tune_pi", "with_spec"]
