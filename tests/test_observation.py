"""deploy.observation: the 49-dim layout, scaling/offsets/clip, batching, and that the training
env builds exactly what the on-board builder builds from the same signals."""

import numpy as np
import pytest

from calib.joints import default_crouch
from deploy.observation import (
    OBS_SIZE,
    TERM_NAMES,
    TERM_SIZES,
    build_observation,
    check_terms,
    default_terms,
    observe_lifted_leg,
    projected_gravity,
)


@pytest.fixture(scope="module")
def tiny_env():
    from policy_train.config import EnvConfig
    from policy_train.env import TripodEnv

    return TripodEnv(EnvConfig(num_envs=4, plans_per_leg=1, seed=3, threads=1))


def _signals(shape=(), seed=0):
    rng = np.random.default_rng(seed)
    return {n: rng.normal(size=shape + (TERM_SIZES[n],)) for n in TERM_NAMES}


def test_layout_is_the_papers_49():
    terms = default_terms(default_crouch("sdk"))
    assert [t["name"] for t in terms] == list(TERM_NAMES)
    assert [t["size"] for t in terms] == [3, 3, 3, 12, 12, 12, 3, 1]
    assert OBS_SIZE == 49


def test_values_scaled_offset_and_zero_source():
    dp = default_crouch("sdk")
    terms = default_terms(dp, "zero")
    sig = _signals()
    obs = build_observation(terms, sig)
    assert obs.dtype == np.float32 and obs.shape == (49,)
    np.testing.assert_array_equal(obs[0:3], 0.0)  # base_lin_vel zero-filled
    np.testing.assert_allclose(obs[3:6], 0.25 * sig["base_ang_vel"], rtol=1e-6)
    np.testing.assert_allclose(obs[9:21], sig["joint_pos"] - dp, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(obs[21:33], 0.05 * sig["joint_vel"], rtol=1e-5)
    np.testing.assert_allclose(obs[48], 0.25 * sig["lift_command"][0], rtol=1e-6)
    del sig["base_lin_vel"]  # a zero term needs no signal
    build_observation(terms, sig)
    measured = default_terms(dp, "leg_odometry")
    with pytest.raises(ValueError, match="base_lin_vel"):
        build_observation(measured, sig)


def test_batched_and_clip_and_metadata_object():
    terms = default_terms(np.zeros(12))
    sig = _signals((4, 5))
    sig["lift_command"] = np.full((4, 5), 3.0)  # scalar per env broadcasts to size 1
    obs = build_observation({"size": 49, "clip": 0.5, "terms": terms}, sig)
    assert obs.shape == (4, 5, 49)
    assert np.abs(obs).max() <= 0.5
    one = build_observation(terms, {k: v[2, 3] for k, v in sig.items()}, clip=0.5)
    np.testing.assert_allclose(obs[2, 3], one)


def test_bad_terms_raise():
    with pytest.raises(ValueError, match="unknown observation term"):
        check_terms([{"name": "foo", "size": 3}])
    with pytest.raises(ValueError, match="size"):
        check_terms([{"name": "joint_pos", "size": 3}])
    with pytest.raises(ValueError, match="end in size"):
        build_observation(default_terms(np.zeros(12)), {**_signals(), "joint_vel": np.zeros(11)})


def test_observe_lifted_leg_one_and_batched():
    """The lifted leg's 3 joints read ``seen`` of their excursion from the centre and ``seen``
    of their rates (0: still at the centre; 1: as measured); every other joint and signal is
    what was measured; the caller's arrays are not written."""
    from calib.joints import sdk_indices

    sig = _signals()
    before = {k: v.copy() for k, v in sig.items()}
    idx, c = sdk_indices("FL"), np.array([0.1, 0.8, -1.5])
    held = observe_lifted_leg(sig, idx, c, 0.0)
    np.testing.assert_array_equal(held["joint_pos"][idx], c)
    np.testing.assert_array_equal(held["joint_vel"][idx], 0.0)
    half = observe_lifted_leg(sig, idx, c, 0.5)
    np.testing.assert_allclose(half["joint_pos"][idx], (c + sig["joint_pos"][idx]) / 2)
    np.testing.assert_allclose(half["joint_vel"][idx], sig["joint_vel"][idx] / 2)
    whole = observe_lifted_leg(sig, idx, c, 1.0)
    np.testing.assert_allclose(whole["joint_pos"], sig["joint_pos"], rtol=1e-15)
    rest = np.setdiff1d(np.arange(12), idx)
    np.testing.assert_array_equal(half["joint_pos"][rest], sig["joint_pos"][rest])
    np.testing.assert_array_equal(half["joint_vel"][rest], sig["joint_vel"][rest])
    assert half["base_ang_vel"] is sig["base_ang_vel"]
    for k, v in before.items():
        np.testing.assert_array_equal(sig[k], v)
    batch = _signals((2,), seed=1)
    cols = np.stack([sdk_indices("FL"), sdk_indices("RR")])
    centre = np.array([[0.1, 0.8, -1.5], [-0.2, 0.9, -1.6]])
    out = observe_lifted_leg(batch, cols, centre, 0.3)
    for r in range(2):
        one = observe_lifted_leg({k: v[r] for k, v in batch.items()}, cols[r], centre[r], 0.3)
        np.testing.assert_allclose(out["joint_pos"][r], one["joint_pos"], rtol=1e-15)
        np.testing.assert_allclose(out["joint_vel"][r], one["joint_vel"], rtol=1e-15)


def test_env_scales_only_the_exciting_legs():
    """``EnvConfig.excitation_seen``: the env shows the policy each exciting env's lifted leg
    at that fraction of its excursion from its plan's ``q0`` (0 here: still at q0; SDK order,
    as deploy does); an env in another phase, or with no leg lifted, is observed as measured."""
    from calib.joints import MODEL_LEGS, sdk_indices
    from deploy.lift_schedule import PHASES
    from policy_train.config import EnvConfig
    from policy_train.env import TripodEnv

    env = TripodEnv(EnvConfig(num_envs=3, plans_per_leg=1, seed=5, threads=1))
    env.step(np.random.default_rng(2).normal(0, 0.3, (3, 12)))
    env.lift_leg[:] = [1, 3, -1]
    env.phase[:] = [PHASES.index("excite"), PHASES.index("hold"), PHASES.index("excite")]
    seen = env.signals(noise=False)
    env.cfg.excitation_seen = 0.0
    hidden = env.signals(noise=False)
    for k in ("joint_pos", "joint_vel"):
        np.testing.assert_array_equal(hidden[k][1:], seen[k][1:])
    idx = sdk_indices(MODEL_LEGS[1])
    np.testing.assert_array_equal(hidden["joint_pos"][0, idx], env.pool.q0[env.lift_plan[0]])
    np.testing.assert_array_equal(hidden["joint_vel"][0, idx], 0.0)
    rest = np.setdiff1d(np.arange(12), idx)
    np.testing.assert_array_equal(hidden["joint_pos"][0, rest], seen["joint_pos"][0, rest])
    assert not np.array_equal(hidden["joint_vel"][0, idx], seen["joint_vel"][0, idx])
    critic = env.signals(noise=False, policy=False)  # the critic sees the leg as measured
    np.testing.assert_array_equal(critic["joint_pos"], seen["joint_pos"])
    obs = env.observations()
    np.testing.assert_array_equal(
        obs["critic"][:, :49], build_observation(env.obs_terms, critic, clip=env.cfg.obs_clip))
    assert not np.array_equal(obs["critic"][0, :49], build_observation(
        env.obs_terms, hidden, clip=env.cfg.obs_clip)[0])


def test_projected_gravity():
    np.testing.assert_allclose(projected_gravity([1, 0, 0, 0]), [0, 0, -1], atol=1e-12)
    a = 0.3  # pitch nose-down by a about y: gravity leans towards +x in the base frame
    g = projected_gravity([np.cos(a / 2), 0, np.sin(a / 2), 0])
    np.testing.assert_allclose(g, [np.sin(a), 0, -np.cos(a)], atol=1e-12)
    q = np.random.default_rng(1).normal(size=(6, 4))
    np.testing.assert_allclose(np.linalg.norm(projected_gravity(q), axis=1), 1.0)


def test_env_observation_equals_builder(tiny_env):
    env = tiny_env
    env.step(np.random.default_rng(0).normal(0, 0.3, (env.N, 12)))
    obs = env.observations()["critic"][:, :49]  # noise-free actor part of the critic input
    ref = build_observation(env.obs_terms, env.signals(noise=False), clip=env.cfg.obs_clip)
    np.testing.assert_array_equal(obs, ref)
    noisy = env.observations()["policy"]
    assert noisy.shape == (env.N, 49) and not np.array_equal(noisy, ref)


def test_history_fills_on_a_fresh_start_and_shifts_newest_first():
    from deploy.observation import ObservationHistory

    h = ObservationHistory(3, 2, (2,))
    np.testing.assert_array_equal(h.push([[1, 1], [2, 2]]), [[1, 1] * 3, [2, 2] * 3])
    np.testing.assert_array_equal(h.push([[3, 3], [4, 4]]), [[3, 3, 1, 1, 1, 1],
                                                             [4, 4, 2, 2, 2, 2]])
    h.reset(1)  # element 1 starts again: its next frame fills its history; 0 goes on
    np.testing.assert_array_equal(h.push([[5, 5], [6, 6]]), [[5, 5, 3, 3, 1, 1], [6] * 6])
    one = ObservationHistory(2, 2)  # on board: no batch
    one.push([1, 2])
    np.testing.assert_array_equal(one.push([3, 4]), [3, 4, 1, 2])
    with pytest.raises(ValueError, match="shape"):
        one.push([1, 2, 3])
    with pytest.raises(ValueError, match=">= 1"):
        ObservationHistory(0, 2)


def test_history_length_checks_the_size():
    from deploy.observation import history_length

    terms = default_terms(default_crouch("sdk"))
    assert history_length({"size": 49, "terms": terms}) == 1
    assert history_length({"size": 245, "history": 5, "terms": terms}) == 5
    for bad in ({"size": 49, "history": 5}, {"size": 245, "history": 0},
                {"size": 98, "history": 2.0}, {"size": 245, "history": True}):
        with pytest.raises(ValueError, match="history|frames"):
            history_length({**bad, "terms": terms})


def test_env_history_is_the_newest_frames():
    """With obs_history 3 the policy sees its last three noisy frames, newest first: frame k
    of a step is frame k - 1 of the step before; a reset episode starts with its first frame
    repeated."""
    from policy_train.config import EnvConfig
    from policy_train.env import TripodEnv

    env = TripodEnv(EnvConfig(num_envs=3, plans_per_leg=1, seed=4, threads=1, obs_history=3))
    assert env.num_obs == 147
    first = env.observations()["policy"].reshape(3, 3, 49)
    np.testing.assert_array_equal(first[:, 1], first[:, 0])
    np.testing.assert_array_equal(first[:, 2], first[:, 0])
    ob, *_ = env.step(np.zeros((3, 12)))
    frames = ob["policy"].reshape(3, 3, 49)
    np.testing.assert_array_equal(frames[:, 1:], first[:, :2])
    assert not np.array_equal(frames[:, 0], frames[:, 1])  # new noise, new state
    env.reset_idx(np.array([1]))
    env._compute_state()
    again = env.observations()["policy"].reshape(3, 3, 49)
    np.testing.assert_array_equal(again[1, 1:], again[1, :1].repeat(2, 0))
    np.testing.assert_array_equal(again[0, 1:], frames[0, :2])
