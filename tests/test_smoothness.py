"""The actor's observation-noise smoothness loss (policy_train/smoothness.py) and the noise
amplitude it draws from, against the environment's own observation noise."""

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from policy_train.config import EnvConfig
from policy_train.env import TripodEnv
from policy_train.smoothness import ObservationSmoothness, smoothness_loss


def test_noise_amplitude_is_the_envs_observation_noise():
    env = TripodEnv(EnvConfig(num_envs=64, plans_per_leg=1, seed=2, threads=1))
    amp = env.observation_noise_amplitude()
    assert amp.shape == (49,)
    draws = [env.observations() for _ in range(20)]  # 1 280 noisy and clean observations
    diff = np.concatenate([o["policy"] - o["critic"][:, :49] for o in draws])
    reach = np.abs(diff).max(0)
    assert np.all(reach <= amp + 1e-6)
    noisy = amp > 0
    assert noisy.sum() == 3 + 3 + 12 + 12  # gyro, gravity, joint positions and velocities
    assert np.all(reach[noisy] > 0.95 * amp[noisy])  # uniform over the whole half-width
    np.testing.assert_allclose(amp[3:6], 0.2 * 0.25)  # gyro +-0.2 rad/s at scale 0.25
    np.testing.assert_allclose(amp[21:33], 1.5 * 0.05)  # joint velocities +-1.5 rad/s
    env.cfg.dr.enabled = False
    assert not env.observation_noise_amplitude().any()


class _Linear(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(4, 2)

    def forward(self, td):
        return self.lin(td["policy"])


def test_the_loss_flattens_the_actor_along_the_noisy_inputs_only():
    torch.manual_seed(0)
    actor = _Linear()
    amp = torch.tensor([0.5, 0.0, 0.2, 0.0])
    obs = TensorDict({"policy": torch.randn(256, 4)}, batch_size=[256])
    w0 = actor.lin.weight.detach().clone()
    # a linear map moves by W delta: E|W delta|^2 = sum_j W_ij^2 amp_j^2 / 3 (uniform noise)
    expect = float((w0 ** 2 * amp ** 2 / 3).sum(1).mean())
    g = torch.Generator().manual_seed(1)
    est = np.mean([float(smoothness_loss(actor, obs, amp, generator=g).detach())
                   for _ in range(50)])
    assert est == pytest.approx(expect, rel=0.05)
    opt = torch.optim.SGD(actor.parameters(), lr=5.0)
    for _ in range(200):
        opt.zero_grad()
        smoothness_loss(actor, obs, amp, generator=g).backward()
        opt.step()
    w = actor.lin.weight.detach()
    assert torch.equal(w[:, [1, 3]], w0[:, [1, 3]])  # no noise there: untouched
    assert torch.all(w[:, [0, 2]].abs() < 0.1 * w0[:, [0, 2]].abs())


class _Mirror:
    use_data_augmentation = True
    use_mirror_loss = False

    def __init__(self):
        self.augmented = 0

    def augment_batch(self, batch, n):
        self.augmented += 1


def test_the_wrapper_keeps_the_mirror_augmentation_and_adds_its_loss():
    actor = _Linear()
    inner = _Mirror()
    s = ObservationSmoothness(inner, 2.0, np.array([0.5, 0.0, 0.2, 0.0]))
    assert s.use_data_augmentation and s.use_mirror_loss and s.mirror_loss_coeff == 1.0

    class Batch:
        observations = TensorDict({"policy": torch.randn(8, 4)}, batch_size=[8])

    s.augment_batch(Batch, 8)
    assert inner.augmented == 1
    loss = s.compute_loss(actor, Batch, 8)
    assert loss.requires_grad and float(loss) == pytest.approx(2.0 * s.take_mean())
    assert np.isnan(s.take_mean())  # taken: nothing since
    with pytest.raises(ValueError):
        ObservationSmoothness(None, -1.0, np.zeros(4))
