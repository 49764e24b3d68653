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

from calib.joints import MODEL_JOINT_NAMES, NUM_MOTORS, check_leg
from sim.model import FOOT_OFFSET

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


# ============================================================================ the effects library
# Names of the library (docs/sim2real.md); ``Effect.name`` of each class below.
EFFECT_NAMES: tuple[str, ...] = (
    "latency", "motor_strength", "coulomb_friction", "viscous_friction", "armature", "backlash",
    "link_mass", "foot_friction", "torque_limit", "imu_bias", "imu_misalignment",
    "imu_time_offset", "packet_loss", "floor_slope", "floor_softness", "foot_payload",
    "friction_cone",
)

ActuationLatency.name = "latency"
MotorStrength.name = "motor_strength"


def _joint_indices(joints) -> np.ndarray:
    """Model-order indices of ``joints`` (None = all 12; names like ``"FL_calf"`` or indices)."""
    if joints is None:
        return np.arange(NUM_MOTORS)
    idx = np.array([MotorStrength._index(j) for j in joints], dtype=int)
    if idx.size == 0:
        raise ValueError("joints must name at least one joint (or be None for all)")
    return idx


def _per_joint(value, idx: np.ndarray, what: str, *, positive: bool = False) -> np.ndarray:
    v = np.broadcast_to(np.asarray(value, dtype=float), idx.shape).copy()
    ok = np.isfinite(v) & ((v > 0.0) if positive else (v >= 0.0))
    if not np.all(ok):
        raise ValueError(f"{what} must be finite and {'> 0' if positive else '>= 0'}, got {value!r}")
    return v


class _JointSpecEffect(Effect):
    """Sets one MuJoCo joint attribute (MuJoCo's own modelling) on selected joints."""

    attr = ""
    what = ""

    def __init__(self, value, joints=None) -> None:
        self.indices = _joint_indices(joints)
        self.value = _per_joint(value, self.indices, self.what)

    def modify_spec(self, spec: mujoco.MjSpec) -> None:
        for i, v in zip(self.indices, self.value, strict=True):
            j = spec.joint(f"{MODEL_JOINT_NAMES[i]}_joint")
            if self.attr == "damping":
                d = np.array(j.damping, dtype=float).reshape(-1)
                d[0] += v  # MuJoCo 4: linear term first, polynomial terms after
                j.damping = d
            else:
                setattr(j, self.attr, float(getattr(j, self.attr)) + float(v))

    def __repr__(self) -> str:
        names = [MODEL_JOINT_NAMES[i] for i in self.indices]
        return f"{type(self).__name__}({self.value.tolist()}, joints={names})"


class CoulombFriction(_JointSpecEffect):
    """Joint dry friction: MuJoCo ``frictionloss`` (N m) added on the selected joints."""

    name = "coulomb_friction"
    attr = "frictionloss"
    what = "Coulomb friction torque (N m)"


class ViscousFriction(_JointSpecEffect):
    """Joint viscous friction: MuJoCo joint ``damping`` (N m s/rad) added on the selected joints."""

    name = "viscous_friction"
    attr = "damping"
    what = "viscous friction (N m s/rad)"


class Armature(_JointSpecEffect):
    """Rotor inertia reflected through the gearbox: MuJoCo ``armature`` (kg m^2) added."""

    name = "armature"
    attr = "armature"
    what = "armature (kg m^2)"


