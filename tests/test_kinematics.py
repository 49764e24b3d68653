"""Leg kinematics: numpy evaluation against pinocchio, the paper's closed form, base rotation."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from scipy.spatial.transform import Rotation

from calib.joints import LEGS, VELOCITY_LIMIT, position_limits
from calib.kinematics import (
    PAPER_FROM_URDF_FOOT,
    LegKinematics,
    base_angular_velocity_from_quaternions,
    closed_form_foot_angular_velocity,
)
from calib.robot import go2_urdf_path


@pytest.fixture(scope="module")
def go2_model():
    return pin.buildModelFromUrdf(str(go2_urdf_path()))


@pytest.fixture(scope="module")
def legs():
    return {leg: LegKinematics.from_urdf(leg=leg) for leg in LEGS}


def _random_q(kin: LegKinematics, rng, n: int) -> np.ndarray:
    # Limits widened by 0.3 rad: the kinematics has no business clipping.
    return rng.uniform(kin.lower - 0.3, kin.upper + 0.3, size=(n, kin.n_joints))


def _pin_leg(model, leg: str, q3: np.ndarray, dq3: np.ndarray, base=None):
    """Pinocchio's foot frame rotation, position and LOCAL angular velocity for one sample."""
    data = model.createData()
    q = pin.neutral(model)
    v = np.zeros(model.nv)
    hip = model.joints[model.getJointId(f"{leg}_hip_joint")]
    q[hip.idx_q : hip.idx_q + 3] = q3
    v[hip.idx_v : hip.idx_v + 3] = dq3
    if base is not None:  # free-flyer: (xyz, quat xyzw) and (v_lin, omega) in the base frame
        q[:7] = base[0]
        v[:6] = base[1]
    pin.forwardKinematics(model, data, q, v)
    pin.updateFramePlacements(model, data)
    fid = model.getFrameId(f"{leg}_foot")
    om = pin.getFrameVelocity(model, data, fid, pin.LOCAL).angular
    return data.oMf[fid].rotation.copy(), data.oMf[fid].translation.copy(), np.array(om)


