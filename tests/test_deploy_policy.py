"""Policy files on board: metadata validation, ONNX runner, delta targets, observation layout."""

import json
import os

import numpy as np
import pytest

from calib.joints import SDK_JOINT_NAMES
from deploy.hold_policy import hold_policy_metadata, write_hold_policy
from deploy.observation import build_observation, projected_gravity
from deploy.policy import PolicyMeta, PolicyRunner, default_policy_path, policies_for_legs

pytest.importorskip("onnx")


@pytest.fixture(scope="module")
def policy_json(tmp_path_factory):
    return write_hold_policy(tmp_path_factory.mktemp("pol"), action_value=0.5)


def test_load_and_run(policy_json):
    meta = PolicyMeta.load(policy_json)
    assert meta.control_dt == 0.02 and meta.obs_size == 49
    assert meta.lift_value("FL") == 1.0 and meta.lift_value(None) == 0.0
    r = PolicyRunner(meta)
    a = r.act(np.zeros(49, np.float32))
    np.testing.assert_allclose(a, 0.5)
    r.reset(meta.default_pose)
    t = r.step(a)  # target = prev + 0.25 * clip(0.5)
    np.testing.assert_allclose(t, np.clip(meta.default_pose + 0.125, meta.soft_lower,
                                          meta.soft_upper))
    for _ in range(200):
        t = r.step(a)
    np.testing.assert_allclose(t, meta.soft_upper)  # clamped to the soft limits
    np.testing.assert_allclose(r.prev_actions, 0.5)


@pytest.mark.parametrize("mutate, msg", [
    (lambda d: d.update(joint_order=list(reversed(SDK_JOINT_NAMES))), "joint_order"),
    (lambda d: d.update(schema_version=2), "schema_version"),
    (lambda d: d.update(kp=[1.0] * 11), "kp"),
    (lambda d: d["action"].update(mode="position"), "action.mode"),
    (lambda d: d["observation"].update(size=50), "observation.size"),
    (lambda d: d["lift_command"].pop("RR"), "RR"),
    (lambda d: d["soft_limits"].update(lower=[2.0] * 12), "soft_limits"),
    (lambda d: d["lift_schedule"].update(typo=1), "lift_schedule"),
    (lambda d: d.update(legs=["XX"]), "legs"),
    (lambda d: d.update(legs=[]), "legs"),
    # found at load, not at the first tick of a lift (which damped the standing robot)
    (lambda d: d["observation"].update(clip=0), "observation.clip"),
    (lambda d: d["observation"].update(clip=None), "observation.clip"),
    (lambda d: d["observation"]["terms"][0].update(source="leg_odometry"), "only as zero"),
    (lambda d: d["lift_schedule"].update(n_basis=1), "n_basis"),
    (lambda d: d["lift_schedule"].update(t_r="0.5"), "t_r must be a number"),
    (lambda d: d["lift_schedule"].update(shift_by_leg={"FL": 2.0, "fl": 3.0}), "twice"),
    (lambda d: d.update(default_pose=[5.0] * 12), "default_pose must lie within"),
    # values of the wrong type: one line, not a TypeError or AttributeError
    (lambda d: d["observation"].update(terms=["joint_pos"]), "malformed"),
    (lambda d: d.update(action=[1, 2]), "malformed"),
    (lambda d: d.update(control_dt=None), "malformed"),
    (lambda d: d["action"].update(target_lead_max=[0.5] * 11), "action.target_lead_max"),
    (lambda d: d["action"].update(target_lead_max=[0.0] * 12), "action.target_lead_max"),
])
def test_bad_metadata_is_refused_with_a_reason(tmp_path, mutate, msg):
    d = hold_policy_metadata()
    mutate(d)
    p = tmp_path / "p.json"
    p.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=msg):
        PolicyMeta.load(p)


def test_a_target_lead_bound_holds_every_target_near_its_joint(tmp_path):
    """``action.target_lead_max``: each tick's target stays within it of the measured joints
    (then the soft limits), so a policy pushing a joint it cannot move winds up no demand."""
    d = hold_policy_metadata()
    d["action"]["target_lead_max"] = [0.2] * 12
    p = tmp_path / "p.json"
    p.write_text(json.dumps(d))
    meta = PolicyMeta.load(p)
    np.testing.assert_allclose(meta.target_lead_max, 0.2)
    r = PolicyRunner.__new__(PolicyRunner)  # the rule alone: no ONNX needed
    r.meta, r.target = meta, meta.default_pose.copy()
    q = meta.default_pose.copy()  # the joints do not follow
    for _ in range(10):
        t = r.step(np.ones(12, np.float32), q)
    np.testing.assert_allclose(t, np.minimum(q + 0.2, meta.soft_upper))
    with pytest.raises(ValueError, match="measured joint positions"):
        r.step(np.ones(12, np.float32))
    assert PolicyMeta.from_dict(hold_policy_metadata(), p).target_lead_max is None


def test_shift_by_leg_names_legs_in_any_case(tmp_path):
    d = hold_policy_metadata()
    d["lift_schedule"]["shift_by_leg"] = {"fl": 2.0}
    p = tmp_path / "p.json"
    p.write_text(json.dumps(d))
    sched = PolicyMeta.load(p).schedule
    assert sched.shift_of("FL") == 2.0 and sched.shift_by_leg == {"FL": 2.0}


