"""deploy.action: the delta-target rule shared by training and deploy, with the target lead
bound (a target never further from its joint than the motor's whole torque asks)."""

import numpy as np
import pytest

from deploy.action import lead_max_for_torque, next_target


def test_without_a_bound_it_is_the_plain_clamped_sum_to_the_bit():
    rng = np.random.default_rng(0)
    t, d = rng.normal(size=(5, 12)), rng.normal(size=(5, 12)) * 0.1
    lo, hi = -np.ones(12) * 0.8, np.ones(12) * 0.9
    np.testing.assert_array_equal(next_target(t, d, lo, hi), np.clip(t + d, lo, hi))


def test_the_bound_holds_the_target_within_lead_of_the_joint_and_the_soft_limits_win():
    lo, hi = -np.ones(12), np.ones(12)
    q = np.zeros(12)
    q[1] = 0.95  # near the upper soft limit
    lead = np.full(12, 0.3)
    t = np.zeros(12)
    d = np.zeros(12)
    d[0], d[1], d[2] = 0.5, 2.0, -0.1
    out = next_target(t, d, lo, hi, q, lead)
    assert out[0] == pytest.approx(0.3)   # held at q + lead
    assert out[1] == pytest.approx(1.0)   # q + lead, 1.25, is past the soft limit: it wins
    assert out[2] == pytest.approx(-0.1)  # within the lead: untouched
    # batched over environments, each its own joints
    qs = np.stack([q, q + 0.2])
    both = next_target(np.zeros((2, 12)), np.tile(d, (2, 1)), lo, hi, qs, lead)
    assert both[1, 0] == pytest.approx(0.5) and both[0, 0] == pytest.approx(0.3)


def test_a_bound_without_the_joints_is_refused():
    with pytest.raises(ValueError, match="measured joint positions"):
        next_target(np.zeros(12), np.zeros(12), -np.ones(12), np.ones(12), None, np.ones(12))


def test_the_torque_bound_is_effort_over_kp_and_refuses_a_zero_gain():
    np.testing.assert_allclose(lead_max_for_torque([29.0, 26.0], [23.7, 45.43]),
                               [23.7 / 29.0, 45.43 / 26.0])
    with pytest.raises(ValueError, match="kp > 0"):
        lead_max_for_torque([0.0, 26.0], [23.7, 45.43])
    # without effort limits: the Go2's, per joint, for one kp or 12
    np.testing.assert_allclose(lead_max_for_torque(20.0)[:3], [23.7 / 20, 23.7 / 20, 45.43 / 20])
    np.testing.assert_allclose(lead_max_for_torque([29.0, 29.0, 26.0] * 4)[9:],
                               [23.7 / 29, 23.7 / 29, 45.43 / 26])
