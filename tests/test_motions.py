"""Baseline motions (walk, spin, wave) and the A2I motion: shapes, limits, consistency, kappa."""

from __future__ import annotations

import numpy as np
import pytest

from calib.excitation import ExcitationConfig, plan_excitation
from calib.joints import LEGS, model_indices, pose_for_leg
from calib.kinematics import base_angular_velocity_from_quaternions
from calib.motions import (
    STAND_HEIGHT,
    TRIPOD_STANCE_POSE_LEG,
    Motion,
    a2i_motion,
    baseline_motions,
    spin_motion,
    tripod_pose,
    walk_motion,
    wave_motion,
)


@pytest.fixture(scope="module")
def motions():
    out = {"walk": walk_motion(8.0, 500.0, seed=1), "spin": spin_motion(8.0, 500.0, seed=1)}
    for leg in LEGS:
        out[f"wave_{leg}"] = wave_motion(leg, 8.0, 500.0, seed=1)
    return out


@pytest.fixture(scope="module")
def plans():
    return {leg: plan_excitation(ExcitationConfig(leg=leg)) for leg in LEGS}


def test_shapes_limits_and_rest_at_the_ends(motions, plans):
    all_motions = list(motions.values()) + [a2i_motion(p, 200.0) for p in plans.values()]
    for m in all_motions:
        n = len(m.t)
        assert m.q.shape == m.dq.shape == (n, 12)
        assert m.base_quat_wxyz.shape == (n, 4) and m.base_omega.shape == m.base_pos.shape == (n, 3)
        assert m.limit_violation() == 0.0, m.name
        np.testing.assert_allclose(np.linalg.norm(m.base_quat_wxyz, axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(m.dq[[0, -1]], 0.0, atol=1e-12)
        np.testing.assert_allclose(m.base_omega[[0, -1]], 0.0, atol=1e-12)
        assert np.all(np.abs(m.base_pos[:, 2] - STAND_HEIGHT) < 0.01)


def test_velocities_are_derivatives(motions):
    for m in motions.values():
        dq_num = np.gradient(m.q, m.t, axis=0)
        np.testing.assert_allclose(dq_num[1:-1], m.dq[1:-1], atol=0.01 * np.abs(m.dq).max())
        w_num = base_angular_velocity_from_quaternions(m.t, m.base_quat_wxyz)
        np.testing.assert_allclose(w_num[1:-1], m.base_omega[1:-1], atol=1e-3)
        # quaternions are sign-continuous (component-wise interpolation is safe)
        assert np.all(np.sum(m.base_quat_wxyz[1:] * m.base_quat_wxyz[:-1], axis=1) > 0)


def test_walk_is_a_trot(motions):
    m = motions["walk"]
    thigh = {leg: m.q[:, model_indices(leg)[1]] for leg in LEGS}
    c = {pair: np.corrcoef(thigh[pair[0]], thigh[pair[1]])[0, 1]
         for pair in (("FL", "RR"), ("FR", "RL"), ("FL", "FR"))}
    assert c[("FL", "RR")] > 0.9 and c[("FR", "RL")] > 0.9 and c[("FL", "FR")] < -0.5
    hips = m.q[:, [model_indices(leg)[0] for leg in LEGS]]
    assert np.max(np.abs(hips - hips[0])) < 0.05  # hip nearly still
    # ~2 Hz stepping: dominant frequency of a thigh
    x = thigh["FL"] - thigh["FL"].mean()
    freqs = np.fft.rfftfreq(len(x), m.t[1] - m.t[0])
    assert 1.8 < freqs[np.argmax(np.abs(np.fft.rfft(x)))] < 2.2
    assert m.base_pos[-1, 0] > 1.0  # slow forward trot
    assert 0.005 < np.max(np.abs(m.base_omega[:, :2])) < 1.0


def test_spin_turns_in_place(motions):
    m = motions["spin"]
    yaw_rate = m.base_omega[:, 2]
    t0, t1 = m.steady_window
    steady = (m.t > t0) & (m.t < t1)
    assert np.mean(yaw_rate[steady]) == pytest.approx(0.5, abs=0.01)
    np.testing.assert_allclose(m.base_pos[:, :2], 0.0)
    hip_swing = np.ptp(m.q[:, [model_indices(leg)[0] for leg in LEGS]], axis=0)
    assert np.all(hip_swing > 0.05)


def test_wave_moves_only_the_lifted_leg(motions):
    for leg in LEGS:
        m = motions[f"wave_{leg}"]
        idx = model_indices(leg)
        others = np.setdiff1d(np.arange(12), idx)
        np.testing.assert_array_equal(m.q[:, others], np.tile(m.q[0, others], (len(m.t), 1)))
        assert 0.5 < np.ptp(m.q[:, idx[0]]) < 0.7  # the hip's loop, 0.3 rad each way
        assert np.ptp(m.q[:, idx[1]]) > 0.5 and np.ptp(m.q[:, idx[2]]) > 0.4
        np.testing.assert_array_equal(m.base_omega, 0.0)


def test_a2i_motion_plays_the_plan(plans):
    for leg, p in plans.items():
        m = a2i_motion(p, 250.0)
        t, q, dq = p.sample(250.0)
        idx = model_indices(leg)
        np.testing.assert_allclose(m.q[:, idx], q)
        np.testing.assert_allclose(m.dq[:, idx], dq)
        for other in set(LEGS) - {leg}:
            np.testing.assert_allclose(m.q[:, model_indices(other)],
                                       np.tile(pose_for_leg(other, TRIPOD_STANCE_POSE_LEG),
                                               (len(t), 1)))
        np.testing.assert_array_equal(m.base_omega, 0.0)
        assert m.steady_window == p.steady_window


def test_baselines_are_far_worse_conditioned_than_a2i(plans, capsys):
    rows = []
    for leg in LEGS:
        a2i = a2i_motion(plans[leg], 200.0).kappa(leg)
        assert a2i <= 1.02
        base = baseline_motions(leg, 20.0, 200.0, seed=0)
        ks = {name: m.kappa(leg) for name, m in base.items()}
        for name in ("walk", "spin"):
            assert ks[name] > 100 * a2i, (leg, name, ks[name])
        # the naive wave conditioned as the paper's (its CN 23-75), not a one-axis strawman
        assert 23 < ks["wave"] < 75, (leg, ks["wave"])
        rows.append(f"{leg}: a2i {a2i:.4f}  " + "  ".join(f"{n} {k:.3g}" for n, k in ks.items()))
    with capsys.disabled():
        print("\nkappa of the relative foot angular velocity\n" + "\n".join(rows))


def test_determinism_and_bad_inputs():
    a, b = walk_motion(3.0, 100.0, seed=4), walk_motion(3.0, 100.0, seed=4)
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.base_quat_wxyz, b.base_quat_wxyz)
    assert not np.array_equal(a.q, walk_motion(3.0, 100.0, seed=5).q)
    with pytest.raises(ValueError):
        walk_motion(-1.0)
    with pytest.raises(ValueError):
        spin_motion(2.0, 0.0)
    with pytest.raises(ValueError):
        wave_motion("XY")
    with pytest.raises(ValueError):
        wave_motion("FL", duration=1.0, ramp=1.0)
    with pytest.raises(ValueError):
        Motion("bad", np.arange(3.0), np.zeros((3, 11)), np.zeros((3, 12)),
               np.zeros((3, 4)), np.zeros((3, 3)), np.zeros((3, 3)))
    assert tripod_pose("RR").shape == (12,)
