"""Identification data that cover the operating envelope (issue 25, part 4): what the data visit, and
what that buys, measured against the data of the paper's experiment.

The paper's experiment (and the workbench's data until now) drives the tuned PI with random references
0-20 V and loads 4-10 Ohm at 48 V: the NNPC then meets the envelope map's loads up to 100 Ohm (DCM from
about 40 Ohm) and its supplies 36 and 60 V without ever having seen them. The *envelope* collection
(:func:`cosim.design.experiments.collection_settings`, ``region="envelope"``) keeps the closed-loop PI --
it holds the states near the operating point asked for, so the samples sit where the controller will
operate, start-ups from rest included -- and moves that operating point over the whole envelope: references
3-20 V (and rests at 0 V), loads log-uniform 4-100 Ohm, supplies uniform 36-60 V, each a held random level
on its own schedule. On top, the excitation that makes the data informative there: an amplitude-modulated
random binary dither (levels +-a, a ~ U(0, 0.2), held 1-8 samples) instead of the white one, so that its
power sits at and below the LC resonance and its held full-amplitude runs resemble the NNPC's own full-duty
and braking moves.

:func:`coverage` says what a data set visits: the share of the envelope's cells (references x loads x
supplies) holding at least :data:`MIN_CELL_SAMPLES` samples, and the shares of samples in DCM and at the
duty's limits. :func:`compare` (``python -m cosim.study.envelope_identification``) measures the two
collections for the same seeds: held-out prediction errors on test sets neither is drawn from (an
envelope-wide one driven by the oracle MPC -- the trajectories of a predictive controller -- and one of
the paper's region), the online NNPC's share of the envelope map (the NNPC alone, on the sweep engine),
and the paper's four scenarios at the nominal point.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from cosim.design.vocabulary import SWITCHING_PERIOD
from cosim.study.vocabulary import PAPER_SPEC

#: the envelope the map measures (cosim.study.envelope.FULL_MAP spans it) and the envelope collection draws from
REFERENCES, LOADS, SUPPLIES = (PAPER_SPEC.output_voltage_range, PAPER_SPEC.load_resistance_range,
                              PAPER_SPEC.input_voltage_range)
#: coverage cells: 4 reference bins (linear) x 4 load bins (log) x 3 supply bins (linear)
REFERENCE_BINS, LOAD_BINS, SUPPLY_BINS = 4, 4, 3
#: samples a cell must hold to count as covered (a held level lasts 20-200 samples at 13.33 us)
MIN_CELL_SAMPLES = 20
#: the identifications compared: name -> (collection, whether the network sees the supply voltage). The paper's region
#: with today's network (load conductance only); the envelope with that network, with the white dither of the paper's
#: region, and with the supply voltage as a further input (the recipe at 13.33 us): which of the changes -- where the
#: data are, how they are excited, what the network sees -- buys what
VARIANTS = {"paper": ("paper", False), "envelope, no supply input": ("envelope", False),
            "envelope, white dither, no supply input": ("envelope, white dither", False),
            "envelope": ("envelope", True)}
#: the variants whose NNPC runs the map (the white-dither one is measured by its prediction errors and nominal runs)
MAP_VARIANTS = ("paper", "envelope, no supply input", "envelope")
#: the test sets' seeds: far from every identification seed
TEST_SEED = 1000
TEST_SAMPLES = 3000
#: the dither of the oracle MPC's test set (small: its own moves are the excitation)
TEST_DITHER = 0.02


def in_dcm(frame: pd.DataFrame) -> np.ndarray:
    """Per sample: the load lies beyond the CCM boundary 2 L fsw / (1 - D) at the sample's operating point
    (D = vo / Vs, measured vo), i.e. the converter runs in discontinuous conduction there in steady state."""
    vs = frame["input_voltage"].to_numpy(dtype=float)
    vo = np.clip(frame["measured_output_voltage"].to_numpy(dtype=float), 0.0, None)
    duty = np.clip(vo / vs, 0.0, 0.999)
    boundary = 2 * PAPER_SPEC.inductance * PAPER_SPEC.switching_frequency / (1 - duty)
    return frame["load_resistance"].to_numpy(dtype=float) > boundary


def coverage(frame: pd.DataFrame) -> dict:
    """What a sample table visits of the envelope: per cell of references x loads x supplies (the
    reference asked, the load and supply in effect; samples at rest, reference < 3 V, count in no cell)
    the samples it holds; the share of cells with >= :data:`MIN_CELL_SAMPLES`; the shares of samples in
    DCM (:func:`in_dcm`, with vo > 1 V) and at the duty's limits (0 or 1: the full-duty and braking moves)."""
    r = frame["reference"].to_numpy(dtype=float)
    load = frame["load_resistance"].to_numpy(dtype=float)
    vs = frame["input_voltage"].to_numpy(dtype=float)
    r_edges = np.linspace(*REFERENCES, REFERENCE_BINS + 1)
    l_edges = np.geomspace(*LOADS, LOAD_BINS + 1)
    s_edges = np.linspace(*SUPPLIES, SUPPLY_BINS + 1)
    counts, _ = np.histogramdd(np.column_stack([r, load, vs]), bins=(r_edges, l_edges, s_edges))
    duty = frame["duty_cycle"].to_numpy(dtype=float)
    on = frame["measured_output_voltage"].to_numpy(dtype=float) > 1.0
    return {"cells": int(counts.size), "cells_covered": int((counts >= MIN_CELL_SAMPLES).sum()),
            "cell_share_pct": 100.0 * float((counts >= MIN_CELL_SAMPLES).mean()),
            "dcm_share_pct": 100.0 * float(in_dcm(frame)[on].mean()) if on.any() else 0.0,
            "duty_limit_share_pct": 100.0 * float(((duty <= 1e-9) | (duty >= 1 - 1e-9)).mean()),
            "supply_range_V": [float(vs.min()), float(vs.max())],
            "load_range_Ohm": [float(load.min()), float(load.max())],
            "reference_range_V": [float(r.min()), float(r.max())]}


