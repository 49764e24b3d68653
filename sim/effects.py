"""Pluggable unmodelled effects: what the real Go2 does that the nominal model does not.

An :class:`Effect` can act at three places, each optional (the base class does nothing):

* :meth:`Effect.modify_spec` edits the :class:`mujoco.MjSpec` before compiling (joint
  ``frictionloss`` / ``damping`` / ``armature``, native actuator ``delay``, masses, ...);
* :meth:`Effect.on_command` transforms each motor command as it is sent (latency: push its
  ``t_apply`` later; packet loss: return None);
* :meth:`Effect.on_torque` transforms the motor torques every physics step, after the PD law and
  the torque clamp (motor strength, torque ripple, ...).

:class:`sim.go2.Go2Sim` calls the hooks in list order; only effects that override
``on_torque`` cost anything per physics step. Effects may keep state; :meth:`Effect.reset` is
called by ``Go2Sim.reset``. Give every simulation its own effect objects.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from calib.joints import MODEL_JOINT_NAMES, NUM_MOTORS

if TYPE_CHECKING:  # pragma: no cover - typing only
    from sim.go2 import Go2Sim

__all__ = ["ActuationLatency", "Effect", "MotorCommand", "MotorStrength"]


@dataclass(frozen=True)
class MotorCommand:
    """One low-level command to the 12 motors, **model order** (FL, FR, RL, RR).

    The motor driver applies ``tau = kp*(q_des - q) + kd*(dq_des - dq) + tau_ff`` (N m) every
    physics step from ``t_apply`` (s, sim time) on, until a later command takes over.
    ``t_sent`` is the sim time at which the command was issued.
    """

    q_des: np.ndarray
    dq_des: np.ndarray
    kp: np.ndarray
    kd: np.ndarray
    tau_ff: np.ndarray
    t_sent: float = 0.0
    t_apply: float = 0.0

    @staticmethod
    def passive(t: float = 0.0) -> MotorCommand:
        """All gains and torques zero: the motors apply nothing."""
        z = np.zeros(NUM_MOTORS)
        return MotorCommand(z, z, z, z, z, t, t)


class Effect:
    """Base class of unmodelled effects; override only the hooks you need."""

    def modify_spec(self, spec: mujoco.MjSpec) -> None:
        """Edit the model before it is compiled (called once per model build)."""

    def reset(self, sim: Go2Sim) -> None:
        """Clear internal state (called by ``Go2Sim.reset``)."""

    def on_command(self, cmd: MotorCommand, sim: Go2Sim) -> MotorCommand | None:
        """Transform a command as it is sent; None drops it (the previous one stays active)."""
        return cmd

    def on_torque(self, tau: np.ndarray, sim: Go2Sim) -> np.ndarray:
        """Transform the (12,) model-order motor torques (N m) of this physics step.

        ``tau`` is a scratch buffer the caller owns; modifying it in place and returning it is
        allowed (and allocation free).
        """
        return tau


class ActuationLatency(Effect):
    """Each command takes effect ``seconds`` after it was sent.

    Models the transport + driver latency of ``rt/lowcmd``: the motor's PD loop keeps running
    on fresh encoder readings, only the set-point / gains arrive late. Resolution is the physics
    step: the command becomes active at the first step whose time is >= t_sent + seconds.
    """

    def __init__(self, seconds: float) -> None:
        if not (np.isfinite(seconds) and seconds >= 0.0):
            raise ValueError(f"latency must be a finite number of seconds >= 0, got {seconds!r}")
        self.seconds = float(seconds)

    def on_command(self, cmd: MotorCommand, sim: Go2Sim) -> MotorCommand:
        return dataclasses.replace(cmd, t_apply=cmd.t_apply + self.seconds)

    def __repr__(self) -> str:
        return f"ActuationLatency({self.seconds!r})"


class MotorStrength(Effect):
    """Motors deliver ``scale`` times the torque the driver computes (after its clamp).

    scale: float or (k,) per selected joint, > 0. joints: None (all 12) or joint names
    (``"FL_calf"``, ...) or model-order indices. The actuator ``ctrlrange`` (the effort limit)
    still caps the result, as the motor's current limit would.
    """

    def __init__(self, scale, joints=None) -> None:
        if joints is None:
            idx = np.arange(NUM_MOTORS)
        else:
            idx = np.array([self._index(j) for j in joints], dtype=int)
            if idx.size == 0:
                raise ValueError("joints must name at least one joint (or be None for all)")
        s = np.broadcast_to(np.asarray(scale, dtype=float), idx.shape).copy()
        if not np.all(np.isfinite(s) & (s > 0.0)):
            raise ValueError(f"motor strength scale must be finite and > 0, got {scale!r}")
        self.indices = idx
        self.scale = s

    @staticmethod
    def _index(j) -> int:
        if isinstance(j, str):
            name = j.removesuffix("_joint")
            if name not in MODEL_JOINT_NAMES:
                raise ValueError(f"unknown joint {j!r}: expected e.g. 'FL_calf'")
            return MODEL_JOINT_NAMES.index(name)
        i = int(j)
        if not 0 <= i < NUM_MOTORS:
            raise ValueError(f"joint index {j!r} out of range 0..{NUM_MOTORS - 1}")
        return i

    def on_torque(self, tau: np.ndarray, sim: Go2Sim) -> np.ndarray:
        tau[self.indices] *= self.scale
        return tau

    def __repr__(self) -> str:
        names = [MODEL_JOINT_NAMES[i] for i in self.indices]
        return f"MotorStrength(scale={self.scale.tolist()}, joints={names})"
