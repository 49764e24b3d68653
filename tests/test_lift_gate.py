"""calib.support (the centre of mass over the feet, from the joints and gravity) and
deploy.lift_gate (the foot leaves the floor once the body stands over the other three)."""

import math

import numpy as np
import pytest

from calib.joints import LEGS, STAND_POSE_LEG, full_pose
from calib.support import SupportModel, go2_support, polygon_margin
from deploy.lift_gate import DEFAULT_GATE, GATE_CAUSE, GateLimits, LiftGate


def _stance(leg):
    return [g for g in LEGS if g != leg]


def test_the_centre_of_mass_and_feet_are_the_simulators_in_the_base_frame():
    mujoco = pytest.importorskip("mujoco")  # noqa: F841 - the simulator is the reference
    from sim.free_base_run import free_base_sim

    rng = np.random.default_rng(4)
    sm = go2_support()
    for _ in range(3):
        q = full_pose(STAND_POSE_LEG) + rng.uniform(-0.3, 0.3, 12)
        sim = free_base_sim(0.001, q)
        r, p = sim.base_rotation, sim.base_pos
        com, _ = sim.com_state()
        c_b, feet_b = sm.com_and_feet(sim.q)
        np.testing.assert_allclose(c_b, r.T @ (com - p), atol=1e-9)
        np.testing.assert_allclose(feet_b, (sim.foot_positions - p) @ r, atol=1e-9)
    assert sm.mass == pytest.approx(float(sim.model.body_subtreemass[sim._base_id]))


def test_the_margin_is_the_one_over_a_level_floor_whatever_the_bodys_attitude():
    pytest.importorskip("mujoco")
    from sim.free_base_run import free_base_sim

    sm = go2_support()
    q = full_pose(STAND_POSE_LEG) + np.linspace(-0.2, 0.2, 12)
    sim = free_base_sim(0.001, q)
    com, _ = sim.com_state()
    feet = sim.foot_positions
    for leg in LEGS:
        ring = [LEGS.index(g) for g in ("FL", "FR", "RR", "RL") if g != leg]
        world = polygon_margin(com[None, :2], feet[ring][None, :, :2])[0]
        # gravity as the body IMU sees it; its length does not matter
        g_b = sim.base_rotation.T @ np.array([0.0, 0.0, -9.81])
        assert sm.margin(sim.q, g_b, _stance(leg)) == pytest.approx(world, abs=1e-9)


def test_at_the_stand_pose_the_front_tripods_lack_what_the_rear_ones_have():
    sm = go2_support()
    q = full_pose(STAND_POSE_LEG)
    down = [0.0, 0.0, -1.0]
    m = {leg: sm.margin(q, down, _stance(leg)) for leg in LEGS}
    # the centre of mass sits ahead of the feet's centre (the base's own 21 mm ahead of its
    # origin): on the lifted front foot's side of the diagonal its tripod stands on
    assert m["FL"] == pytest.approx(m["FR"]) and m["RL"] == pytest.approx(m["RR"])
    assert m["FL"] < 0 < m["RL"] and m["RL"] == pytest.approx(-m["FL"])
    # four feet: inside
    assert sm.margin(q, down, LEGS) > 0.1
    # the body pitched nose down 10 deg (as on a floor falling away ahead) moves the projection
    # ahead, towards the lifted front foot; nose up, back over the tripod
    a = math.radians(10.0)
    nose_down, nose_up = [math.sin(a), 0.0, -math.cos(a)], [-math.sin(a), 0.0, -math.cos(a)]
    assert sm.margin(q, nose_down, _stance("FL")) < m["FL"] - 0.02
    assert sm.margin(q, nose_up, _stance("FL")) > m["FL"] + 0.02


_LEVEL, _TRIPOD = [0.0, 0.0, -1.0], ("FR", "RL", "RR")


