"""Sensor models: joint encoders, the body IMU and foot IMUs, on arrays (batch) and streaming.

The truth comes from :class:`sim.go2.Go2Sim` (or anything else: these are plain numpy). Noise
is added here because MuJoCo does not apply sensor ``noise`` itself (FACTS.md).

Foot IMU conventions (ARCHITECTURE.md)
--------------------------------------
* Spatial: ``omega_F = R_I^F @ omega_I``; the IMU measures ``R_I^F.T @ omega_F`` (and the same
  rotation for the specific force; the IMU is taken to sit at the foot frame origin).
* Temporal: ``t_d = t_I - t_E``. The IMU samples the motion at true times
  ``tau_k = t0 + phase + k / rate`` (its own clock, uniform) and stamps sample k with
  ``tau_k + time_offset + jitter_k``. Encoders are stamped with true time.
* Noise densities follow the continuous-time convention (Kalibr, IMU datasheets): white noise of
  density ``sigma_c`` (unit/sqrt(Hz)) has per-sample std ``sigma_c * sqrt(rate)``; a bias random
  walk of density ``sigma_b`` (unit/s/sqrt(Hz)) moves the bias by ``sigma_b * sqrt(1/rate)`` std
  per sample, so its variance grows as ``sigma_b**2 * t``.
* Random numbers: per sample k, 14 standard normals in a fixed order (jitter, gyro noise 3,
  accel noise 3, gyro bias step 3, accel bias step 3, dropout), so the batch and the streaming
  paths give identical samples for the same config and truth.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import ndtr

__all__ = [
    "PAPER_GYRO_NOISE_DEG",
    "BodyImuModel",
    "EncoderModel",
    "FootImuConfig",
    "FootImuModel",
    "ImuBatch",
    "ImuSample",
    "deg_density_to_rad",
    "rad_density_to_deg",
    "random_mounting",
    "white_noise_std",
]

PAPER_GYRO_NOISE_DEG: tuple[float, ...] = (0.006, 0.03, 0.06)
"""Foot-gyro noise densities of the A2I-Calib simulation study, deg/s/sqrt(Hz)."""

_N_DRAWS = 14  # standard normals per IMU sample (see the module docstring)


def deg_density_to_rad(x):
    """deg/s/sqrt(Hz) -> rad/s/sqrt(Hz) (also for deg/s^2/sqrt(Hz) -> rad/s^2/sqrt(Hz))."""
    return np.deg2rad(x)


def rad_density_to_deg(x):
    """rad/s/sqrt(Hz) -> deg/s/sqrt(Hz)."""
    return np.rad2deg(x)


def white_noise_std(density: float, rate: float) -> float:
    """Per-sample standard deviation of white noise with ``density`` (unit/sqrt(Hz)) sampled at
    ``rate`` (Hz): ``density * sqrt(rate)``."""
    if rate <= 0:
        raise ValueError(f"rate must be > 0 Hz, got {rate!r}")
    return float(density) * float(np.sqrt(rate))


def _nonneg(x, name: str) -> float:
    v = float(x)
    if not (np.isfinite(v) and v >= 0.0):
        raise ValueError(f"{name} must be finite and >= 0, got {x!r}")
    return v


def _vec3(x, name: str) -> np.ndarray:
    # the streaming update calls this twice per physics step and foot on the mock: the common
    # (3,) case skips broadcast_to, whose Python layers cost more than the copy
    a = np.array(x, dtype=float)
    if a.shape != (3,):
        try:
            a = np.broadcast_to(a, (3,)).copy()
        except ValueError:
            raise ValueError(f"{name} must have shape (3,) or be a scalar, got {np.shape(x)}"
                             ) from None
    if not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite")
    return a


# ---------------------------------------------------------------------------- encoders
@dataclass
class EncoderModel:
    """Joint encoder readings from true joint positions / velocities.

    resolution: position quantisation step, rad. Default 2*pi/2**15 = 1.92e-4 rad, a 15-bit
    single-turn count at the joint. The Go2's motor encoder sits on the rotor before the 6.33:1
    gear, so the real step is finer; this default is deliberately conservative. 0 disables quantisation. q_noise_std (rad) is added before quantisation (as
    analog noise would be); dq_noise_std (rad/s) is added to the velocity. seed: numpy seed.
    """

    resolution: float = 2.0 * np.pi / 2**15
    q_noise_std: float = 0.0
    dq_noise_std: float = 0.0
    seed: int | None = 0
    _rng: np.random.Generator = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.resolution = _nonneg(self.resolution, "resolution")
        self.q_noise_std = _nonneg(self.q_noise_std, "q_noise_std")
        self.dq_noise_std = _nonneg(self.dq_noise_std, "dq_noise_std")
        self._rng = np.random.default_rng(self.seed)

    def measure(self, q, dq) -> tuple[np.ndarray, np.ndarray]:
        """(q_meas, dq_meas) for true ``q`` (rad) and ``dq`` (rad/s) of any matching shape."""
        qa = np.asarray(q, dtype=float)
        dqa = np.asarray(dq, dtype=float)
        if qa.shape != dqa.shape:
            raise ValueError(f"q and dq shapes differ: {qa.shape} vs {dqa.shape}")
        if self.q_noise_std > 0:
            qa = qa + self._rng.normal(0.0, self.q_noise_std, qa.shape)
        if self.resolution > 0:
            qa = np.round(qa / self.resolution) * self.resolution
        else:
            qa = qa.copy()
        if self.dq_noise_std > 0:
            dqa = dqa + self._rng.normal(0.0, self.dq_noise_std, dqa.shape)
        else:
            dqa = dqa.copy()
        return qa, dqa


# ---------------------------------------------------------------------------- body IMU
@dataclass
class BodyImuModel:
    """The body IMU: white noise and a constant bias on the gyro and the accelerometer.

    gyro_noise_density rad/s/sqrt(Hz), accel_noise_density m/s^2/sqrt(Hz), rate Hz (the rate at
    which :meth:`measure` is called: it sets the per-sample std), gyro_bias rad/s (3,),
    accel_bias m/s^2 (3,), seed.
    """

    gyro_noise_density: float = 0.0
    accel_noise_density: float = 0.0
    rate: float = 500.0
    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    seed: int | None = 0
    _rng: np.random.Generator = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.gyro_noise_density = _nonneg(self.gyro_noise_density, "gyro_noise_density")
        self.accel_noise_density = _nonneg(self.accel_noise_density, "accel_noise_density")
        if not (np.isfinite(self.rate) and self.rate > 0):
            raise ValueError(f"rate must be > 0 Hz, got {self.rate!r}")
        self.gyro_bias = _vec3(self.gyro_bias, "gyro_bias")
        self.accel_bias = _vec3(self.accel_bias, "accel_bias")
        self._rng = np.random.default_rng(self.seed)

    def measure(self, gyro, accel) -> tuple[np.ndarray, np.ndarray]:
        """(gyro_meas, accel_meas) for true body-frame angular velocity (rad/s) and specific
        force (m/s^2), each (..., 3)."""
        g = np.asarray(gyro, dtype=float)
        a = np.asarray(accel, dtype=float)
        if g.shape[-1:] != (3,) or a.shape != g.shape:
            raise ValueError(f"gyro and accel must both be (..., 3), got {g.shape}, {a.shape}")
        sg = white_noise_std(self.gyro_noise_density, self.rate)
        sa = white_noise_std(self.accel_noise_density, self.rate)
        g = g + self.gyro_bias + (self._rng.normal(0.0, sg, g.shape) if sg > 0 else 0.0)
        a = a + self.accel_bias + (self._rng.normal(0.0, sa, a.shape) if sa > 0 else 0.0)
        return g, a


# ---------------------------------------------------------------------------- foot IMU
@dataclass
class FootImuConfig:
    """A foot IMU: mounting, clock, noise (units in the field comments; module docstring)."""

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    """R_I^F (3, 3): maps IMU-frame vectors into the foot frame."""
    time_offset: float = 0.0
    """t_d = t_I - t_E, s."""
    rate: float = 200.0
    """Sample rate, Hz."""
    phase: float = 0.0
    """First sample at the first truth time + phase, s (0 <= phase < 1/rate)."""
    gyro_noise_density: float = 0.0
    """rad/s/sqrt(Hz)."""
    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Initial gyro bias, rad/s (3,)."""
    gyro_bias_random_walk: float = 0.0
    """rad/s^2/sqrt(Hz)."""
    accel_noise_density: float = 0.0
    """m/s^2/sqrt(Hz)."""
    accel_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Initial accelerometer bias, m/s^2 (3,)."""
    accel_bias_random_walk: float = 0.0
    """m/s^3/sqrt(Hz)."""
    jitter_std: float = 0.0
    """Timestamp jitter, s (the stamp moves; the sampled instant does not)."""
    dropout_prob: float = 0.0
    """Probability that a sample is lost (its sequence number is skipped)."""
    seed: int | None = 0

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=float)
        if r.shape != (3, 3) or not np.all(np.isfinite(r)):
            raise ValueError(f"rotation must be a finite (3, 3) matrix, got shape {r.shape}")
        if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            raise ValueError("rotation must be a proper rotation matrix (R^T R = I, det +1)")
        self.rotation = r
        if not np.isfinite(self.time_offset):
            raise ValueError("time_offset must be finite")
        self.time_offset = float(self.time_offset)
        if not (np.isfinite(self.rate) and self.rate > 0):
            raise ValueError(f"rate must be > 0 Hz, got {self.rate!r}")
        self.rate = float(self.rate)
        if not (0.0 <= self.phase < 1.0 / self.rate):
            raise ValueError(f"phase must be in [0, 1/rate), got {self.phase!r}")
        for name in ("gyro_noise_density", "gyro_bias_random_walk", "accel_noise_density",
                     "accel_bias_random_walk", "jitter_std"):
            setattr(self, name, _nonneg(getattr(self, name), name))
        self.gyro_bias = _vec3(self.gyro_bias, "gyro_bias")
        self.accel_bias = _vec3(self.accel_bias, "accel_bias")
        if not (0.0 <= self.dropout_prob < 1.0):
            raise ValueError(f"dropout_prob must be in [0, 1), got {self.dropout_prob!r}")

    @property
    def gyro_noise_std(self) -> float:
        """Per-sample gyro white-noise std, rad/s."""
        return white_noise_std(self.gyro_noise_density, self.rate)

    @property
    def accel_noise_std(self) -> float:
        """Per-sample accelerometer white-noise std, m/s^2."""
        return white_noise_std(self.accel_noise_density, self.rate)


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One foot-IMU sample: seq (int, +1 per sample, gaps = losses), stamp (s, IMU clock mapped
    to encoder time, includes t_d and jitter), gyro (rad/s, IMU frame), accel (m/s^2, IMU
    frame), true_time (s, the instant the sample describes; for tests and benches)."""

    seq: int
    stamp: float
    gyro: np.ndarray
    accel: np.ndarray
    true_time: float


