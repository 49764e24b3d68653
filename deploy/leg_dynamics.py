"""Inverse dynamics of one leg with the base held still: the lifted leg's feed-forward torque.

The lifted leg follows a known trajectory under a soft PD law (kp 40 N m/rad): without help it
lags the plan by the torque that gravity and the leg's own inertia ask for, divided by kp
(0.02 rad RMS, which raises the executed excitation's condition number from 1.00 to 1.10).
Adding ``tau = M(q) ddq + C(q, dq) dq + g(q)`` of the *planned* motion to the motor command
(computed-torque feed-forward) removes most of that lag without stiffening the leg, so the
body meets the same compliance when it is shoved.

The base is taken as fixed: its rotation rate (under 0.5 rad/s in the tripod) and
acceleration are left out; only the direction of gravity in the base frame is an input
(the measured projected gravity, or level). Recursive Newton-Euler over the leg's three
links, vectorised over samples (and over legs, one row of parameters per sample, for the
training environment's lifted legs: :meth:`LegDynamics.torques_of_legs`), with the link
inertias of the URDF (the foot sphere merged into the calf, as pinocchio merges fixed links)
plus the motors' reflected rotor inertia on each joint. Pure numpy at run time; pinocchio
only reads the URDF once, and a machine without the URDF or pinocchio (a lent training
machine) loads the same numbers from a pack file (:meth:`LegDynamics.save_pack`, written by
``a2i-train pack``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from calib.joints import check_leg
from calib.kinematics import LegKinematics
from calib.robot import go2_urdf_path

__all__ = ["GRAVITY", "ROTOR_INERTIA", "LegDynamics", "TorqueTable"]

_PACKED: dict[str, LegDynamics] = {}  # legs loaded by LegDynamics.load_pack, before the URDF's
_ARRAYS = ("placement_rotation", "placement_translation", "axes", "mass", "com", "inertia")

GRAVITY = 9.81  # m/s^2
ROTOR_INERTIA = 0.01
"""Reflected rotor inertia of a Go2 joint motor, kg m^2 (MuJoCo Menagerie's Go2 ``armature``;
the URDF has none). The training model puts it on every joint (``policy_train.model``)."""


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product (broadcasting (3,) against (N, 3)); np.cross costs ~20 us a
    call, which dominates one on-board tick's recursion. The differences are written into
    the result, not stacked (0.8 of the time at 1 500 rows, the same bits)."""
    a1, a2, a3 = a[..., 0], a[..., 1], a[..., 2]
    b1, b2, b3 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    np.subtract(a2 * b3, a3 * b2, out=out[..., 0])
    np.subtract(a3 * b1, a1 * b3, out=out[..., 1])
    np.subtract(a1 * b2, a2 * b1, out=out[..., 2])
    return out


@dataclass(frozen=True)
class TorqueTable:
    """The torques of a tabulated motion, N m, with the tilt left open: the torque is linear in
    the gravity direction at fixed (q, dq, ddq), so sample ``i`` under gravity ``g`` is
    ``motion[i] + gravity[i] @ g``, a 3x3 product where the recursion is a millisecond (a
    MuJoCo rollout at 1 kHz asks for it every step).

    motion (N, 3): gravity left out; gravity (N, 3, 3): per unit of the gravity direction in
    the base frame; limit (3,): the torques are clipped to +-limit (None: not clipped).
    """

    motion: np.ndarray
    gravity: np.ndarray
    limit: np.ndarray | None = None

    def at(self, i: int, gravity_b=None) -> np.ndarray:
        """(3,) N m at sample ``i`` under ``gravity_b`` (unit, base frame; None: level)."""
        g = np.array([0.0, 0.0, -1.0]) if gravity_b is None else np.asarray(gravity_b, float)
        tau = self.motion[i] + self.gravity[i] @ g
        return tau if self.limit is None else np.clip(tau, -self.limit, self.limit)