def coverage_text(cover: dict) -> str:
    return (f"{cover['cells_covered']} of {cover['cells']} cells ({cover['cell_share_pct']:.0f} %), "
            f"{cover['dcm_share_pct']:.0f} % of the samples in DCM, {cover['duty_limit_share_pct']:.0f} % at the "
            f"duty's limits; supplies {cover['supply_range_V'][0]:.0f}-{cover['supply_range_V'][1]:.0f} V, loads "
            f"{cover['load_range_Ohm'][0]:.3g}-{cover['load_range_Ohm'][1]:.3g} Ohm")


# ---------------------------------------------------------------------------------------------
# The comparison (a command: python -m cosim.study.envelope_identification)


def _pi(results: Path):
    from controllers.pi import PIController
    from cosim.design.vocabulary import pipeline_tag

    tuning = json.loads((results / "tuning" / f"pi__{pipeline_tag('nominal-switched', SWITCHING_PERIOD)}.json")
                        .read_text(encoding="utf-8"))
    return PIController(tuning["kp"], tuning["ki"], SWITCHING_PERIOD, name="PI")


def test_sets(binding, pi, samples: int = TEST_SAMPLES) -> dict[str, pd.DataFrame]:
    """The held-out test sets, seeded apart from every identification: ``envelope (oracle MPC)`` -- the oracle
    MPC (C twin) under the envelope collection's random references, loads and supplies with a small dither,
    the trajectories of a predictive controller over the envelope; ``paper region (PI)`` -- the paper's
    experiment (PI, 0-20 V, 4-10 Ohm, 48 V)."""
    from cosim.design.controller_factory import true_parameters
    from cosim.design.data_collection import collect
    from cosim.design.experiments import collection_settings, implemented, model_mpc

    oracle = implemented(model_mpc(true_parameters(binding), SWITCHING_PERIOD, "MPC-oracle", binding=binding))
    envelope = replace(collection_settings(SWITCHING_PERIOD, samples, TEST_SEED, region="envelope",
                                           spec=binding.converter),
                       dither="gaussian", excitation=TEST_DITHER)
    return {"envelope (oracle MPC)": collect(binding, oracle, envelope),
            "paper region (PI)": collect(binding, pi, collection_settings(SWITCHING_PERIOD, samples, TEST_SEED,
                                                                          region="paper", spec=binding.converter))}


