"""The tripod policy on board: its metadata JSON and its ONNX network (``docs/policy-format.md``).

``PolicyMeta.load(json_path)`` validates everything ``deploy`` relies on, so that nothing about a
policy is hard-coded here; ``PolicyRunner`` runs the ONNX graph with ONNX Runtime on one thread
(batch 1) and keeps the ``delta_target`` action state. Joint vectors are in SDK order
(FR, FL, RR, RL x hip, thigh, calf), rad.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.joints import LEGS, SDK_JOINT_NAMES, check_leg
from deploy.action import next_target
from deploy.lift_schedule import LiftSchedule
from deploy.observation import TERM_SIZES, ObservationHistory, check_terms, history_length

__all__ = ["PolicyMeta", "PolicyRunner", "default_policy_path", "policies_for_legs"]

ACTION_MODES = ("delta_target",)


def _vec12(d: Mapping, key: str, where: str = "") -> np.ndarray:
    if key not in d:
        raise ValueError(f"policy metadata lacks {where}{key}")
    v = np.asarray(d[key], dtype=float)
    if v.shape != (12,) or not np.all(np.isfinite(v)):
        raise ValueError(f"policy metadata {where}{key} must be 12 finite numbers (SDK order)")
    return v


@dataclass
class PolicyMeta:
    """What the policy JSON (schema_version 1) tells deploy. Units SI, joint order SDK.

    control_dt s; default_pose rad; kp N m/rad, kd N m s/rad; action_scale rad per unit action;
    action_clip (unitless, on the raw action); soft_lower/soft_upper rad; target_lead_max rad
    (or None): how far a target may lead its joint (``deploy.action``); observation: the
    metadata's ``observation`` object (size, clip, terms); lift_command: leg -> term value
    (``"none"`` included); schedule: the :class:`LiftSchedule` of ``lift_schedule``.
    """

    path: Path
    onnx_path: Path
    name: str
    control_dt: float
    default_pose: np.ndarray
    kp: np.ndarray
    kd: np.ndarray
    action_scale: float
    action_clip: float
    action_mode: str
    soft_lower: np.ndarray
    soft_upper: np.ndarray
    observation: dict
    lift_command: dict[str, float]
    schedule: LiftSchedule
    legs: tuple[str, ...] = LEGS
    target_lead_max: np.ndarray | None = None
    raw: dict = field(repr=False, default_factory=dict)

    @classmethod
    def load(cls, path: str | os.PathLike) -> PolicyMeta:
        """The metadata at ``path``; an ``.onnx`` path means the JSON beside it, as every other
        command names a policy by its ONNX."""
        p = Path(path)
        if p.suffix == ".onnx":
            p = p.with_suffix(".json")
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except OSError as e:
            raise ValueError(f"cannot read policy metadata {str(p)!r}: {e.strerror or e}") from None
        except UnicodeDecodeError:
            raise ValueError(f"policy metadata {str(p)!r} is not JSON text (name the policy's "
                             ".json or .onnx)") from None
        except json.JSONDecodeError as e:
            raise ValueError(f"policy metadata {str(p)!r} is not valid JSON: {e.msg}") from None
        try:
            return cls.from_dict(d, p)
        except ValueError as e:
            raise ValueError(f"{p}: {e}") from None

    @classmethod
    def from_dict(cls, d: Mapping, path: Path) -> PolicyMeta:
        """The metadata ``d`` (read from ``path``); ValueError (one line) if malformed."""
        try:
            return cls._from_dict(d, path)
        except (TypeError, AttributeError, KeyError) as e:  # a value of the wrong type
            raise ValueError(f"malformed metadata ({type(e).__name__}: {e})") from None

    @classmethod
    def _from_dict(cls, d: Mapping, path: Path) -> PolicyMeta:
        if not isinstance(d, Mapping):
            raise ValueError("policy metadata must be a JSON object")  # noqa: TRY004
        if d.get("schema_version") != 1:
            raise ValueError(f"unsupported schema_version {d.get('schema_version')!r} (need 1)")
        if list(d.get("joint_order", [])) != list(SDK_JOINT_NAMES):
            raise ValueError("joint_order must be the SDK order " + ", ".join(SDK_JOINT_NAMES))
        onnx_name = d.get("onnx")
        if not isinstance(onnx_name, str) or not onnx_name:
            raise ValueError("policy metadata lacks the onnx file name")
        dt = float(d.get("control_dt", float("nan")))
        if not (np.isfinite(dt) and 0.001 <= dt <= 0.1):
            raise ValueError(f"control_dt must be in [0.001, 0.1] s, got {d.get('control_dt')}")
        act = d.get("action") or {}
        if int(act.get("size", 0)) != 12:
            raise ValueError("action.size must be 12")
        mode = act.get("mode")
        if mode not in ACTION_MODES:
            raise ValueError(f"action.mode must be one of {ACTION_MODES}, got {mode!r}")
        scale, clip = float(act.get("scale", "nan")), float(act.get("clip", "nan"))
        if not (np.isfinite(scale) and scale > 0 and np.isfinite(clip) and clip > 0):
            raise ValueError("action.scale and action.clip must be positive numbers")
        lead_max = None
        if act.get("target_lead_max") is not None:
            lead_max = _vec12(act, "target_lead_max", "action.")
            if np.any(lead_max <= 0):
                raise ValueError("action.target_lead_max must be positive on every joint")
        lim = d.get("soft_limits") or {}
        lower = _vec12(lim, "lower", "soft_limits.")
        upper = _vec12(lim, "upper", "soft_limits.")
        if np.any(lower >= upper):
            raise ValueError("soft_limits.lower must be below soft_limits.upper")
        obs = d.get("observation")
        if not isinstance(obs, Mapping) or "terms" not in obs:
            raise ValueError("policy metadata lacks observation.terms")
        check_terms(obs["terms"])
        history_length(obs)  # ValueError unless size is whole frames of the terms
        c = obs.get("clip")  # checked here, not at the first tick of a lift
        if isinstance(c, bool) or not isinstance(c, int | float) or not (np.isfinite(c) and c > 0):
            raise ValueError(f"observation.clip must be a positive number, got {c!r}")
        for t in obs["terms"]:
            if t["name"] == "base_lin_vel" and t.get("source", "zero") != "zero":
                # the loop has no velocity estimate: it would feed such a policy zeros
                raise ValueError(f"base_lin_vel from {t.get('source')!r}: deploy gives it only "
                                 "as zero (source 'zero')")
        lc = d.get("lift_command") or {}
        lift = {}
        for leg in ("none", "FL", "FR", "RL", "RR"):
            if leg not in lc or not np.isfinite(float(lc[leg])):
                raise ValueError(f"lift_command lacks a finite value for {leg!r}")
            lift[leg] = float(lc[leg])
        kp, kd = _vec12(d, "kp"), _vec12(d, "kd")
        if np.any(kp < 0) or np.any(kd < 0):
            raise ValueError("kp and kd must be >= 0")
        default_pose = _vec12(d, "default_pose")
        if np.any(default_pose < lower) or np.any(default_pose > upper):
            raise ValueError("default_pose must lie within soft_limits")
        legs = d.get("legs", list(LEGS))
        if not isinstance(legs, list) or not legs or any(g not in LEGS for g in legs):
            raise ValueError(f"legs must be a non-empty list of {', '.join(LEGS)}")
        return cls(
            path=path, onnx_path=path.parent / onnx_name, name=str(d.get("name", path.stem)),
            control_dt=dt, default_pose=default_pose, kp=kp, kd=kd,
            action_scale=scale, action_clip=clip, action_mode=mode,
            soft_lower=lower, soft_upper=upper, observation=dict(obs), lift_command=lift,
            schedule=LiftSchedule.from_metadata(d.get("lift_schedule") or {}),
            legs=tuple(g for g in LEGS if g in legs), target_lead_max=lead_max, raw=dict(d),
        )

    @property
    def trained_latency_s(self) -> tuple[float, float] | None:
        """(lo, hi) s: the actuation latency the policy was trained under (its training's
        ``latency_steps`` of physics steps); None where its JSON does not say, or the training
        drew none (randomisation off)."""
        env = (self.raw.get("train_config") or {}).get("env") or {}
        dr = env.get("dr") or {}
        steps, dt = dr.get("latency_steps"), env.get("physics_dt")
        try:
            lo, hi = (float(v) * float(dt) for v in steps)
        except (TypeError, ValueError):
            return None
        ok = np.isfinite(lo) and np.isfinite(hi) and 0 <= lo <= hi
        return (lo, hi) if ok and dr.get("enabled", True) else None

    def lift_value(self, leg: str | None) -> float:
        """The ``lift_command`` term's value for ``leg`` (None: no leg lifted)."""
        return self.lift_command["none" if leg is None else check_leg(leg)]

    @property
    def obs_size(self) -> int:
        """Values in one observation frame (49)."""
        return sum(TERM_SIZES[t["name"]] for t in self.observation["terms"])

    @property
    def history(self) -> int:
        """Frames the network sees, newest first (``observation.history``, 1 when absent)."""
        return history_length(self.observation)

    @property
    def input_size(self) -> int:
        """The network's input width: ``history`` frames of ``obs_size``."""
        return self.obs_size * self.history