class LegDynamics:
    """Fixed-base inverse dynamics of one Go2 leg (hip, thigh, calf), vectorised over samples.

    Build with :meth:`of_leg` (cached). ``torques`` takes joint angles, rates and accelerations
    in the leg's own URDF signs (rad, rad/s, rad/s^2) and returns joint torques, N m.
    """

    def __init__(self, leg: str, placement_rotation: np.ndarray,
                 placement_translation: np.ndarray, axes: np.ndarray, mass: np.ndarray,
                 com: np.ndarray, inertia: np.ndarray,
                 rotor_inertia: float = ROTOR_INERTIA) -> None:
        """The leg's chain as :class:`calib.kinematics.LegKinematics` has it: placement_rotation
        (3, 3, 3) and placement_translation (3, 3), m, of each joint's frame in its parent's,
        axes (3, 3) unit, in the joint's frame. mass (3,) kg; com (3, 3) centre of mass of each
        link in its joint frame, m; inertia (3, 3, 3) about the centre of mass in the joint
        frame's axes, kg m^2; rotor_inertia kg m^2 on every joint."""
        self.leg = check_leg(leg)
        self._r0 = np.asarray(placement_rotation, dtype=float).reshape(3, 3, 3)
        self._p0 = np.asarray(placement_translation, dtype=float).reshape(3, 3)
        self._axes = np.asarray(axes, dtype=float).reshape(3, 3)
        self.mass = np.asarray(mass, dtype=float).reshape(3)
        self.com = np.asarray(com, dtype=float).reshape(3, 3)
        self.inertia = np.asarray(inertia, dtype=float).reshape(3, 3, 3)
        self.rotor_inertia = float(rotor_inertia)
        self._kk, self._kk2 = _axis_matrices(self._axes)

    @classmethod
    def of_leg(cls, leg: str) -> LegDynamics:
        """The Go2 leg (FL, FR, RL or RR): from a loaded pack (:meth:`load_pack`), else from
        example-robot-data's URDF."""
        leg = check_leg(leg)
        return _PACKED.get(leg) or cls._from_urdf(leg)

    @classmethod
    @cache
    def _from_urdf(cls, leg: str) -> LegDynamics:
        import pinocchio as pin  # deferred, as in calib.kinematics

        kin = LegKinematics.from_urdf(None, leg)
        model = pin.buildModelFromUrdf(str(go2_urdf_path()))
        ids = [model.getJointId(n) for n in kin.joint_names]
        ins = [model.inertias[j] for j in ids]
        return cls(leg, kin.placement_rotation, kin.placement_translation, kin.axes,
                   np.array([i.mass for i in ins]), np.array([i.lever for i in ins]),
                   np.array([i.inertia for i in ins]))

    @staticmethod
    def save_pack(path, legs=("FL", "FR", "RL", "RR")) -> None:
        """Write the legs' parameters (``.npz``) for a machine without the URDF."""
        arrays = {}
        for leg in legs:
            d = LegDynamics.of_leg(leg)
            values = (d._r0, d._p0, d._axes, d.mass, d.com, d.inertia)
            arrays.update({f"{leg}.{k}": v for k, v in zip(_ARRAYS, values)})
            arrays[f"{leg}.rotor_inertia"] = np.array(d.rotor_inertia)
        with open(path, "wb") as f:  # a file object: np.savez would append ".npz" to a name
            np.savez(f, **arrays)

    @staticmethod
    def load_pack(path) -> tuple[str, ...]:
        """Use the legs of a :meth:`save_pack` file from now on (in this process); returns
        them. ValueError if the file is not such a pack."""
        try:
            with np.load(path) as z:
                legs = sorted({k.split(".")[0] for k in z.files})
                loaded = {leg: LegDynamics(leg, *(z[f"{leg}.{k}"] for k in _ARRAYS),
                                           rotor_inertia=float(z[f"{leg}.rotor_inertia"]))
                          for leg in legs}
        except (OSError, KeyError, ValueError) as e:
            raise ValueError(f"{path}: not a leg-dynamics pack ({e})") from None
        if not loaded:
            raise ValueError(f"{path}: not a leg-dynamics pack (no legs)")
        _PACKED.update(loaded)
        return tuple(loaded)

    def table(self, q, dq, ddq, limit=None) -> TorqueTable:
        """:class:`TorqueTable` of the motion (q, dq, ddq), each (N, 3) (as :meth:`torques`)."""
        motion = self.torques(q, dq, ddq, np.zeros(3))
        q = np.atleast_2d(np.asarray(q, dtype=float))
        still = np.zeros_like(q)
        gravity = np.stack([self.torques(q, still, still, e) for e in np.eye(3)], axis=-1)
        return TorqueTable(motion, gravity, None if limit is None else np.asarray(limit, float))

    def _arrays(self) -> tuple[np.ndarray, ...]:
        """The parameters as :func:`_rnea` takes them, for one leg (a leading axis of 1)."""
        return (self._r0[None], self._p0[None], self._axes[None], self.mass[None],
                self.com[None], self.inertia[None], np.array([self.rotor_inertia]),
                self._kk[None], self._kk2[None])

    def torques(self, q, dq, ddq, gravity_b=None) -> np.ndarray:
        """Joint torques (N, 3), N m, that move the leg along (q, dq, ddq) with the base still.

        q, dq, ddq: (N, 3) or (3,), rad, rad/s, rad/s^2 (hip, thigh, calf). gravity_b: the unit
        direction of gravity in the base frame, (N, 3) or (3,) (the projected gravity;
        default level, (0, 0, -1); zero: gravity left out).
        """
        return _rnea(self._arrays(), *_samples(q, dq, ddq, gravity_b))

    @staticmethod
    def torques_of_legs(legs, q, dq, ddq, gravity_b=None) -> np.ndarray:
        """:meth:`torques` of several legs in one pass: sample i is leg ``legs[i]`` (N names;
        the training environment's lifted legs, whose calls one leg at a time cost more than
        their arithmetic). Other arguments as :meth:`torques`."""
        q, dq, ddq, g = _samples(q, dq, ddq, gravity_b)
        names, which = np.unique(np.asarray(legs, dtype=str), return_inverse=True)
        if which.shape != (len(q),):
            raise ValueError(f"legs: one name per sample ({len(q)}), not {which.shape}")
        per_leg = [LegDynamics.of_leg(str(leg))._arrays() for leg in names]
        # one row of parameters per sample even for one leg: each row computed alone
        arrays = tuple(np.concatenate(a)[which] for a in zip(*per_leg))
        return _rnea(arrays, q, dq, ddq, g)


