"""deploy.leg_dynamics: the leg's fixed-base inverse dynamics equals pinocchio's RNEA on the
whole Go2 (any gravity direction), plus the rotor inertia; and the lift schedule's
feed-forward torque is that of its planned motion."""

import numpy as np
import pinocchio as pin
import pytest

from calib.robot import go2_urdf_path
from deploy.leg_dynamics import GRAVITY, ROTOR_INERTIA, LegDynamics
from deploy.lift_schedule import LiftSchedule, blend_accelerations, blend_targets


@pytest.mark.parametrize("leg", ["FL", "FR", "RL", "RR"])
def test_matches_pinocchio_rnea(leg):
    model = pin.buildModelFromUrdf(str(go2_urdf_path()))
    data = model.createData()
    dyn = LegDynamics.of_leg(leg)
    idx = [model.joints[model.getJointId(f"{leg}_{j}_joint")].idx_v
           for j in ("hip", "thigh", "calf")]
    rng = np.random.default_rng(3)
    n = 16
    q, dq, ddq = (rng.uniform(-lim, lim, (n, model.nv)) for lim in (1.5, 4.0, 30.0))
    g = rng.normal(size=(n, 3))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    mine = dyn.torques(q[:, idx], dq[:, idx], ddq[:, idx], g)
    for i in range(n):
        model.gravity.linear = GRAVITY * g[i]
        ref = pin.rnea(model, data, q[i], dq[i], ddq[i])[idx]
        np.testing.assert_allclose(mine[i], ref + ROTOR_INERTIA * ddq[i, idx], atol=1e-9)


def test_several_legs_in_one_pass_are_each_legs_torques():
    rng = np.random.default_rng(8)
    legs = np.array(["RR", "FL", "FL", "RL", "FR", "RR", "RL"])
    q, dq, ddq = (rng.uniform(-lim, lim, (7, 3)) for lim in (1.0, 6.0, 60.0))
    g = rng.normal(size=(7, 3))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    mixed = LegDynamics.torques_of_legs(legs, q, dq, ddq, g)
    for i, leg in enumerate(legs):
        np.testing.assert_allclose(mixed[i], LegDynamics.of_leg(leg).torques(
            q[i], dq[i], ddq[i], g[i])[0], atol=1e-12)
    with pytest.raises(ValueError, match="one name per sample"):
        LegDynamics.torques_of_legs(legs[:3], q, dq, ddq, g)


def test_level_default_and_broadcasting():
    dyn = LegDynamics.of_leg("RL")
    q = np.array([0.0, 0.9, -1.8])
    still = dyn.torques(q, np.zeros(3), np.zeros(3))
    np.testing.assert_allclose(still, dyn.torques(q, 0, 0, [0.0, 0.0, -1.0]))
    assert still.shape == (1, 3)
    # standing still, level: the thigh and calf hold the leg up against gravity
    assert abs(still[0, 1]) > 0.1 and abs(still[0, 2]) > 0.05
    np.testing.assert_allclose(dyn.torques(q, 0, 0, [0.0, 0.0, 0.0]), 0.0, atol=1e-12)


def test_table_gives_the_torque_under_any_tilt_within_the_limit():
    dyn = LegDynamics.of_leg("FR")
    rng = np.random.default_rng(5)
    q, dq, ddq = (rng.uniform(-lim, lim, (8, 3)) for lim in (1.0, 6.0, 60.0))
    limit = np.array([2.0, 3.0, 4.0])
    table = dyn.table(q, dq, ddq, limit)
    full = dyn.table(q, dq, ddq)
    for i in range(8):
        g = rng.normal(size=3)
        g /= np.linalg.norm(g)
        ref = dyn.torques(q[i], dq[i], ddq[i], g)[0]
        np.testing.assert_allclose(full.at(i, g), ref, atol=1e-12)
        np.testing.assert_allclose(table.at(i, g), np.clip(ref, -limit, limit), atol=1e-12)
    np.testing.assert_allclose(full.at(3), dyn.torques(q[3], dq[3], ddq[3])[0], atol=1e-12)
    assert np.any(np.abs([full.at(i) for i in range(8)]) > limit)  # the clip was exercised


