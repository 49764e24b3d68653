"""Metrics: CN, CC, Euler RE vs geodesic error, conversions."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from calib.metrics import (
    condition_number,
    covariance_condition,
    euler_rotation_error_deg,
    geodesic_error_deg,
    offset_error_s,
    quaternion_wxyz,
    rotation_from_rpy_deg,
    rpy_deg,
    trace_correlation,
)


def test_condition_number_of_known_covariance():
    rng = np.random.default_rng(0)
    w = rng.standard_normal((200_000, 3)) * np.array([1.0, 2.0, 3.0])
    assert condition_number(w) == pytest.approx(9.0, rel=0.02)
    q = Rotation.random(random_state=1).as_matrix()
    assert condition_number(w @ q.T) == pytest.approx(condition_number(w), rel=1e-9)
    flat = w.copy()
    flat[:, 2] = 0.0
    assert condition_number(flat) == np.inf


def test_condition_singular_to_round_off_is_inf():
    # A motion about two axes only, turned off the axes: the third eigenvalue of its covariance
    # comes out as round-off (tiny, either sign), which must read as singular, not as 1e16.
    rng = np.random.default_rng(2)
    w = np.zeros((5000, 3))
    w[:, :2] = rng.standard_normal((5000, 2))
    w = w @ Rotation.random(random_state=3).as_matrix().T
    assert condition_number(w) == np.inf
    assert covariance_condition(np.zeros((3, 3))) == np.inf
    assert covariance_condition(np.diag([4.0, 2.0, 1.0])) == pytest.approx(4.0)


def test_trace_correlation_one_for_rotated_copy_and_low_for_independent():
    rng = np.random.default_rng(1)
    wf = rng.standard_normal((5000, 3))
    r = Rotation.random(random_state=2).as_matrix()
    assert trace_correlation(wf @ r + 0.3, wf) == pytest.approx(1.0, abs=1e-12)
    assert trace_correlation(rng.standard_normal((5000, 3)), wf) < 0.1
    noisy = wf @ r + rng.standard_normal((5000, 3))  # SNR 1 per axis: r^2 = 1/2
    assert trace_correlation(noisy, wf) == pytest.approx(np.sqrt(0.5), abs=0.02)
    with pytest.raises(ValueError, match="differ in shape"):
        trace_correlation(wf[:10], wf)


@settings(max_examples=40, deadline=None)
@given(
    roll=st.floats(-179.0, 179.0), pitch=st.floats(-89.0, 89.0), yaw=st.floats(-179.0, 179.0)
)
def test_rpy_round_trip_and_convention(roll, pitch, yaw):
    r = rotation_from_rpy_deg(roll, pitch, yaw)
    np.testing.assert_allclose(rpy_deg(r), [roll, pitch, yaw], atol=1e-6)
    rx = Rotation.from_rotvec([np.radians(roll), 0, 0]).as_matrix()
    ry = Rotation.from_rotvec([0, np.radians(pitch), 0]).as_matrix()
    rz = Rotation.from_rotvec([0, 0, np.radians(yaw)]).as_matrix()
    np.testing.assert_allclose(r, rz @ ry @ rx, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), angle=st.floats(0.0, 179.0))
def test_geodesic_error_is_the_separating_angle(seed, angle):
    rng = np.random.default_rng(seed)
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    r_true = Rotation.random(random_state=rng).as_matrix()
    r_est = r_true @ Rotation.from_rotvec(np.radians(angle) * axis).as_matrix()
    assert geodesic_error_deg(r_est, r_true) == pytest.approx(angle, abs=1e-6)
    assert geodesic_error_deg(r_true, r_est) == pytest.approx(angle, abs=1e-6)


def test_geodesic_accurate_for_tiny_angles():
    r = Rotation.from_rotvec([1e-9, 0, 0]).as_matrix()
    assert geodesic_error_deg(r, np.eye(3)) == pytest.approx(np.degrees(1e-9), rel=1e-6)


def test_euler_re_matches_paper_definition_and_wraps():
    r_true = rotation_from_rpy_deg(10.0, 20.0, 30.0)
    r_est = rotation_from_rpy_deg(11.0, 18.0, 30.5)
    assert euler_rotation_error_deg(r_est, r_true) == pytest.approx(np.sqrt(1 + 4 + 0.25))
    # yaw 179 vs -179: 2 degrees apart, not 358
    a, b = rotation_from_rpy_deg(0, 0, 179.0), rotation_from_rpy_deg(0, 0, -179.0)
    assert euler_rotation_error_deg(a, b) == pytest.approx(2.0, abs=1e-9)
    # small single-axis error: RE and geodesic agree
    c = rotation_from_rpy_deg(0.3, 0, 0)
    assert euler_rotation_error_deg(c, np.eye(3)) == pytest.approx(
        geodesic_error_deg(c, np.eye(3)), rel=1e-9
    )


def test_quaternion_wxyz_convention():
    r = Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix()
    np.testing.assert_allclose(quaternion_wxyz(r), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-12)
    for seed in range(20):
        q = quaternion_wxyz(Rotation.random(random_state=seed).as_matrix())
        assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)


def test_offset_error_and_bad_input():
    assert offset_error_s(0.0123, 0.0121) == pytest.approx(2e-4)
    assert offset_error_s(-0.1, 0.1) == pytest.approx(0.2)
    with pytest.raises(ValueError, match="3x3"):
        geodesic_error_deg(np.eye(2), np.eye(3))
    with pytest.raises(ValueError, match=r"\(N>=2, 3\)"):
        condition_number(np.zeros((10, 2)))
