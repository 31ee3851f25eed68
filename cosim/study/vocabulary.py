"""The paper study's vocabulary: the names and numbers only the paper's study uses (its converter, rates and seeds,
its ablations, the drift study, the tolerance study). The design steps' names -- controllers, rates, recipes, plants
-- are :mod:`cosim.design.vocabulary`'s.
"""

from __future__ import annotations

from cosim.design.vocabulary import (
    CONTROLLER_STYLES,
    MPC_NOMINAL,
    MPC_ORACLE,
    NNPC,
    PAPER_PERIOD,
    SWITCHING_PERIOD,
)
from cosim.fmi.binding import BUILTIN_SPEC

#: the converter the paper studies: the built-in plant's spec, Table II (cosim.converter_spec) -- the study's one name
#: for it; the design steps take the spec of the plant they design for
PAPER_SPEC = BUILTIN_SPEC
#: the paper study's rates: the paper's 1 ms and one switching period
STUDY_PERIODS = (PAPER_PERIOD, SWITCHING_PERIOD)

#: identification seeds: the reproduction identifies the NNPC from each seed's data and reports every
#: one (seed 0 is the NNPC of the main tables); targets hold over the worst of them
STUDY_SEEDS = (0, 1, 2, 3, 4)

#: ablation variants (reproduction only)
MPC_ORACLE_AVERAGED = f"{MPC_ORACLE} (averaged model)"
MPC_ORACLE_SYNC = f"{MPC_ORACLE} (sync. sample)"


def horizon_variant(name: str, horizon: int) -> str:
    """``NNPC (N=3)``: a controller run with another prediction horizon."""
    return f"{name} (N={horizon})"


#: identification ablation (nominal switched plant at one switching period, every seed): the
#: workbench's earlier network (7 hidden, one-step), the NNPC's network after the one-step stage,
#: the NNPC (after the simulation-error stage), and the NNPC refined on one round of data with
#: itself in the loop
NNPC_SMALL_ONE_STEP = f"{NNPC} (7 hidden, one-step)"
NNPC_ONE_STEP = f"{NNPC} (one-step)"
NNPC_CLOSED_LOOP = f"{NNPC} (+ closed-loop round)"
IDENTIFICATION_ABLATION = (NNPC_SMALL_ONE_STEP, NNPC_ONE_STEP, NNPC, NNPC_CLOSED_LOOP)
#: the scenarios the ablation variants run in closed loop: the two where the identification shows
#: (start-up overshoot; the worst IAE / oracle ratio, in reference_up for every seed and variant);
#: load change and reference down stay within 2 % of the oracle for every identified network
ABLATION_SCENARIOS = ("startup", "reference_up")
#: the MPC of the paper's kind: the nominal model without the disturbance estimate (not offset-free)
MPC_NOMINAL_NO_ESTIMATE = f"{MPC_NOMINAL} (no disturbance estimate)"
#: the drift study (mismatch-study plant at one switching period)
NNPC_DRIFTED = f"{NNPC} (identified on the drifted plant)"
DRIFT_SCENARIO = "capacitor_ageing"
DRIFT_STUDY = "drift"  # the drift study's job and its rows' "pipeline" in the metrics tables
#: the drifted plant: C falls by 30 %, the inductor's DCR doubles
DRIFT_CAPACITANCE_FACTOR, DRIFT_RESISTANCE_FACTOR = 0.7, 2.0
#: the drift study's analysis window: from here to the end of the scenario, after the drift [s]
DRIFT_ANALYSIS_START = 0.024

#: figure colour and line style per controller name: the design layer's, and the study's own variants
STUDY_STYLES = {**CONTROLLER_STYLES,
                MPC_NOMINAL_NO_ESTIMATE: ("tab:brown", (0, (3, 1, 1, 1))),
                NNPC_DRIFTED: ("tab:gray", (0, (4, 2)))}

#: the reproduction's tolerance study: the shipped sweep file it runs, and its folder under results/
TOLERANCE_STUDY = "tolerance-reproduction"
TOLERANCE_STUDY_DIR = "tolerance-study"
