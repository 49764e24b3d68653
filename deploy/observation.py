"""The tripod policy's observation vector, built the same way in training and on board.

Pure numpy (no torch, no mujoco): ``policy_train`` builds its observations with this module and
``deploy`` builds the robot's with it, from the metadata JSON beside the ONNX
(``docs/policy-format.md``). The vector is::

    obs = clip(concat_k(scale_k * (value_k - offset_k)), -clip, clip)        float32

over the terms in metadata order (paper Table II): ``base_lin_vel`` (3, base frame, m/s),
``base_ang_vel`` (3, base frame, rad/s, the body gyro), ``projected_gravity`` (3, unit gravity
direction in the base frame), ``joint_pos`` (12, rad, SDK order, offset = the default pose),
``joint_vel`` (12, rad/s, SDK order), ``previous_actions`` (12, raw network outputs of the
previous step), ``commands`` (3, base angular-velocity command, base frame, rad/s),
``lift_command`` (1, 0 none, else the metadata's ``lift_command`` value of the leg).

A policy may see the last ``history`` such vectors, newest first, concatenated
(:class:`ObservationHistory`; the metadata's ``observation.history``, 1 when absent): the
paper's policy sees one, a distilled one (``docs/policy-training.md``, v8) a few, so that it
can tell the sensor noise from the motion.

A term whose ``source`` is ``"zero"`` is zero-filled whatever the signals hold: the tripod
policy is trained without a base linear velocity (the Go2 does not measure it; see
``docs/policy-training.md``), so deploy needs nothing but LowState.

Signals are arrays with any leading (batch) dimensions and the term size last; scalars are
broadcast. Joint vectors are in the SDK order (FR, FL, RR, RL).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

__all__ = [
    "OBS_SIZE",
    "TERM_NAMES",
    "TERM_SIZES",
    "ObservationHistory",
    "build_observation",
    "check_terms",
    "default_terms",
    "history_length",
    "observe_lifted_leg",
    "projected_gravity",
]

TERM_NAMES: tuple[str, ...] = (
    "base_lin_vel",
    "base_ang_vel",
    "projected_gravity",
    "joint_pos",
    "joint_vel",
    "previous_actions",
    "commands",
    "lift_command",
)
TERM_SIZES: dict[str, int] = {
    "base_lin_vel": 3,
    "base_ang_vel": 3,
    "projected_gravity": 3,
    "joint_pos": 12,
    "joint_vel": 12,
    "previous_actions": 12,
    "commands": 3,
    "lift_command": 1,
}
OBS_SIZE = sum(TERM_SIZES.values())  # 49
SOURCES = ("measured", "zero", "leg_odometry")


def default_terms(default_pose, lin_vel_source: str = "zero") -> list[dict]:
    """The tripod policy's terms (paper order) with their scales, as metadata dicts.

    default_pose: (12,) rad, SDK order, the ``joint_pos`` offset. lin_vel_source: the
    ``source`` of ``base_lin_vel`` (``"zero"`` for the shipped policy).
    """
    dp = np.asarray(default_pose, dtype=float)
    if dp.shape != (12,) or not np.all(np.isfinite(dp)):
        raise ValueError("default_pose must be 12 finite angles (rad, SDK order)")
    if lin_vel_source not in SOURCES:
        raise ValueError(f"lin_vel_source must be one of {SOURCES}, got {lin_vel_source!r}")
    return [
        {"name": "base_lin_vel", "size": 3, "scale": 2.0, "source": lin_vel_source},
        {"name": "base_ang_vel", "size": 3, "scale": 0.25, "source": "measured"},
        {"name": "projected_gravity", "size": 3, "scale": 1.0, "source": "measured"},
        {"name": "joint_pos", "size": 12, "scale": 1.0, "offset": [float(x) for x in dp],
         "source": "measured"},
        {"name": "joint_vel", "size": 12, "scale": 0.05, "source": "measured"},
        {"name": "previous_actions", "size": 12, "scale": 1.0, "source": "measured"},
        {"name": "commands", "size": 3, "scale": 0.25, "source": "measured"},
        {"name": "lift_command", "size": 1, "scale": 0.25, "source": "measured"},
    ]


def check_terms(terms: Sequence[Mapping]) -> None:
    """Raise ValueError unless ``terms`` name known terms with their sizes and finite scales."""
    if not isinstance(terms, Sequence) or len(terms) == 0:
        raise ValueError("observation terms must be a non-empty list")
    for t in terms:
        name = t.get("name")
        if name not in TERM_SIZES:
            raise ValueError(f"unknown observation term {name!r}: expected one of {TERM_NAMES}")
        if int(t.get("size", -1)) != TERM_SIZES[name]:
            raise ValueError(f"term {name} must have size {TERM_SIZES[name]}, got {t.get('size')}")
        if t.get("source", "measured") not in SOURCES:
            raise ValueError(f"term {name}: unknown source {t.get('source')!r}")
        for key in ("scale", "offset"):
            if key in t:
                v = np.asarray(t[key], dtype=float)
                if v.shape not in ((), (TERM_SIZES[name],)) or not np.all(np.isfinite(v)):
                    raise ValueError(f"term {name}: {key} must be finite, scalar or size {t['size']}")


def build_observation(terms, signals: Mapping[str, np.ndarray], clip: float | None = None
                      ) -> np.ndarray:
    """The observation vector(s), float32, shape (*batch, sum of sizes).

    terms: the metadata's ``observation.terms`` list, or the whole ``observation`` object
    (then its ``clip`` is used unless ``clip`` is given). signals: term name -> value array
    (*batch, size) in the units of the module docstring; terms with source ``"zero"`` need no
    signal. All signals must broadcast to one batch shape.
    """
    if isinstance(terms, Mapping):
        if clip is None and terms.get("clip") is not None:
            clip = float(terms["clip"])
        terms = terms["terms"]
    check_terms(terms)
    parts = []
    batch = None
    for t in terms:
        name, size = t["name"], TERM_SIZES[t["name"]]
        if t.get("source", "measured") == "zero":
            parts.append(None)
            continue
        if name not in signals:
            raise ValueError(f"missing signal {name!r} for the observation")
        v = np.asarray(signals[name], dtype=np.float64)
        if v.ndim == 0 or v.shape[-1] != size:
            if size == 1:
                v = v[..., None]
            else:
                raise ValueError(f"signal {name} must end in size {size}, got shape {v.shape}")
        v = (v - np.asarray(t.get("offset", 0.0), dtype=np.float64)) * np.asarray(
            t.get("scale", 1.0), dtype=np.float64)
        lead = v.shape[:-1]
        batch = lead if batch is None else np.broadcast_shapes(batch, lead)
        parts.append(v)
    batch = () if batch is None else batch
    out = []
    for t, p in zip(terms, parts, strict=True):
        size = TERM_SIZES[t["name"]]
        out.append(np.zeros(batch + (size,)) if p is None else np.broadcast_to(p, batch + (size,)))
    obs = np.concatenate(out, axis=-1)
    if clip is not None:
        if not (np.isfinite(clip) and clip > 0):
            raise ValueError(f"clip must be a positive number, got {clip}")
        np.clip(obs, -clip, clip, out=obs)
    return obs.astype(np.float32)


def observe_lifted_leg(signals: Mapping[str, np.ndarray], idx, q_centre, seen: float) -> dict:
    """``signals`` with the lifted leg's joints observed at ``seen`` of their excursion from
    ``q_centre``: ``joint_pos`` ``q_centre + seen (q - q_centre)`` rad, ``joint_vel`` ``seen
    dq`` rad/s (a lift schedule's ``excitation_seen``, :class:`deploy.lift_schedule.LiftSchedule`;
    0: the leg still at ``q_centre``). idx: the leg's 3 columns of the joints (SDK order), or
    (n, 3) of n rows of batched signals; q_centre: rad, (3,) or (n, 3). The other signals are
    the same objects; the caller's arrays are not written."""
    q = np.array(signals["joint_pos"], dtype=float)
    dq = np.array(signals["joint_vel"], dtype=float)
    idx = np.asarray(idx)
    c = np.asarray(q_centre, dtype=float)
    if q.ndim == 1:
        q[idx] = c + seen * (q[idx] - c)
        dq[idx] *= seen
    else:
        leg = np.take_along_axis(q, idx, axis=1)
        np.put_along_axis(q, idx, c + seen * (leg - c), axis=1)
        np.put_along_axis(dq, idx, seen * np.take_along_axis(dq, idx, axis=1), axis=1)
    return {**signals, "joint_pos": q, "joint_vel": dq}