def prediction_errors(model, tests: dict[str, pd.DataFrame], horizon: int) -> list[dict]:
    """Per test set: the one-step RMSE of iL and vo and the vo RMSE over the controller's horizon (open loop
    with the recorded duties, the load estimate held at its first value as the controller holds it)."""
    rows = []
    for name, frame in tests.items():
        r = model.rmse_report(frame, horizon)
        rows.append({"test_set": name, "one_step_rmse_current_mA": 1e3 * r["one_step_rmse_current_A"],
                     "one_step_rmse_voltage_mV": 1e3 * r["one_step_rmse_voltage_V"],
                     "horizon_rmse_voltage_mV": 1e3 * r["horizon_mean_rmse_voltage_V_held_extras"],
                     f"{horizon}_step_rmse_voltage_mV": 1e3 * r[f"{horizon}_step_rmse_voltage_V_held_extras"]})
    return rows


def nominal_scenarios(binding, model, name: str) -> list[dict]:
    """The paper's four scenarios at the nominal point (12 V, 6 Ohm, 48 V; time-compressed at 1/fsw) with the
    online NNPC (C twin) on ``model``: IAE and overshoot per scenario."""
    from cosim.design.experiments import implemented, nnpc, scenarios_for
    from cosim.master import simulate
    from cosim.metrics import run_metrics

    rows = []
    for scenario in scenarios_for(SWITCHING_PERIOD, spec=binding.converter):
        m = run_metrics(simulate(binding, implemented(nnpc(model, SWITCHING_PERIOD, name)), scenario,
                                 record_period=1e-5))
        rows.append({"controller": name, "scenario": scenario.name, "iae_Vs": m["iae_Vs"],
                     "overshoot_pct": m["overshoot_pct"], "settling_time_ms": m["settling_time_ms"]})
    return rows


def variant_settings(collection: str, seed: int, samples: int):
    """The collection settings of a :data:`VARIANTS` collection."""
    from cosim.design.experiments import collection_settings

    if collection == "envelope, white dither":
        paper = collection_settings(SWITCHING_PERIOD, samples, seed, region="paper", spec=PAPER_SPEC)
        return replace(collection_settings(SWITCHING_PERIOD, samples, seed, region="envelope", spec=PAPER_SPEC),
                       dither="gaussian",
                       dither_hold=(1, 1), excitation=paper.excitation)
    return collection_settings(SWITCHING_PERIOD, samples, seed, region=collection, spec=PAPER_SPEC)


def variant_config(variant: str):
    """The network of a :data:`VARIANTS` entry: the recipe's (with the supply voltage) or without that input."""
    from cosim.design.experiments import nn_configs

    config = nn_configs(SWITCHING_PERIOD)["nnpc"]
    if VARIANTS[variant][1]:
        return config
    return replace(config, extra_signals=tuple(s for s in config.extra_signals if s != "input_voltage"))


def identified(binding, pi, variant: str, seed: int, samples: int, folder: Path):
    """The online NNPC's network identified by the workbench's recipe from the data of collection ``variant``
    (:data:`VARIANTS`) and ``seed`` (cached in ``folder`` by variant, seed and samples); (model path, model, data)."""
    from controllers.nn_model import load_model, save_model
    from cosim.design.data_collection import collect, save_samples
    from cosim.design.identification import Recipe, identify
    from cosim.results import read_parquet

    config = variant_config(variant)
    path = folder / f"nnpc__{variant.replace(', ', '-').replace(' ', '-')}__seed{seed}__{samples}.pt"
    data_path = path.with_suffix(".parquet")
    if path.is_file() and data_path.is_file():
        return path, load_model(path, expect_period=SWITCHING_PERIOD, expect_config=config), read_parquet(data_path)[0]
    settings = variant_settings(VARIANTS[variant][0], seed, samples)
    data = collect(binding, pi, settings)
    result = identify(binding, pi, SWITCHING_PERIOD, config, seed, Recipe(samples=samples), data=data,
                      collection=settings)
    save_model(result.model, path)
    save_samples(data, data_path)
    return path, result.model, data


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in name).strip("-")


