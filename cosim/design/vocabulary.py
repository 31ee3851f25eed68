"""The design layer's vocabulary: the one definition of every name and number the design steps share.

The design steps (tuning, data collection, identification, classical design, distillation, frequency response,
sweeps), the studies built on them, the command line, the benchmarks and the tests import these instead of typing
them again:

* **rates** -- the paper's 1 ms, one switching period of the built-in plant, and the regime test
  :func:`transient_within_sample` that decides every rate-dependent setting;
* **plants** -- the built-in plant's nominal circuit (its spec: Table II, :mod:`plant_fmu.table_ii`) and the
  mismatch circuit, the sensor choices, :func:`lc_period` and :func:`plant_tag` (how files and tables name a
  built-in plant);
* **controllers** -- the command-line keys and the names runs carry, with their plot styles;
* **recipes** -- the identification recipe's sizes, the collection regions and dithers;
* **time compression** -- how the scenarios are shortened at the fast rate;
* **implementations** -- a controller's C twin or its Python reference.

The paper study's own names (its seeds, ablations, drift study, tolerance study) are
:mod:`cosim.study.vocabulary`'s. Labels of periods (``1ms``, ``13.33 µs``) are the core's
(:mod:`cosim.base.labels`): run files are named with them outside the design layer too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from controllers.predictors import CircuitParameters
from cosim.base.labels import period_label
from cosim.fmi.binding import BUILTIN_SPEC

# ---------------------------------------------------------------------------------------------
# Rates

PAPER_PERIOD = 1e-3  # [s] the paper's sample period
SWITCHING_PERIOD = BUILTIN_SPEC.switching_period  # [s] one PWM period of the built-in plant, 13.33 us
#: at control periods this long or longer the LC transient (about 0.48 ms at Table II) is over
#: within one sample, so one step of prediction decides the move ("the paper's regime")
TRANSIENT_WITHIN_SAMPLE_PERIOD = 0.5e-3  # [s]


def transient_within_sample(control_period: float) -> bool:
    """True when the LC transient settles within one control period (1 ms: yes; 13.33 us: no)."""
    return control_period >= TRANSIENT_WITHIN_SAMPLE_PERIOD


#: identification: the duty dither (standard deviation) added to the PI where the transient is
#: over within a sample, and where it is not (the NNPC there plans full-duty and braking moves
#: far from the PI's own trajectories, which the network must have seen)
DITHER_SLOW, DITHER_FAST = 0.01, 0.1


def identification_dither(control_period: float) -> float:
    return DITHER_SLOW if transient_within_sample(control_period) else DITHER_FAST


#: the identification recipe (cosim/design/identification.py), sized to the reproduction's time
#: target: the one-step stage stops after ONE_STEP_ITERATIONS L-BFGS iterations at most (capping it
#: at 1000 cost accuracy the simulation-error stage did not win back: measured, 10-step RMSE up to
#: 150 mV instead of 126 mV over the five seeds); that stage takes one window every
#: MULTI_STEP_STRIDE samples (neighbouring windows share all but one step), at most
#: MULTI_STEP_ITERATIONS iterations
ONE_STEP_ITERATIONS, MULTI_STEP_STRIDE, MULTI_STEP_ITERATIONS = 3000, 6, 300
#: NNPC-in-the-loop data rounds (the ablation's): samples per round, the refinement's iterations
#: at most, the dither on the NNPC's duty, and the seed offset of their random references and
#: loads (round r of seed s uses s + r * offset). The rounds draw from the rate's collection region: at
#: 13.33 us the envelope, where the dither is the amplitude-modulated binary one, CLOSED_LOOP_DITHER its
#: largest level; at 1 ms the paper's region, a white dither of that standard deviation
CLOSED_LOOP_SAMPLES, CLOSED_LOOP_ITERATIONS, CLOSED_LOOP_DITHER, CLOSED_LOOP_SEED_OFFSET = 1000, 150, 0.03, 1000
#: samples of PI data a network the command line trains on demand is identified from (run/export-controller --samples)
ON_DEMAND_SAMPLES = 10_000


# ---------------------------------------------------------------------------------------------
# Plants

#: the circuit of Table II, ideal (no parasitics)
NOMINAL = CircuitParameters(**BUILTIN_SPEC.circuit("the study's nominal circuit"))
#: the mismatch-study plant: L +20 %, C -20 % and realistic parasitics
MISMATCH = CircuitParameters(inductance=264e-6, capacitance=8e-6, inductor_resistance=0.15,
                             switch_on_resistance=0.1, diode_forward_voltage=0.7, capacitor_esr=0.05)
PLANT_VARIANTS = {"nominal": NOMINAL, "mismatch": MISMATCH}
#: what the controllers' sensors read: the mean over the last PWM period, or a synchronous sample
SENSORS = ("average", "synchronous")


def lc_period(spec) -> float:
    """One LC ringing period 2 pi sqrt(L C) of a converter spec's nominal circuit [s] (refused, naming the key, where
    the spec gives no L or C): what the predictive controllers' horizon spans at fast rates."""
    purpose = "the prediction horizon at fast rates (one LC ringing period)"
    return 2 * math.pi * math.sqrt(spec.require("inductance", purpose) * spec.require("capacitance", purpose))