def test_policy_named_by_its_onnx(policy_json, tmp_path):
    """Every other command names a policy by its ONNX: the JSON beside it is read; a file
    that is not JSON text is refused with a reason, not a decoding error."""
    meta = PolicyMeta.load(policy_json.with_suffix(".onnx"))
    assert meta.path == policy_json
    assert PolicyRunner(meta).act(np.zeros(49, np.float32)).shape == (12,)
    blob = tmp_path / "p.json"
    blob.write_bytes(bytes(range(256)))
    with pytest.raises(ValueError, match="not JSON text"):
        PolicyMeta.load(blob)


def test_missing_network_and_newest_policy(tmp_path):
    old = write_hold_policy(tmp_path, name="old")
    new = write_hold_policy(tmp_path, name="new")
    d = json.loads(new.read_text())
    d["created_utc"] = "2030-01-01T00:00:00+00:00"
    new.write_text(json.dumps(d))
    os.utime(old, (1, 1))
    assert default_policy_path([tmp_path]) == new
    with pytest.raises(ValueError, match="no policy JSON"):
        default_policy_path([tmp_path / "empty"])
    # a stray JSON with no usable legs list is passed over, not a TypeError for every leg
    stray = json.loads(old.read_text())
    stray.update(legs=None, created_utc="2031-01-01T00:00:00+00:00")
    (tmp_path / "stray.json").write_text(json.dumps(stray))
    assert default_policy_path([tmp_path], leg="FL") == new
    (tmp_path / "new.onnx").unlink()
    with pytest.raises(ValueError, match="not found"):
        PolicyRunner(PolicyMeta.load(new))


def test_observation_from_metadata_terms(policy_json):
    """The vector follows the metadata: order, offsets, scales, zero-source terms."""
    meta = PolicyMeta.load(policy_json)
    rng = np.random.default_rng(1)
    q = meta.default_pose + rng.normal(0, 0.1, 12)
    dq = rng.normal(0, 1, 12)
    gyro = np.array([0.1, -0.2, 0.3])
    quat = np.array([np.cos(0.1), np.sin(0.1), 0, 0])
    prev = rng.normal(0, 1, 12)
    obs = build_observation(meta.observation, {
        "base_ang_vel": gyro, "projected_gravity": projected_gravity(quat), "joint_pos": q,
        "joint_vel": dq, "previous_actions": prev, "commands": np.zeros(3),
        "lift_command": meta.lift_value("RL")})
    terms = {t["name"]: t for t in meta.observation["terms"]}
    np.testing.assert_allclose(obs[0:3], 0.0)  # base_lin_vel source "zero"
    np.testing.assert_allclose(obs[3:6], gyro * terms["base_ang_vel"]["scale"], rtol=1e-6)
    np.testing.assert_allclose(obs[6:9], [0, -np.sin(0.2), -np.cos(0.2)], atol=1e-6)
    np.testing.assert_allclose(obs[9:21], q - meta.default_pose, atol=1e-6)
    np.testing.assert_allclose(obs[21:33], dq * terms["joint_vel"]["scale"], rtol=1e-5)
    np.testing.assert_allclose(obs[33:45], prev, rtol=1e-6)
    assert obs[48] == pytest.approx(3.0 * terms["lift_command"]["scale"])


def test_the_latency_a_policy_was_trained_under(policy_json, tmp_path):
    """From its training's latency_steps and physics step; None where the JSON has none."""
    assert PolicyMeta.load(policy_json).trained_latency_s is None
    d = json.loads(policy_json.read_text())
    d["train_config"] = {"env": {"physics_dt": 0.005, "dr": {"enabled": True,
                                                            "latency_steps": [0, 4]}}}
    p = tmp_path / "lat.json"
    p.write_text(json.dumps(d))
    assert PolicyMeta.load(p).trained_latency_s == pytest.approx((0.0, 0.02))
    d["train_config"]["env"]["dr"]["enabled"] = False
    p.write_text(json.dumps(d))
    assert PolicyMeta.load(p).trained_latency_s is None


def _with(path, **changes):
    d = json.loads(path.read_text())
    d.update(changes)
    path.write_text(json.dumps(d))
    return path


def test_each_leg_gets_the_newest_policy_that_serves_it(tmp_path):
    front = _with(write_hold_policy(tmp_path, name="all4"), created_utc="2030-01-01T00:00:00")
    rear = _with(write_hold_policy(tmp_path, name="rear"), created_utc="2031-01-01T00:00:00",
                 legs=["RL", "RR"])
    assert PolicyMeta.load(rear).legs == ("RL", "RR")
    assert PolicyMeta.load(front).legs == ("FL", "FR", "RL", "RR")  # no list: all four
    assert default_policy_path([tmp_path]) == front  # a policy for all four legs
    assert default_policy_path([tmp_path], leg="RR") == rear
    got = policies_for_legs(["FL", "RR", "RL"], search=[tmp_path])
    assert got["FL"].path == front and got["RR"].path == got["RL"].path == rear
    assert got["RR"] is got["RL"]  # one object (and one runner in deploy) per file
    # --policy: one file for every leg, which must serve them all
    assert {m.path for m in policies_for_legs(["FL", "RR"], front).values()} == {front}
    with pytest.raises(ValueError, match="serves RL, RR, not FL"):
        policies_for_legs(["FL"], rear)


def test_policies_that_cannot_share_a_run_are_refused(tmp_path):
    write_hold_policy(tmp_path, name="all4")
    d = hold_policy_metadata()
    rear = write_hold_policy(tmp_path, name="rear")
    _with(rear, legs=["RR"], created_utc="2031-01-01T00:00:00",
          default_pose=[x + 0.1 for x in d["default_pose"]])
    with pytest.raises(ValueError, match="default_pose"):
        policies_for_legs(["FL", "RR"], search=[tmp_path])