def default_policy_path(search: list[Path] | None = None, leg: str | None = None) -> Path:
    """The newest policy JSON (by ``created_utc``, then file time) in ``policies/`` of the
    working directory, else of the installed source tree, that serves ``leg`` (its ``legs``
    list; absent = all four; ``leg`` None: a policy for all four legs); ValueError when there
    is none."""
    dirs = search or [Path.cwd() / "policies", Path(__file__).resolve().parents[1] / "policies"]
    want = set(LEGS) if leg is None else {check_leg(leg)}
    for d in dirs:
        found = []
        for p in sorted(d.glob("*.json")):
            try:
                meta = json.loads(p.read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError, json.JSONDecodeError):
                continue
            legs = meta.get("legs", LEGS) if isinstance(meta, dict) else None
            if (isinstance(meta, dict) and meta.get("schema_version") == 1 and "onnx" in meta
                    and isinstance(legs, list | tuple) and want <= set(map(str, legs))):
                found.append((str(meta.get("created_utc", "")), p.stat().st_mtime, p.name, p))
        if found:
            return max(found)[-1]
    where = " or ".join(str(d) for d in dirs)
    what = "" if leg is None else f" serving {leg}"
    raise ValueError(f"no policy JSON{what} found in {where}: give --policy PATH")