def compare(results: Path, folder: Path, seeds=(0, 1), samples: int = 10_000, workers: int = 1,
            map_runs: bool = True, variants=tuple(VARIANTS), map_variants=MAP_VARIANTS) -> dict:
    """The comparison of the module docstring, written to ``folder`` (``comparison.json``, ``errors.csv``,
    ``map.csv``, ``nominal.csv``); ``results``: a reproduction's folder, for the tuned PI."""
    import torch

    from cosim.design.experiments import horizon_settings
    from cosim.design.plants import plant_binding
    from cosim.design.sweeps.spec import ControllerEntry
    from cosim.design.vocabulary import NNPC
    from cosim.study import envelope

    torch.set_num_threads(1)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    binding = plant_binding("nominal", "switched")
    pi = _pi(Path(results))
    horizon = horizon_settings(SWITCHING_PERIOD).horizon
    tests = test_sets(binding, pi)
    out = {"test_sets": {k: coverage(v) for k, v in tests.items()}, "data": {}}
    errors, nominal, entries = [], [], []
    for region in variants:
        for seed in seeds:
            path, model, data = identified(binding, pi, region, seed, samples, folder)
            name = f"{NNPC} [{region}] (seed {seed})"
            out["data"][name] = coverage(data)
            errors += [{"controller": name, "region": region, "seed": seed, **row}
                       for row in prediction_errors(model, tests, horizon)]
            nominal += [{"region": region, "seed": seed, **row} for row in nominal_scenarios(binding, model, name)]
            if region in map_variants:
                entries.append(ControllerEntry("nnpc", name, model=path, origin=f"{region} data, seed {seed}"))
            print(f"{name}: {coverage_text(out['data'][name])}", flush=True)
    pd.DataFrame(errors).to_csv(folder / "errors.csv", index=False, float_format="%.6g")
    pd.DataFrame(nominal).to_csv(folder / "nominal.csv", index=False, float_format="%.6g")
    if map_runs:  # one sweep per network, so that a rerun with other variants resumes what is there
        steps = pd.concat([envelope.run_entries([e], folder / "map" / _slug(e.name), workers=workers)
                           for e in entries], ignore_index=True)
        steps.to_csv(folder / "map.csv", index=False, float_format="%.8g")
        points = envelope.point_results(steps)
        light = points["load_Ohm"] >= 40
        out["map"] = {name: {"share_pct": 100 * float(p["meets"].mean()),
                             "below_40_ohm_pct": 100 * float(p[~light.loc[p.index]]["meets"].mean()),
                             "from_40_ohm_pct": 100 * float(p[light.loc[p.index]]["meets"].mean()),
                             **{f"at_{v:g}_V_pct": 100 * float(p[p["input_voltage_V"] == v]["meets"].mean())
                                for v in sorted(p["input_voltage_V"].unique())}}
                      for name, p in points.groupby("controller", sort=False)}
    (folder / "comparison.json").write_text(json.dumps(out, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m cosim.study.envelope_identification",
                                     description="The envelope collection against the paper's: prediction errors, "
                                                 "the NNPC's map share, the nominal scenarios.")
    parser.add_argument("--results", type=Path, default=Path("results"), help="a reproduction's folder (the PI)")
    parser.add_argument("--out", type=Path, required=True, help="where the models, tables and map go")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--samples", type=int, default=10_000)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--no-map", action="store_true", help="prediction errors and nominal scenarios only")
    args = parser.parse_args(argv)
    out = compare(args.results, args.out, tuple(args.seeds), args.samples, args.workers, not args.no_map,
                  tuple(args.variants), tuple(v for v in MAP_VARIANTS if v in args.variants))
    errors = pd.read_csv(args.out / "errors.csv")
    print(errors.to_string(index=False))
    nominal = pd.read_csv(args.out / "nominal.csv")
    print(nominal.pivot_table(index="controller", columns="scenario", values="iae_Vs").to_string())
    print(nominal.pivot_table(index="controller", columns="scenario", values="overshoot_pct").to_string())
    for name, row in out.get("map", {}).items():
        print(name, {k: round(v, 1) for k, v in row.items()})


if __name__ == "__main__":
    main()
