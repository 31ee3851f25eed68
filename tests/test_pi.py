"""PI controller: the discrete law in numbers, limits and anti-windup."""

from __future__ import annotations

import pytest

from controllers.base import Measurement
from controllers.pi import PIController


def meas(error, reference=12.0):
    return Measurement(time=0.0, reference=reference, output_voltage=reference - error)


def test_discrete_law_in_numbers():
    pi = PIController(kp=0.1, ki=10.0, sample_period=1e-3)
    assert pi.step(meas(2.0)) == pytest.approx(0.1 * 2 + 10 * 1e-3 * 2)  # 0.22
    assert pi.integral == pytest.approx(0.02)
    assert pi.step(meas(1.0)) == pytest.approx(0.1 * 1 + 0.02 + 0.01)  # 0.13
    pi.reset()
    assert pi.integral == 0.0


def test_pure_integral_with_ki_ts_equal_one_over_vs_is_deadbeat_on_a_static_plant():
    vs = 48.0
    pi = PIController(0.0, 1.0 / (vs * 1e-3), 1e-3)
    vo = 0.0
    for _ in range(3):
        vo = vs * pi.step(Measurement(0.0, 12.0, vo))  # plant settles within one sample: vo = Vs d
    assert vo == pytest.approx(12.0)
    assert pi.step(Measurement(0.0, 12.0, vo)) == pytest.approx(0.25)


def test_duty_limits_are_respected():
    pi = PIController(1.0, 0.0, 1e-3, duty_limits=(0.1, 0.6))
    assert pi.step(meas(5.0)) == 0.6
    assert pi.step(meas(-5.0)) == 0.1


def test_anti_windup_freezes_the_integral_while_saturated():
    pi = PIController(0.01, 100.0, 1e-3, duty_limits=(0.0, 0.5))
    for _ in range(50):
        assert pi.step(meas(10.0)) == 0.5  # would wind up by 0.1 per step without clamping
    assert pi.integral == pytest.approx(0.0)
    assert pi.step(meas(-0.01)) == 0.0  # the opposite error leaves the upper limit at once
    pi = PIController(0.01, 100.0, 1e-3, duty_limits=(0.0, 0.5))
    pi.integral = 0.3  # mid-range integral, then saturate high for a while
    for _ in range(20):
        pi.step(meas(50.0))
    assert pi.integral == pytest.approx(0.3)
    assert pi.step(meas(-0.5)) == pytest.approx(0.01 * -0.5 + 0.3 - 0.05)  # integrates again: 0.245


def test_anti_windup_limits_overshoot_after_long_saturation():
    """A slow first-order plant, saturated for a long time: clamping avoids the windup overshoot."""

    def simulate(pi):
        y, peak = 0.0, 0.0
        for _ in range(400):
            d = pi.step(Measurement(0.0, 12.0, y))
            y += 0.02 * (48.0 * d - y)  # tau = 50 samples
            peak = max(peak, y)
        return peak

    clamped = PIController(0.05, 20.0, 1e-3, duty_limits=(0.0, 0.3))
    assert simulate(clamped) < 12.0 * 1.10


@pytest.mark.parametrize("kwargs,message", [
    ({"kp": -1.0, "ki": 0.0}, "PI gains kp = -1.0, ki = 0.0 are invalid"),
    ({"kp": 0.0, "ki": 1.0, "sample_period": 0.0}, "PI: sample period 0.0 s is invalid"),
    ({"kp": 0.0, "ki": 1.0, "duty_limits": (0.5, 0.2)}, r"PI: duty limits \(0.5, 0.2\) are invalid"),
    ({"kp": 0.0, "ki": 1.0, "duty_limits": (0.0, 1.2)}, r"PI: duty limits \(0.0, 1.2\) are invalid"),
])
def test_invalid_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        PIController(**kwargs)


def test_describe_names_gains_and_units():
    info = PIController(0.1, 10.0, 1e-3, duty_limits=(0.0, 0.9)).describe()
    assert info["kp_per_V"] == 0.1 and info["ki_per_V_s"] == 10.0 and info["duty_limits"] == [0.0, 0.9]