def _samples(q, dq, ddq, gravity_b):
    """q, dq, ddq, gravity direction as (N, 3) each (see :meth:`LegDynamics.torques`)."""
    q, dq, ddq = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (q, dq, ddq))
    n = max(len(q), len(dq), len(ddq))
    q, dq, ddq = (np.broadcast_to(x, (n, 3)) for x in (q, dq, ddq))
    g = np.array([0.0, 0.0, -1.0]) if gravity_b is None else np.asarray(gravity_b, float)
    return q, dq, ddq, np.broadcast_to(np.atleast_2d(g), (n, 3))


def _axis_matrices(axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cross-product matrix K of each joint axis (3, 3) and K @ K, each (3, 3, 3): fixed
    per leg, so built once, not in every call (that was 12 % of an on-board tick's call and
    6 % of the training environment's 1 800-row calls, for the same bits)."""
    a = np.asarray(axes, dtype=float).reshape(3, 3)
    z = np.zeros(3)
    kk = np.stack([z, -a[:, 2], a[:, 1], a[:, 2], z, -a[:, 0], -a[:, 1], a[:, 0], z],
                  axis=-1).reshape(3, 3, 3)
    return kk, kk @ kk


def _mv(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise matrix-vector product, (N or 1, 3, 3) by (N, 3). One matrix for several rows
    is a single BLAS product; rows of their own matrices are each computed alone, so a row's
    result does not depend on which rows share its call."""
    return v @ a[0].T if len(a) == 1 < len(v) else np.einsum("nij,nj->ni", a, v)


def _rnea(arrays, q, dq, ddq, g) -> np.ndarray:
    """Recursive Newton-Euler over the three links, (N, 3) N m. ``arrays``: per-sample leg
    parameters with a leading axis of N or 1 (:meth:`LegDynamics._arrays`): placement
    rotations (., 3, 3, 3), translations (., 3, 3), axes (., 3, 3), masses (., 3), centres of
    mass (., 3, 3), inertias (., 3, 3, 3), rotor inertia (.,), the axes' cross-product
    matrices and their squares (., 3, 3, 3) (:func:`_axis_matrices`); link k is axis 1."""
    r0, p0, axes, mass, com, inertia, rotor, kk, kk2 = arrays
    n = len(q)
    rot = []  # joint frame k in its parent's at q (Rodrigues), (N, 3, 3)
    for k in range(3):
        s, c1 = np.sin(q[:, k]), 1.0 - np.cos(q[:, k])
        rot.append(r0[:, k] @ (np.eye(3) + s[:, None, None] * kk[:, k]
                               + c1[:, None, None] * kk2[:, k]))
    acc = -GRAVITY * g  # the base "accelerates up" at g: gravity on every link at once
    force, moment = [], []
    for k in range(3):
        rt = np.swapaxes(rot[k], 1, 2)
        p, ax = p0[:, k], axes[:, k]
        sa = dq[:, k, None] * ax
        if k == 0:  # the base is still: the hip's parent neither turns nor speeds its turn
            acc = _mv(rt, acc)
            w, dw = sa, ddq[:, k, None] * ax
        else:
            acc = _mv(rt, acc + _cross(dw, p) + _cross(w, _cross(w, p)))
            w_in = _mv(rt, w)
            w = w_in + sa
            dw = _mv(rt, dw) + ddq[:, k, None] * ax + _cross(w_in, sa)
        c = com[:, k]
        ac = acc + _cross(dw, c) + _cross(w, _cross(w, c))
        force.append(mass[:, k, None] * ac)
        moment.append(_mv(inertia[:, k], dw) + _cross(w, _mv(inertia[:, k], w)))
    tau = np.empty((n, 3))
    f_next = np.zeros((n, 3))
    m_next = np.zeros((n, 3))
    for k in (2, 1, 0):
        f = force[k] + f_next
        m = moment[k] + m_next + _cross(com[:, k], force[k])
        tau[:, k] = (m * axes[:, k]).sum(-1) + rotor * ddq[:, k]
        if k > 0:  # into the parent's frame, about the parent's origin
            f_next = _mv(rot[k], f)
            m_next = _mv(rot[k], m) + _cross(p0[:, k], f_next)
    return tau