#: one LC ringing period of the paper's nominal circuit [s] (about 0.295 ms)
LC_PERIOD = lc_period(BUILTIN_SPEC)


def pipeline_tag(plant: str, control_period: float) -> str:
    """One plant at one rate, as files name it: ``nominal-switched__13p33us`` (tuned gains, data,
    models, pipeline summaries, metrics tables)."""
    return f"{plant}__{period_label(control_period)}"


def plant_tag(variant: str, mode: str, sensor: str = "average") -> str:
    """How files and tables name a built-in plant: ``nominal-switched``, ``nominal-switched-sync``
    (an external plant is ``bound-<binding file stem>``: :attr:`cosim.fmi.binding.PlantBinding.tag`)."""
    return f"{variant}-{mode}" + ("" if sensor == "average" else "-sync")


# ---------------------------------------------------------------------------------------------
# Controllers

PI = "PI"
NNPC = "NNPC"
NNPC_PAPER = "NNPC-paper"
MPC_ORACLE = "MPC-oracle"
MPC_NOMINAL = "MPC-nominal"
MPC_MISMATCHED = "MPC-mismatched"
#: the explicit NNPC: a policy network distilled from the online NNPC (cosim.design.distillation)
NNPC_EXPLICIT = "NNPC-explicit"
#: the classical baselines designed from the small-signal model (cosim.design.classical_design) and the PI
#: tuned over the envelope (cosim.design.pi_tuning.tune_pi_envelope)
CURRENT_MODE = "CMC"
#: the current-mode controller designed and run without the computation delay (the NNPC has none either: the
#: like-for-like comparison of the envelope map; no microcontroller computes in zero time, so it is a bound)
CURRENT_MODE_NO_DELAY = "CMC (no delay)"
TYPE_III = "Type-III"
PI_ENVELOPE = "PI-envelope"
#: the NNPC whose network's output layer follows the plant online (controllers.adaptation)
NNPC_ADAPTIVE = f"{NNPC}-adaptive"
CLASSICAL = (PI, PI_ENVELOPE, CURRENT_MODE, TYPE_III)
#: command-line key -> the name a run, a metrics row and a figure legend carry
CONTROLLERS = {"pi": PI, "nnpc": NNPC, "nnpc-adaptive": NNPC_ADAPTIVE, "nnpc-paper": NNPC_PAPER,
               "mpc-oracle": MPC_ORACLE, "mpc-nominal": MPC_NOMINAL, "nnpc-explicit": NNPC_EXPLICIT,
               "current-mode": CURRENT_MODE, "type-iii": TYPE_III, "pi-envelope": PI_ENVELOPE}
