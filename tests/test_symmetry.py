"""policy_train.symmetry: the mirror of observations and actions is the mirror of the robot.

A state and its physical mirror image (base y, roll and yaw rates negated, legs swapped, hips
negated) must give mirrored observations; the same action, mirrored, must keep them mirrored
after a physics step; the mirror is an involution; rsl-rl's augmentation gets 2x the batch."""

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from calib.joints import MODEL_LEGS
from policy_train.config import EnvConfig, TrainConfig
from policy_train.env import LIFT_VALUES, TripodEnv
from policy_train.symmetry import joint_mirror, mirror_augmentation


def _mirror_state(qpos: np.ndarray, qvel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Physical mirror through the base x-z plane of MuJoCo (qpos, qvel), model leg order."""
    jidx, jsign = joint_mirror(MODEL_LEGS)
    p, v = qpos.copy(), qvel.copy()
    p[1] = -qpos[1]
    p[3:7] = qpos[3:7] * np.array([1.0, -1.0, 1.0, -1.0])  # reflect y: (w, -x, y, -z)
    p[7:19] = qpos[7:19][jidx] * jsign
    v[1] = -qvel[1]
    v[3:6] = qvel[3:6] * np.array([-1.0, 1.0, -1.0])
    v[6:18] = qvel[6:18][jidx] * jsign
    return p, v


@pytest.fixture(scope="module")
def env():
    cfg = EnvConfig(num_envs=2, plans_per_leg=1, threads=1, p_reference_start=0.0)
    cfg.dr.enabled = False
    return TripodEnv(cfg)


def _set_pair(env, rng):
    q = env.default_pose + rng.uniform(-0.15, 0.15, 12)
    qpos = np.concatenate([[0.1, 0.05, 0.30], [1.0, 0.0, 0.0, 0.0], q])
    ax = rng.normal(size=3)
    ang = 0.1
    qpos[3:7] = np.concatenate([[np.cos(ang / 2)], np.sin(ang / 2) * ax / np.linalg.norm(ax)])
    qvel = rng.normal(size=18) * 0.3
    mp, mv = _mirror_state(qpos, qvel)
    env.qpos[0], env.qvel[0] = qpos, qvel
    env.qpos[1], env.qvel[1] = mp, mv
    env.target[0] = q
    env.target[1] = mp[7:19]
    env.cmd_hist[:, :, 0] = env.target[:, None]
    env.ctrl[:] = env.target
    env.batch.forward(np.arange(2))
    env._compute_state()


def test_observation_mirror_is_the_robot_mirror(env):
    rng = np.random.default_rng(3)
    _set_pair(env, rng)
    env.lift_leg[:] = [MODEL_LEGS.index("FL"), MODEL_LEGS.index("FR")]
    env.commands[0] = [0.1, -0.2, 0.3]
    env.commands[1] = [-0.1, -0.2, -0.3]
    a = rng.normal(size=12)
    env.actions[0] = a
    _, mirrored_actions = mirror_augmentation(env, None, torch.from_numpy(a[None]))
    env.actions[1] = mirrored_actions[1].numpy()
    obs = env.observations()
    td = TensorDict({k: torch.from_numpy(v[:1]) for k, v in obs.items()}, batch_size=[1])
    aug, _ = mirror_augmentation(env, td, None)
    np.testing.assert_allclose(aug["policy"][1].numpy(), obs["policy"][1], atol=1e-5)
    # the critic: the clean policy part and the privileged terms
    np.testing.assert_allclose(aug["critic"][1].numpy(), obs["critic"][1], atol=1e-5)
    assert obs["policy"][0, -1] != obs["policy"][1, -1]  # FL and FR commands differ


def test_mirrored_actions_keep_the_states_mirrored(env):
    rng = np.random.default_rng(5)
    _set_pair(env, rng)
    env.lift_leg[:] = -1
    a = rng.normal(size=12) * 0.5
    _, acts = mirror_augmentation(env, None, torch.from_numpy(a[None]))
    for _ in range(3):
        env.step(acts.numpy())
    mp, _ = _mirror_state(env.qpos[0], env.qvel[0])
    # the Go2 model is symmetric up to the base's inertial offset (mm): physics agrees
    np.testing.assert_allclose(env.qpos[1, 7:19], mp[7:19], atol=5e-3)
    np.testing.assert_allclose(env.qpos[1, :3], mp[:3], atol=5e-3)


def test_mirror_is_an_involution_and_doubles_the_batch(env):
    rng = np.random.default_rng(7)
    n = 16
    pol = torch.from_numpy(rng.normal(size=(n, 49)).astype(np.float32))
    lift_scale = next(t["scale"] for t in env.obs_terms if t["name"] == "lift_command")
    lift_scale = float(np.ravel(lift_scale)[0])
    pol[:, -1] = torch.from_numpy(rng.integers(0, 5, n) * lift_scale).float()
    crit = torch.from_numpy(rng.normal(size=(n, env.observations()["critic"].shape[1])).astype(np.float32))
    crit[:, 48] = pol[:, -1]
    td = TensorDict({"policy": pol, "critic": crit}, batch_size=[n])
    act = torch.from_numpy(rng.normal(size=(n, 12)).astype(np.float32))
    o1, a1 = mirror_augmentation(env, td, act)
    assert o1.batch_size[0] == 2 * n and a1.shape == (2 * n, 12)
    o2, a2 = mirror_augmentation(env, o1[n:], a1[n:])
    for k in ("policy", "critic"):
        torch.testing.assert_close(o2[k][n:], td[k])
    torch.testing.assert_close(a2[n:], act)
    # lift commands: FL <-> FR, RL <-> RR, none stays none
    v = torch.round(o1["policy"][n:, -1] / lift_scale).long()
    swap = {0: 0, LIFT_VALUES["FL"]: LIFT_VALUES["FR"], LIFT_VALUES["FR"]: LIFT_VALUES["FL"],
            LIFT_VALUES["RL"]: LIFT_VALUES["RR"], LIFT_VALUES["RR"]: LIFT_VALUES["RL"]}
    orig = torch.round(pol[:, -1] / lift_scale).long()
    assert [swap[int(x)] for x in orig] == v.tolist()


def test_augmentation_follows_the_tensors_device(env):
    """The update may run on a GPU (a2i-train tripod --device cuda): the mirrors move to the
    device of what they mirror (here torch's meta device, which every machine has), and
    nothing to mirror gives nothing."""
    n = 4
    td = TensorDict({"policy": torch.zeros(n, 49), "critic": torch.zeros(
        n, env.observations()["critic"].shape[1])}, batch_size=[n])
    mirror_augmentation(env, td, torch.zeros(n, 12))  # the CPU's mirrors first
    o, a = mirror_augmentation(env, td.to("meta"), torch.zeros(n, 12, device="meta"))
    assert o["policy"].device.type == "meta" and a.device.type == "meta"
    assert o.batch_size[0] == 2 * n and a.shape == (2 * n, 12)
    assert mirror_augmentation(env, None, None) == (None, None)


def test_old_configs_train_without_mirror():
    d = TrainConfig().to_dict()
    del d["ppo"]["mirror_augmentation"]
    assert TrainConfig.from_dict(d).ppo.mirror_augmentation is False
    assert TrainConfig().ppo.mirror_augmentation is True


def test_mirror_of_a_history_mirrors_each_frame(env):
    """A history of frames (newest first) mirrors frame by frame, each frame's lift command
    by its own value; the mirrored-legs actor decides on the newest frame's command."""
    from policy_train.symmetry import Mirror, MirroredLegsActor, policy_terms

    terms, scale = policy_terms(env.obs_terms)
    one, three = Mirror(terms, scale), Mirror(terms, scale, frames=3)
    rng = np.random.default_rng(5)
    x = torch.from_numpy(rng.normal(size=(4, 3, 49)).astype(np.float32))
    x[:, :, 48] = torch.tensor([LIFT_VALUES["FL"], LIFT_VALUES["FL"], 0.0]) * scale
    got = three(x.reshape(4, 147)).reshape(4, 3, 49)
    for f in range(3):
        torch.testing.assert_close(got[:, f], one(x[:, f]))
    assert torch.all(got[:, 0, 48] == LIFT_VALUES["FR"] * scale) and torch.all(got[:, 2, 48] == 0)
    torch.manual_seed(0)
    net = torch.nn.Linear(147, 12)
    actor = MirroredLegsActor(net, env.obs_terms, {"FR": "FL"}, frames=3)
    fr = x.clone()
    fr[:, 0, 48] = LIFT_VALUES["FR"] * scale  # the newest frame names FR: mirrored
    torch.testing.assert_close(actor(fr.reshape(4, 147)),
                               actor.action_mirror(net(three(fr.reshape(4, 147)))))
    torch.testing.assert_close(actor(x.reshape(4, 147)), net(x.reshape(4, 147)))


def test_augmentation_of_a_history_env_mirrors_every_frame():
    """PPO's mirror augmentation on an env whose policy sees a history mirrors each frame of
    the policy's input and the critic's single frame."""
    from policy_train.symmetry import Mirror, policy_terms

    cfg = EnvConfig(num_envs=2, plans_per_leg=1, threads=1, p_reference_start=0.0,
                    obs_history=3)
    hist = TripodEnv(cfg)
    ob = hist.observations()
    td = TensorDict({k: torch.from_numpy(v) for k, v in ob.items()}, batch_size=[2])
    out, _ = mirror_augmentation(hist, td, None)
    terms, scale = policy_terms(hist.obs_terms)
    one = Mirror(terms, scale)
    got = out["policy"][2:].reshape(2, 3, 49)
    for f in range(3):
        torch.testing.assert_close(got[:, f], one(td["policy"].reshape(2, 3, 49)[:, f]))
    assert out["critic"].shape == (4, td["critic"].shape[1])