def projected_gravity(quat_wxyz) -> np.ndarray:
    """Unit gravity direction in the base frame from the base orientation (w, x, y, z,
    base -> world), batched over leading dims: ``R^T @ (0, 0, -1)``. Level base: (0, 0, -1).
    """
    q = np.asarray(quat_wxyz, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ValueError(f"quaternion must end in size 4 (w, x, y, z), got {q.shape}")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < 1e-9):
        raise ValueError("zero quaternion")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    # third row of R (world z in base coordinates), negated
    return -np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)


def history_length(observation: Mapping) -> int:
    """Frames the policy sees (the metadata ``observation`` object's ``history``, default 1);
    ValueError unless ``size`` is that many 49-value frames."""
    h = observation.get("history", 1)
    if isinstance(h, bool) or not isinstance(h, int) or h < 1:
        raise ValueError(f"observation history must be a positive integer, got {h!r}")
    frame = sum(TERM_SIZES[t["name"]] for t in observation["terms"])
    if int(observation.get("size", frame * h)) != frame * h:
        raise ValueError(f"observation size {observation.get('size')} is not {h} frames of "
                         f"{frame}")
    return h


class ObservationHistory:
    """The last ``length`` observation frames, newest first, as the policy's input.

    Batched over ``batch`` (a shape; ``()`` on board). A frame pushed for a batch element
    that is fresh (just constructed, or named in :meth:`reset`) fills its whole history, so a
    policy starts as if it had stood still in that state: no zeros it never saw in training.
    """

    def __init__(self, length: int, frame_size: int, batch: tuple[int, ...] = ()):
        if length < 1:
            raise ValueError(f"history length must be >= 1, got {length}")
        self.length, self.frame_size = int(length), int(frame_size)
        self.frames = np.zeros((*batch, self.length, self.frame_size), dtype=np.float32)
        self.fresh = np.ones(batch, dtype=bool)

    def reset(self, index=...) -> None:
        """Mark batch elements (all by default) fresh: their next frame fills the history."""
        self.fresh[index] = True

    def push(self, frame: np.ndarray) -> np.ndarray:
        """Add the newest frame(s) (*batch, frame_size); return the policy input
        (*batch, length * frame_size) float32, newest frame first."""
        f = np.asarray(frame, dtype=np.float32)
        if f.shape != self.frames.shape[:-2] + (self.frame_size,):
            raise ValueError(f"frame must have shape {self.frames.shape[:-2] + (self.frame_size,)}"
                             f", got {f.shape}")
        self.frames[..., 1:, :] = self.frames[..., :-1, :]
        self.frames[..., 0, :] = f
        if np.any(self.fresh):
            self.frames[self.fresh] = f[self.fresh][..., None, :]
            self.fresh[...] = False
        return self.frames.reshape(*self.frames.shape[:-2], -1).copy()