class Backlash(Effect):
    """Gear play (lost motion) of total width ``2 * half_width`` rad on the selected joints.

    The encoder sits on the rotor, the link behind a gear with play: inside the play the motor's
    spring term pushes nothing. Modelled as a dead zone on the PD position error,
    ``kp * deadzone(q_des - q, half_width)`` replacing ``kp * (q_des - q)`` (the damping and
    feed-forward terms are unchanged). MuJoCo has no native backlash (the documented pattern is
    an extra hinge, which would change the joint layout every tool relies on), so this acts in
    ``on_torque``. It follows the commands itself (``on_command``): list it after any effect
    that delays or drops commands.
    """

    name = "backlash"

    def __init__(self, half_width, joints=None) -> None:
        self.indices = _joint_indices(joints)
        self.half_width = _per_joint(half_width, self.indices, "backlash half width (rad)")
        self._pending: list[MotorCommand] = []
        self._active = MotorCommand.passive()

    def reset(self, sim: Go2Sim) -> None:
        self._pending = []
        self._active = MotorCommand.passive()

    def on_command(self, cmd: MotorCommand, sim: Go2Sim) -> MotorCommand:
        self._pending.append(cmd)
        self._pending.sort(key=lambda c: c.t_apply)
        return cmd

    def on_torque(self, tau: np.ndarray, sim: Go2Sim) -> np.ndarray:
        t = sim.data.time + 1e-9
        while self._pending and self._pending[0].t_apply <= t:
            self._active = self._pending.pop(0)
        c, i = self._active, self.indices
        q = sim.data.qpos[-NUM_MOTORS:][i]
        dq = sim.data.qvel[-NUM_MOTORS:][i]
        err = c.q_des[i] - q
        dz = np.sign(err) * np.maximum(np.abs(err) - self.half_width, 0.0)
        # tau comes clamped to the motor's limits: swap the clamped PD law for the clamped
        # dead-zone one (subtracting kp * play from a saturated torque would give less than
        # the limit while the dead-zone law is still above it); what effects before this one
        # added is kept
        u = c.kp[i] * err + c.kd[i] * (c.dq_des[i] - dq) + c.tau_ff[i]
        lo, hi = sim._tau_lo[i], sim._tau_hi[i]
        tau[i] += np.clip(u - c.kp[i] * (err - dz), lo, hi) - np.clip(u, lo, hi)
        return tau

    def __repr__(self) -> str:
        names = [MODEL_JOINT_NAMES[i] for i in self.indices]
        return f"Backlash({self.half_width.tolist()}, joints={names})"


def _link_bodies(location: str) -> list[str]:
    """Bodies of a link named by its joint (``"FR_calf"`` -> the calf and its fused foot) or
    ``"base"``."""
    if location == "base":
        return ["base"]
    name = location.removesuffix("_joint")
    if name not in MODEL_JOINT_NAMES:
        raise ValueError(f"unknown link {location!r}: expected 'base' or a joint like 'FR_calf'")
    return [name, name.split("_")[0] + "_foot"] if name.endswith("_calf") else [name]


class LinkMass(Effect):
    """A link heavier or lighter than the URDF: mass and inertia times ``scale`` (> 0), and the
    centre of mass shifted by ``com_shift`` (m, link frame). ``link``: ``"base"`` or a joint
    name (``"FR_calf"`` = the link that joint moves; the calf includes the foot).

    ``add_kg`` (base only, with ``scale`` 1): a payload, exactly that many kg on the compiled
    base. On the base, ``com_shift`` moves the compiled centre of mass by exactly that much,
    with or without a payload. The compiled base also holds
    the bodies fused into it (the URDF's hip rotors: 7.277 kg against the spec's 6.921), so a
    scale of the spec's base adds 5 % less than ``scale - 1`` times the compiled mass, and a
    spec ``ipos`` shift moves the compiled centre of mass 5 % less."""

    name = "link_mass"

    def __init__(self, scale: float, link: str = "base", com_shift=(0.0, 0.0, 0.0),
                 add_kg: float = 0.0) -> None:
        s = float(scale)
        if not (np.isfinite(s) and s > 0.0):
            raise ValueError(f"link mass scale must be finite and > 0, got {scale!r}")
        self.scale = s
        self.bodies = _link_bodies(link)
        self.link = link
        self.com_shift = np.asarray(com_shift, dtype=float).reshape(3)
        self.add_kg = float(add_kg)
        if not np.isfinite(self.add_kg) or (self.add_kg and (link != "base" or s != 1.0)):
            raise ValueError("a payload (add_kg) goes on the base, with scale 1")

    def modify_spec(self, spec: mujoco.MjSpec) -> None:
        if self.add_kg or (self.link == "base" and np.any(self.com_shift)):
            self._payload(spec)
            return
        for n in self.bodies:
            b = spec.body(n)
            if b is None:
                if n.endswith("_foot"):  # a model whose foot is a geom of the calf body
                    continue
                raise ValueError(f"link mass: the model has no body {n!r}")
            b.mass = float(b.mass) * self.scale
            b.inertia = np.asarray(b.inertia, dtype=float) * self.scale
            b.ipos = np.asarray(b.ipos, dtype=float) + self.com_shift

    def _payload(self, spec: mujoco.MjSpec) -> None:
        """Mass ``m_spec * scale + add_kg`` on the spec's base, placed so that the compiled
        base (with whatever is fused into it) gains ``add_kg`` and moves its centre of mass by
        ``com_shift``: M' c' = M c + (the spec base's change of m p)."""
        fused = spec.copy().compile().body("base")
        big_m, c = float(fused.mass[0]), np.asarray(fused.ipos, dtype=float)
        b = spec.body("base")
        m, p = float(b.mass), np.asarray(b.ipos, dtype=float)
        m_new = m * self.scale + self.add_kg
        if not m_new > 0:
            raise ValueError(f"link mass: a payload of {self.add_kg} kg leaves the base no mass")
        big_new = big_m + m_new - m
        b.ipos = ((c + self.com_shift) * big_new - (c * big_m - m * p)) / m_new
        b.inertia = np.asarray(b.inertia, dtype=float) * (m_new / m)
        b.mass = m_new

    def __repr__(self) -> str:
        extra = f", add_kg={self.add_kg!r}" if self.add_kg else ""
        return (f"LinkMass({self.scale!r}, link={self.link!r}, "
                f"com_shift={self.com_shift.tolist()}{extra})")


