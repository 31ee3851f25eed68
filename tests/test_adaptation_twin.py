"""The adaptive NNPC's C twin (controllers/c/adaptation.c) against its Python reference (controllers/adaptation.py
around the same C NNPC): the same duties, output layers and guard counts on a recorded closed loop of the drifted
plant, and the C benchmark harness running it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from controllers import native
from controllers.adaptation import AdaptationSettings
from controllers.base import Measurement
from controllers.nn_model import load_model
from cosim.benchmark_harness import record_measurements, replay
from cosim.benchmarks.subjects import _mixed_scenario
from cosim.design.experiments import adaptive_nnpc
from cosim.design.plants import plant_binding
from cosim.design.vocabulary import SWITCHING_PERIOD

FIXTURES = Path(__file__).parent / "fixtures"
#: guards that act within a short run: small steps and deviation (bounded), checkpoints every 100 samples
SETTINGS = AdaptationSettings(max_step=0.01, max_deviation=0.1, checkpoint_every=100, warmup=20)


@pytest.fixture(scope="module")
def recorded():
    """(the adaptive NNPC with the RTI, 400 measurements of the mismatch plant it drove at 13.33 us)."""
    model = load_model(FIXTURES / "nnpc_nominal_averaged_13p33us.pt", expect_period=SWITCHING_PERIOD)
    adaptive = adaptive_nnpc(model, SWITCHING_PERIOD, settings=SETTINGS, optimizer="rti")
    measurements = record_measurements(plant_binding("mismatch", "switched"), native.native_twin(adaptive),
                                       _mixed_scenario(SWITCHING_PERIOD, 400))
    return adaptive, measurements


def test_the_c_adaptation_follows_the_python_reference_on_a_recorded_closed_loop(recorded):
    """Per step within 1e-9 in duty and in the output layer, and the same decisions of every guard. The two
    differ in the last bits (numpy's BLAS products against the twin's loops, as every twin does), and the
    recursion carries that forward: 1e-15 after the first update, ~1e-13 here after 400 samples, ~1e-11 after
    650 on the reproduction's network -- until a guard's threshold decides differently, so a whole run is
    compared by the closed loop, not per step."""
    adaptive, measurements = recorded
    reference = native.native_twin(adaptive)  # the Python adaptation around the C NNPC
    twin = native.NativeAdaptiveNNPC.from_python(adaptive)
    reference.reset()
    twin.reset()
    for k, row in enumerate(measurements):
        m = Measurement(*row)
        expected, got = reference.step(m), twin.step(m)
        assert abs(expected - got) <= 1e-9, k
        np.testing.assert_allclose(twin.output_weights, reference.output_weights, rtol=0, atol=1e-9)
    counters = twin.counters
    assert counters == reference.counters
    assert counters["updates"] > 50 and counters["bounded"] > 0 and counters["checkpoints"] >= 1
    assert counters["saturated"] > 0 and counters["steady"] > 0


def test_the_harness_times_the_c_adaptive_step_with_the_twins_duties(recorded):
    """The C harness (Python out of the loop) builds the adaptive NNPC from the generated header: its duties are
    the ctypes twin's, and its per-step update flags add up to the twin's update count."""
    adaptive, measurements = recorded
    twin = native.NativeAdaptiveNNPC.from_python(adaptive)
    twin.reset()
    duties, solvers = [], []
    for row in measurements:
        duties.append(twin.step(Measurement(*row)))
        solvers.append(twin.last_solver)
    result = replay(adaptive, measurements, repeats=1)
    np.testing.assert_allclose(result.duty, np.array(duties), rtol=0, atol=1e-12)
    assert int(result.updated.sum()) == twin.counters["updates"]
    # the harness flags the samples the RTI planned as the twin chose them (the rest: its fallback rule)
    np.testing.assert_array_equal(result.rti, np.array(solvers) == "rti")
    assert result.rti.sum() > 0.8 * len(measurements)


def test_the_c_adaptation_refuses_what_the_reference_refuses(recorded):
    from cosim.fmi.controller_export import controller_sources

    adaptive, _ = recorded
    predictive = native.PredictiveConfig.from_buffer_copy(native.NativeAdaptiveNNPC.from_python(adaptive)
                                                          .predictive_config)
    config = native.NativeAdaptiveNNPC.from_python(adaptive).adaptation_config
    predictive.predictor.nn.residual = 1
    with pytest.raises(ValueError, match="residual: the adaptation adapts networks that predict the state itself"):
        native.NativeAdaptiveNNPC(predictive, config, "adaptive", {}, 8)
    predictive.predictor.nn.residual = 0
    predictive.predictor.kind = native.PREDICTOR_AVERAGED
    with pytest.raises(ValueError, match="predictor kind: the adaptation adapts the NN predictor's network"):
        native.NativeAdaptiveNNPC(predictive, config, "adaptive", {}, 8)
    with pytest.raises(ValueError, match="NNPC-adaptive has no controller FMU: the adaptive NNPC's C twin"):
        controller_sources(adaptive, "adaptive")
