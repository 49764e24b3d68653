"""The unmodelled-effects library (sim/effects.py): each effect moves the simulation the way
its physics says, and the IMU effects transform readings as documented."""

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sim.effects import (
    EFFECT_NAMES,
    ActuationLatency,
    Armature,
    Backlash,
    CoulombFriction,
    FloorSlope,
    FloorSoftness,
    FootFriction,
    FootPayload,
    FrictionCone,
    ImuBias,
    ImuMisalignment,
    ImuTimeOffset,
    LinkMass,
    MotorStrength,
    PacketLoss,
    TorqueLimit,
    ViscousFriction,
    apply_imu_effects,
)
from sim.go2 import Go2Sim, SimConfig, stand_pose
from sim.model import FOOT_RADIUS

CALF = 2  # FL_calf, model order


def _run(effects, q_des=None, kp=20.0, kd=0.5, tau_ff=0.0, steps=300, base="fixed"):
    sim = Go2Sim(SimConfig(base=base, effects=effects))
    sim.reset(stand_pose())
    q = stand_pose() if q_des is None else q_des
    sim.set_command(q, 0.0, kp, kd, tau_ff)
    qs, dqs = [], []
    for _ in range(steps):
        sim.step()
        qs.append(sim.q)
        dqs.append(sim.dq)
    return sim, np.array(qs), np.array(dqs)


def _step_target():
    q = stand_pose()
    q[CALF] += 0.3
    return q


def test_names_and_classes():
    for cls in (ActuationLatency, MotorStrength, CoulombFriction, ViscousFriction, Armature,
                Backlash, LinkMass, FootFriction, TorqueLimit, PacketLoss, ImuBias,
                ImuMisalignment, ImuTimeOffset, FloorSlope, FloorSoftness, FootPayload,
                FrictionCone):
        assert cls.name in EFFECT_NAMES


def test_coulomb_friction_holds_a_joint_against_a_small_torque():
    ff = np.zeros(12)
    ff[CALF] = 0.3
    _, q0, _ = _run([], kp=0.0, kd=0.0, tau_ff=ff, steps=200)
    _, q1, _ = _run([CoulombFriction(1.0, joints=["FL_calf"])], kp=0.0, kd=0.0, tau_ff=ff,
                    steps=200)
    moved0 = abs(q0[-1, CALF] - stand_pose()[CALF])
    moved1 = abs(q1[-1, CALF] - stand_pose()[CALF])
    assert moved1 < 0.3 * moved0
    with pytest.raises(ValueError):
        CoulombFriction(-1.0)


def test_viscous_friction_and_armature_slow_a_step_response():
    target = _step_target()
    _, _, d0 = _run([], q_des=target, steps=150)
    _, _, d1 = _run([ViscousFriction(0.3, joints=["FL_calf"])], q_des=target, steps=150)
    _, q2, _ = _run([Armature(0.03, joints=["FL_calf"])], q_des=target, steps=150)
    peak0 = np.abs(d0[:, CALF]).max()
    assert np.abs(d1[:, CALF]).max() < 0.8 * peak0
    # armature: slower start (smaller displacement after 20 ms)
    _, q0, _ = _run([], q_des=target, steps=20)
    assert abs(q2[19, CALF] - stand_pose()[CALF]) < 0.8 * abs(q0[-1, CALF] - stand_pose()[CALF])
    # the other joints are untouched
    assert np.abs(d1[:, 5] - d0[:, 5]).max() < 1e-3


def test_backlash_on_a_saturated_joint_keeps_the_motor_at_its_limit():
    import types

    from sim.effects import MotorCommand

    b = Backlash(0.02)
    kp, lim = np.full(12, 60.0), np.full(12, 23.7)
    b.on_command(MotorCommand(np.ones(12), np.zeros(12), kp, np.zeros(12), np.zeros(12)), None)
    sim = types.SimpleNamespace(data=types.SimpleNamespace(time=0.0, qpos=np.zeros(19),
                                                           qvel=np.zeros(18)),
                                _tau_lo=-lim, _tau_hi=lim)
    # 1 rad off: 60 N m asked, 58.8 through the play, the motor gives its 23.7 either way
    np.testing.assert_allclose(b.on_torque(np.clip(kp * 1.0, -lim, lim), sim), lim)
    sim.data.qpos[-12:] = 0.99  # 0.01 rad off: inside the play, no spring at all
    np.testing.assert_allclose(b.on_torque(kp * 0.01, sim), 0.0, atol=1e-12)


def test_backlash_and_link_mass_increase_the_gravity_sag():
    _, q0, _ = _run([], kp=10.0, kd=0.5, steps=600)
    _, q1, _ = _run([Backlash(0.03, joints=["FL_thigh"])], kp=10.0, kd=0.5, steps=600)
    _, q2, _ = _run([LinkMass(3.0, "FL_thigh")], kp=10.0, kd=0.5, steps=600)
    sag0 = abs(q0[-1, 1] - stand_pose()[1])
    assert abs(q1[-1, 1] - stand_pose()[1]) > sag0 + 0.01
    assert abs(q2[-1, 1] - stand_pose()[1]) > 1.5 * sag0
    sim = Go2Sim(SimConfig(base="fixed", effects=[LinkMass(2.0, "FL_calf")]))
    nominal = Go2Sim(SimConfig(base="fixed"))
    b = sim.model.body("FL_calf").id
    assert sim.model.body_mass[b] == pytest.approx(2.0 * nominal.model.body_mass[b])
    with pytest.raises(ValueError):
        LinkMass(1.2, "FL_knee")


