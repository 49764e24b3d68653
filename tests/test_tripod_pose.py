"""Level tripod reference stances (sim.tripod_pose): geometry and static equilibrium."""

from __future__ import annotations

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from calib.excitation import TRIPOD_LIFT_POSE_LEG
from calib.joints import MODEL_LEGS, default_crouch, pose_for_leg
from calib.support import polygon_margin
from policy_train.model import TrainModel
from sim.tripod_pose import FOOT_RADIUS, capture_margins, support_point, tripod_pose


@pytest.fixture(scope="module")
def model():
    return TrainModel(0.005, 20.0, 0.5).model


def _tilt_after(m, qpos, ctrl, leg, seconds):
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    d.ctrl[:] = ctrl
    gain, bias = m.actuator_gainprm.copy(), m.actuator_biasprm.copy()
    try:
        for j in range(3 * leg, 3 * leg + 3):  # the lifted leg's schedule gains
            m.actuator_gainprm[j, 0], m.actuator_biasprm[j, 1:3] = 40.0, (-40.0, -1.0)
        for _ in range(round(seconds / m.opt.timestep)):
            mujoco.mj_step(m, d)
    finally:
        m.actuator_gainprm[:], m.actuator_biasprm[:] = gain, bias
    x, y = d.qpos[4:6]
    return np.degrees(np.arccos(np.clip(1 - 2 * (x * x + y * y), -1, 1)))


def test_polygon_margin_is_the_signed_distance_to_the_nearest_edge():
    # four feet in order around, either way; beyond a corner: the farther line crossed
    quad = np.array([[0.2, 0.1], [0.2, -0.1], [-0.2, -0.1], [-0.2, 0.1]])
    pts = np.array([[0.0, 0.0], [0.15, 0.05], [0.0, -0.3], [0.3, 0.3]])
    want = [0.1, 0.05, -0.2, -0.2]
    for q in (quad, quad[::-1]):
        np.testing.assert_allclose(polygon_margin(pts, np.broadcast_to(q, (4, 4, 2))), want)
    tri = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])  # any order of a triangle's corners
    for t in (tri, tri[[2, 0, 1]], tri[::-1]):
        assert polygon_margin(np.array([[0.25, 0.25]]), t[None])[0] == pytest.approx(0.25)


def test_capture_margins_put_the_capture_point_where_the_pendulum_says():
    # soles on the floor (foot centres FOOT_RADIUS up), the centre of mass 0.4 m over them:
    # 1 / w0 = sqrt(0.4 / 9.81) s
    tri = np.array([[0.0, 0.0, FOOT_RADIUS], [1.0, 0.0, FOOT_RADIUS], [0.0, 1.0, FOOT_RADIUS]])
    com = np.array([[0.25, 0.25, 0.4], [0.25, 0.25, 0.4], [0.5, 0.1, 0.4]])
    vel = np.array([[0.0, 0.0], [0.0, -1.0], [0.0, 0.0]])
    m_com, m_xi = capture_margins(com, vel, np.broadcast_to(tri, (3, 3, 3)))
    np.testing.assert_allclose(m_com, [0.25, 0.25, 0.1])
    np.testing.assert_allclose(m_xi, [0.25, 0.25 - np.sqrt(0.4 / 9.81), 0.1])


def test_support_point_is_the_nearest_point_with_the_margin():
    tri = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    assert np.allclose(support_point([0.3, 0.3], tri, 0.1), [0.3, 0.3])  # already inside
    assert np.allclose(support_point([0.5, -0.2], tri, 0.1), [0.5, 0.1])  # one edge
    p = support_point([-1.0, -1.0], tri, 0.1)  # a corner: both edges active
    assert np.allclose(p, [0.1, 0.1])


@pytest.mark.parametrize("leg", range(4))
def test_tripod_pose_is_level_balanced_and_on_the_stance_feet(model, leg):
    m = model
    q_lift = pose_for_leg(MODEL_LEGS[leg], TRIPOD_LIFT_POSE_LEG)
    p = tripod_pose(m, leg, default_crouch("model"), q_lift, 0.31, margin=0.05)
    assert p.qpos[2] == pytest.approx(0.31)
    assert np.allclose(p.qpos[3:7], [1, 0, 0, 0])
    assert p.com_margin == pytest.approx(0.05, abs=1e-4)
    total = float(m.body_subtreemass[m.body("base").id]) * 9.81
    assert p.foot_forces.sum() == pytest.approx(total, rel=1e-3)
    assert np.all(p.foot_forces > 0)
    d = mujoco.MjData(m)
    d.qpos[:] = p.qpos
    mujoco.mj_kinematics(m, d)
    z = [d.site_xpos[m.site(f"{lg}_foot").id, 2] for lg in MODEL_LEGS]
    for i in range(4):
        if i == leg:
            assert z[i] > FOOT_RADIUS + 0.05  # the lifted foot is well off the floor
        else:
            assert z[i] == pytest.approx(FOOT_RADIUS, abs=1e-6)
    # static equilibrium: with its targets held (no controller) it stays level for a while;
    # the same stance with the targets at the joint angles (no load) tips over at once
    assert _tilt_after(m, p.qpos, p.target, leg, 0.3) < 1.0
    unloaded = p.qpos[7:19].copy()
    unloaded[3 * leg: 3 * leg + 3] = q_lift
    assert _tilt_after(m, p.qpos, unloaded, leg, 0.3) > 3.0


@pytest.mark.parametrize("leg", [0, 3])
def test_shifted_stance_keeps_the_foot_down_and_unloaded(model, leg):
    m = model
    q_lift = pose_for_leg(MODEL_LEGS[leg], TRIPOD_LIFT_POSE_LEG)
    up = tripod_pose(m, leg, default_crouch("model"), q_lift, 0.31, margin=0.05)
    p = tripod_pose(m, leg, default_crouch("model"), q_lift, 0.31, margin=0.05, lifted=False)
    assert p.com_margin == pytest.approx(0.05, abs=1e-4)
    d = mujoco.MjData(m)
    d.qpos[:] = p.qpos
    mujoco.mj_kinematics(m, d)
    z = [d.site_xpos[m.site(f"{lg}_foot").id, 2] for lg in MODEL_LEGS]
    assert np.allclose(z, FOOT_RADIUS, atol=1e-6)  # all four feet down
    # the base stands where it will stand once the leg is up (only the leg's mass differs)
    assert np.linalg.norm(p.qpos[:2] - up.qpos[:2]) < 0.02
    assert _tilt_after(m, p.qpos, p.target, leg, 0.3) < 1.0


def test_tripod_pose_rejects_a_bad_leg(model):
    with pytest.raises(ValueError, match="leg"):
        tripod_pose(model, 4, default_crouch("model"), np.zeros(3), 0.31)