def test_schedule_feedforward_is_the_planned_motion_torque():
    plain = LiftSchedule(t_r=0.3, periods=1, n_basis=6)
    ff = LiftSchedule(t_r=0.3, periods=1, n_basis=6, feedforward=True)
    q_start = np.array([-0.1, 0.85, -1.55])
    d = ff.durations("FR")
    plan = ff.plan("FR")
    g = np.array([0.05, -0.03, -1.0]) / np.linalg.norm([0.05, -0.03, -1.0])
    for t in np.linspace(0.0, d.sum() + 0.5, 23):
        a, b = plain.targets("FR", t, q_start), ff.targets("FR", t, q_start, g)
        assert a.tau is None and a.phase == b.phase
        if b.q_des is None:
            assert b.tau is None
            continue
        np.testing.assert_allclose(b.q_des, a.q_des)
        te = t - d[:3].sum()
        ddq = blend_accelerations(np.array([t]), d, q_start[None], plan.q0[None],
                                  plan.accelerations([te]))
        np.testing.assert_allclose(
            b.tau, LegDynamics.of_leg("FR").torques(b.q_des, b.dq_des, ddq, g)[0])
    with pytest.raises(ValueError, match="feedforward"):
        LiftSchedule(feedforward="yes")
    old = {k: v for k, v in ff.to_metadata().items() if k != "feedforward"}
    assert LiftSchedule.from_metadata(old).feedforward is False
    assert LiftSchedule.from_metadata(ff.to_metadata()).feedforward is True


def test_blended_accelerations_are_the_rates_derivative():
    sched = LiftSchedule(t_r=0.3, periods=1, n_basis=6)
    plan = sched.plan("FL")
    d = sched.durations("FL")
    t = np.arange(0.0, d.sum() + 0.3, 1e-4)
    te = t - d[:3].sum()
    qs, q0 = np.tile([0.1, 0.85, -1.55], (len(t), 1)), np.tile(plan.q0, (len(t), 1))
    _, dq, ph = blend_targets(t, d, qs, q0, plan.positions(te), plan.velocities(te))
    dd = blend_accelerations(t, d, qs, q0, plan.accelerations(te))
    assert np.isnan(dd[(ph == 0) | (ph == 5)]).all()
    on = (ph >= 1) & (ph <= 4)
    num = np.gradient(dq, t, axis=0)
    # away from the phase boundaries (where a one-sided difference straddles two phases)
    ends = np.cumsum(d)
    far = on & (np.abs(t[:, None] - ends[None]).min(1) > 1e-3)
    np.testing.assert_allclose(dd[far], num[far], atol=2e-3 * np.abs(dd[far]).max())


def test_prepare_builds_what_the_loop_needs_before_it_starts():
    cached = LegDynamics._from_urdf.__func__
    cached.cache_clear()
    plain = LiftSchedule(t_r=0.3, periods=1, n_basis=6)
    plain.prepare("RR")
    assert "RR" in plain._plans and cached.cache_info().currsize == 0
    ff = LiftSchedule(t_r=0.3, periods=1, n_basis=6, feedforward=True)
    ff.prepare("RR")
    assert cached.cache_info().currsize == 1
    hits = cached.cache_info().hits
    ff.targets("RR", ff.total("RR") - 0.1, np.array([0.0, 0.9, -1.8]))
    assert cached.cache_info().hits > hits and cached.cache_info().currsize == 1


def test_a_pack_gives_the_urdfs_torques_where_there_is_no_pinocchio(tmp_path):
    """``save_pack`` here, ``load_pack`` in a process that can import neither pinocchio nor
    find the URDF (a lent training machine): the same torques, bit for bit."""
    import json
    import subprocess
    import sys

    pack = tmp_path / "leg_dynamics.npz"
    LegDynamics.save_pack(pack)
    rng = np.random.default_rng(3)
    q, dq, ddq = rng.normal(size=(3, 5, 3))
    g = np.array([0.1, -0.2, -0.97])
    code = f"""
import sys, json
sys.modules["pinocchio"] = None
import numpy as np
import calib.robot
def _none():
    raise RuntimeError("no URDF")
calib.robot.go2_urdf_path = _none
from deploy.leg_dynamics import LegDynamics
from deploy.lift_schedule import LiftSchedule
print(json.dumps(LegDynamics.load_pack({str(pack)!r})))
q, dq, ddq = (np.array(x) for x in json.loads(sys.stdin.read()))
print(json.dumps({{leg: LiftSchedule.feedforward_torque(leg, q, dq, ddq, {g.tolist()}).tolist()
                  for leg in ("FL", "FR", "RL", "RR")}}))
"""
    p = subprocess.run([sys.executable, "-c", code], input=json.dumps([q.tolist(), dq.tolist(),
                       ddq.tolist()]), capture_output=True, text=True, timeout=60, check=False)
    assert p.returncode == 0, p.stderr[-2000:]
    legs, torques = (json.loads(line) for line in p.stdout.splitlines())
    assert legs == ["FL", "FR", "RL", "RR"]
    for leg in legs:
        np.testing.assert_array_equal(
            torques[leg], LiftSchedule.feedforward_torque(leg, q, dq, ddq, g))


def test_a_file_that_is_no_pack_is_refused_with_its_name(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_text("not numpy")
    with pytest.raises(ValueError, match="bad.npz: not a leg-dynamics pack"):
        LegDynamics.load_pack(bad)
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros(3))
    with pytest.raises(ValueError, match="not a leg-dynamics pack"):
        LegDynamics.load_pack(other)
