"""Calibration motions compared in the paper's Table I: walk, spin, naive wave, and A2I.

Each generator returns a :class:`Motion`: joint trajectories of all 12 joints in **model order**
(FL, FR, RL, RR x hip, thigh, calf; convert with ``calib.joints.model_to_sdk`` at interfaces)
and a **prescribed** base motion (orientation, angular velocity, position). A simulator drives
the base along it kinematically and the joints along ``q``/``dq``, so a foot IMU sees the base
rotation plus the leg motion, as on the robot. The leg motions are kinematic patterns (not
contact-consistent gaits): they reproduce the joint and base angular velocities that matter
for the calibration, not the forces.

Every motion starts and ends at rest in its nominal pose: the oscillating parts are scaled by a
C2 envelope rising over ``ramp`` seconds at the start and falling over the last ``ramp``.
Generators are deterministic for a given seed (the seed jitters amplitudes, frequency and
phases by a few percent). Units: s, rad, rad/s, m; ``base_quat_wxyz`` is the base orientation
in the world (w, x, y, z), ``base_omega`` the base angular velocity in the base frame,
``base_pos`` the base origin in the world (z up, ground at z = 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from calib.excitation import (
    FOOT_RADIUS,
    TRIPOD_LIFT_POSE_LEG,
    ExcitationPlan,
    foot_kappa,
    foot_omega,
    stance_foot_z,
)
from calib.joints import (
    LEGS,
    STAND_POSE_LEG,
    check_leg,
    full_pose,
    is_front,
    is_left,
    model_indices,
    pose_for_leg,
    position_limits,
)

# Stance legs of the tripod (left-leg signs, mirrored per leg): the stand pose. The tripod
# policy also shifts the body away from the lifted foot; for a still base that only adds a
# constant offset, which changes no angular velocity.
TRIPOD_STANCE_POSE_LEG = STAND_POSE_LEG.copy()
STAND_HEIGHT = float(-stance_foot_z() + FOOT_RADIUS)
"""Base height (m) over flat ground with the feet at STAND_POSE_LEG (hip axes at base height)."""


@dataclass
class Motion:
    """A whole-robot motion. t (N,) s; q, dq (N, 12) model order, rad, rad/s;
    base_quat_wxyz (N, 4) world, sign-continuous; base_omega (N, 3) rad/s in the base frame;
    base_pos (N, 3) m; steady_window (t0, t1) s: the part between the lead-in and lead-out."""

    name: str
    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    base_quat_wxyz: np.ndarray
    base_omega: np.ndarray
    base_pos: np.ndarray
    steady_window: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        n = np.asarray(self.t).shape[0] if np.ndim(self.t) == 1 else -1
        if n < 2:
            raise ValueError("t must be a 1-D array of at least 2 times (s)")
        shapes = {"q": 12, "dq": 12, "base_quat_wxyz": 4, "base_omega": 3, "base_pos": 3}
        for name, width in shapes.items():
            a = np.asarray(getattr(self, name), dtype=float)
            if a.shape != (n, width):
                raise ValueError(f"{name} must have shape ({n}, {width}), got {a.shape}")
            setattr(self, name, a)
        self.t = np.asarray(self.t, dtype=float)

    @property
    def rate(self) -> float:
        """Sample rate, Hz."""
        return float((len(self.t) - 1) / (self.t[-1] - self.t[0]))

    def leg(self, leg: str) -> tuple[np.ndarray, np.ndarray]:
        """(q, dq) of one leg, (N, 3) each, (hip, thigh, calf)."""
        idx = model_indices(leg)
        return self.q[:, idx], self.dq[:, idx]

    def relative_foot_omega(self, leg: str) -> np.ndarray:
        """Foot angular velocity relative to the base, foot (calf) frame, (N, 3) rad/s."""
        return foot_omega(*self.leg(leg))

    def kappa(self, leg: str, whole: bool = False) -> float:
        """kappa(Sigma_FF) of the relative foot angular velocity of ``leg`` (inf if singular),
        over the steady window (``whole=False`` and a window set) or over the whole motion."""
        q, dq = self.leg(leg)
        if not whole and self.steady_window is not None:
            t0, t1 = self.steady_window
            keep = (self.t >= t0 - 1e-9) & (self.t < t1 - 1e-9)
            q, dq = q[keep], dq[keep]
        return foot_kappa(q, dq)

    def limit_violation(self) -> float:
        """Largest excursion (rad) of any joint outside its position limits; 0 when inside."""
        worst = 0.0
        for leg in LEGS:
            lo, hi = position_limits(leg)
            q = self.q[:, model_indices(leg)]
            worst = max(worst, float(np.max(np.maximum(q - hi, 0) + np.maximum(lo - q, 0))))
        return worst


# --------------------------------------------------------------------------------------------
# helpers


def _times(duration: float, rate: float) -> np.ndarray:
    if not (np.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be positive (s), got {duration}")
    if not (np.isfinite(rate) and rate > 0):
        raise ValueError(f"rate must be positive (Hz), got {rate}")
    n = int(np.floor(duration * rate + 1e-9)) + 1
    if n < 2:
        raise ValueError("duration * rate gives fewer than 2 samples")
    return np.arange(n) / float(rate)


def _envelope(t: np.ndarray, duration: float, ramp: float):
    """C2 envelope e(t) (0 at both ends, 1 between ramps), its derivative and integral."""
    if not (np.isfinite(ramp) and ramp > 0 and 2 * ramp <= duration):
        raise ValueError(f"ramp must be positive and at most duration/2, got {ramp}")
    a = np.clip(t / ramp, 0, 1)
    b = np.clip((duration - t) / ramp, 0, 1)

    def s(x):
        return x**3 * (10 - 15 * x + 6 * x**2)

    def ds(x):
        return 30 * x**2 * (1 - x) ** 2

    def si(x):  # integral of s from 0 to x
        return 2.5 * x**4 - 3 * x**5 + x**6

    e = s(a) * s(b)  # the two ramps never overlap (2 ramp <= duration)
    de = ds(a) / ramp * s(b) - s(a) * ds(b) / ramp
    total = duration - ramp
    integ = np.where(t < duration / 2, ramp * si(a) + np.clip(t - ramp, 0, None),
                     total - ramp * si(b) - np.clip(duration - ramp - t, 0, None))
    return e, de, integ


def _euler_base(yaw, pitch, roll, dyaw, dpitch, droll):
    """Quaternion (w, x, y, z) of R = Rz(yaw) Ry(pitch) Rx(roll) and the body-frame rates."""
    quat = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], -1)).as_quat(scalar_first=True)
    # q and -q are the same rotation: keep consecutive samples in one hemisphere so that
    # consumers may interpolate component-wise
    flip = np.concatenate([[False], np.sum(quat[1:] * quat[:-1], axis=1) < 0])
    quat *= np.where(np.cumsum(flip) % 2 == 1, -1.0, 1.0)[:, None]
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    omega = np.stack([
        droll - dyaw * sp,
        dpitch * cr + dyaw * cp * sr,
        -dpitch * sr + dyaw * cp * cr,
    ], -1)
    return quat, omega


def _still_base(n: int):
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    pos = np.tile([0.0, 0.0, STAND_HEIGHT], (n, 1))
    return quat, np.zeros((n, 3)), pos


def tripod_pose(lifted_leg: str, lifted_pose: np.ndarray | None = None) -> np.ndarray:
    """12 joint angles (model order, rad): ``lifted_leg`` at ``lifted_pose`` (its own signs;
    None: the excitation's tripod lifted pose), the other legs at the tripod stance pose."""
    leg = check_leg(lifted_leg)
    d = {k: pose_for_leg(k, TRIPOD_STANCE_POSE_LEG) for k in LEGS}
    d[leg] = (pose_for_leg(leg, TRIPOD_LIFT_POSE_LEG) if lifted_pose is None
              else np.asarray(lifted_pose, dtype=float))
    return full_pose(d)


def _trot(t, duration, seed, ramp, step_hz, lift, fore_aft, hip_amp, hip_sign):
    """Joint trajectories of a trot: diagonal pairs (FL+RR, FR+RL) in antiphase.

    Per leg, gait phase phi = 2 pi step_hz t + offset; swing while sin(phi) > 0. Swing lift:
    thigh + 0.5 lift b, calf - lift b with b = max(sin phi, 0)^3 (C2), which raises the foot
    with little fore-aft motion. Fore-aft and hip parts: amp * sign * cos(phi), which moves the
    foot one way during stance and back during swing.
    """
    rng = np.random.default_rng(seed)
    e, de, _ = _envelope(t, duration, ramp)
    fstep = step_hz * (1 + rng.uniform(-0.05, 0.05))
    w = 2 * np.pi * fstep
    q = np.zeros((len(t), 12))
    dq = np.zeros_like(q)
    for leg in LEGS:
        off = 0.0 if leg in ("FL", "RR") else np.pi
        off += rng.uniform(-0.05, 0.05)
        k = rng.uniform(0.9, 1.1, size=3)
        phi = w * t + off
        sphi, cphi = np.sin(phi), np.cos(phi)
        b = np.maximum(sphi, 0) ** 3
        db = 3 * np.maximum(sphi, 0) ** 2 * cphi * w
        hs, xs = hip_sign(leg)
        osc = np.stack([
            k[2] * hip_amp * hs * cphi,
            0.5 * k[0] * lift * b + k[1] * fore_aft * xs * cphi,
            -k[0] * lift * b,
        ], -1)
        dosc = np.stack([
            -k[2] * hip_amp * hs * sphi * w,
            0.5 * k[0] * lift * db - k[1] * fore_aft * xs * sphi * w,
            -k[0] * lift * db,
        ], -1)
        idx = model_indices(leg)
        q[:, idx] = pose_for_leg(leg, STAND_POSE_LEG) + e[:, None] * osc
        dq[:, idx] = de[:, None] * osc + e[:, None] * dosc
    return q, dq, fstep, rng


def _oscillating_base(t, duration, ramp, fstep, rng, roll_amp, pitch_amp, bob, yaw_rate, speed):
    e, de, integ = _envelope(t, duration, ramp)
    w = 2 * np.pi * fstep
    pr, pp, pz = rng.uniform(0, 2 * np.pi, size=3)
    # trot: roll sways once per stride, pitch and height twice (each diagonal pair's support)
    roll = roll_amp * e * np.sin(w * t + pr)
    droll = roll_amp * (de * np.sin(w * t + pr) + e * w * np.cos(w * t + pr))
    pitch = pitch_amp * e * np.sin(2 * w * t + pp)
    dpitch = pitch_amp * (de * np.sin(2 * w * t + pp) + e * 2 * w * np.cos(2 * w * t + pp))
    yaw = yaw_rate * integ
    dyaw = yaw_rate * e
    quat, omega = _euler_base(yaw, pitch, roll, dyaw, dpitch, droll)
    # forward along the current heading: x' = v e cos(yaw), y' = v e sin(yaw)
    dt = np.diff(t)
    vx, vy = speed * e * np.cos(yaw), speed * e * np.sin(yaw)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (vx[1:] + vx[:-1]) * dt)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (vy[1:] + vy[:-1]) * dt)])
    z = STAND_HEIGHT + bob * e * np.sin(2 * w * t + pz)
    return quat, omega, np.stack([x, y, z], -1)


