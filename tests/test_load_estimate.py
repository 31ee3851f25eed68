"""The one load estimate: the controller's sample-by-sample rule and the training data's column agree."""

from __future__ import annotations

import math

import numpy as np

from controllers.load_estimate import MIN_VOLTAGE, conductance_series, estimate_conductance
from cosim.design.data_collection import CollectionSettings, collect
from cosim.design.plants import plant_binding


def test_conductance_is_io_over_vo_else_il_over_vo_else_the_previous_estimate():
    assert estimate_conductance(12.0, 2.0, 2.5, 0.1) == 2.0 / 12.0  # io / vo
    assert estimate_conductance(12.0, math.nan, 2.5, 0.1) == 2.5 / 12.0  # no io sensor: iL / vo
    assert estimate_conductance(MIN_VOLTAGE / 2, 0.01, 0.01, 0.1) == 0.1  # start-up from rest: hold
    assert estimate_conductance(12.0, 0.0, 2.5, 0.1) == 0.1  # open load: hold (never 1/R = 0)
    assert estimate_conductance(12.0, math.nan, math.nan, 0.1) == 0.1  # no current sensor at all


def test_the_series_is_the_sample_rule_applied_in_order():
    rng = np.random.default_rng(3)
    vo = np.concatenate([np.zeros(5), rng.uniform(-0.1, 15.0, 300)])
    io = np.where(rng.random(305) < 0.2, np.nan, rng.uniform(-0.5, 3.0, 305))
    il = np.where(rng.random(305) < 0.1, np.nan, rng.uniform(-0.5, 3.0, 305))
    expected, g = [], 1 / 6.0
    for v, i, l in zip(vo, io, il):
        g = estimate_conductance(v, i, l, g)
        expected.append(g)
    np.testing.assert_array_equal(conductance_series(vo, io, il, 1 / 6.0), expected)


def test_training_data_carry_the_controllers_estimate(buck_fmu):
    from controllers.pi import PIController

    data = collect(plant_binding("nominal", "switched"), PIController(0.0015, 15.6, 1e-3),
                   CollectionSettings(samples=300, seed=5))
    g = 1 / 6.0
    for row in data.itertuples():
        g = estimate_conductance(row.measured_output_voltage, row.measured_load_current,
                                 row.measured_inductor_current, g)
        assert row.load_conductance == g
    settled = data[data["measured_output_voltage"] > 1.0]
    # the period-mean sensors see the load one sample late after a load step: compare where it held
    held = settled["load_resistance"].diff().fillna(0.0).eq(0) & settled["load_resistance"].shift().eq(
        settled["load_resistance"])
    np.testing.assert_allclose(1 / settled.loc[held, "load_conductance"], settled.loc[held, "load_resistance"],
                               rtol=1e-2)
