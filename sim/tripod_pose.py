"""Static, level tripod stances of the Go2, for whatever must stand on three legs without a
balance controller's help.

* Reference states for the tripod training's resets (``policy_train.env``): PPO that starts
  every episode on four legs first finds the cheap way to stand on three: lean the body over
  the support triangle (v1 leaned 15-35 deg). Starting a share of the episodes in a level
  tripod that is already in static equilibrium (reference-state initialisation, as in
  DeepMimic) shows the policy the state it should hold from the first iteration.
* The naive single-foot waving on a free base (``sim.free_base_run.naive_wave_free``): open
  loop, it first moves the body over the three other feet, as anyone lifting a leg of a
  standing robot by hand would, instead of tipping over at the lift.

One stance per lifted leg, on flat ground, base level at ``height`` and yaw 0:

1. the stance feet stay where the default pose puts them; the lifted leg is at ``q_lift``
   (the excitation start pose);
2. the base moves horizontally until the centre of mass projects ``margin`` m inside the
   triangle of the three stance feet (nearest such point), the stance legs by inverse
   kinematics of their foot sites;
3. static equilibrium: vertical foot forces from the three-point support, joint torques
   ``tau = g(q) - J^T f`` (MuJoCo's gravity bias and foot-site Jacobians), and PD targets
   ``q + tau / kp`` so that the motors hold exactly that load (``kp_lift`` for the lifted leg,
   which the schedule drives to ``q_lift``: its joints sit at ``q_lift - tau / kp_lift``).

Positions world m, angles rad, joint vectors in model order (FL, FR, RL, RR).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from calib.joints import MODEL_LEGS
from calib.support import polygon_margin
from sim.model import FOOT_RADIUS  # a foot site's height when the foot stands on the floor

__all__ = ["FOOT_RADIUS", "TripodPose", "capture_margins", "support_point", "tripod_pose"]


@dataclass(frozen=True)
class TripodPose:
    """A level tripod stance in static equilibrium.

    leg: lifted leg (model index). qpos: (19,) MuJoCo qpos (base xyz m, quaternion wxyz, 12
    joints rad, model order). target: (12,) rad, the PD targets that hold it (lifted leg: its
    schedule target ``q_lift``). com_margin: m, distance of the centre of mass's projection
    inside the support triangle. foot_forces: (3,) N, vertical loads of the stance feet.
    """

    leg: int
    qpos: np.ndarray
    target: np.ndarray
    com_margin: float
    foot_forces: np.ndarray


def _edge_distances(p: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances (m, positive inside) of point p (2,) to the edges of triangle tri
    (3, 2), and the edges' inward unit normals (3, 2)."""
    a, b, c = tri
    orient = np.sign((b - a)[0] * (c - a)[1] - (b - a)[1] * (c - a)[0]) or 1.0
    d, n = [], []
    for p0, p1 in ((a, b), (b, c), (c, a)):
        e = (p1 - p0) / np.linalg.norm(p1 - p0)
        nin = orient * np.array([-e[1], e[0]])
        d.append(float(nin @ (p - p0)))
        n.append(nin)
    return np.array(d), np.array(n)


def capture_margins(com: np.ndarray, vel_xy: np.ndarray, feet: np.ndarray,
                    gravity: float = 9.81) -> tuple[np.ndarray, np.ndarray]:
    """(CoM margin, capture-point margin), m, each (N,): the signed :func:`polygon_margin` of
    the centre of mass's ground projection and of the instantaneous capture point
    ``c + v / w0``, ``w0 = sqrt(g / h)`` (a linear inverted pendulum on point feet, ``h`` the
    centre of mass's height over the feet's soles), in the polygon of the stance feet.
    com (N, 3) world m; vel_xy (N, 2) its horizontal velocity, m/s; feet (N, k, 3) the stance
    feet's centres (world m, k >= 3, in order around the polygon; a triangle's in any order);
    gravity m/s^2. A capture point outside the feet cannot be held without a step."""
    com, v, feet = (np.asarray(a, dtype=float) for a in (com, vel_xy, feet))
    h = com[:, 2] - np.mean(feet[:, :, 2] - FOOT_RADIUS, axis=1)
    xi = com[:, :2] + v / np.sqrt(gravity / np.maximum(h, 1e-3))[:, None]
    m = polygon_margin(np.concatenate([com[:, :2], xi]), np.concatenate([feet[:, :, :2]] * 2))
    return m[:len(com)], m[len(com):]


def support_point(com_xy: np.ndarray, tri: np.ndarray, margin: float) -> np.ndarray:
    """The point nearest ``com_xy`` that lies at least ``margin`` m inside triangle ``tri``
    (a shrunken triangle; alternating projections onto its edge half-planes converge to the
    nearest point because the feasible set is their intersection)."""
    p = np.asarray(com_xy, dtype=float).copy()
    for _ in range(200):
        d, n = _edge_distances(p, tri)
        k = int(np.argmin(d))
        if d[k] >= margin - 1e-9:
            break
        p = p + (margin - d[k]) * n[k]
    return p


