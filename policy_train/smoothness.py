"""Observation-noise smoothness of the actor: an auxiliary PPO loss (the spatial term of CAPS,
Mysore et al., "Regularizing Action Policies for Smooth Control with Reinforcement Learning",
ICRA 2021).

The tripod policy is one 49-value frame with no history (paper Table II), and the Go2's gyro
and joint velocities are noisy. v7 answers the noise itself: measured over its held tripods
under the training randomisation, the noise alone moves its action mean by 0.35 RMS per joint
(the actions are clipped to +-1), a target jitter of 3.5 mrad per 20 ms step, and with the
noise held nominal its base angular rate halves and most failures go
(``docs/policy-training.md``). PPO sees that jitter only through the rewards; this loss asks
for it directly:

    L_smooth = coef * mean over samples and actions of (mu(o + delta) - mu(o))^2

with ``delta`` drawn from the training's own observation noise (uniform, half-width
:meth:`policy_train.env.TripodEnv.observation_noise_amplitude`), ``mu`` the actor's mean. It
is added to the PPO loss of every mini-batch, so one Adam step balances it against the
surrogate (a separate step would be scale-free under Adam, its coefficient meaningless).

It rides rsl-rl's hook for an auxiliary actor loss, the one its ``Symmetry`` extension uses
(``PPO.update`` adds ``mirror_loss_coeff * compute_loss(actor, batch, n)``): the wrapper
keeps the mirror augmentation when there is one and adds its own term.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["ObservationSmoothness", "smoothness_loss"]


def smoothness_loss(actor, obs: torch.Tensor, amplitude: torch.Tensor, key: str = "policy",
                    generator: torch.Generator | None = None) -> torch.Tensor:
    """Mean squared change of the actor's mean action when uniform noise of half-width
    ``amplitude`` (per observation element, observation units) is added to ``obs[key]``."""
    clean = obs.detach().clone()
    noisy = obs.detach().clone()
    x = noisy[key]
    delta = (2.0 * torch.rand(x.shape, generator=generator, dtype=x.dtype) - 1.0) * amplitude
    noisy[key] = x + delta
    return torch.mean((actor(noisy) - actor(clean)) ** 2)


class ObservationSmoothness:
    """Stands in for PPO's ``symmetry`` extension: augments batches as the wrapped one does (if
    any) and returns its mirror loss (if used) plus ``coef`` times :func:`smoothness_loss`.

    :meth:`take_mean`: the mean smoothness loss (before ``coef``) since the last call, for the
    log.
    """

    def __init__(self, inner, coef: float, amplitude: np.ndarray, seed: int = 0):
        if coef < 0:
            raise ValueError("the smoothness coefficient must be >= 0")
        self.inner = inner
        self.coef = float(coef)
        self.amplitude = torch.as_tensor(np.asarray(amplitude, dtype=np.float32))
        self.generator = torch.Generator().manual_seed(int(seed))
        self.use_mirror_loss = True  # PPO adds mirror_loss_coeff * compute_loss(...)
        self.mirror_loss_coeff = 1.0
        self.use_data_augmentation = bool(inner is not None and inner.use_data_augmentation)
        self._sum, self._count = 0.0, 0

    def augment_batch(self, batch, original_batch_size: int) -> None:
        if self.inner is not None:
            self.inner.augment_batch(batch, original_batch_size)

    def compute_loss(self, actor, batch, original_batch_size: int) -> torch.Tensor:
        obs = batch.observations[:original_batch_size]
        smooth = smoothness_loss(actor, obs, self.amplitude, generator=self.generator)
        self._sum += float(smooth.detach())
        self._count += 1
        loss = self.coef * smooth
        if self.inner is not None and self.inner.use_mirror_loss:
            loss = loss + self.inner.mirror_loss_coeff * self.inner.compute_loss(
                actor, batch, original_batch_size)
        return loss

    def take_mean(self) -> float:
        m = self._sum / self._count if self._count else float("nan")
        self._sum, self._count = 0.0, 0
        return m