class ImuBatch(NamedTuple):
    """Samples as arrays: stamps (K,) s, gyro (K, 3) rad/s, accel (K, 3) m/s^2, seq (K,) int,
    true_time (K,) s. Unpacks as ``stamps, gyro, accel, seq, true_time``."""

    stamps: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    seq: np.ndarray
    true_time: np.ndarray


def _interp_rows(t_query: np.ndarray, t: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(t_query, t, x[:, j]) for j in range(x.shape[1])], axis=1)


class FootImuModel:
    """A foot IMU sampling the foot's true motion (see the module docstring for conventions).

    Batch: :meth:`sample` turns a high-rate truth into samples, always from the config's initial
    state (same config, same output). Streaming: :meth:`update` is fed the truth as sim time
    passes and returns the samples due; it starts over at :meth:`reset`. Both give identical
    samples for the same truth (up to the interpolation of that truth).
    """

    def __init__(self, config: FootImuConfig) -> None:
        if not isinstance(config, FootImuConfig):
            raise TypeError("FootImuModel needs a FootImuConfig")
        self.config = config
        self._rt = config.rotation.T  # R_F^I: foot-frame vectors into the IMU frame
        self.reset()

    # -- shared per-sample process
    def _fresh_process(self):
        c = self.config
        return (np.random.default_rng(c.seed), c.gyro_bias.copy(), c.accel_bias.copy())

    def _draw_params(self):
        c = self.config
        dt = 1.0 / c.rate
        return (c.jitter_std, c.gyro_noise_std, c.accel_noise_std,
                c.gyro_bias_random_walk * np.sqrt(dt), c.accel_bias_random_walk * np.sqrt(dt))

    def reset(self) -> None:
        """Forget the streaming state: the next :meth:`update` is the first."""
        self._rng, self._bg, self._ba = self._fresh_process()
        self._k = 0
        self._t0: float | None = None
        self._last: tuple[float, np.ndarray, np.ndarray] | None = None

    def sample_times(self, t_start: float, t_end: float) -> np.ndarray:
        """True sample instants tau_k = t_start + phase + k/rate within [t_start, t_end], s."""
        c = self.config
        first = t_start + c.phase
        if t_end < first:
            return np.zeros(0)
        n = int(np.floor((t_end - first) * c.rate + 1e-9)) + 1
        return first + np.arange(n) / c.rate

    def sample(self, t, omega_foot=None, specific_force_foot=None) -> ImuBatch:
        """Samples from a truth, from the config's initial state (bias, seed).

        Either arrays: ``t`` (N,) increasing true times (s), ``omega_foot`` (N, 3) rad/s and
        ``specific_force_foot`` (N, 3) m/s^2 (None = zeros), both in the foot frame, linearly
        interpolated at the sample instants within [t[0], t[-1]]; or ``t`` = (t_start, t_end)
        and ``omega_foot`` a callable ``tau (K,) -> (omega (K, 3), specific_force (K, 3))``.
        """
        if callable(omega_foot):
            try:
                t_start, t_end = (float(v) for v in t)
            except (TypeError, ValueError):
                raise ValueError("with a truth function, t must be (t_start, t_end)") from None
            tau = self.sample_times(t_start, t_end)
            om, sf = omega_foot(tau)
            om = np.asarray(om, dtype=float).reshape(len(tau), 3)
            sf = np.asarray(sf, dtype=float).reshape(len(tau), 3)
        else:
            ta = np.asarray(t, dtype=float)
            if ta.ndim != 1 or ta.size < 2 or np.any(np.diff(ta) <= 0):
                raise ValueError("t must be a strictly increasing (N,) array, N >= 2")
            om_in = np.asarray(omega_foot, dtype=float)
            if om_in.shape != (ta.size, 3):
                raise ValueError(f"omega_foot must be ({ta.size}, 3), got {om_in.shape}")
            sf_in = (np.zeros_like(om_in) if specific_force_foot is None
                     else np.asarray(specific_force_foot, dtype=float))
            if sf_in.shape != om_in.shape:
                raise ValueError(f"specific_force_foot must be ({ta.size}, 3), got {sf_in.shape}")
            tau = self.sample_times(ta[0], ta[-1])
            om = _interp_rows(tau, ta, om_in)
            sf = _interp_rows(tau, ta, sf_in)
        return self._measure_batch(tau, om, sf)

    def _measure_batch(self, tau, om, sf) -> ImuBatch:
        c = self.config
        rng, bg0, ba0 = self._fresh_process()
        k = len(tau)
        z = rng.standard_normal((k, _N_DRAWS))
        s_j, s_g, s_a, s_bg, s_ba = self._draw_params()
        # bias of sample k = initial + sum of the steps of samples 0..k-1
        bg = bg0 + np.vstack([np.zeros((1, 3)), np.cumsum(z[:-1, 7:10] * s_bg, axis=0)])[:k]
        ba = ba0 + np.vstack([np.zeros((1, 3)), np.cumsum(z[:-1, 10:13] * s_ba, axis=0)])[:k]
        gyro = om @ self._rt.T + bg + z[:, 1:4] * s_g
        accel = sf @ self._rt.T + ba + z[:, 4:7] * s_a
        stamps = tau + c.time_offset + z[:, 0] * s_j
        keep = ndtr(z[:, 13]) >= c.dropout_prob
        seq = np.arange(k)
        return ImuBatch(stamps[keep], gyro[keep], accel[keep], seq[keep], tau[keep])

    def update(self, t: float, omega_foot, specific_force_foot=None) -> list[ImuSample]:
        """Feed the truth at sim time ``t`` (s; increasing): foot-frame angular velocity (3,)
        rad/s and specific force (3,) m/s^2 (None = zeros). Returns the samples whose instants
        fell in (previous t, t], interpolating linearly between the two truths; the first call
        fixes the sampling grid at t + phase.
        """
        t = float(t)
        om = _vec3(omega_foot, "omega_foot")
        sf = np.zeros(3) if specific_force_foot is None else _vec3(
            specific_force_foot, "specific_force_foot")
        c = self.config
        if self._t0 is None:
            self._t0 = t + c.phase
            self._last = (t, om, sf)
        t_prev, om_prev, sf_prev = self._last
        if t < t_prev:
            raise ValueError(f"time went backwards: {t} < {t_prev}")
        out: list[ImuSample] = []
        draws = None
        while True:
            tau = self._t0 + self._k / c.rate
            if tau > t + 1e-9:
                break
            if draws is None:
                s_j, s_g, s_a, s_bg, s_ba = draws = self._draw_params()
            if t > t_prev:
                w = (tau - t_prev) / (t - t_prev)
                om_k = om_prev + w * (om - om_prev)
                sf_k = sf_prev + w * (sf - sf_prev)
            else:
                om_k, sf_k = om, sf
            z = self._rng.standard_normal(_N_DRAWS)
            if ndtr(z[13]) >= c.dropout_prob:
                out.append(ImuSample(
                    seq=self._k,
                    stamp=tau + c.time_offset + z[0] * s_j,
                    gyro=self._rt @ om_k + self._bg + z[1:4] * s_g,
                    accel=self._rt @ sf_k + self._ba + z[4:7] * s_a,
                    true_time=tau,
                ))
            self._bg = self._bg + z[7:10] * s_bg
            self._ba = self._ba + z[10:13] * s_ba
            self._k += 1
        self._last = (t, om, sf)
        return out

    @staticmethod
    def to_batch(samples: list[ImuSample]) -> ImuBatch:
        """Stack streamed samples into an :class:`ImuBatch`."""
        if not samples:
            z = np.zeros(0)
            return ImuBatch(z, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=int), z)
        return ImuBatch(
            np.array([s.stamp for s in samples]),
            np.stack([s.gyro for s in samples]),
            np.stack([s.accel for s in samples]),
            np.array([s.seq for s in samples]),
            np.array([s.true_time for s in samples]),
        )


def random_mounting(
    seed: int,
    max_offset: float = 0.2,
    gyro_noise_deg: float = PAPER_GYRO_NOISE_DEG[1],
    rate: float = 200.0,
    **overrides,
) -> FootImuConfig:
    """A foot IMU with a uniformly random mounting rotation and time offset in
    [-max_offset, max_offset] s, gyro noise ``gyro_noise_deg`` deg/s/sqrt(Hz) (default the paper's
    middle level), a typical low-cost accelerometer (0.002 m/s^2/sqrt(Hz)) and a random phase.
    ``overrides`` replace any :class:`FootImuConfig` field. For mocks and benches.
    """
    rng = np.random.default_rng(seed)
    rot = Rotation.random(random_state=rng).as_matrix()
    cfg = FootImuConfig(
        rotation=rot,
        time_offset=float(rng.uniform(-max_offset, max_offset)),
        rate=rate,
        phase=float(rng.uniform(0.0, 1.0 / rate)),
        gyro_noise_density=float(deg_density_to_rad(gyro_noise_deg)),
        accel_noise_density=0.002,
        seed=int(rng.integers(2**31)),
    )
    return dataclasses.replace(cfg, **overrides) if overrides else cfg