class FootFriction(Effect):
    """Foot-ground sliding friction coefficient ``mu`` (MuJoCo takes the larger of the two
    geoms' coefficients, so both the feet and the floor are set)."""

    name = "foot_friction"

    def __init__(self, mu: float) -> None:
        m = float(mu)
        if not (np.isfinite(m) and m > 0.0):
            raise ValueError(f"foot friction must be finite and > 0, got {mu!r}")
        self.mu = m

    def modify_spec(self, spec: mujoco.MjSpec) -> None:
        for g in spec.geoms:
            if g.name == "floor" or g.name in {f"{leg}_foot" for leg in ("FL", "FR", "RL", "RR")}:
                f = np.array(g.friction, dtype=float)
                f[0] = self.mu
                g.friction = f

    def __repr__(self) -> str:
        return f"FootFriction({self.mu!r})"


class FloorSlope(Effect):
    """The floor tilted by ``angle`` rad (0 <= angle < 0.5), descending towards ``azimuth``
    (rad from the world x axis towards y), about a horizontal axis through the world origin.
    ``Go2Sim.reset`` places the robot on the level floor; this effect's reset then turns it with
    the floor about the origin, so it starts standing on the slope as it would on the level
    (every foot on the floor, the base tilted by ``angle`` from the vertical). Gravity stays
    world -z, so the IMU and the base tilt read the slope as a real robot's would. Free base
    only."""

    name = "floor_slope"

    def __init__(self, angle: float, azimuth: float = 0.0) -> None:
        a, z = float(angle), float(azimuth)
        if not (np.isfinite(a) and 0.0 <= a < 0.5 and np.isfinite(z)):
            raise ValueError(f"floor slope must be finite and in [0, 0.5) rad, got {angle!r} "
                             f"(azimuth {azimuth!r})")
        self.angle, self.azimuth = a, z
        axis = np.array([-np.sin(z), np.cos(z), 0.0])  # z x (the downhill direction)
        self.quat_wxyz = np.r_[np.cos(a / 2), np.sin(a / 2) * axis]
        self.rotation = np.zeros(9)
        mujoco.mju_quat2Mat(self.rotation, self.quat_wxyz)
        self.rotation = self.rotation.reshape(3, 3)

    def modify_spec(self, spec: mujoco.MjSpec) -> None:
        floors = [g for g in spec.geoms if g.name == "floor"]
        if not floors:
            raise ValueError("a floor slope needs the model's floor (SimConfig(floor=True))")
        floors[0].quat = self.quat_wxyz

    def reset(self, sim: Go2Sim) -> None:
        if sim.config.base != "free":
            raise ValueError("a floor slope needs a free base")
        q = np.zeros(4)
        mujoco.mju_mulQuat(q, self.quat_wxyz, sim.base_quat_wxyz)
        sim.set_base_state(self.rotation @ sim.base_pos, q)

    def __repr__(self) -> str:
        return f"FloorSlope({self.angle!r}, azimuth={self.azimuth!r})"


MUJOCO_TIMECONST_S = 0.02
"""MuJoCo's default contact ``solref`` time constant, s: the floor of the nominal model."""

FLOOR_SOLMIX = 1e6
"""The ``solmix`` a floor that gives is set to: the other geom's weight is its own, 1, so the
floor's contact parameters govern every contact it has."""


def check_floor_timeconst(timeconst: float, timestep: float) -> None:
    """ValueError where a floor's ``solref`` time constant (s) is under two physics steps of
    ``timestep`` s: MuJoCo would stiffen it to that silently."""
    if timeconst < 2 * timestep:
        raise ValueError(f"a floor time constant of {timeconst} s is under two physics steps "
                         f"({2 * timestep} s): MuJoCo would stiffen it silently")