def test_a_foot_imu_node_weighs_on_its_calf():
    """30-80 g strapped above a foot (the transfer check's foot_imus) on a calf of 194 g; on a
    third party's MJCF: tests/test_external_model.py."""
    from calib.joints import LEGS

    nodes = [FootPayload(0.05, leg) for leg in LEGS]
    urdf = Go2Sim(SimConfig(base="fixed", effects=nodes)).model
    bare = Go2Sim(SimConfig(base="fixed")).model
    c = bare.body("FL_calf").id
    assert urdf.body_mass[c] == pytest.approx(bare.body_mass[c] + 0.05)  # fused into the calf
    # the centre of mass of the two, the node 4 cm above the foot centre (0.213 m down)
    m = bare.body_mass[c]
    z = (m * bare.body_ipos[c, 2] + 0.05 * (-0.213 + 0.04)) / (m + 0.05)
    assert urdf.body_ipos[c, 2] == pytest.approx(z, abs=1e-9)
    assert urdf.body_subtreemass[0] == pytest.approx(bare.body_subtreemass[0] + 0.2)
    # the calf's thicker end pulls the knee down further under the same PD
    _, q0, _ = _run([], kp=10.0, kd=0.5, steps=600)
    _, q1, _ = _run([FootPayload(0.3, "FL")], kp=10.0, kd=0.5, steps=600)
    assert abs(q1[-1, CALF] - q0[-1, CALF]) > 0.01
    for bad in ({"kg": 0.0, "leg": "FL"}, {"kg": 0.05, "leg": "XX"},
                {"kg": 0.05, "leg": "FL", "offset": (0, 0, 0.2)}):
        with pytest.raises(ValueError):
            FootPayload(**bad)


def test_torque_limit_caps_the_motor():
    target = _step_target()
    target[5] += 0.3  # FR_calf too
    sim, _, _ = _run([TorqueLimit(2.0, joints=["FL_calf"])], q_des=target, kp=60.0, steps=5)
    assert abs(sim.tau[CALF]) <= 2.0 + 1e-9
    assert abs(sim.tau[5]) > 2.0  # FR_calf: not limited


def test_packet_loss_drops_commands():
    sim = Go2Sim(SimConfig(base="fixed", effects=[PacketLoss(0.5)], seed=3))
    kept = 0
    for k in range(200):
        sim.set_command(stand_pose() + 1e-3 * k, 0.0, 20.0, 0.5, 0.0)
        sim.step(2)
        kept += sim.command.q_des[0] == pytest.approx(stand_pose()[0] + 1e-3 * k)
    assert 70 < kept < 130
    det = Go2Sim(SimConfig(base="fixed", effects=[PacketLoss(drop_times=[0.0])]))
    det.set_command(stand_pose(), 0.0, 20.0, 0.5, 0.0)
    det.step()
    np.testing.assert_array_equal(det.command.kp, 0.0)


def test_foot_friction_sets_the_floor_and_feet():
    sim = Go2Sim(SimConfig(base="free", effects=[FootFriction(0.3)]))
    m = sim.model
    assert m.geom_friction[m.geom("floor").id][0] == pytest.approx(0.3)
    assert m.geom_friction[m.geom("FL_foot").id][0] == pytest.approx(0.3)


@pytest.mark.parametrize("azimuth", [0.0, 2.0, -1.2])
def test_floor_slope_tilts_the_floor_and_starts_the_robot_standing_on_it(azimuth):
    angle = np.radians(4.0)
    sim = Go2Sim(SimConfig(base="free", effects=[FloorSlope(angle, azimuth)]))
    m = sim.model
    normal = sim.data.geom_xmat[m.geom("floor").id].reshape(3, 3)[:, 2]
    downhill = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
    assert np.degrees(np.arccos(normal[2])) == pytest.approx(4.0)
    assert normal @ downhill == pytest.approx(np.sin(angle))  # the floor falls away that way
    # every foot sphere rests on the tilted plane, and the base leans with it
    np.testing.assert_allclose(sim.foot_positions @ normal, FOOT_RADIUS, atol=1e-9)
    assert sim.base_tilt == pytest.approx(angle)
    level = Go2Sim(SimConfig(base="free"))
    assert sim.base_pos @ normal == pytest.approx(level.base_pos[2])  # as high over the floor
    sim.reset()  # a reset puts it back on the slope
    np.testing.assert_allclose(sim.foot_positions @ normal, FOOT_RADIUS, atol=1e-9)
    for bad in (-0.1, 0.5, np.nan):
        with pytest.raises(ValueError):
            FloorSlope(bad)
    with pytest.raises(ValueError, match="free base"):
        Go2Sim(SimConfig(base="fixed", effects=[FloorSlope(0.05)]))
    with pytest.raises(ValueError, match="floor"):
        Go2Sim(SimConfig(base="free", floor=False, effects=[FloorSlope(0.05)]))


