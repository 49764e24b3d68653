"""The MuJoCo Go2: model structure, PD law, base modes, truth accessors, effects."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from calib.joints import (
    EFFORT_LIMIT,
    MODEL_JOINT_NAMES,
    MODEL_LEGS,
    model_indices,
    model_to_sdk,
)
from calib.kinematics import LegKinematics
from sim.effects import ActuationLatency, Effect, MotorStrength
from sim.go2 import (
    Go2BatchSim,
    Go2Sim,
    SimConfig,
    rotation_about_axis_trajectory,
    stand_pose,
)
from sim.model import BODY_IMU_OFFSET, FOOT_RADIUS, build_go2_model

G = 9.81
TOTAL_MASS = 16.085  # kg, FACTS.md


@pytest.fixture(scope="module")
def free_model():
    return build_go2_model("free")


def _pd(cmd_q, cmd_dq, kp, kd, ff, q, dq, lim):
    return np.clip(kp * (cmd_q - q) + kd * (cmd_dq - dq) + ff, -lim, lim)


# ---------------------------------------------------------------------------- model
@pytest.mark.parametrize("base,nq,nv", [("free", 19, 18), ("fixed", 12, 12), ("mocap", 19, 18)])
def test_model_loads_with_expected_structure(base, nq, nv):
    m = build_go2_model(base)
    assert (m.nq, m.nv, m.nu) == (nq, nv, 12)
    assert m.body_mass.sum() == pytest.approx(TOTAL_MASS, abs=1e-6)
    assert m.opt.timestep == pytest.approx(0.001)
    assert m.body("base").id == 1  # kept as a body even when fixed (not fused into the world)
    for leg in MODEL_LEGS:
        g = m.geom(f"{leg}_foot")
        assert m.geom_type[g.id] == mujoco.mjtGeom.mjGEOM_SPHERE
        assert m.geom_size[g.id][0] == pytest.approx(FOOT_RADIUS)
        assert m.body(int(m.geom_bodyid[g.id])).name == f"{leg}_calf"
        for s in (f"{leg}_foot", f"{leg}_imu"):
            assert m.body(int(m.site_bodyid[m.site(s).id])).name == f"{leg}_calf"
    # no foot mesh left to collide beside the sphere
    foot_mesh = m.mesh("foot_convex").id if "foot_convex" in [
        m.mesh(i).name for i in range(m.nmesh)] else -1
    assert not np.any((m.geom_type == mujoco.mjtGeom.mjGEOM_MESH) & (m.geom_dataid == foot_mesh))
    np.testing.assert_allclose(m.site_pos[m.site("imu").id], BODY_IMU_OFFSET)
    assert m.body(int(m.site_bodyid[m.site("imu").id])).name == "base"
    pairs = {frozenset((m.body(int(a)).name, m.body(int(b)).name))
             for a, b in zip(m.exclude_signature >> 16, m.exclude_signature & 0xFFFF, strict=True)}
    assert pairs == {frozenset(("base", f"{leg}_{link}")) for leg in MODEL_LEGS
                     for link in ("hip", "thigh")}


def test_bad_arguments_raise():
    with pytest.raises(ValueError):
        build_go2_model("floating")
    with pytest.raises(ValueError):
        build_go2_model(timestep=0.0)
    with pytest.raises(ValueError):
        Go2Sim(SimConfig(base="hung"))


def test_joint_and_actuator_order_is_model_order(free_model):
    m = free_model
    hinges = [m.joint(i).name for i in range(m.njnt) if m.jnt_type[i] == mujoco.mjtJoint.mjJNT_HINGE]
    assert hinges == [f"{n}_joint" for n in MODEL_JOINT_NAMES]
    assert [m.actuator(i).name for i in range(m.nu)] == list(MODEL_JOINT_NAMES)
    np.testing.assert_allclose(m.actuator_ctrlrange[:, 1], np.tile(EFFORT_LIMIT, 4))
    np.testing.assert_allclose(m.actuator_ctrlrange[:, 0], -np.tile(EFFORT_LIMIT, 4))
    # actuator k drives joint k
    for k in range(12):
        assert m.joint(int(m.actuator_trnid[k, 0])).name == f"{MODEL_JOINT_NAMES[k]}_joint"
    np.testing.assert_array_equal(m.dof_armature[6:], 0.0)
    np.testing.assert_array_equal(m.dof_damping[6:], 0.0)
    np.testing.assert_array_equal(m.dof_frictionloss[6:], 0.0)


def test_foot_sites_match_leg_kinematics():
    sim = Go2Sim(SimConfig(base="fixed"))
    rng = np.random.default_rng(1)
    q = stand_pose() + rng.uniform(-0.3, 0.3, 12)
    sim.reset(q=q)
    r = sim.base_rotation
    feet_b = (sim.foot_positions - sim.base_pos) @ r
    for k, leg in enumerate(MODEL_LEGS):
        kin = LegKinematics.from_urdf(leg=leg)
        np.testing.assert_allclose(feet_b[k], kin.foot_position(q[model_indices(leg)]), atol=1e-9)
        rot = sim.data.site_xmat[sim.model.site(f"{leg}_imu").id].reshape(3, 3)
        np.testing.assert_allclose(r.T @ rot, kin.foot_rotation(q[model_indices(leg)]), atol=1e-9)


# ---------------------------------------------------------------------------- standing
def test_free_base_stands_with_stand_pd():
    sim = Go2Sim(SimConfig(base="free"))
    feet_z = sim.foot_positions[:, 2]
    np.testing.assert_allclose(feet_z, FOOT_RADIUS, atol=1e-9)  # reset puts the feet on the floor
    sim.set_command(stand_pose(), 0.0, 60.0, 5.0, 0.0)
    for _ in range(20):
        sim.step(100)
        assert sim.body_contacts() == []
        assert sim.base_tilt < 0.05
    # The stand pose (0, 0.67, -1.3) puts the hips 0.339 m above the foot centres, 0.361 m above
    # the floor with the 0.022 m foot; PD kp 60 sags it by ~2 cm under 16 kg.
    assert 0.30 < sim.base_pos[2] < 0.36
    f = sim.foot_contact_forces
    assert np.all(f > 20.0)
    assert f.sum() == pytest.approx(TOTAL_MASS * G, rel=0.02)
    np.testing.assert_allclose(sim.base_specific_force, [0, 0, G], atol=0.05)
    np.testing.assert_allclose(sim.base_ang_vel, 0.0, atol=1e-3)
    np.testing.assert_allclose(sim.base_lin_vel, 0.0, atol=1e-3)


def test_falls_without_command_and_reports_body_contacts():
    sim = Go2Sim(SimConfig(base="free"))  # passive motors after reset
    sim.step(1500)
    assert sim.body_contacts() != []
    assert sim.base_pos[2] < 0.2


# ---------------------------------------------------------------------------- PD law
def test_fixed_base_tracks_a_joint_step_and_pd_is_recomputed_every_step():
    sim = Go2Sim(SimConfig(base="fixed"))
    q0 = stand_pose()
    sim.set_command(q0, 0.0, 60.0, 5.0, 0.0)
    sim.step(300)
    target = q0.copy()
    target[model_indices("FL")] += [0.2, 0.4, -0.3]
    sim.set_command(target, 0.0, 60.0, 5.0, 0.0)  # sent once, then only stepping
    lim = np.tile(EFFORT_LIMIT, 4)
    for _ in range(80):
        sim.step(9)
        expect = _pd(target, 0.0, 60.0, 5.0, 0.0, sim.q, sim.dq, lim)
        np.testing.assert_allclose(sim.tau, expect, atol=1e-9)
    assert np.max(np.abs(sim.q - target)) < 0.05  # within the gravity sag of kp 60
    assert np.max(np.abs(sim.dq)) < 0.05


def test_divergence_raises():
    sim = Go2Sim(SimConfig(base="fixed"))
    sim.data.qvel[0] = np.nan
    with pytest.raises(RuntimeError, match="diverged"):
        sim.step(3)
    sim.reset()
    sim.step(3)  # usable again after a reset


def test_torque_clamp_and_sdk_order():
    sim = Go2Sim(SimConfig(base="fixed", torque_limits=5.0))
    q_des = stand_pose() + 1.0
    sim.set_command_sdk(model_to_sdk(q_des), 0.0, 500.0, 0.0, 0.0)
    np.testing.assert_array_equal(sim.command.q_des, q_des)
    np.testing.assert_allclose(sim.tau, 5.0)
    sim.set_command(q_des, 0.0, 0.0, 0.0, np.linspace(-60, 60, 12))
    np.testing.assert_allclose(sim.tau, np.clip(np.linspace(-60, 60, 12), -5, 5))
    with pytest.raises(ValueError):
        sim.set_command(q_des, 0.0, -1.0, 0.0, 0.0)
    with pytest.raises(ValueError):
        sim.set_command(q_des[:11], 0.0, 1.0, 0.0, 0.0)


# ---------------------------------------------------------------------------- mocap base
def _omega_chain(q, dq, w_base):
    """Foot angular velocity in the calf frame, by hand: hip about x, thigh/calf about y."""
    def rx(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])

    def ry(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])

    w = rx(q[0]).T @ w_base + [dq[0], 0, 0]
    w = ry(q[1]).T @ w + [0, dq[1], 0]
    return ry(q[2]).T @ w + [0, dq[2], 0]


def test_mocap_base_is_exact_and_foot_gyro_truth_matches_kinematics():
    traj = rotation_about_axis_trajectory([0.3, 1.0, 0.5], 0.4, 1.3)
    sim = Go2Sim(SimConfig(base="mocap"))
    sim.set_base_trajectory(traj)
    sim.reset()
    q0 = stand_pose()
    kins = {leg: LegKinematics.from_urdf(leg=leg) for leg in MODEL_LEGS}
    worst_kin = worst_chain = 0.0
    for k in range(60):
        qd = q0 + 0.3 * np.sin(2 * np.pi * 1.5 * sim.time + np.arange(12))
        sim.set_command(qd, 0.0, 20.0, 0.5, 0.0)
        sim.step(13)
        ref = traj(sim.time)
        np.testing.assert_allclose(sim.base_ang_vel, ref.ang_vel_base, atol=1e-12)
        np.testing.assert_allclose(sim.base_quat_wxyz, ref.quat_wxyz, atol=1e-12)
        np.testing.assert_allclose(sim.base_pos, ref.pos, atol=1e-12)
        q, dq, wb = sim.q, sim.dq, sim.base_ang_vel
        for leg in MODEL_LEGS:
            i = model_indices(leg)
            w = sim.foot_angular_velocity(leg)
            worst_chain = max(worst_chain, np.abs(w - _omega_chain(q[i], dq[i], wb)).max())
            wk = kins[leg].foot_angular_velocity(q[i], dq[i], wb)
            worst_kin = max(worst_kin, np.abs(w - wk).max())
            # MuJoCo's own velocity of the calf body, in the calf frame
            v6 = np.zeros(6)
            mujoco.mj_objectVelocity(sim.model, sim.data, mujoco.mjtObj.mjOBJ_XBODY,
                                     sim.model.body(f"{leg}_calf").id, v6, 1)
            np.testing.assert_allclose(w, v6[:3], atol=1e-12)
    assert np.abs(sim.dq).max() > 0.5  # the legs really moved
    assert worst_chain < 1e-10
    assert worst_kin < 1e-10


def test_mocap_base_acceleration_is_prescribed():
    traj = rotation_about_axis_trajectory([0.0, 1.0, 0.0], 0.5, 1.0)
    sim = Go2Sim(SimConfig(base="mocap"))
    sim.set_base_trajectory(traj)
    sim.reset()
    sim.set_command(stand_pose(), 0.0, 40.0, 1.0, 0.0)
    sim.step(137)
    _ = sim.tau  # prepares the step at sim.time
    t, dt = sim.time, sim.model.opt.timestep
    a_ang = (traj(t + dt).ang_vel_base - traj(t).ang_vel_base) / dt
    np.testing.assert_allclose(sim.data.qacc[3:6], a_ang, atol=1e-8)
    np.testing.assert_allclose(sim.data.qacc[:3], 0.0, atol=1e-8)


def test_mocap_held_base_feels_gravity_like_fixed_base():
    held = Go2Sim(SimConfig(base="mocap"))
    fixed = Go2Sim(SimConfig(base="fixed"))
    for s in (held, fixed):
        s.set_command(stand_pose(), 0.0, 20.0, 0.5, 0.0)
        s.step(400)
    np.testing.assert_allclose(held.base_pos, fixed.base_pos, atol=1e-9)
    np.testing.assert_allclose(held.q, fixed.q, atol=1e-6)
    assert np.abs(held.q - stand_pose()).max() > 0.01  # a sag that free fall would not show
    np.testing.assert_allclose(held.base_specific_force, [0, 0, G], atol=1e-6)


def test_set_base_state_moves_at_constant_velocity():
    sim = Go2Sim(SimConfig(base="mocap"))
    sim.set_base_state([0, 0, 1.0], [1, 0, 0, 0], [0.1, 0, 0], [0, 0, 0.5])
    sim.set_command(stand_pose(), 0.0, 30.0, 1.0, 0.0)
    sim.step(1000)
    np.testing.assert_allclose(sim.base_pos, [0.1, 0, 1.0], atol=1e-6)
    np.testing.assert_allclose(sim.base_ang_vel, [0, 0, 0.5], atol=1e-9)
    yaw = 2 * np.arctan2(sim.base_quat_wxyz[3], sim.base_quat_wxyz[0])
    assert yaw == pytest.approx(0.5, abs=1e-6)
    with pytest.raises(ValueError):
        Go2Sim(SimConfig(base="fixed")).set_base_state([0, 0, 1], [1, 0, 0, 0])


# ---------------------------------------------------------------------------- effects
def test_actuation_latency_equals_sending_later():
    lat = 0.02
    delayed = Go2Sim(SimConfig(base="fixed", effects=[ActuationLatency(lat)]))
    ref = Go2Sim(SimConfig(base="fixed"))
    cmds = [(stand_pose() + 0.1 * k, 60.0, 3.0) for k in range(4)]
    # delayed: a command at every 30 ms from t=0; ref: the same commands 20 ms later
    log_d, log_r = [], []
    for k in range(120):
        if k % 30 == 0:
            q, kp, kd = cmds[k // 30]
            delayed.set_command(q, 0.0, kp, kd, 0.0)
        if k >= 20 and (k - 20) % 30 == 0:
            q, kp, kd = cmds[(k - 20) // 30]
            ref.set_command(q, 0.0, kp, kd, 0.0)
        if k == 10:
            np.testing.assert_array_equal(delayed.command.kp, 0.0)  # not arrived yet
        delayed.step()
        ref.step()
        log_d.append(delayed.q)
        log_r.append(ref.q)
    np.testing.assert_array_equal(np.array(log_d), np.array(log_r))
    with pytest.raises(ValueError):
        ActuationLatency(-1.0)


def test_motor_strength_scales_selected_joints():
    eff = MotorStrength(0.5, joints=["FL_calf", 11])
    sim = Go2Sim(SimConfig(base="fixed", effects=[eff]))
    nominal = Go2Sim(SimConfig(base="fixed"))
    for s in (sim, nominal):
        s.set_command(stand_pose(), 0.0, 30.0, 1.0, 0.0)
        s.step(50)
    lim = np.tile(EFFORT_LIMIT, 4)
    expect = _pd(stand_pose(), 0.0, 30.0, 1.0, 0.0, sim.q, sim.dq, lim)
    expect[[2, 11]] *= 0.5
    np.testing.assert_allclose(sim.tau, expect, atol=1e-9)
    sim.step(500)
    nominal.step(500)
    sag = np.abs(sim.q - stand_pose())
    sag_nom = np.abs(nominal.q - stand_pose())
    assert sag[2] > 1.5 * sag_nom[2]  # half the stiffness, about twice the sag
    with pytest.raises(ValueError):
        MotorStrength(0.0)
    with pytest.raises(ValueError):
        MotorStrength(1.0, joints=["FL_knee"])


def test_modify_spec_hook_reaches_the_model():
    class Damping(Effect):
        def modify_spec(self, spec):
            for j in spec.joints:
                if j.name.endswith("_calf_joint"):
                    j.damping = [0.3, 0.0, 0.0]  # MuJoCo 4: linear + polynomial terms

    sim = Go2Sim(SimConfig(base="fixed", effects=[Damping()]))
    calf_dofs = [sim.model.joint(f"{leg}_calf_joint").dofadr[0] for leg in MODEL_LEGS]
    np.testing.assert_allclose(sim.model.dof_damping[calf_dofs], 0.3)
    assert np.count_nonzero(sim.model.dof_damping) == 4


# ---------------------------------------------------------------------------- batch
def test_batch_sim_matches_single_sims():
    cfg = SimConfig(base="free")
    batch = Go2BatchSim(cfg, 3, threads=2)
    try:
        q = stand_pose() + np.array([[0.0], [0.05], [-0.05]])
        batch.set_commands(q, 0.0, 60.0, 5.0, 0.0)
        batch.step(200)
        for i in range(3):
            single = Go2Sim(cfg)
            single.set_command(q[i], 0.0, 60.0, 5.0, 0.0)
            single.step(200)
            np.testing.assert_array_equal(batch.envs[i].q, single.q)
    finally:
        batch.close()