class FloorSoftness(Effect):
    """A floor that gives: its contacts' ``solref`` time constant ``timeconst`` s (MuJoCo's
    default 0.02 lets a Go2 standing on four legs sink its feet 2 mm; 0.03 about 4-5 mm, 0.04
    about 7-9 mm, 0.06 about 16-20 mm, as a foam mat) and damping ratio ``dampratio``. The
    floor's ``solmix`` makes its parameters govern every contact it has, feet and any other
    body alike."""

    name = "floor_softness"

    def __init__(self, timeconst: float, dampratio: float = 1.0) -> None:
        tc, dr = float(timeconst), float(dampratio)
        if not (np.isfinite(tc) and 0.0 < tc <= 0.2 and np.isfinite(dr) and 0.0 < dr <= 10.0):
            raise ValueError(f"floor softness needs a time constant in (0, 0.2] s and a damping "
                             f"ratio in (0, 10], got {timeconst!r}, {dampratio!r}")
        self.timeconst, self.dampratio = tc, dr

    def modify_spec(self, spec: mujoco.MjSpec) -> None:
        floors = [g for g in spec.geoms if g.name == "floor"]
        if not floors:
            raise ValueError("a floor softness needs the model's floor (SimConfig(floor=True))")
        check_floor_timeconst(self.timeconst, spec.option.timestep)
        over = [g.name or "(unnamed)" for g in spec.geoms if g.priority > floors[0].priority]
        if over:  # MuJoCo takes the contact settings of the geom with the higher priority
            raise ValueError(f"a floor softness would not act: {', '.join(over)} have priority "
                             "over the floor, their own contact settings govern")
        floors[0].solref = [self.timeconst, self.dampratio]
        floors[0].solmix = FLOOR_SOLMIX

    def __repr__(self) -> str:
        return f"FloorSoftness({self.timeconst!r}, dampratio={self.dampratio!r})"


_CONES = {"pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL, "elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC}


class FrictionCone(Effect):
    """The contacts' friction cone as a plain MJCF or URDF load gets it: MuJoCo's default
    ``pyramidal`` cone with ``impratio`` 1 (Unitree's own ``unitree_rl_gym`` model runs on it),
    where :mod:`sim.model` and MuJoCo Menagerie's Go2 use an ``elliptic`` one with ``impratio``
    100. A simulator setting a checker may leave at its default, not a property of the robot:
    on it the deploy policy loses half its lifts on weak motors (docs/policy-training.md,
    stop 80)."""

    name = "friction_cone"

    def __init__(self, cone: str = "pyramidal", impratio: float = 1.0) -> None:
        if cone not in _CONES:
            raise ValueError(f"a friction cone is one of {', '.join(_CONES)}, got {cone!r}")
        r = float(impratio)
        if not (np.isfinite(r) and r >= 1.0):
            raise ValueError(f"impratio must be >= 1, got {impratio!r}")
        self.cone, self.impratio = cone, r

    @property
    def mjt_cone(self) -> int:
        """MuJoCo's ``opt.cone`` value for this cone."""
        return int(_CONES[self.cone])

    def modify_spec(self, spec: mujoco.MjSpec) -> None:
        spec.option.cone = self.mjt_cone
        spec.option.impratio = self.impratio

    def __repr__(self) -> str:
        return f"FrictionCone({self.cone!r}, impratio={self.impratio!r})"