@pytest.mark.parametrize("q, gravity, stance, message", [
    (np.zeros(11), _LEVEL, _TRIPOD, "12 finite"),
    (np.full(12, np.nan), _LEVEL, _TRIPOD, "12 finite"),
    (np.zeros(12), [0.0, 0.0, 0.0], _TRIPOD, "non-zero"),
    (np.zeros(12), _LEVEL, ("FR", "RL"), "three feet"),
    (np.zeros(12), _LEVEL, ("FR", "RL", "XX"), "unknown leg"),
])
def test_bad_input_is_refused(q, gravity, stance, message):
    with pytest.raises(ValueError, match=message):
        go2_support().margin(q, gravity, stance)


def test_a_file_that_is_no_urdf_is_refused(tmp_path):
    with pytest.raises(ValueError, match="URDF not found"):
        SupportModel(tmp_path / "none.urdf")
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='base'/></robot>")
    with pytest.raises(ValueError, match="has no joint FL_hip_joint"):
        SupportModel(bad)


def test_the_gate_waits_for_the_margin_then_stays_open():
    g = LiftGate(GateLimits(0.02, 0.1))
    assert g.check(0.005, 0.02) == "wait" and g.check(0.019, 0.02) == "wait"
    assert g.waited_s == pytest.approx(0.04)
    assert g.check(0.021, 0.02) == "go"
    assert g.check(-0.5, 0.02) == "go"  # once lifted, the foot is the tip guard's
    g.reset()
    assert not g.passed and g.waited_s == 0.0
    assert g.check(0.03, 0.02) == "go"


def test_the_gate_calls_the_lift_off_when_the_wait_runs_out():
    g = LiftGate(GateLimits(0.02, 0.1))
    verdicts = [g.check(-0.012, 0.02) for _ in range(6)]
    assert verdicts[:5] == ["wait"] * 5
    assert verdicts[5].startswith(GATE_CAUSE)
    assert "-12 mm" in verdicts[5] and "after 0.1 s more shift" in verdicts[5]
    assert "needs +20" in verdicts[5]
    assert LiftGate(GateLimits(0.02, 0.0)).check(0.0, 0.02).startswith(GATE_CAUSE)  # no wait
    assert LiftGate(None).check(-1.0, 0.02) == "go"  # off
    blind = LiftGate(GateLimits(0.02, 0.0))  # no body attitude: the session's -inf
    assert blind.check(-math.inf, 0.02) == f"{GATE_CAUSE} unknown (no body attitude) after 0.0 s " \
        "more shift"


def test_gate_limits_from_numbers_pairs_and_text():
    assert GateLimits.of(0.03) == GateLimits(0.03, 2.0) and GateLimits.of((0.01, 1)) == \
        GateLimits(0.01, 1.0)
    assert GateLimits.of(None) is None and GateLimits.of(DEFAULT_GATE) is DEFAULT_GATE
    assert GateLimits.parse("20,2") == DEFAULT_GATE and GateLimits.parse(" 15 ") == \
        GateLimits(0.015, 2.0)
    assert GateLimits.parse("off") is None and GateLimits.parse("-5,0") == GateLimits(-0.005, 0)
    assert str(DEFAULT_GATE) == "20,2" and DEFAULT_GATE.to_json() == [0.02, 2.0]
    assert GateLimits.of(DEFAULT_GATE.to_json()) == DEFAULT_GATE
    assert GateLimits.parse(str(GateLimits(0.0125, 0.5))) == GateLimits(0.0125, 0.5)


def test_bad_gate_limits_and_text_are_refused():
    for bad in (0.3, float("nan"), (0.02, -1.0), (0.02, 31.0), (0.02,), True, "0.02"):
        with pytest.raises(ValueError, match="lift gate"):
            LiftGate(bad)
    for text in ("x", "20,", "20,2,1", "", "300"):  # 300 mm: past the 0.2 m bound
        with pytest.raises(ValueError, match="lift gate"):
            GateLimits.parse(text)