def policies_for_legs(legs, path: str | os.PathLike | None = None,
                      search: list[Path] | None = None) -> dict[str, PolicyMeta]:
    """leg -> :class:`PolicyMeta` for each of ``legs``: ``path`` for all of them (ValueError if
    its ``legs`` list lacks one), else each leg's newest policy (:func:`default_policy_path`).
    Legs that share a file share one object. All must agree on what the loop and the stand
    rely on (control period, default pose, soft limits), since deploy switches between them
    only at TRIPOD's first tick."""
    legs = [check_leg(g) for g in legs]
    if not legs:
        raise ValueError("no legs to find a policy for")
    paths = {g: Path(path) if path is not None else default_policy_path(search, g) for g in legs}
    loaded: dict[Path, PolicyMeta] = {}
    out = {}
    for g, p in paths.items():
        if p not in loaded:
            loaded[p] = PolicyMeta.load(p)
        m = loaded[p]
        if g not in m.legs:
            raise ValueError(f"policy {p} serves {', '.join(m.legs)}, not {g}")
        out[g] = m
    first = next(iter(loaded.values()))
    for m in loaded.values():
        if (m.control_dt != first.control_dt or not np.allclose(m.default_pose, first.default_pose)
                or not np.allclose(m.soft_lower, first.soft_lower)
                or not np.allclose(m.soft_upper, first.soft_upper)):
            raise ValueError(f"policies {first.path} and {m.path} differ in control_dt, "
                             "default_pose or soft_limits: they cannot share one run")
    return out


class PolicyRunner:
    """ONNX Runtime on one thread, batch 1: ``act(obs (49,)) -> raw actions (12,)`` float32.

    A policy that sees several frames (``PolicyMeta.history``) gets the newest ``act`` was
    given, newest first (:class:`deploy.observation.ObservationHistory`), as in training.
    Targets follow the metadata's ``delta_target`` rule (``step``): ``target = prev + scale *
    clip(a, -c, c)``, clamped to the soft limits; ``reset(q)`` sets the previous target to the
    joint positions when the policy (re)starts, zeroes the previous actions and starts a new
    history (the next frame fills it, as a training episode's first frame does).
    """

    def __init__(self, meta: PolicyMeta):
        import onnxruntime as ort  # deploy extra; imported here so the module loads without it

        if not meta.onnx_path.is_file():
            raise ValueError(f"policy network {meta.onnx_path} not found (named in {meta.path})")
        so = ort.SessionOptions()
        so.intra_op_num_threads = 1
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.log_severity_level = 3
        self.session = ort.InferenceSession(str(meta.onnx_path), so,
                                            providers=["CPUExecutionProvider"])
        ins = {i.name: i for i in self.session.get_inputs()}
        outs = {o.name: o for o in self.session.get_outputs()}
        if "obs" not in ins or "actions" not in outs:
            raise ValueError(f"{meta.onnx_path}: expected input 'obs' and output 'actions', got "
                             f"{sorted(ins)} -> {sorted(outs)}")
        width = ins["obs"].shape[-1]
        if isinstance(width, int) and width != meta.input_size:
            raise ValueError(f"{meta.onnx_path}: obs width {width} != metadata {meta.input_size} "
                             f"({meta.history} frame(s) of {meta.obs_size})")
        self.meta = meta
        self._in = np.zeros((1, meta.input_size), np.float32)
        self.frames = ObservationHistory(meta.history, meta.obs_size)
        self.prev_actions = np.zeros(12, np.float32)
        self.target = meta.default_pose.copy()

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Raw network output (12,) float32 for the newest observation frame (49,)."""
        self._in[0] = self.frames.push(obs)
        out = self.session.run(["actions"], {"obs": self._in})[0]
        a = np.asarray(out, np.float32).reshape(-1)
        if a.shape != (12,):
            raise ValueError(f"policy output has shape {np.shape(out)}, expected (1, 12)")
        return a

    def reset(self, q: np.ndarray) -> None:
        self.target = np.asarray(q, dtype=float).copy()
        self.prev_actions = np.zeros(12, np.float32)
        self.frames.reset()

    def step(self, actions: np.ndarray, q: np.ndarray | None = None) -> np.ndarray:
        """Apply raw ``actions`` to the target (the delta_target rule, :mod:`deploy.action`);
        returns the new target. q: the measured joints, rad (SDK order), which a policy with a
        ``target_lead_max`` needs."""
        m = self.meta
        a = np.clip(actions.astype(float), -m.action_clip, m.action_clip)
        self.target = next_target(self.target, m.action_scale * a, m.soft_lower, m.soft_upper,
                                  None if q is None else np.asarray(q, dtype=float),
                                  m.target_lead_max)
        self.prev_actions = actions.astype(np.float32)
        return self.target