class FootPayload(Effect):
    """A foot IMU node (board, case, mount, the cable's end) of ``kg`` strapped to ``leg``'s foot:
    a rigid mass, a ``radius`` m solid sphere, ``offset`` m from the foot centre in the calf's
    frame (default 4 cm up the calf, above the foot sphere): a body with no geometry, fixed to
    the calf (fused into it where the model fuses static bodies). The model's calf and foot are
    left as they are. On both models (the URDF's and an MJCF's, :mod:`sim.external_model`) the
    foot is 0.213 m down the calf."""

    name = "foot_payload"

    def __init__(self, kg: float, leg: str, offset=(0.0, 0.0, 0.04), radius: float = 0.02) -> None:
        self.kg, self.radius = float(kg), float(radius)
        if not (np.isfinite(self.kg) and 0.0 < self.kg < 1.0):
            raise ValueError(f"a foot payload must be in (0, 1) kg, got {kg!r}")
        if not (np.isfinite(self.radius) and 0.0 < self.radius < 0.1):
            raise ValueError(f"a foot payload's radius must be in (0, 0.1) m, got {radius!r}")
        self.leg = check_leg(leg)
        self.offset = np.asarray(offset, dtype=float).reshape(3)
        if not (np.all(np.isfinite(self.offset)) and np.linalg.norm(self.offset) < 0.1):
            raise ValueError(f"a foot payload sits within 0.1 m of the foot, got offset {offset!r}")

    def modify_spec(self, spec: mujoco.MjSpec) -> None:
        calf = spec.body(f"{self.leg}_calf")
        if calf is None:
            raise ValueError(f"foot payload: the model has no body {self.leg}_calf")
        inertia = 0.4 * self.kg * self.radius**2
        # ipos and iquat given: left unset, MuJoCo 4.0 placed a geomless body's mass at twice
        # its offset from the parent when fusing it
        node = calf.add_body(name=f"{self.leg}_imu_node", pos=FOOT_OFFSET + self.offset,
                             mass=self.kg, inertia=[inertia] * 3, ipos=[0.0, 0.0, 0.0],
                             iquat=[1.0, 0.0, 0.0, 0.0])
        node.explicitinertial = True

    def __repr__(self) -> str:
        return (f"FootPayload({self.kg!r}, leg={self.leg!r}, offset={self.offset.tolist()}, "
                f"radius={self.radius!r})")


class TorqueLimit(Effect):
    """Torque saturation below the URDF effort limit, with voltage sag: the motor delivers at
    most ``limit - droop * |dq|`` N m (>= 0) on the selected joints (droop N m s/rad models the
    back-EMF of a sagging battery)."""

    name = "torque_limit"

    def __init__(self, limit, joints=None, droop=0.0) -> None:
        self.indices = _joint_indices(joints)
        self.limit = _per_joint(limit, self.indices, "torque limit (N m)", positive=True)
        self.droop = _per_joint(droop, self.indices, "torque droop (N m s/rad)")

    def on_torque(self, tau: np.ndarray, sim: Go2Sim) -> np.ndarray:
        i = self.indices
        dq = sim.data.qvel[-NUM_MOTORS:][i]
        lim = np.maximum(self.limit - self.droop * np.abs(dq), 0.0)
        tau[i] = np.clip(tau[i], -lim, lim)
        return tau

    def __repr__(self) -> str:
        names = [MODEL_JOINT_NAMES[i] for i in self.indices]
        return f"TorqueLimit({self.limit.tolist()}, joints={names}, droop={self.droop.tolist()})"


class PacketLoss(Effect):
    """Dropped and jittered command packets.

    Each command is dropped with ``probability`` (the previous one stays active), drawn from the
    simulation's ``rng``; surviving ones take effect ``U(0, jitter)`` s late. ``drop_times``
    (s, sim send times) instead drops exactly the commands sent then (within 0.5 ms): the
    deterministic form the diagnoser replays.
    """

    name = "packet_loss"

    def __init__(self, probability: float = 0.0, jitter: float = 0.0, drop_times=None) -> None:
        p, j = float(probability), float(jitter)
        if not (0.0 <= p < 1.0):
            raise ValueError(f"packet loss probability must be in [0, 1), got {probability!r}")
        if not (np.isfinite(j) and j >= 0.0):
            raise ValueError(f"jitter must be finite and >= 0 s, got {jitter!r}")
        self.probability, self.jitter = p, j
        self.drop_times = None if drop_times is None else np.sort(np.asarray(drop_times, float))

    def on_command(self, cmd: MotorCommand, sim: Go2Sim) -> MotorCommand | None:
        if self.drop_times is not None:
            k = np.searchsorted(self.drop_times, cmd.t_sent - 5e-4)
            if k < self.drop_times.size and abs(self.drop_times[k] - cmd.t_sent) <= 5e-4:
                return None
        elif self.probability > 0.0 and sim.rng.random() < self.probability:
            return None
        if self.jitter > 0.0:
            return dataclasses.replace(cmd, t_apply=cmd.t_apply + sim.rng.uniform(0, self.jitter))
        return cmd

    def __repr__(self) -> str:
        return f"PacketLoss({self.probability!r}, jitter={self.jitter!r})"


