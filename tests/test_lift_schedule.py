"""deploy.lift_schedule: phase order, continuity of the targets, velocities consistent with the
positions, metadata round trip, and the batched core equal to the per-robot call."""

import numpy as np
import pytest

from calib.excitation import ExcitationConfig, foot_position_mirrored, stance_foot_z
from deploy.lift_schedule import PHASES, LiftSchedule, blend_targets


@pytest.fixture(scope="module")
def sched():
    return LiftSchedule(t_r=0.3, periods=1, n_basis=6)


Q_START = np.array([0.1, 0.85, -1.55])


def test_phases_in_order(sched):
    d = sched.durations("FL")
    ends = np.cumsum(d)
    assert sched.phase("FL", 0.0) == "shift"
    for name, t in zip(PHASES[1:], ends, strict=True):
        assert sched.phase("FL", t + 1e-6) == name
    assert sched.targets("FL", 0.2, Q_START).q_des is None
    assert sched.targets("FL", ends[-1] + 0.1, Q_START).phase == "done"
    assert sched.targets("FL", ends[-1] + 0.1, Q_START).q_des is None


def test_targets_continuous_and_consistent(sched):
    plan = sched.plan("RR")
    ends = np.cumsum(sched.durations("RR"))
    eps = 1e-7
    at = lambda t: sched.targets("RR", t, Q_START)
    np.testing.assert_allclose(at(ends[0] + eps).q_des, Q_START, atol=1e-6)
    np.testing.assert_allclose(at(ends[1] - eps).q_des, plan.q0, atol=1e-6)
    np.testing.assert_allclose(at(ends[2] + eps).q_des, plan.q0, atol=1e-5)
    np.testing.assert_allclose(at(ends[3] - eps).q_des, plan.q0, atol=1e-5)
    np.testing.assert_allclose(at(ends[4] - eps).q_des, Q_START, atol=1e-6)
    # dq_des is the derivative of q_des, ddq_des that of dq_des, in every phase with targets
    for t in np.linspace(ends[0] + 0.01, ends[4] - 0.01, 37):
        h = 1e-5
        fd = (at(t + h).q_des - at(t - h).q_des) / (2 * h)
        np.testing.assert_allclose(at(t).dq_des, fd, atol=2e-3)
        fdd = (at(t + h).dq_des - at(t - h).dq_des) / (2 * h)
        np.testing.assert_allclose(at(t).ddq_des, fdd, atol=2e-2)
    assert at(ends[0] / 2).ddq_des is None  # shift: the policy's
    tg = at(ends[2] + 1.0)
    assert tg.phase == "excite" and tg.kp == sched.kp and tg.kd == sched.kd


def test_metadata_round_trip_and_errors(sched):
    d = sched.to_metadata()
    assert LiftSchedule.from_metadata(d) == sched
    with pytest.raises(ValueError, match="unknown lift_schedule keys"):
        LiftSchedule.from_metadata({**d, "bogus": 1})
    assert LiftSchedule.from_metadata({**d, "adapt": True}).adapt
    half = LiftSchedule.from_metadata({**d, "excitation_seen": 0.5})
    assert half.excitation_seen == 0.5 and sched.excitation_seen == 1.0
    assert LiftSchedule.from_metadata(half.to_metadata()) == half
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="excitation_seen must be in"):
            LiftSchedule.from_metadata({**d, "excitation_seen": bad})
    for bad in ("half", True, None):
        with pytest.raises(ValueError, match="excitation_seen must be a number"):
            LiftSchedule.from_metadata({**d, "excitation_seen": bad})
    for key in ("feedforward", "adapt"):
        with pytest.raises(ValueError, match=f"{key} must be true or false"):
            LiftSchedule.from_metadata({**d, key: "yes"})
    with pytest.raises(ValueError):
        LiftSchedule(shift=0.0)
    for kp, kd in ((0.0, 1.0), (40.0, -1.0), (float("inf"), 1.0), (40.0, float("nan"))):
        with pytest.raises(ValueError, match="kp must be > 0 and kd >= 0"):
            LiftSchedule(kp=kp, kd=kd)
    with pytest.raises(ValueError):
        sched.targets("FL", -1.0, Q_START)
    with pytest.raises(ValueError):
        sched.targets("XX", 1.0, Q_START)