def _standing_foot_heights(effects) -> np.ndarray:
    """The foot centres' heights (m) after 2 s standing at the stand pose, firm gains."""
    sim = Go2Sim(SimConfig(base="free", effects=effects))
    sim.set_command(stand_pose(), np.zeros(12), np.full(12, 60.0), np.full(12, 2.0), np.zeros(12))
    sim.step(2000)
    assert sim.body_contacts() == []
    return sim.foot_positions[:, 2]


def test_floor_softness_lets_the_feet_sink_in():
    firm = _standing_foot_heights([])
    soft = _standing_foot_heights([FloorSoftness(0.04)])
    assert np.all(FOOT_RADIUS - firm < 0.003)  # MuJoCo's default contact: 2 mm
    sink = FOOT_RADIUS - soft
    assert np.all((sink > 0.005) & (sink < 0.010)), sink  # a mat: the docstring's 6 mm
    for bad in ((0.0,), (0.3,), (np.nan,), (0.04, 0.0)):
        with pytest.raises(ValueError, match="floor softness"):
            FloorSoftness(*bad)
    with pytest.raises(ValueError, match="physics step"):  # stiffer than the step can resolve
        Go2Sim(SimConfig(timestep=0.005, effects=[FloorSoftness(0.008)]))
    with pytest.raises(ValueError, match="floor"):
        Go2Sim(SimConfig(floor=False, effects=[FloorSoftness(0.04)]))


def test_friction_cone_sets_the_models_contact_option():
    """FrictionCone: MuJoCo's default cone (pyramidal, impratio 1) where the URDF's model
    has an elliptic one with impratio 100; bad cones and ratios refused."""
    own = Go2Sim(SimConfig(base="free")).model.opt
    assert (own.cone, own.impratio) == (mujoco.mjtCone.mjCONE_ELLIPTIC, 100.0)
    opt = Go2Sim(SimConfig(base="free", effects=[FrictionCone()])).model.opt
    assert (opt.cone, opt.impratio) == (mujoco.mjtCone.mjCONE_PYRAMIDAL, 1.0)
    for bad in (("round",), ("pyramidal", 0.5), ("elliptic", np.nan)):
        with pytest.raises(ValueError, match="cone|impratio"):
            FrictionCone(*bad)


def test_a_floor_that_swallows_the_feet_meets_the_calves_lower_end():
    """On a floor soft enough to take the whole foot sphere, the calves touch it too, at
    their lower end (which wraps the top of the foot), and the health record says where."""
    from sim.free_base_run import HealthTracker

    firm = Go2Sim(SimConfig(base="free"))
    assert np.isnan(firm.calf_contact_reach()).all()
    sim = Go2Sim(SimConfig(base="free", effects=[FloorSoftness(0.08)]))
    sim.set_command(stand_pose(), np.zeros(12), np.full(12, 60.0), np.full(12, 2.0), np.zeros(12))
    sim.step(3000)
    assert np.all(sim.foot_positions[:, 2] < 0.0)  # the foot centres below the floor
    assert sim.body_contacts() == ["FL_calf", "FR_calf", "RL_calf", "RR_calf"]
    reach = sim.calf_contact_reach()
    assert np.all((reach > FOOT_RADIUS) & (reach < 0.030)), reach  # not the shank, nor the knee
    health = HealthTracker("FL")
    health.update(sim)
    h = health.result()
    assert set(h.calf_reach_mm) == {"FL", "FR", "RL", "RR"}
    assert h.calf_reach_mm["RR"] == pytest.approx(1e3 * reach[3], abs=0.01)
    assert type(h).from_dict(h.to_dict()) == h


def test_imu_effects_transform_readings():
    t = np.arange(0, 1, 0.002)
    gyro = np.stack([np.sin(2 * np.pi * t), np.cos(2 * np.pi * t), 0 * t], 1)
    acc = np.tile([0.0, 0.0, 9.81], (t.size, 1))
    quat = np.tile([1.0, 0, 0, 0], (t.size, 1))
    g, a, _ = ImuBias([0.1, 0, 0]).apply_imu(t, gyro, acc, quat)
    np.testing.assert_allclose(g - gyro, np.tile([0.1, 0, 0], (t.size, 1)))
    rv = np.array([0.0, 0.05, 0.0])
    g, a, q = ImuMisalignment(rv).apply_imu(t, gyro, acc, quat)
    r = Rotation.from_rotvec(rv).as_matrix()
    np.testing.assert_allclose(a[0], r.T @ acc[0])
    np.testing.assert_allclose(q[0], Rotation.from_rotvec(rv).as_quat()[[3, 0, 1, 2]], atol=1e-12)
    g, _, _ = apply_imu_effects([ImuTimeOffset(0.01)], t, gyro, acc, quat)
    k = 100
    assert g[k, 0] == pytest.approx(np.sin(2 * np.pi * (t[k] - 0.01)), abs=2e-3)