# ---------------------------------------------------------------------------- body-IMU effects
class ImuEffect(Effect):
    """An effect on the body IMU's readings only (the dynamics are untouched).

    :meth:`apply_imu` maps true samples to what the IMU reports: ``t`` (N,) s, ``gyro`` (N, 3)
    rad/s and ``accel`` (N, 3) m/s^2 in the base frame, ``quat_wxyz`` (N, 4) base->world.
    """

    def apply_imu(self, t, gyro, accel, quat_wxyz):
        return gyro, accel, quat_wxyz


class ImuBias(ImuEffect):
    """Constant gyro bias (rad/s, (3,)) and accelerometer bias (m/s^2, (3,))."""

    name = "imu_bias"

    def __init__(self, gyro_bias=(0.0, 0.0, 0.0), accel_bias=(0.0, 0.0, 0.0)) -> None:
        self.gyro_bias = np.asarray(gyro_bias, dtype=float).reshape(3)
        self.accel_bias = np.asarray(accel_bias, dtype=float).reshape(3)

    def apply_imu(self, t, gyro, accel, quat_wxyz):
        return np.asarray(gyro) + self.gyro_bias, np.asarray(accel) + self.accel_bias, quat_wxyz

    def __repr__(self) -> str:
        return f"ImuBias({self.gyro_bias.tolist()}, {self.accel_bias.tolist()})"


def _rotvec_matrix(rv) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    return Rotation.from_rotvec(np.asarray(rv, dtype=float).reshape(3)).as_matrix()


class ImuMisalignment(ImuEffect):
    """The IMU is mounted rotated by ``rotvec`` (rad, base frame) and its gyro reads ``scale``
    times the rate: it reports ``scale * R.T @ omega`` and ``R.T @ f``, and an orientation of
    ``q_base * R`` (its own frame to world)."""

    name = "imu_misalignment"

    def __init__(self, rotvec=(0.0, 0.0, 0.0), gyro_scale: float = 1.0) -> None:
        self.rotvec = np.asarray(rotvec, dtype=float).reshape(3)
        self.gyro_scale = float(gyro_scale)

    def apply_imu(self, t, gyro, accel, quat_wxyz):
        from scipy.spatial.transform import Rotation
        r = _rotvec_matrix(self.rotvec)
        g = self.gyro_scale * np.asarray(gyro) @ r
        a = np.asarray(accel) @ r
        q = np.asarray(quat_wxyz, dtype=float)
        rq = Rotation.from_quat(q[:, [1, 2, 3, 0]]) * Rotation.from_rotvec(self.rotvec)
        xyzw = rq.as_quat()
        return g, a, xyzw[:, [3, 0, 1, 2]]

    def __repr__(self) -> str:
        return f"ImuMisalignment({self.rotvec.tolist()}, gyro_scale={self.gyro_scale!r})"


class ImuTimeOffset(ImuEffect):
    """The IMU sample stamped ``t`` describes the motion at ``t - seconds`` (it lags when > 0);
    linear interpolation, ends held."""

    name = "imu_time_offset"

    def __init__(self, seconds: float) -> None:
        s = float(seconds)
        if not np.isfinite(s):
            raise ValueError(f"IMU time offset must be finite, got {seconds!r}")
        self.seconds = s

    def apply_imu(self, t, gyro, accel, quat_wxyz):
        t = np.asarray(t, dtype=float)
        ts = t - self.seconds

        def sh(x):
            x = np.asarray(x, dtype=float)
            return np.stack([np.interp(ts, t, x[:, k]) for k in range(x.shape[1])], axis=1)

        q = sh(quat_wxyz)
        return sh(gyro), sh(accel), q / np.linalg.norm(q, axis=1, keepdims=True)

    def __repr__(self) -> str:
        return f"ImuTimeOffset({self.seconds!r})"


def apply_imu_effects(effects, t, gyro, accel, quat_wxyz):
    """Apply every :class:`ImuEffect` in ``effects`` (in order) to body-IMU arrays."""
    for e in effects:
        if isinstance(e, ImuEffect):
            gyro, accel, quat_wxyz = e.apply_imu(t, gyro, accel, quat_wxyz)
    return gyro, accel, quat_wxyz


__all__ += [
    "EFFECT_NAMES", "MUJOCO_TIMECONST_S", "Armature", "Backlash", "CoulombFriction", "FloorSlope",
    "FloorSoftness", "FootFriction", "FootPayload", "FrictionCone", "ImuBias", "ImuEffect",
    "ImuMisalignment", "ImuTimeOffset", "LinkMass", "PacketLoss", "TorqueLimit", "ViscousFriction",
    "apply_imu_effects",
]
