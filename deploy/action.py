"""The policy's joint targets from its actions (``action.mode`` ``delta_target``), the same in
training and on board.

Pure numpy. ``target = clip(target + delta, soft_lower, soft_upper)``, ``delta`` the action
scale times the clipped raw action, every 12-vector in one joint order (the caller's). With
``lead_max`` the new target is first held within ``lead_max`` of the joints' measured positions
``q``: at ``effort / kp`` from its joint a motor's PD law already asks for the motor's whole
torque, so a target further out gives no more torque now, only a wound-up demand the network
must take back, one ``scale`` per tick, once the load passes (``docs/policy-format.md``,
``action.target_lead_max``; ``docs/policy-training.md``, "Stop 75").
"""

from __future__ import annotations

import numpy as np

from calib.joints import EFFORT_LIMIT

__all__ = ["lead_max_for_torque", "next_target"]


def next_target(target: np.ndarray, delta: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                q: np.ndarray | None = None, lead_max: np.ndarray | None = None) -> np.ndarray:
    """The new joint targets, rad, (..., 12): ``target + delta`` held within ``lead_max`` rad
    of ``q`` (when ``lead_max`` is given; ``q`` rad, the measured joints), then within the soft
    limits ``lower`` / ``upper`` rad, which always win. Leading dimensions broadcast
    (environments)."""
    new = target + delta
    if lead_max is not None:
        if q is None:
            raise ValueError("a target lead bound needs the measured joint positions q")
        new = np.clip(new, q - lead_max, q + lead_max)
    return np.clip(new, lower, upper)


def lead_max_for_torque(kp, effort=None) -> np.ndarray:
    """``effort / kp`` rad per joint: how far a target may lead its joint before the PD law
    (kp N m/rad) asks for more than the motor's effort limit (N m). kp: one value or 12, in
    either joint order (both go hip, thigh, calf per leg); effort: the Go2's limits,
    :data:`calib.joints.EFFORT_LIMIT` per joint, unless given. ValueError unless every kp and
    effort is positive and finite."""
    if effort is None:
        kp, effort = np.broadcast_to(np.asarray(kp, dtype=float), (12,)), np.tile(EFFORT_LIMIT, 4)
    kp, effort = np.asarray(kp, dtype=float), np.asarray(effort, dtype=float)
    if not (np.all(np.isfinite(kp)) and np.all(kp > 0) and np.all(np.isfinite(effort))
            and np.all(effort > 0)):
        raise ValueError("a torque lead bound needs kp > 0 and effort limits > 0 on every joint")
    return effort / kp
