"""Seeded synthetic foot/IMU angular-velocity streams for testing and benchmarking the solver.

The truth follows the project conventions: ``omega_F = R_I^F @ omega_I`` and ``t_d = t_I - t_E``,
so an IMU sample stamped ``s`` measures ``R_F^I @ omega_F(s - t_d) + bias + noise`` with
``R_F^I = (R_I^F)^T``. Encoder-side angular velocity is the smooth truth (optionally noisy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

MOTIONS = ("rich", "planar", "single_axis")


@dataclass(frozen=True)
class MotionSpec:
    """A smooth foot angular velocity: per axis a sum of sines, ``amp * sin(2 pi f t + phase)``.

    ``freqs_hz``, ``amps`` (rad/s) and ``phases`` (rad) are (3, K). ``basis`` (3, 3) maps the three
    sine channels into the foot frame (identity for "rich"; rank 2 or 1 for degenerate motions).
    """

    freqs_hz: np.ndarray
    amps: np.ndarray
    phases: np.ndarray
    basis: np.ndarray

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Foot angular velocity (N, 3) in rad/s, foot frame, at times ``t`` (N,) in s."""
        t = np.asarray(t, dtype=float)
        arg = 2.0 * np.pi * self.freqs_hz[None, :, :] * t[:, None, None] + self.phases[None]
        channels = np.sum(self.amps[None] * np.sin(arg), axis=2)  # (N, 3)
        return channels @ self.basis.T


def make_motion(
    rng: np.random.Generator,
    motion: str = "rich",
    n_sines: int = 3,
    min_frequency: float = 0.3,
    max_frequency: float = 3.0,
    amplitude: float = 1.0,
) -> MotionSpec:
    """Random smooth motion: distinct frequencies on every axis in [min, max] Hz, amplitudes
    around ``amplitude`` rad/s. ``motion`` = "rich" (3 independent axes), "planar" (angular
    velocity confined to a plane) or "single_axis" (rotation about one fixed axis)."""
    if motion not in MOTIONS:
        raise ValueError(f"unknown motion {motion!r}: expected one of {', '.join(MOTIONS)}")
    # Distinct frequencies across all axes so that no two channels are coherent.
    freqs = rng.permutation(np.linspace(min_frequency, max_frequency, 3 * n_sines))
    freqs = freqs.reshape(3, n_sines) * rng.uniform(0.97, 1.03, size=(3, n_sines))
    amps = amplitude * rng.uniform(0.5, 1.5, size=(3, n_sines)) / np.sqrt(n_sines)
    phases = rng.uniform(0.0, 2.0 * np.pi, size=(3, n_sines))
    q = Rotation.random(random_state=rng).as_matrix()
    if motion == "rich":
        basis = np.eye(3)
    elif motion == "planar":
        basis = q @ np.diag([1.0, 1.0, 0.0])
    else:
        basis = q @ np.diag([1.0, 0.0, 0.0])
    return MotionSpec(freqs, amps, phases, basis)


def irregular_stamps(
    rng: np.random.Generator,
    rate_hz: float,
    t0: float,
    t1: float,
    irregularity: float = 0.1,
    drop_fraction: float = 0.0,
    gaps: tuple[tuple[float, float], ...] = (),
) -> np.ndarray:
    """True sample instants (s) between ``t0`` and ``t1`` at a nominal ``rate_hz`` whose period
    varies by +-``irregularity`` (relative, uniform); ``drop_fraction`` of samples removed at
    random and every sample inside the ``gaps`` (start, length) intervals removed."""
    period = 1.0 / rate_hz
    n = int(np.ceil((t1 - t0) * rate_hz)) + 2
    steps = period * (1.0 + irregularity * rng.uniform(-1.0, 1.0, size=n))
    t = t0 + np.concatenate([[0.0], np.cumsum(steps[:-1])])
    t = t[t <= t1]
    keep = rng.uniform(size=t.size) >= drop_fraction
    for start, length in gaps:
        keep &= ~((t >= start) & (t < start + length))
    return t[keep]


@dataclass
class SyntheticCase:
    """Two recorded streams plus their truth. Stamps in s, angular velocities in rad/s."""

    t_enc: np.ndarray
    omega_foot: np.ndarray
    t_imu: np.ndarray
    omega_imu: np.ndarray
    rotation: np.ndarray  # R_I^F (3, 3)
    time_offset: float  # t_d = t_I - t_E (s)
    bias: np.ndarray  # gyro bias (3,), IMU frame, rad/s
    motion: MotionSpec


def make_case(
    seed: int,
    duration: float = 16.0,
    enc_rate: float = 1000.0,
    imu_rate: float = 400.0,
    rotation: np.ndarray | None = None,
    time_offset: float = 0.0,
    bias: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    noise_density: float = 1e-3,
    enc_noise_std: float = 0.0,
    jitter_s: float = 0.0,
    drop_fraction: float = 0.0,
    irregularity: float = 0.1,
    enc_gaps: tuple[tuple[float, float], ...] = (),
    imu_gaps: tuple[tuple[float, float], ...] = (),
    motion: str | MotionSpec = "rich",
    max_frequency: float = 3.0,
    amplitude: float = 1.0,
) -> SyntheticCase:
    """One seeded calibration recording.

    ``noise_density`` is the gyro white noise in rad/s/sqrt(Hz) (per-sample std =
    ``noise_density * sqrt(imu_rate)``); ``enc_noise_std`` the per-sample std (rad/s) added to
    the encoder-side angular velocity; ``jitter_s`` the std (s) of Gaussian timestamp jitter on
    both streams (stamps, not the sampling instants, are perturbed). ``rotation`` is R_I^F (a
    random rotation if None). Both streams cover ``[0, duration]`` of the encoder clock.
    """
    rng = np.random.default_rng(seed)
    spec = motion if isinstance(motion, MotionSpec) else make_motion(
        rng, motion, max_frequency=max_frequency, amplitude=amplitude
    )
    R = Rotation.random(random_state=rng).as_matrix() if rotation is None else np.asarray(rotation)
    b = np.asarray(bias, dtype=float)

    te_true = irregular_stamps(rng, enc_rate, 0.0, duration, irregularity, drop_fraction, enc_gaps)
    w_foot = spec(te_true) + enc_noise_std * rng.standard_normal((te_true.size, 3))
    t_enc = te_true + jitter_s * rng.standard_normal(te_true.size)

    # IMU stamps live on the IMU clock: stamp s <-> encoder time s - t_d.
    ti_true = irregular_stamps(
        rng, imu_rate, time_offset, duration + time_offset, irregularity, drop_fraction, imu_gaps
    )
    sigma = noise_density * np.sqrt(imu_rate)
    w_imu = spec(ti_true - time_offset) @ R + b + sigma * rng.standard_normal((ti_true.size, 3))
    t_imu = ti_true + jitter_s * rng.standard_normal(ti_true.size)

    oe, oi = np.argsort(t_enc, kind="stable"), np.argsort(t_imu, kind="stable")
    return SyntheticCase(
        t_enc[oe], w_foot[oe], t_imu[oi], w_imu[oi], R, float(time_offset), b, spec
    )