# --------------------------------------------------------------------------------------------
# generators


def walk_motion(duration: float = 20.0, rate: float = 200.0, seed: int = 0, *,
                speed: float = 0.2, step_hz: float = 2.0, ramp: float = 0.5) -> Motion:
    """Slow forward trot: diagonal pairs stepping at ~``step_hz`` Hz, swing lifts the foot with
    thigh and calf (hip nearly still, +-0.02 rad), base forward at ``speed`` m/s with the
    small roll (~0.02 rad) / pitch (~0.015 rad) / height (5 mm) oscillation of a trot."""
    t = _times(duration, rate)
    q, dq, fstep, rng = _trot(t, duration, seed, ramp, step_hz, lift=0.5, fore_aft=0.12,
                              hip_amp=0.02, hip_sign=lambda leg: (1.0, 1.0))
    quat, omega, pos = _oscillating_base(t, duration, ramp, fstep, rng, roll_amp=0.02,
                                         pitch_amp=0.015, bob=0.005, yaw_rate=0.0, speed=speed)
    return Motion("walk", t, q, dq, quat, omega, pos, (ramp, duration - ramp))


def spin_motion(duration: float = 20.0, rate: float = 200.0, seed: int = 0, *,
                yaw_rate: float = 0.5, step_hz: float = 2.0, ramp: float = 0.5) -> Motion:
    """Turning in place at ``yaw_rate`` rad/s (positive: counter-clockwise seen from above):
    trot stepping; during stance each foot slides, relative to the body, along the circle
    about the body centre, i.e. the hip abducts/adducts (front and rear in opposite senses)
    and the thigh moves the left feet forward, the right feet backward."""
    t = _times(duration, rate)
    # stance displacement of a foot ~ yaw_rate * half stride * lever (~0.24 m): hip ~0.06 rad
    amp = 0.12 * abs(yaw_rate)
    sgn = np.sign(yaw_rate) if yaw_rate != 0 else 1.0

    def signs(leg):
        # For CCW yaw, a world-fixed foot moves relative to the body with velocity w (r_y, -r_x):
        # front feet move inward-left/right (hips decrease in the URDF sign), rear hips increase;
        # left feet move forward (thigh decreases), right feet backward.
        return (sgn * (-1.0 if is_front(leg) else 1.0), sgn * (-1.0 if is_left(leg) else 1.0))

    q, dq, fstep, rng = _trot(t, duration, seed, ramp, step_hz, lift=0.5,
                              fore_aft=amp * 0.7, hip_amp=amp, hip_sign=signs)
    quat, omega, pos = _oscillating_base(t, duration, ramp, fstep, rng, roll_amp=0.015,
                                         pitch_amp=0.01, bob=0.004, yaw_rate=yaw_rate, speed=0.0)
    return Motion("spin", t, q, dq, quat, omega, pos, (ramp, duration - ramp))


