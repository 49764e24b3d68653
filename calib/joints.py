"""Leg and joint naming, and the one place where joint orders are mapped.

Two orders exist on a Go2:

* SDK order (wire, logs, policy, CSV): FR, FL, RR, RL x (hip, thigh, calf), indices 0-11.
* Model order (URDF, pinocchio, MuJoCo): FL, FR, RL, RR x (hip, thigh, calf).

Every conversion between them goes through ``SDK_TO_MODEL`` / ``MODEL_TO_SDK`` below.
"""

from __future__ import annotations

import numpy as np

LEGS: tuple[str, ...] = ("FL", "FR", "RL", "RR")
"""Leg names in the URDF / model order."""
JOINTS: tuple[str, ...] = ("hip", "thigh", "calf")

SDK_LEGS: tuple[str, ...] = ("FR", "FL", "RR", "RL")
"""Leg order of the Unitree SDK motor indices (motor 3*i+j is leg SDK_LEGS[i], joint JOINTS[j])."""
MODEL_LEGS: tuple[str, ...] = LEGS

SDK_JOINT_NAMES: tuple[str, ...] = tuple(f"{leg}_{j}" for leg in SDK_LEGS for j in JOINTS)
MODEL_JOINT_NAMES: tuple[str, ...] = tuple(f"{leg}_{j}" for leg in MODEL_LEGS for j in JOINTS)

# model_array = sdk_array[SDK_TO_MODEL];  sdk_array = model_array[MODEL_TO_SDK]
SDK_TO_MODEL: np.ndarray = np.array([SDK_JOINT_NAMES.index(n) for n in MODEL_JOINT_NAMES])
MODEL_TO_SDK: np.ndarray = np.array([MODEL_JOINT_NAMES.index(n) for n in SDK_JOINT_NAMES])

NUM_MOTORS = 12


def check_leg(leg: str) -> str:
    """Return ``leg`` upper-cased, or raise ValueError naming the valid legs."""
    up = str(leg).upper()
    if up not in LEGS:
        raise ValueError(f"unknown leg {leg!r}: expected one of {', '.join(LEGS)}")
    return up


def sdk_indices(leg: str) -> np.ndarray:
    """SDK motor indices (hip, thigh, calf) of ``leg``."""
    i = SDK_LEGS.index(check_leg(leg))
    return np.arange(3 * i, 3 * i + 3)


def model_indices(leg: str) -> np.ndarray:
    """Model-order joint indices (hip, thigh, calf) of ``leg``."""
    i = MODEL_LEGS.index(check_leg(leg))
    return np.arange(3 * i, 3 * i + 3)


def sdk_to_model(x: np.ndarray) -> np.ndarray:
    """Reorder the last axis (length 12) from SDK order to model order."""
    return np.asarray(x)[..., SDK_TO_MODEL]


def model_to_sdk(x: np.ndarray) -> np.ndarray:
    """Reorder the last axis (length 12) from model order to SDK order."""
    return np.asarray(x)[..., MODEL_TO_SDK]


def is_front(leg: str) -> bool:
    return check_leg(leg)[0] == "F"


def is_left(leg: str) -> bool:
    return check_leg(leg)[1] == "L"


# Go2 joint limits (rad, rad/s, N m), per leg, (hip, thigh, calf); from the example-robot-data URDF.
HIP_RANGE = (-1.0472, 1.0472)
FRONT_THIGH_RANGE = (-1.5708, 3.4907)
REAR_THIGH_RANGE = (-0.5236, 4.5379)
CALF_RANGE = (-2.7227, -0.83776)
VELOCITY_LIMIT = np.array([30.1, 30.1, 15.7])
EFFORT_LIMIT = np.array([23.7, 23.7, 45.43])


def position_limits(leg: str) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) joint position limits of ``leg`` (hip, thigh, calf), rad."""
    thigh = FRONT_THIGH_RANGE if is_front(leg) else REAR_THIGH_RANGE
    lo = np.array([HIP_RANGE[0], thigh[0], CALF_RANGE[0]])
    hi = np.array([HIP_RANGE[1], thigh[1], CALF_RANGE[1]])
    return lo, hi


# Poses (per leg hip, thigh, calf; hip sign: left +, right -), rad.
STAND_POSE_LEG = np.array([0.0, 0.67, -1.3])
LIE_POSE_LEG = np.array([0.0, 1.36, -2.65])
CROUCH_POSE_FRONT = np.array([0.1, 0.8, -1.5])
CROUCH_POSE_REAR = np.array([0.1, 1.0, -1.5])


def pose_for_leg(leg: str, leg_pose: np.ndarray) -> np.ndarray:
    """Mirror a (hip, thigh, calf) pose for ``leg``: hip angle keeps its sign on left legs."""
    p = np.array(leg_pose, dtype=float)
    if not is_left(leg):
        p[0] = -p[0]
    return p


def full_pose(per_leg: dict[str, np.ndarray] | np.ndarray, order: str = "model") -> np.ndarray:
    """12-vector of joint positions from one (hip, thigh, calf) pose (mirrored per leg) or a dict."""
    legs = MODEL_LEGS if order == "model" else SDK_LEGS
    out = []
    for leg in legs:
        p = per_leg[leg] if isinstance(per_leg, dict) else pose_for_leg(leg, per_leg)
        out.append(np.asarray(p, dtype=float))
    return np.concatenate(out)


def default_crouch(order: str = "model") -> np.ndarray:
    """The common RL default crouch pose (FACTS.md) as a 12-vector in ``order``."""
    d = {
        leg: pose_for_leg(leg, CROUCH_POSE_FRONT if is_front(leg) else CROUCH_POSE_REAR)
        for leg in LEGS
    }
    return full_pose(d, order)