#: the command-line keys export-controller writes as FMUs: every built-in controller with a C twin (the adaptive
#: NNPC adapts its network online in Python, which no C twin does)
EXPORTABLE_CONTROLLERS = tuple(k for k in CONTROLLERS if k != "nnpc-adaptive")
#: the command-line keys whose C twin has a float32 build (export-controller --precision float32; the Cortex-M4F)
FLOAT32_CONTROLLERS = ("pi", "nnpc-explicit", "current-mode", "type-iii")
#: the NN plant models per rate, by command-line key
NETWORKS = ("nnpc", "nnpc-paper")
#: the command-line keys of the predictive controllers: those whose optimizer (the RTI or the search) --optimizer
#: chooses and whose RTI settings --rti changes
PREDICTIVE_CONTROLLERS = ("nnpc", "nnpc-paper", "nnpc-adaptive", "mpc-oracle", "mpc-nominal")

def seed_variant(name: str, seed: int) -> str:
    """``NNPC (seed 2)``: a controller identified from another seed's data."""
    return f"{name} (seed {seed})"


def is_seed_variant(name: str, base: str = NNPC) -> bool:
    return name.startswith(f"{base} (seed ")


def seed_of(name: str, base: str = NNPC) -> int | None:
    """The seed of ``base`` or of one of its seed variants (``NNPC`` is seed 0), else None."""
    if name == base:
        return 0
    if is_seed_variant(name, base):
        return int(name[len(base) + len(" (seed "):-1])
    return None


#: figure colour and line style per controller name (a study adds its own variants': cosim.study.vocabulary)
CONTROLLER_STYLES = {
    PI: ("tab:blue", "-"),
    NNPC: ("tab:red", "-"),
    NNPC_PAPER: ("tab:orange", (0, (4, 2))),
    MPC_ORACLE: ("tab:green", "-"),
    MPC_MISMATCHED: ("tab:purple", (0, (1, 1))),
    MPC_NOMINAL: ("tab:purple", (0, (1, 1))),
    NNPC_ADAPTIVE: ("tab:green", "-"),
    NNPC_EXPLICIT: ("tab:brown", (0, (5, 1))),
    CURRENT_MODE: ("tab:cyan", "-"),
    CURRENT_MODE_NO_DELAY: ("tab:cyan", (0, (3, 1))),
    TYPE_III: ("tab:olive", (0, (3, 1))),
    PI_ENVELOPE: ("tab:pink", (0, (2, 1))),
}

# ---------------------------------------------------------------------------------------------
# Scenarios at the fast rate


@dataclass(frozen=True)
class TimeCompression:
    """How the paper's scenarios are shortened where every controller settles within ~1 ms."""

    settle: float = 3e-3  # [s] closed-loop operation before t = 0 (for scenarios that settle at all)
    event_time: float = 1.5e-3  # [s] every event moves here
    duration: float = 6e-3  # [s] recorded

    def describe(self) -> str:
        return (f"settle {self.settle * 1e3:g} ms, events at {self.event_time * 1e3:g} ms, "
                f"{self.duration * 1e3:g} ms recorded")


FAST_RATE_COMPRESSION = TimeCompression()


#: where the identification data come from, over the converter spec's operating points: the paper's region scaled
#: to it (Table II: references 0-20 V, loads 4-10 Ohm, 48 V) or its operating envelope (Table II: references 3-20 V,
#: loads 4-100 Ohm, supplies 36-60 V; cosim.study.envelope_identification)
COLLECTION_REGIONS = ("paper", "envelope")
#: the envelope collection's dither: the amplitude-modulated random binary sequence, levels +-a with
#: a ~ U(0, ENVELOPE_DITHER), held 1-8 samples
ENVELOPE_DITHER, ENVELOPE_DITHER_HOLD = 0.2, (1, 8)


# ---------------------------------------------------------------------------------------------
# Implementations

#: how a controller runs: its C twin (controllers/c, equivalent to the Python reference at every sample; the
#: default, far faster for the predictive controllers: results/benchmarks.md) or the Python reference
IMPLEMENTATIONS = ("c", "python")
DEFAULT_IMPLEMENTATION = "c"

#: the predictive controllers' optimizers: the real-time iteration (Gauss-Newton steps from the last plan, the
#: search as fallback at a cold start and at large steps) and the search alone (grid + pattern search, the reference)
OPTIMIZERS = ("rti", "search")
#: how tables and benchmark rows name each implementation
IMPLEMENTATION_NAMES = {"c": "C twin", "python": "Python reference"}
