"""Where the centre of mass stands over the feet: the support polygon's margin, and the Go2's
whole-body centre of mass and foot centres from its joint angles.

A robot standing still on three feet stays up only while its centre of mass, projected along
gravity, lies inside the triangle of those feet (static stability). On board the robot knows
its joint angles (encoders) and the direction of gravity in its base frame (the body IMU), so
it can tell how far inside it stands without knowing where it is in the world:
:meth:`SupportModel.margin` projects the centre of mass and the stance feet, all in the base
frame, onto the plane perpendicular to gravity, and measures the margin there. The masses are
the URDF's; what is bolted on beyond them (a payload, foot IMU nodes) moves the true centre of
mass by what it weighs times how far it sits from it, over the robot's 15-16 kg.

Frames: ``B`` the base (the URDF's root link, where the body IMU sits). Lengths m, angles rad,
joint vectors in model order (FL, FR, RL, RR x hip, thigh, calf; :mod:`calib.joints`).
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np

from calib.joints import MODEL_JOINT_NAMES, MODEL_LEGS, check_leg
from calib.robot import go2_urdf_path

__all__ = ["SupportModel", "go2_support", "polygon_margin"]

_RING = ("FL", "FR", "RR", "RL")  # the feet in order around the body


def polygon_margin(p_xy: np.ndarray, vertices_xy: np.ndarray) -> np.ndarray:
    """Signed margin (m) of ground points in convex polygons: inside, the distance to the
    nearest edge (> 0); outside, minus the farthest past any edge's line (the distance to the
    polygon beyond an edge, a little less beyond a corner). p_xy (N, 2); vertices_xy
    (N, k, 2), k >= 3, in order around the polygon, either way (a triangle's in any order)."""
    p = np.asarray(p_xy, dtype=float)
    v = np.asarray(vertices_xy, dtype=float)

    def cross(u, w):
        return u[..., 0] * w[..., 1] - u[..., 1] * w[..., 0]

    orient = np.sign(cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]))
    orient = np.where(orient == 0, 1.0, orient)
    e = np.roll(v, -1, axis=1) - v  # (N, k, 2) edges
    d = orient[:, None] * cross(e, p[:, None] - v) / np.maximum(np.linalg.norm(e, axis=-1), 1e-6)
    return d.min(axis=1)


class SupportModel:
    """The Go2's centre of mass and foot centres in its base frame, from the URDF's links
    (pinocchio, fixed base: the base is the frame everything is expressed in)."""

    def __init__(self, urdf_path: str | Path | None = None) -> None:
        import pinocchio as pin  # deferred, as in calib.kinematics

        path = Path(urdf_path) if urdf_path is not None else go2_urdf_path()
        if not path.is_file():
            raise ValueError(f"URDF not found: {path}")
        try:
            self._model = pin.buildModelFromUrdf(str(path))
        except (RuntimeError, ValueError) as exc:
            msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ValueError(f"cannot load URDF {path}: {msg}") from exc
        m = self._model
        missing = [n for n in MODEL_JOINT_NAMES if not m.existJointName(f"{n}_joint")]
        if missing:
            raise ValueError(f"{path.name} has no joint {missing[0]}_joint")
        if m.nq != len(MODEL_JOINT_NAMES):
            raise ValueError(f"{path.name} has {m.nq} joint coordinates, not 12 revolute joints")
        # pinocchio's q index of each model-order joint
        self._q_index = np.array([m.joints[m.getJointId(f"{n}_joint")].idx_q
                                  for n in MODEL_JOINT_NAMES])
        self._feet = [m.getFrameId(f"{g}_foot") for g in MODEL_LEGS]
        if any(f >= len(m.frames) for f in self._feet):
            raise ValueError(f"{path.name} lacks a <leg>_foot frame")
        self._data = m.createData()
        self._pin = pin
        self._masses = [float(i.mass) for i in m.inertias]
        self._levers = [np.array(i.lever) for i in m.inertias]
        self.mass = float(sum(self._masses))
        """kg, every link of the URDF."""

    def com_and_feet(self, q_model) -> tuple[np.ndarray, np.ndarray]:
        """(centre of mass (3,), foot centres (4, 3) in leg order FL, FR, RL, RR), base frame,
        m, at joint angles ``q_model`` (12,) rad, model order."""
        q_in = np.asarray(q_model, dtype=float)
        if q_in.shape != (12,) or not np.all(np.isfinite(q_in)):
            raise ValueError(f"joint angles must be 12 finite numbers, got shape {q_in.shape}")
        q = np.zeros(self._model.nq)
        q[self._q_index] = q_in
        pin, m, d = self._pin, self._model, self._data
        pin.framesForwardKinematics(m, d, q)
        # every link's mass at its centre, the base's (joint 0, the fixed root) too:
        # pin.centerOfMass leaves the root's inertia out of a fixed-base model
        com = sum(self._masses[i] * d.oMi[i].act(self._levers[i])
                  for i in range(m.njoints)) / self.mass
        feet = np.array([d.oMf[f].translation for f in self._feet])
        return com, feet

    def margin(self, q_model, gravity_b, stance) -> float:
        """Signed margin (m; > 0 inside, :func:`polygon_margin`) of the centre of mass in the
        polygon of the ``stance`` feet (three or four leg names), both projected along
        ``gravity_b``, the direction of gravity in the base frame (the body IMU's projected
        gravity; any length), at joint angles ``q_model``."""
        legs = {check_leg(g) for g in stance}
        if len(legs) < 3:
            raise ValueError(f"a support polygon needs three feet or more, got {sorted(legs)}")
        g = np.asarray(gravity_b, dtype=float)
        n = np.linalg.norm(g)
        if g.shape != (3,) or not np.isfinite(n) or n < 1e-6:
            raise ValueError(f"gravity must be a non-zero 3-vector, got {gravity_b!r}")
        g = g / n
        com, feet = self.com_and_feet(q_model)
        # a basis of the plane perpendicular to gravity
        a = np.cross(g, [1.0, 0.0, 0.0] if abs(g[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(g, a)
        ring = feet[[MODEL_LEGS.index(leg) for leg in _RING if leg in legs]]
        plane = np.stack([a, b], axis=1)  # (3, 2)
        return float(polygon_margin((com @ plane)[None], (ring @ plane)[None])[0])


@cache
def go2_support() -> SupportModel:
    """The :class:`SupportModel` of the Go2 of example-robot-data (built once)."""
    return SupportModel()