def _foot_sites(m: mujoco.MjModel) -> list[int]:
    return [m.site(f"{leg}_foot").id for leg in MODEL_LEGS]


def _ik_leg(m, d, leg: int, target: np.ndarray, qadr: int, dadr: int, site: int) -> None:
    """Gauss-Newton on the leg's three joints so that its foot site reaches ``target`` (world)."""
    jac = np.zeros((3, m.nv))
    for _ in range(50):
        mujoco.mj_kinematics(m, d)
        err = target - d.site_xpos[site]
        if np.linalg.norm(err) < 1e-7:
            return
        mujoco.mj_comPos(m, d)
        mujoco.mj_jacSite(m, d, jac, None, site)
        j = jac[:, dadr + 3 * leg: dadr + 3 * leg + 3]
        d.qpos[qadr + 3 * leg: qadr + 3 * leg + 3] += np.linalg.lstsq(j, err, rcond=None)[0]
    raise ValueError(f"tripod pose: no inverse kinematics for leg {MODEL_LEGS[leg]} "
                     f"(residual {np.linalg.norm(err):.1e} m)")


def tripod_pose(model: mujoco.MjModel, leg: int, default_pose: np.ndarray, q_lift: np.ndarray,
                height: float, margin: float = 0.05, kp: float | np.ndarray = 20.0,
                kp_lift: float = 40.0, lifted: bool = True) -> TripodPose:
    """Level tripod stance lifting model leg ``leg`` (0..3), see the module docstring.

    model: the training model (free base ``base`` body, foot sites ``<leg>_foot``, hinge joints
    after the free joint). default_pose: (12,) rad, the four-leg stance that fixes the stance
    feet. q_lift: (3,) rad, the lifted leg's joints. height: base height, m. margin: m.
    kp, kp_lift: N m/rad of the stance motors (one, or (12,) in model order) and of the lifted
    leg's motors.
    lifted: False gives the stance at the end of the schedule's shift phase instead: the same
    support (the body over the three other feet) with the leg's foot still on the floor but
    unloaded (its target then holds only the leg's own weight, with ``kp``).
    """
    if leg not in range(4):
        raise ValueError(f"leg must be a model leg index 0..3, got {leg}")
    m = model
    d = mujoco.MjData(m)
    qadr, dadr = 7, 6
    sites = _foot_sites(m)
    base = m.body("base").id
    d.qpos[:3] = (0.0, 0.0, height)
    d.qpos[3:7] = (1.0, 0.0, 0.0, 0.0)
    d.qpos[qadr:qadr + 12] = default_pose
    mujoco.mj_kinematics(m, d)
    stance = [i for i in range(4) if i != leg]
    feet = d.site_xpos[sites].copy()
    feet[:, 2] = FOOT_RADIUS
    if lifted:
        d.qpos[qadr + 3 * leg: qadr + 3 * leg + 3] = q_lift
    tri = feet[stance, :2]
    for _ in range(20):  # base shift <-> centre of mass (the legs move with the base)
        for i in stance if lifted else range(4):
            _ik_leg(m, d, i, feet[i], qadr, dadr, sites[i])
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        com = d.subtree_com[base, :2].copy()
        goal = support_point(com, tri, margin)
        if np.linalg.norm(goal - com) < 1e-6:
            break
        d.qpos[:2] += goal - com
    else:
        raise ValueError("tripod pose: the base shift did not converge")
    mujoco.mj_forward(m, d)
    mass = float(m.body_subtreemass[base])
    g = -float(m.opt.gravity[2])
    com = d.subtree_com[base, :2]
    r = feet[stance, :2] - com
    # three vertical forces: sum = m g, zero moment about the centre of mass
    f = np.linalg.solve(np.vstack([np.ones(3), r[:, 0], r[:, 1]]), [mass * g, 0.0, 0.0])
    if np.any(f <= 0):
        raise ValueError(f"tripod pose: a stance foot carries no load ({f} N)")
    tau = d.qfrc_bias[dadr:dadr + 12].copy()  # gravity (qvel = 0)
    jac = np.zeros((3, m.nv))
    for i, fi in zip(stance, f, strict=True):
        mujoco.mj_jacSite(m, d, jac, None, sites[i])
        tau -= jac[:, dadr:dadr + 12].T @ np.array([0.0, 0.0, fi])
    q = d.qpos[qadr:qadr + 12].copy()
    target = q + tau / kp
    qpos = d.qpos.copy()
    if lifted:
        lj = slice(3 * leg, 3 * leg + 3)
        target[lj] = q_lift
        qpos[qadr + 3 * leg: qadr + 3 * leg + 3] = q_lift - tau[lj] / kp_lift
    margin_now = float(polygon_margin(com[None], tri[None])[0])
    return TripodPose(leg, qpos, target, margin_now, f)
