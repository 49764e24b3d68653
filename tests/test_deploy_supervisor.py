"""Safety supervisor: stale state, lost and hot motors, tilt, non-finite values, target limits."""

import math

import numpy as np
import pytest

from deploy.supervisor import SafetySupervisor, SupervisorConfig, tilt_rad

LOWER = np.full(12, -1.0)
UPPER = np.full(12, 1.0)


def quat_about_x(deg: float) -> np.ndarray:
    a = math.radians(deg) / 2
    return np.array([math.cos(a), math.sin(a), 0.0, 0.0])


def good_state(**over):
    d = {"q": np.zeros(12), "dq": np.zeros(12), "quat_wxyz": np.array([1.0, 0, 0, 0]),
             "gyro": np.zeros(3), "temperature": np.full(12, 40), "lost": np.zeros(12, int)}
    d.update(over)
    return d


def sup(**cfg):
    return SafetySupervisor(SupervisorConfig(**cfg), LOWER, UPPER, dt=0.02)


def test_tilt_angle_from_quaternion():
    assert tilt_rad([1, 0, 0, 0]) == pytest.approx(0.0)
    assert math.degrees(tilt_rad(quat_about_x(29.0))) == pytest.approx(29.0)
    # a yaw rotation is no tilt
    assert tilt_rad([math.cos(0.5), 0, 0, math.sin(0.5)]) == pytest.approx(0.0, abs=1e-7)


def test_healthy_state_passes():
    s = sup()
    for _ in range(10):
        assert s.check_state(True, **good_state()) is None


def test_stale_lowstate_faults_after_more_than_three_ticks():
    s = sup()
    assert s.check_state(True, **good_state()) is None
    for _ in range(3):
        assert s.check_state(False, **good_state()) is None
    cause = s.check_state(False, **good_state())
    assert cause is not None and "stale" in cause
    # a fresh sample resets the count
    s2 = sup()
    for _ in range(3):
        assert s2.check_state(False) is None
    assert s2.check_state(True, **good_state()) is None
    assert s2.check_state(False) is None


def test_tilt_over_30_degrees_faults():
    s = sup()
    assert s.check_state(True, **good_state(quat_wxyz=quat_about_x(29.5))) is None
    cause = s.check_state(True, **good_state(quat_wxyz=quat_about_x(31.0)))
    assert cause is not None and "tilt 31.0 deg" in cause


def test_over_temperature_faults():
    t = np.full(12, 40)
    t[7] = 95
    cause = sup().check_state(True, **good_state(temperature=t))
    assert cause is not None and "motor 7 over temperature" in cause


def test_lost_motor_needs_consecutive_increments():
    s = sup(lost_ticks=3)
    lost = np.zeros(12, int)
    assert s.check_state(True, **good_state(lost=lost.copy())) is None
    lost[4] += 1  # a single glitch
    assert s.check_state(True, **good_state(lost=lost.copy())) is None
    assert s.check_state(True, **good_state(lost=lost.copy())) is None
    for i in range(3):
        lost[4] += 1
        cause = s.check_state(True, **good_state(lost=lost.copy()))
        assert (cause is None) == (i < 2)
    assert "motor 4 lost" in cause


@pytest.mark.parametrize("field", ["q", "dq", "gyro"])
def test_non_finite_state_faults(field):
    v = np.zeros(3 if field == "gyro" else 12)
    v[1] = np.nan
    cause = sup().check_state(True, **good_state(**{field: v}))
    assert cause is not None and "non-finite" in cause


def test_check_finite_names_the_bad_entry():
    assert SafetySupervisor.check_finite("action", np.zeros(12)) is None
    a = np.zeros(12)
    a[5] = np.inf
    assert "index 5" in SafetySupervisor.check_finite("action", a)


def test_targets_clamped_and_rate_limited():
    s = sup(max_rate=10.0)  # 0.2 rad per 20 ms tick
    prev = np.zeros(12)
    q = s.limit(np.full(12, 5.0), None)
    np.testing.assert_allclose(q, UPPER)
    q = s.limit(np.full(12, 0.5), prev)
    np.testing.assert_allclose(q, 0.2)
    q = s.limit(np.full(12, -0.1), prev)
    np.testing.assert_allclose(q, -0.1)
    assert s.clamped == 1 and s.rate_limited == 1


def test_config_validation():
    with pytest.raises(ValueError):
        SupervisorConfig(max_tilt_rad=0.0)
    with pytest.raises(ValueError):
        SupervisorConfig(max_rate=np.zeros(12))