def wave_motion(leg: str, duration: float = 20.0, rate: float = 200.0, seed: int = 0, *,
                freq_hz: float = 0.5, hip_amp: float = 0.3, thigh_amp: float = 0.35,
                calf_amp: float = 0.3, ramp: float = 1.0) -> Motion:
    """The paper's naive single-foot waving: the lifted ``leg`` swings thigh and calf in phase
    and the hip a quarter period ahead, at one frequency, around the tripod lifted pose
    (amplitudes in rad); the other legs hold the tripod stance; the base is still.

    The paper gives no amplitudes, only the wave's CN: 23-75 over its legs and noise levels.
    Thigh and calf alone turn the foot about one axis (kappa unbounded, 1e8 in a simulation: a
    baseline no one would wave); the hip's 0.3 rad puts kappa at 48-56, inside the paper's range.
    The foot goes up and down and, less, out and in: nothing is chosen to fill the third axis."""
    leg = check_leg(leg)
    t = _times(duration, rate)
    rng = np.random.default_rng(seed)
    e, de, _ = _envelope(t, duration, ramp)
    w = 2 * np.pi * freq_hz * (1 + rng.uniform(-0.05, 0.05))
    ph = rng.uniform(0, 2 * np.pi)
    amp = np.array([hip_amp * (1 if is_left(leg) else -1), thigh_amp, calf_amp])
    amp *= rng.uniform(0.95, 1.05)
    # the hip a quarter period ahead (the foot goes round a loop): in phase with the thigh the
    # foot's rates about x and y are proportional and kappa stays in the thousands
    phase = w * t[:, None] + ph + np.array([np.pi / 2, 0.0, 0.0])
    osc = amp * np.sin(phase)
    dosc = amp * w * np.cos(phase)
    q = np.tile(tripod_pose(leg), (len(t), 1))
    dq = np.zeros_like(q)
    idx = model_indices(leg)
    q[:, idx] += e[:, None] * osc
    dq[:, idx] = de[:, None] * osc + e[:, None] * dosc
    return Motion(f"wave_{leg}", t, q, dq, *_still_base(len(t)), (ramp, duration - ramp))


def a2i_motion(plan: ExcitationPlan, rate: float = 200.0) -> Motion:
    """The optimised excitation of ``plan.leg`` (its whole duration, ramps included), the other
    legs holding the tripod stance, the base still."""
    t, ql, dql = plan.sample(rate)
    q = np.tile(tripod_pose(plan.leg, plan.q0), (len(t), 1))
    dq = np.zeros_like(q)
    idx = model_indices(plan.leg)
    q[:, idx] = ql
    dq[:, idx] = dql
    return Motion(f"a2i_{plan.leg}", t, q, dq, *_still_base(len(t)), plan.steady_window)


def baseline_motions(leg: str, duration: float = 20.0, rate: float = 200.0,
                     seed: int = 0) -> dict[str, Motion]:
    """walk, spin and wave (for ``leg``) with one duration, rate and seed."""
    return {
        "walk": walk_motion(duration, rate, seed),
        "spin": spin_motion(duration, rate, seed),
        "wave": wave_motion(leg, duration, rate, seed),
    }
