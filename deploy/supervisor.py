"""The safety supervisor: checks every tick's state and command; any fault means DAMP.

Faults (each a one-line cause, logged with the DAMP transition):

* stale LowState: no new LowState for more than ``stale_ticks`` loop ticks;
* a lost motor: a motor's ``lost`` counter rises on ``lost_ticks`` consecutive ticks (the
  driver keeps missing it; a single increment is a glitch the Go2 reports routinely);
* over-temperature: a motor at or above ``max_motor_temp_c``;
* tilt: the body's z axis more than ``max_tilt_rad`` from the vertical;
* NaN or Inf in the robot state, the observation or the action.

Commands: joint targets are clamped to the policy's soft limits and rate-limited to
``max_rate`` (rad/s per joint, SDK order) relative to the previous target sent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from calib.joints import VELOCITY_LIMIT

__all__ = ["DAMP_KD", "SafetySupervisor", "SupervisorConfig", "tilt_rad"]

DAMP_KD = 4.0
"""Damping of every joint in DAMP / PASSIVE (N m s/rad; kp 0): Unitree's passive mode."""


def tilt_rad(quat_wxyz) -> float:
    """Angle between the body z axis and the world vertical (rad), from (w, x, y, z)."""
    w, x, y, z = (float(v) for v in quat_wxyz)
    n2 = w * w + x * x + y * y + z * z
    if not n2 > 0:
        return math.pi
    r22 = 1.0 - 2.0 * (x * x + y * y) / n2
    return math.acos(max(-1.0, min(1.0, r22)))


@dataclass(frozen=True)
class SupervisorConfig:
    """Limits. Times in loop ticks; angles rad; rates rad/s (12, SDK order); temperature deg C."""

    stale_ticks: int = 3
    lost_ticks: int = 3
    max_motor_temp_c: int = 90
    max_tilt_rad: float = math.radians(30.0)
    max_rate: np.ndarray = field(default_factory=lambda: np.tile(VELOCITY_LIMIT, 4))
    damp_kd: float = DAMP_KD

    def __post_init__(self):
        if self.stale_ticks < 1 or self.lost_ticks < 1:
            raise ValueError("stale_ticks and lost_ticks must be >= 1")
        if not 0 < self.max_tilt_rad < math.pi:
            raise ValueError(f"max_tilt_rad must be in (0, pi), got {self.max_tilt_rad}")
        r = np.asarray(self.max_rate, dtype=float)
        if r.shape == ():
            r = np.full(12, float(r))
        if r.shape != (12,) or np.any(~(r > 0)):
            raise ValueError("max_rate must be 12 positive rates (rad/s) or one")
        object.__setattr__(self, "max_rate", r)


class SafetySupervisor:
    """Per-tick checks. ``check_state`` and ``check_finite`` return a fault cause or None;
    ``limit`` clamps and rate-limits a joint target. dt: loop period (s)."""

    def __init__(self, config: SupervisorConfig, soft_lower, soft_upper, dt: float):
        self.config = config
        self.lower = np.asarray(soft_lower, dtype=float)
        self.upper = np.asarray(soft_upper, dtype=float)
        self.max_step = config.max_rate * float(dt)
        self.stale = 0
        self._lost_prev: np.ndarray | None = None
        self._lost_run = np.zeros(12, int)
        self.clamped = 0
        self.rate_limited = 0

    def check_state(self, fresh: bool, q=None, dq=None, quat_wxyz=None, gyro=None,
                    temperature=None, lost=None) -> str | None:
        """One tick's robot state. ``fresh``: a new LowState arrived this tick; the other
        arguments are that LowState's fields (SDK order), or None when there is none yet."""
        c = self.config
        self.stale = 0 if fresh else self.stale + 1
        if self.stale > c.stale_ticks:
            return f"stale LowState: none for {self.stale} ticks (robot or bridge gone?)"
        if q is None:
            return None
        for name, v in (("q", q), ("dq", dq), ("body quaternion", quat_wxyz),
                        ("body gyro", gyro)):
            if v is not None and not np.all(np.isfinite(v)):
                return f"non-finite {name} in LowState"
        if temperature is not None:
            t = np.asarray(temperature)
            hot = np.flatnonzero(t >= c.max_motor_temp_c)
            if hot.size:
                return (f"motor {int(hot[0])} over temperature ({int(t[hot[0]])} C >= "
                        f"{c.max_motor_temp_c} C)")
        if lost is not None and fresh:
            lo = np.asarray(lost, dtype=np.int64)
            if self._lost_prev is not None:
                rising = lo > self._lost_prev
                self._lost_run = np.where(rising, self._lost_run + 1, 0)
                bad = np.flatnonzero(self._lost_run >= c.lost_ticks)
                if bad.size:
                    self._lost_prev = lo
                    return (f"motor {int(bad[0])} lost (its lost counter rose on "
                            f"{c.lost_ticks} ticks in a row, now {int(lo[bad[0]])})")
            self._lost_prev = lo
        if quat_wxyz is not None:
            tilt = tilt_rad(quat_wxyz)
            if tilt > c.max_tilt_rad:
                return (f"tilt {math.degrees(tilt):.1f} deg > "
                        f"{math.degrees(c.max_tilt_rad):.0f} deg")
        return None

    @staticmethod
    def check_finite(name: str, v) -> str | None:
        """Fault cause if ``v`` holds NaN or Inf."""
        a = np.asarray(v, dtype=float)
        if np.all(np.isfinite(a)):
            return None
        bad = np.flatnonzero(~np.isfinite(a.reshape(-1)))
        return f"non-finite {name} (index {int(bad[0])}: {a.reshape(-1)[bad[0]]})"

    def limit(self, q_des, prev, fraction: float = 1.0) -> np.ndarray:
        """``q_des`` clamped to the soft limits and to ``max_rate`` from ``prev`` (rad), sent
        ``fraction`` of a tick after it."""
        q = np.clip(q_des, self.lower, self.upper)
        if np.any(q != q_des):
            self.clamped += 1
        if prev is not None:
            step = self.max_step * fraction
            lo, hi = prev - step, prev + step
            r = np.clip(q, lo, hi)
            if np.any(r != q):
                self.rate_limited += 1
            q = r
        return q