def test_shift_per_leg():
    """``shift_by_leg``: those legs' shift phase, the others ``shift``; the JSON keeps the key
    only where it is set; bad values are refused with the key named."""
    s = LiftSchedule(shift=1.0, shift_by_leg={"FL": 2, "FR": 2.5}, t_r=0.3, periods=1, n_basis=6)
    assert [s.shift_of(g) for g in ("FL", "FR", "RL", "RR")] == [2.0, 2.5, 1.0, 1.0]
    assert s.durations("FR")[0] == 2.5 and s.durations("RL")[0] == 1.0
    assert s.phase("FL", 1.5) == "shift" and s.phase("RL", 1.5) == "lift"
    assert s.total("FR") - s.total("RR") == pytest.approx(1.5)
    assert LiftSchedule.from_metadata(s.to_metadata()).shift_by_leg == {"FL": 2.0, "FR": 2.5}
    assert "shift_by_leg" not in LiftSchedule().to_metadata()
    for bad in ({"XX": 2.0}, {"FL": 0.0}, {"FL": True}, {"FL": "2"}, [("FL", 2.0)]):
        with pytest.raises(ValueError):
            LiftSchedule(shift_by_leg=bad)


def test_ground_clearance_reaches_the_plans():
    # a JSON written before the field existed means the generator's default (v1-v4 plans)
    old = {k: v for k, v in LiftSchedule().to_metadata().items() if k != "ground_clearance"}
    assert LiftSchedule.from_metadata(old).ground_clearance == ExcitationConfig.ground_clearance
    high = LiftSchedule(periods=1, ground_clearance=0.12)
    assert high.excitation_config("FL").ground_clearance == 0.12
    lo, hi = LiftSchedule(periods=1).plan("FL"), high.plan("FL")
    z = lambda plan: foot_position_mirrored(plan.positions(np.linspace(0, plan.duration, 800)))[:, 2]
    assert z(hi).min() >= stance_foot_z() + 0.12 - 1e-3 > z(lo).min()
    with pytest.raises(ValueError, match="ground_clearance"):
        LiftSchedule(ground_clearance=-0.01)


def test_batched_core_matches(sched):
    plan = sched.plan("FL")
    d = sched.durations("FL")
    t = np.linspace(0, d.sum() + 1, 50)
    te = t - d[:3].sum()
    q, dq, ph = blend_targets(t, d, np.tile(Q_START, (50, 1)), np.tile(plan.q0, (50, 1)),
                              plan.positions(te), plan.velocities(te))
    for i in range(0, 50, 7):
        tg = sched.targets("FL", t[i], Q_START)
        assert PHASES[ph[i]] == tg.phase
        if tg.q_des is None:
            assert np.isnan(q[i]).all()
        else:
            np.testing.assert_allclose(q[i], tg.q_des)
            np.testing.assert_allclose(dq[i], tg.dq_des)


def test_targets_at_several_times_equal_the_single_calls():
    """One vectorised evaluation for a tick's frames, across phase boundaries (shift -> lift,
    lower -> done), with the feed-forward torque for a tilted body."""
    ff = LiftSchedule(t_r=0.3, periods=1, n_basis=6, feedforward=True)
    ends = np.cumsum(ff.durations("RR"))
    g = np.array([0.1, -0.05, -0.99])
    for t0 in (ends[0] - 0.01, ends[2] + 0.3, ends[-1] - 0.01):
        ts = t0 + np.arange(5) * 0.004
        many = ff.targets_at("RR", ts, Q_START, g)
        assert len({x.phase for x in many}) == (1 if t0 == ends[2] + 0.3 else 2)
        for t, x in zip(ts, many, strict=True):
            y = ff.targets("RR", t, Q_START, g)
            assert x.phase == y.phase
            if y.q_des is None:
                assert x.q_des is None and x.tau is None
            else:
                np.testing.assert_allclose(x.q_des, y.q_des, atol=1e-12)
                np.testing.assert_allclose(x.dq_des, y.dq_des, atol=1e-12)
                np.testing.assert_allclose(x.tau, y.tau, atol=1e-9)
    with pytest.raises(ValueError, match="times"):
        ff.targets_at("RR", [0.1, -0.004], Q_START)
