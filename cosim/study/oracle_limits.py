"""Why the oracle MPC meets the envelope map's spec where it does not (issue 25, section 4).

The oracle predicts with the plant's own circuit, solved exactly per PWM period -- in continuous
conduction. Its map share is far below 100 % and its failures sit at the light loads (DCM). Three
candidates could limit it there: the **spec** (the overshoot is measured on the instantaneous output
voltage, ripple included, in % of a step of 0.2 r: at 3 V that is 30 mV, the order of the DCM ripple),
the **horizon** (one LC period, 23 samples) or the **model** (in DCM its CCM model, with the predicted
current clipped at 0, underestimates what a duty does to vo: it asks for too much and overshoots).

:func:`diagnose` reruns the oracle's two steps at the map points it fails (from ``envelope/map.csv``)
and separates them:

* ``ripple`` -- the overshoot measured on the period mean of vo (what the averaging sensor reads: the
  ripple averaged out) next to the instantaneous one: where the mean stays within 5 %, the spec's
  ripple, not the control, fails the point;
* ``horizon`` -- the same steps with a longer horizon (32 samples, the most the C twin holds: 1.4 LC
  periods): where that meets the spec, the horizon limits it;
* what neither explains is the model's (the DCM gain the CCM model does not know).

``python -m cosim.study.oracle_limits --results results --out DIR`` runs it (the oracle's C twin; a
few minutes) and writes ``DIR/oracle_limits.csv``.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from cosim.design.vocabulary import DEFAULT_IMPLEMENTATION, MPC_ORACLE, SWITCHING_PERIOD

#: the longer horizon measured [samples at 1/fsw]: the longest the C twin holds (BUCKC_MAX_HORIZON), 1.4 LC ringing
#: periods against the study's one (23 samples)
LONG_HORIZON = 32


def _overshoot_of_mean(result, scenario) -> float:
    """The step's overshoot [% of the step] on the sensor's period mean of vo after the step."""
    frame = result.frame
    t0 = scenario.events[-1].time
    after = frame[frame["time"] >= t0]
    mean = after["measured_output_voltage"].to_numpy(dtype=float)
    final = scenario.events[-1].changes.get("reference", scenario.initial["reference"])
    start = float(frame.loc[frame["time"] <= t0, "measured_output_voltage"].iloc[-1])
    step = final - start
    if abs(step) > 0.02 * final:  # the reference step: beyond r_f in the step's direction, of the step
        return 100.0 * max(0.0, float(np.max((mean - final) * np.sign(step)))) / abs(step)
    return 100.0 * max(0.0, float(np.max(mean - final))) / final  # the load step: above r, of r


def oracle(binding, horizon: int | None = None, implementation: str = DEFAULT_IMPLEMENTATION):
    """The oracle MPC on ``binding`` (its own circuit), with ``horizon`` samples (None: the study's)."""
    from cosim.design.controller_factory import true_parameters
    from cosim.design.experiments import horizon_settings, implemented, model_mpc

    period = SWITCHING_PERIOD
    name = MPC_ORACLE if horizon is None else f"{MPC_ORACLE} (N={horizon_settings(period, horizon).horizon})"
    return implemented(model_mpc(true_parameters(binding), period, name, binding=binding, horizon=horizon),
                       implementation)


def diagnose(results: Path, settle: float | None = None) -> pd.DataFrame:
    """Per failing point of the oracle and step: the overshoot (instantaneous and of the period mean) and
    the settling of the study's oracle and of the oracle with :data:`LONG_HORIZON` samples of horizon;
    whether each meets the spec; and the verdict (``ripple``, ``horizon`` or ``model``)."""
    from cosim.design.plants import plant_binding
    from cosim.design.sweeps.plan import at_operating_point
    from cosim.master import simulate
    from cosim.metrics import run_metrics
    from cosim.study import envelope

    steps = envelope.load_steps(results)
    if steps is None:
        raise FileNotFoundError(f"{Path(results) / envelope.ENVELOPE_DIR / 'map.csv'} is missing: run the map first")
    points = envelope.point_results(steps[steps["controller"] == MPC_ORACLE])
    failing = points[~points["meets"]]
    binding = plant_binding(envelope.MAP_PLANT.split("-")[0], envelope.MAP_PLANT.split("-")[1])
    settings = envelope.FULL_MAP
    settle = settings.settle_predictive if settle is None else settle
    anchors = (("reference", "final"), ("load_resistance", "final"))
    rows = []
    for _, point in failing.iterrows():
        values = {"reference": point["reference_V"], "load_resistance": point["load_Ohm"],
                  "input_voltage": point["input_voltage_V"]}
        for template in envelope.step_scenarios(settings):
            scenario = replace(at_operating_point(template, values, anchors), settle=settle)
            row = {"reference_V": point["reference_V"], "load_Ohm": point["load_Ohm"],
                   "input_voltage_V": point["input_voltage_V"], "step": template.name}
            for label, n in (("", None), ("_long", LONG_HORIZON)):
                result = simulate(binding, oracle(binding, n), scenario, record_period=1e-5)
                m = run_metrics(result)
                row[f"overshoot_pct{label}"] = m["overshoot_pct"]
                row[f"overshoot_of_mean_pct{label}"] = _overshoot_of_mean(result, scenario)
                row[f"settling_time_ms{label}"] = m["settling_time_ms"]
                row[f"ripple_mV{label}"] = m["output_voltage_ripple_mV"]
            rows.append(row)
    frame = pd.DataFrame(rows)
    return verdicts(frame)


def _meets(overshoot, settling) -> pd.Series:
    settling = settling.astype(float).fillna(math.inf)
    from cosim.study.envelope import OVERSHOOT_TARGET_PCT, SETTLING_TARGET_MS

    return (overshoot <= OVERSHOOT_TARGET_PCT) & (settling <= SETTLING_TARGET_MS)


def verdicts(frame: pd.DataFrame) -> pd.DataFrame:
    """Per point (both steps): meets as run, meets on the period mean of vo (ripple out of the overshoot),
    meets with the longer horizon; the verdict: ``ripple`` if the period mean meets it, else ``horizon`` if
    the longer horizon does, else ``model``."""
    frame = frame.copy()
    frame["meets"] = _meets(frame["overshoot_pct"], frame["settling_time_ms"])
    frame["meets_on_mean"] = _meets(frame["overshoot_of_mean_pct"], frame["settling_time_ms"])
    frame["meets_long"] = _meets(frame["overshoot_pct_long"], frame["settling_time_ms_long"])
    keys = ["reference_V", "load_Ohm", "input_voltage_V"]
    per_point = frame.groupby(keys)[["meets", "meets_on_mean", "meets_long"]].all()
    per_point["verdict"] = np.where(per_point["meets_on_mean"], "ripple",
                                    np.where(per_point["meets_long"], "horizon", "model"))
    return frame.merge(per_point[["verdict"]].reset_index(), on=keys)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m cosim.study.oracle_limits",
                                     description="What limits the oracle MPC at the envelope map's failing points.")
    parser.add_argument("--results", type=Path, default=Path("results"))
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    frame = diagnose(args.results)
    args.out.mkdir(parents=True, exist_ok=True)
    frame.to_csv(args.out / "oracle_limits.csv", index=False, float_format="%.6g")
    pd.set_option("display.width", 250)
    print(frame.to_string(index=False))
    points = frame.drop_duplicates(["reference_V", "load_Ohm", "input_voltage_V"])
    print(points["verdict"].value_counts().to_string())


if __name__ == "__main__":
    main()