def paper_foot_angular_velocity(q: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """The paper's Eq. (FK), typed in from the paper: modified-DH foot frame."""
    phi = q[:, 1] + q[:, 2]
    return np.stack([-dq[:, 0] * np.sin(phi), -dq[:, 0] * np.cos(phi), dq[:, 1] + dq[:, 2]], axis=1)


# ------------------------------------------------------------------------------ Go2 structure
def test_go2_chain_and_limits(legs):
    for leg, kin in legs.items():
        assert kin.leg == leg
        assert kin.foot_frame == f"{leg}_foot"
        assert kin.joint_names == (f"{leg}_hip_joint", f"{leg}_thigh_joint", f"{leg}_calf_joint")
        assert kin.n_joints == 3
        lo, hi = position_limits(leg)
        np.testing.assert_allclose(kin.lower, lo, atol=1e-4)
        np.testing.assert_allclose(kin.upper, hi, atol=1e-4)
        np.testing.assert_allclose(kin.velocity_limit, VELOCITY_LIMIT)


def test_go2_foot_position_at_zero(legs):
    # Hip offset (+-0.1934, +-0.0465, 0), thigh offset (0, +-0.0955, 0), thigh and calf 0.213 m.
    for leg, kin in legs.items():
        sx = 1.0 if leg[0] == "F" else -1.0
        sy = 1.0 if leg[1] == "L" else -1.0
        np.testing.assert_allclose(
            kin.foot_position(np.zeros(3)),
            [sx * 0.1934, sy * (0.0465 + 0.0955), -0.426],
            atol=1e-12,
        )
        np.testing.assert_allclose(kin.foot_rotation(np.zeros(3)), np.eye(3), atol=1e-15)


def test_case_insensitive_leg_and_bad_leg():
    assert LegKinematics.from_urdf(leg="fl").leg == "FL"
    with pytest.raises(ValueError, match="unknown leg"):
        LegKinematics.from_urdf(leg="XX")


# ------------------------------------------------------------------------------ vs pinocchio
@pytest.mark.parametrize("leg", LEGS)
def test_matches_pinocchio_random_configurations(go2_model, legs, leg):
    rng = np.random.default_rng(LEGS.index(leg))
    kin = legs[leg]
    q = _random_q(kin, rng, 40)
    dq = rng.normal(scale=5.0, size=q.shape)
    rot, pos, om = kin.foot_rotation(q), kin.foot_position(q), kin.foot_angular_velocity(q, dq)
    assert rot.shape == (40, 3, 3) and pos.shape == (40, 3) and om.shape == (40, 3)
    for i in range(q.shape[0]):
        r_ref, p_ref, w_ref = _pin_leg(go2_model, leg, q[i], dq[i])
        np.testing.assert_allclose(rot[i], r_ref, atol=1e-12)
        np.testing.assert_allclose(pos[i], p_ref, atol=1e-12)
        np.testing.assert_allclose(om[i], w_ref, atol=1e-11)
        # Single-sample form gives the same numbers with the batch dimension dropped.
        np.testing.assert_allclose(kin.foot_angular_velocity(q[i], dq[i]), w_ref, atol=1e-11)
        np.testing.assert_allclose(kin.foot_rotation(q[i]), r_ref, atol=1e-12)
        np.testing.assert_allclose(kin.foot_position(q[i]), p_ref, atol=1e-12)


@pytest.mark.parametrize("leg", LEGS)
def test_absolute_matches_pinocchio_floating_base(legs, leg):
    model = pin.buildModelFromUrdf(str(go2_urdf_path()), pin.JointModelFreeFlyer())
    rng = np.random.default_rng(7 + LEGS.index(leg))
    kin = legs[leg]
    q = _random_q(kin, rng, 15)
    dq = rng.normal(scale=3.0, size=q.shape)
    w_base = rng.normal(scale=2.0, size=(15, 3))
    got = kin.foot_angular_velocity(q, dq, base_omega=w_base)
    for i in range(15):
        quat = Rotation.random(random_state=int(rng.integers(1 << 30))).as_quat()  # xyzw
        base_q = np.concatenate([rng.normal(size=3), quat])
        base_v = np.concatenate([rng.normal(size=3), w_base[i]])
        _, _, w_ref = _pin_leg(model, leg, q[i], dq[i], base=(base_q, base_v))
        np.testing.assert_allclose(got[i], w_ref, atol=1e-11)


def test_relative_matches_finite_difference_of_rotation(legs):
    # Independent of pinocchio: omega_F^ = R^T dR/dt along a smooth joint trajectory.
    kin = legs["RR"]
    t = np.linspace(0.0, 1.0, 2001)
    q = np.stack(
        [0.5 * np.sin(3 * t), 1.0 + 0.8 * np.sin(2 * t + 1), -1.5 + 0.5 * np.cos(5 * t)], 1
    )
    dq = np.stack([1.5 * np.cos(3 * t), 1.6 * np.cos(2 * t + 1), -2.5 * np.sin(5 * t)], 1)
    r = kin.foot_rotation(q)
    rel = np.einsum("nji,njk->nik", r[1:-1], (r[2:] - r[:-2]) / (t[2] - t[0]))
    w_fd = np.stack([rel[:, 2, 1], rel[:, 0, 2], rel[:, 1, 0]], 1)
    np.testing.assert_allclose(kin.foot_angular_velocity(q, dq)[1:-1], w_fd, atol=2e-5)


# ------------------------------------------------------------------------------ base rotation
def test_base_spinning_about_z_legs_still(legs):
    kin = legs["FL"]
    rng = np.random.default_rng(3)
    q = _random_q(kin, rng, 25)
    wz = 1.7
    base = np.tile([0.0, 0.0, wz], (25, 1))
    got = kin.foot_angular_velocity(q, np.zeros_like(q), base_omega=base)
    r = kin.foot_rotation(q)
    np.testing.assert_allclose(got, np.einsum("nji,j->ni", r, [0.0, 0.0, wz]), atol=1e-14)
    # And from first principles: R_W^F(t) = Rz(wz t) R_B^F, differentiated numerically.
    dt = 1e-6
    rz = Rotation.from_rotvec([0.0, 0.0, wz * dt]).as_matrix()
    for i in range(25):
        step = r[i].T @ rz @ r[i]  # R_W^F(0)^T R_W^F(dt)
        np.testing.assert_allclose(got[i], Rotation.from_matrix(step).as_rotvec() / dt, atol=1e-8)
    # With the legs still, the relative part is zero.
    np.testing.assert_allclose(kin.foot_angular_velocity(q, np.zeros_like(q)), 0.0, atol=0)


def test_absolute_is_relative_plus_rotated_base(legs):
    kin = legs["RL"]
    rng = np.random.default_rng(11)
    q = _random_q(kin, rng, 100)
    dq = rng.normal(size=q.shape)
    w = rng.normal(size=(100, 3))
    r = kin.foot_rotation(q)
    np.testing.assert_allclose(
        kin.foot_angular_velocity(q, dq, w),
        kin.foot_angular_velocity(q, dq) + np.einsum("nji,nj->ni", r, w),
        atol=1e-13,
    )
    # Single sample; and one base rate (3,) applies to every sample.
    np.testing.assert_allclose(
        kin.foot_angular_velocity(q[0], dq[0], w[0]), kin.foot_angular_velocity(q, dq, w)[0]
    )
    np.testing.assert_allclose(
        kin.foot_angular_velocity(q, dq, w[0]),
        kin.foot_angular_velocity(q, dq, np.tile(w[0], (100, 1))),
    )


# ------------------------------------------------------------------------------ paper frame
@pytest.mark.parametrize("leg", LEGS)
def test_paper_formula_is_constant_rotation_of_urdf_foot(legs, leg):
    rng = np.random.default_rng(100 + LEGS.index(leg))
    kin = legs[leg]
    q = _random_q(kin, rng, 500)
    dq = rng.normal(scale=4.0, size=q.shape)
    ours = kin.foot_angular_velocity(q, dq)
    np.testing.assert_allclose(
        paper_foot_angular_velocity(q, dq), ours @ PAPER_FROM_URDF_FOOT.T, atol=1e-12
    )


def test_paper_rotation_is_proper_and_keeps_condition_number(legs):
    p = PAPER_FROM_URDF_FOOT
    np.testing.assert_allclose(p @ p.T, np.eye(3), atol=0)
    assert np.linalg.det(p) == pytest.approx(1.0)
    assert not p.flags.writeable
    kin = legs["FL"]
    t = np.linspace(0, 8, 4001)
    q = np.stack([0.3 * np.sin(t), 0.8 + 0.5 * np.sin(2 * t), -1.5 + 0.3 * np.sin(3 * t)], 1)
    dq = np.stack([0.3 * np.cos(t), 1.0 * np.cos(2 * t), 0.9 * np.cos(3 * t)], 1)
    w_urdf = kin.foot_angular_velocity(q, dq)
    w_paper = paper_foot_angular_velocity(q, dq)
    s_urdf, s_paper = np.cov(w_urdf.T), np.cov(w_paper.T)
    np.testing.assert_allclose(s_paper, p @ s_urdf @ p.T, atol=1e-12)
    assert np.linalg.cond(s_paper) == pytest.approx(np.linalg.cond(s_urdf), rel=1e-9)


@pytest.mark.parametrize("leg", LEGS)
def test_closed_form_equals_general(legs, leg):
    rng = np.random.default_rng(200 + LEGS.index(leg))
    kin = legs[leg]
    q = _random_q(kin, rng, 300)
    dq = rng.normal(scale=4.0, size=q.shape)
    np.testing.assert_allclose(
        closed_form_foot_angular_velocity(q, dq), kin.foot_angular_velocity(q, dq), atol=1e-12
    )
    assert closed_form_foot_angular_velocity(q[0], dq[0]).shape == (3,)


# ------------------------------------------------------------------------------ input checks
def test_shape_errors(legs):
    kin = legs["FL"]
    with pytest.raises(ValueError, match=r"q must have shape \(N, 3\)"):
        kin.foot_rotation(np.zeros((5, 4)))
    with pytest.raises(ValueError, match="differ in length"):
        kin.foot_angular_velocity(np.zeros((5, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="base_omega has 2 samples"):
        kin.foot_angular_velocity(np.zeros((5, 3)), np.zeros((5, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="base_omega must have shape"):
        kin.foot_angular_velocity(np.zeros((5, 3)), np.zeros((5, 3)), np.zeros((5, 2)))


# ------------------------------------------------------------------------------ other URDFs
_TINY_URDF = """<?xml version="1.0"?>
<robot name="tiny">
  <link name="root"/>
  <link name="a"/>
  <link name="b"/>
  <link name="b2"/>
  <link name="c"/>
  <link name="tip"/>
  <link name="slider"/>
  <joint name="j1" type="revolute">
    <parent link="root"/><child link="a"/>
    <origin xyz="0.1 0.0 0.05" rpy="0.2 -0.1 0.3"/>
    <axis xyz="0 0 1"/>
    <limit lower="-1.0" upper="1.5" effort="5" velocity="7"/>
  </joint>
  <joint name="j2" type="revolute">
    <parent link="a"/><child link="b"/>
    <origin xyz="0.0 0.2 0.0" rpy="0.0 0.4 0.0"/>
    <axis xyz="0 0.6 0.8"/>
    <limit lower="-2.0" upper="2.0" effort="5" velocity="9"/>
  </joint>
  <joint name="fixed_mid" type="fixed">
    <parent link="b"/><child link="b2"/>
    <origin xyz="0.0 0.0 -0.1" rpy="0.5 0 0"/>
  </joint>
  <joint name="j3" type="continuous">
    <parent link="b2"/><child link="c"/>
    <origin xyz="0.0 0.0 -0.15" rpy="0 0 -0.7"/>
    <axis xyz="1 0 0"/>
    <limit effort="5" velocity="11"/>
  </joint>
  <joint name="tip_joint" type="fixed">
    <parent link="c"/><child link="tip"/>
    <origin xyz="0.02 0.0 -0.2" rpy="0.1 0.2 0.3"/>
  </joint>
  <joint name="p1" type="prismatic">
    <parent link="root"/><child link="slider"/>
    <origin xyz="0 0 0" rpy="0 0 0"/>
    <axis xyz="1 0 0"/>
    <limit lower="-0.1" upper="0.1" effort="5" velocity="1"/>
  </joint>
</robot>
"""


def test_non_go2_urdf_against_pinocchio(tmp_path):
    path = tmp_path / "tiny.urdf"
    path.write_text(_TINY_URDF)
    kin = LegKinematics.from_urdf(path, leg="L1", foot_frame="tip")
    assert kin.joint_names == ("j1", "j2", "j3")
    assert kin.leg == "L1" and kin.foot_frame == "tip"
    np.testing.assert_allclose(kin.lower[:2], [-1.0, -2.0])
    np.testing.assert_allclose(kin.upper[:2], [1.5, 2.0])
    assert kin.lower[2] == -np.inf and kin.upper[2] == np.inf
    np.testing.assert_allclose(kin.velocity_limit, [7, 9, 11])

    model = pin.buildModelFromUrdf(str(path))
    data = model.createData()
    fid = model.getFrameId("tip")
    rng = np.random.default_rng(5)
    q = rng.uniform(-2, 2, size=(30, 3))
    dq = rng.normal(scale=3, size=(30, 3))
    rot, pos, om = kin.foot_rotation(q), kin.foot_position(q), kin.foot_angular_velocity(q, dq)
    idx = {model.names[j]: model.joints[j] for j in range(1, model.njoints)}
    for i in range(30):
        qp, vp = pin.neutral(model), np.zeros(model.nv)
        for k, name in enumerate(kin.joint_names):
            jm = idx[name]
            if jm.nq == 2:  # continuous joint: (cos, sin)
                qp[jm.idx_q : jm.idx_q + 2] = [np.cos(q[i, k]), np.sin(q[i, k])]
            else:
                qp[jm.idx_q] = q[i, k]
            vp[jm.idx_v] = dq[i, k]
        pin.forwardKinematics(model, data, qp, vp)
        pin.updateFramePlacements(model, data)
        np.testing.assert_allclose(rot[i], data.oMf[fid].rotation, atol=1e-12)
        np.testing.assert_allclose(pos[i], data.oMf[fid].translation, atol=1e-12)
        w_ref = pin.getFrameVelocity(model, data, fid, pin.LOCAL).angular
        np.testing.assert_allclose(om[i], w_ref, atol=1e-12)


def test_urdf_errors(tmp_path):
    path = tmp_path / "tiny.urdf"
    path.write_text(_TINY_URDF)
    with pytest.raises(ValueError, match="frame 'nope' not found in tiny.urdf"):
        LegKinematics.from_urdf(path, foot_frame="nope")
    with pytest.raises(ValueError, match="joint 'p1' .* not a revolute joint"):
        LegKinematics.from_urdf(path, foot_frame="slider")
    with pytest.raises(ValueError, match="fixed to the base"):
        LegKinematics.from_urdf(path, foot_frame="root")
    with pytest.raises(ValueError, match="URDF not found"):
        LegKinematics.from_urdf(tmp_path / "missing.urdf", foot_frame="tip")
    with pytest.raises(ValueError, match="frame 'FL_toe' not found.*FL_foot"):
        LegKinematics.from_urdf(leg="FL", foot_frame="FL_toe")
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'/>")
    with pytest.raises(ValueError, match="cannot load URDF"):
        LegKinematics.from_urdf(bad, foot_frame="a")


def test_intermediate_frame_of_go2(go2_model):
    # The calf link itself (same orientation as FL_foot, at the knee).
    kin = LegKinematics.from_urdf(leg="FL", foot_frame="FL_calf")
    foot = LegKinematics.from_urdf(leg="FL")
    rng = np.random.default_rng(9)
    q = _random_q(kin, rng, 50)
    np.testing.assert_allclose(kin.foot_rotation(q), foot.foot_rotation(q), atol=1e-15)
    np.testing.assert_allclose(
        foot.foot_position(q) - kin.foot_position(q),
        foot.foot_rotation(q) @ np.array([0.0, 0.0, -0.213]),
        atol=1e-14,
    )


# ------------------------------------------------------------------------------ quaternions
def _spin_wobble(t: np.ndarray):
    """R_W^B = Rz(a(t)) Ry(b(t)) with its analytic body-frame angular velocity."""
    a, da = 0.9 * t + 0.4 * np.sin(2.0 * t), 0.9 + 0.8 * np.cos(2.0 * t)
    b, db = 0.6 * np.sin(3.0 * t), 1.8 * np.cos(3.0 * t)
    rot = Rotation.from_euler("ZY", np.stack([a, b], 1))
    ry = Rotation.from_euler("Y", b[:, None])
    w = ry.inv().apply(np.stack([np.zeros_like(t), np.zeros_like(t), da], 1))
    w[:, 1] += db
    return rot, w


def test_base_angular_velocity_from_quaternions_irregular_and_sign_flips():
    rng = np.random.default_rng(21)
    n = 2000
    t = np.cumsum(rng.uniform(0.7, 1.3, n) * 5e-3)  # ~200 Hz, irregular
    rot, w_true = _spin_wobble(t)
    quat = rot.as_quat(scalar_first=True)
    got = base_angular_velocity_from_quaternions(t, quat)
    assert got.shape == (n, 3)
    err = np.abs(got[1:-1] - w_true[1:-1]).max()
    assert err < 2e-3, err
    assert np.abs(got[[0, -1]] - w_true[[0, -1]]).max() < 3e-2  # one-sided ends
    # q and -q alternate, and the quaternions are not unit: same answer.
    flips = rng.choice([-1.0, 1.0], size=(n, 1)) * rng.uniform(0.5, 2.0, size=(n, 1))
    np.testing.assert_allclose(
        base_angular_velocity_from_quaternions(t, quat * flips), got, atol=1e-9
    )


def test_base_angular_velocity_from_quaternions_errors():
    t = np.arange(5) * 0.01
    q = np.tile([1.0, 0, 0, 0], (5, 1))
    np.testing.assert_allclose(base_angular_velocity_from_quaternions(t, q), 0.0)
    with pytest.raises(ValueError, match="strictly increasing"):
        base_angular_velocity_from_quaternions(t[::-1], q)
    with pytest.raises(ValueError, match="shape"):
        base_angular_velocity_from_quaternions(t, q[:, :3])
    q0 = q.copy()
    q0[2] = 0
    with pytest.raises(ValueError, match="zero quaternion"):
        base_angular_velocity_from_quaternions(t, q0)
