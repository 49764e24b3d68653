"""Export a training checkpoint to the deploy contract: ``<name>.onnx`` + ``<name>.json``.

The ONNX holds the actor's mean only (no sampling), input ``obs`` float32 [batch, 49 x the
observation history (1 frame for the PPO policies)], output
``actions`` float32 [batch, 12], dynamic batch, one file (no external data); it is checked with
onnxruntime against torch on random inputs before anything is written. The JSON follows
``docs/policy-format.md`` (schema_version 1). Both files are written atomically.
"""

from __future__ import annotations

import datetime
import io
import json
import subprocess
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from calib.atomic import write_bytes_atomic, write_text_atomic
from calib.joints import SDK_JOINT_NAMES, check_leg, model_to_sdk
from deploy.action import lead_max_for_torque
from deploy.lift_schedule import LiftSchedule
from deploy.observation import OBS_SIZE
from policy_train.config import TrainConfig

__all__ = ["average_checkpoints", "build_metadata", "derive_policy", "export_policy",
           "git_commit", "train_state_path"]

# s, the deploy schedule's excitation: 0.4, faster than calib's 0.5 default, for more foot
# angular velocity per second at the same success (docs/policy-training.md, "Adopted: a
# faster excitation"); the committed policies' JSONs carried it by hand until v17
EVAL_T_R = 0.4
EVAL_PERIODS = 4


class _Actor(torch.nn.Module):
    def __init__(self, mlp: torch.nn.Module):
        super().__init__()
        self.mlp = mlp

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.mlp(obs)


def _actor_from_checkpoint(d: dict, cfg: TrainConfig) -> torch.nn.Module:
    """Rebuild the actor MLP (mean) from the rsl-rl state dict."""
    from rsl_rl.modules import MLP

    sd = d["actor_state_dict"]
    mlp = MLP(OBS_SIZE * cfg.env.obs_history, 12, list(cfg.ppo.actor_hidden), "elu")
    mlp.load_state_dict({k[len("mlp."):]: v for k, v in sd.items() if k.startswith("mlp.")})
    if any(k.startswith("obs_normalizer.") for k in sd):
        raise ValueError("actor observation normalisation is not supported by this exporter")
    return _Actor(mlp).eval()


def average_checkpoints(ckpts: list[dict]) -> dict:
    """One checkpoint whose actor is the element-wise mean of the given ones' actor weights
    (the last one's configuration, iteration and history). Neighbouring PPO checkpoints of one
    run differ by 10-20 points of success under randomisation (docs/policy-training.md, v7);
    their mean is steadier than any of them. They must come from one run: the same
    configuration, network and keys."""
    if not ckpts:
        raise ValueError("no checkpoint to average")
    last = max(ckpts, key=lambda d: int(d["iter"]))
    shapes = {k: v.shape for k, v in last["actor_state_dict"].items()}

    def ppo(d):  # how often a run saved says nothing of its network
        return {k: v for k, v in d["train_config"]["ppo"].items() if k != "save_interval"}

    for d in ckpts:
        if ppo(d) != ppo(last) or \
                {k: v.shape for k, v in d["actor_state_dict"].items()} != shapes:
            raise ValueError(f"checkpoint of iteration {d['iter']} has another PPO configuration "
                             "or network than the others: average checkpoints of one run only")
    sd = {k: (torch.stack([d["actor_state_dict"][k] for d in ckpts]).mean(0)
              if v.is_floating_point() else v)
          for k, v in last["actor_state_dict"].items()}
    return {**last, "actor_state_dict": sd,
            "averaged_iterations": sorted(int(d["iter"]) for d in ckpts)}


def git_commit(repo: str | Path | None = None) -> str:
    """``git rev-parse HEAD`` of the repository at ``repo`` (default: the one this package is
    in, wherever the command runs from), + ``-dirty`` when a tracked file differs from it or
    a Python file is not yet tracked; ``unknown`` outside a repository. The files a run writes
    beside the code (policies, pages, ES states) are not the code: left untracked while
    it runs, they would have made every policy trained or refined in a checkout read dirty."""
    repo = Path(__file__).resolve().parents[1] if repo is None else Path(repo)
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True,
                              text=True, check=True, timeout=10).stdout.strip()
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=all"],
                                cwd=repo, capture_output=True, text=True, check=True,
                                timeout=10).stdout.splitlines()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    dirty = any(not line.startswith("??") or line.rstrip().rstrip('"').endswith(".py")
                for line in status)  # porcelain quotes a name with odd characters
    return head + ("-dirty" if dirty else "")


def build_metadata(name: str, cfg: TrainConfig, seed: int, iterations: int,
                   legs=None) -> dict:
    """The JSON object of ``docs/policy-format.md`` (``evaluation`` empty until eval runs).
    legs: the legs deploy may lift with this policy (None: all four)."""
    import calib.joints as cj
    from deploy.observation import default_terms
    from policy_train.env import LIFT_VALUES
    from policy_train.model import ARMATURE

    e = cfg.env
    default = cj.default_crouch("sdk")
    lo, hi = e.soft_limits(cj.SDK_LEGS)
    sched = LiftSchedule(shift=e.shift_s, shift_by_leg=e.shift_by_leg, lift=e.lift_s,
                         hold=e.hold_s, lower=e.lower_s, kp=e.lift_kp, kd=e.lift_kd, t_r=EVAL_T_R, n_basis=e.n_basis,
                         periods=EVAL_PERIODS, seed=0, ground_clearance=e.ground_clearance,
                         feedforward=e.lift_feedforward, adapt=e.lift_adapt,
                         excitation_seen=e.excitation_seen)
    fl = lambda a: [float(x) for x in np.asarray(a, dtype=float)]
    return {
        "schema_version": 1,
        "name": name,
        "onnx": f"{name}.onnx",
        "created_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "commit": git_commit(),
        "seed": int(seed),
        "iterations": int(iterations),
        "train_config": cfg.to_dict(),
        "control_dt": e.physics_dt * e.decimation,
        "physics_dt": e.physics_dt,
        "decimation": e.decimation,
        "joint_order": list(SDK_JOINT_NAMES),
        "default_pose": fl(default),
        # the environment's gains are in model order (one value: every joint)
        "kp": fl(model_to_sdk(np.broadcast_to(np.asarray(e.kp, dtype=float), (12,)))),
        "kd": fl(model_to_sdk(np.broadcast_to(np.asarray(e.kd, dtype=float), (12,)))),
        "action": {"size": 12, "scale": e.action_scale, "clip": e.action_clip,
                   "mode": "delta_target",
                   **({} if e.target_lead_max is None else {"target_lead_max": fl(
                       model_to_sdk(np.asarray(e.target_lead_max, dtype=float)))})},
        "soft_limits": {"lower": fl(lo), "upper": fl(hi)},
        "observation": {"size": OBS_SIZE * e.obs_history, "history": e.obs_history,
                        "clip": e.obs_clip, "terms": default_terms(default, "zero")},
        "lift_command": {k: int(v) for k, v in LIFT_VALUES.items()},
        "lift_schedule": sched.to_metadata(),
        "lift_command_after_done": 0,
        "legs": [cj.check_leg(g) for g in legs] if legs else list(cj.LEGS),
        "training_model": {"integrator": "implicitfast", "armature": ARMATURE,
                           "actuator": "position (kp, kv), forcerange = min(motor strength, 1) "
                                       "x effort limits"},
        "evaluation": {},
    }


def export_policy(checkpoint, out_stem: str | Path,
                  legs=None, mirror_legs=None, lift_gains=None) -> tuple[Path, Path]:
    """Write ``<out_stem>.onnx``, ``<out_stem>.json`` and the training state
    ``<out_stem>.train.pt`` (:func:`train_state_path`) from a training checkpoint, or from
    the weight average of several of one run (a list: :func:`average_checkpoints`; the JSON's
    ``averaged_iterations``); legs: the JSON's ``legs`` (the legs deploy may lift with it;
    None: all four). mirror_legs: legs whose lifts the graph plays as the mirror image of the
    opposite side's (:class:`policy_train.symmetry.MirroredLegsActor`; the JSON's
    ``mirrored_legs``); None on a distillation checkpoint: its teacher's. lift_gains: (kp, kd)
    of the lifted leg in the JSON's ``lift_schedule`` (None: the training's); the policy never
    commands that leg, so its gains are a deploy setting the evaluation then measures."""
    from policy_train.symmetry import MirroredLegsActor, mirror_source

    paths = [checkpoint] if isinstance(checkpoint, (str, Path)) else list(checkpoint)
    loaded = [torch.load(c, weights_only=False, map_location="cpu") for c in paths]
    d = loaded[0] if len(loaded) == 1 else average_checkpoints(loaded)
    cfg = TrainConfig.from_dict(d["train_config"])
    actor = _actor_from_checkpoint(d, cfg)
    out_stem = Path(out_stem)
    name = out_stem.name.removesuffix(".onnx")
    meta = build_metadata(name, cfg, int(d.get("seed", 0)), int(d["iter"]), legs)
    if "averaged_iterations" in d:
        meta["averaged_iterations"] = d["averaged_iterations"]
    if "distill" in d:  # a distilled student plays its teacher's schedule (policy_train.distill)
        meta["lift_schedule"] = d["distill"]["lift_schedule"]
        if mirror_legs is None:  # and its legs as the teacher did (v8, v9's predate the key)
            mirror_legs = list(d["distill"].get("mirrored_legs") or {}) or None
        meta["distilled_from"] = {k: d["distill"].get(k) for k in (
            "teacher_name", "teacher_commit", "history")}
        meta["distilled_from"]["labels"] = d["distill"].get("labels", "now")
    if lift_gains is not None:
        kp, kd = (float(g) for g in lift_gains)
        meta["lift_schedule"] = {**meta["lift_schedule"], "kp": kp, "kd": kd}
        LiftSchedule.from_metadata(meta["lift_schedule"])  # deploy's rule for the gains
    if mirror_legs:
        pairs = {g: mirror_source(g) for g in mirror_legs}
        actor = MirroredLegsActor(actor, meta["observation"]["terms"], pairs,
                                  cfg.env.obs_history).eval()
        meta["mirrored_legs"] = pairs
    onnx_path = out_stem.with_name(name + ".onnx")
    json_path = out_stem.with_name(name + ".json")
    onnx_path.parent.mkdir(parents=True, exist_ok=True)
    data = onnx_bytes(actor, OBS_SIZE * cfg.env.obs_history)
    # every 10th iteration; the curve of a policy this run started from is thinned already
    hist = d.get("history", [])
    kept = [h for h in hist if h.get("from_policy")] + [
        h for h in hist if not h.get("from_policy")][::10]
    meta["training_history"] = [
        {k: h.get(k) for k in ("iteration", "mean_step_reward", "mean_episode_reward",
                               "mean_episode_length_s", "stage")} for h in kept]
    # the whole training state (the actor as exported, the newest checkpoint's critic,
    # optimiser and exploration std): runs/ does not outlive its machine, and a continuation
    # from the ONNX alone (--from-policy) must rebuild all of that (docs/policy-training.md)
    state = io.BytesIO()
    torch.save({**d, "exported_as": name}, state)
    write_bytes_atomic(onnx_path, data)
    write_text_atomic(json_path, json.dumps(meta, indent=1) + "\n")
    write_bytes_atomic(train_state_path(onnx_path), state.getvalue())
    return onnx_path, json_path


def onnx_bytes(actor: torch.nn.Module, n_in: int) -> bytes:
    """The actor as a single-file ONNX model (opset 18, input ``obs`` (batch, n_in), output
    ``actions`` (batch, 12), a dynamic batch), checked by onnx and run by onnxruntime against
    torch on three batch sizes (RuntimeError where they disagree)."""
    import tempfile

    import onnx
    import onnxruntime as ort

    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir) / "actor.onnx"
        torch.onnx.export(actor, (torch.zeros(2, n_in),), str(tmp), input_names=["obs"],
                          output_names=["actions"],
                          dynamic_shapes={"obs": {0: torch.export.Dim("batch", min=1, max=65536)}},
                          opset_version=18, external_data=False, dynamo=True)
        model = onnx.load(str(tmp))
    onnx.checker.check_model(model)
    buf = io.BytesIO()
    onnx.save_model(model, buf)
    data = buf.getvalue()
    sess = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    for n in (1, 7, 256):
        x = rng.normal(0, 1, (n, n_in)).astype(np.float32)
        y = sess.run(["actions"], {"obs": x})[0]
        with torch.no_grad():
            ref = actor(torch.from_numpy(x)).numpy()
        if y.shape != (n, 12) or not np.allclose(y, ref, atol=1e-4, rtol=1e-4):
            raise RuntimeError(f"onnxruntime disagrees with torch (batch {n}): "
                               f"max err {np.abs(y - ref).max():.2e}")
    return data


def derive_policy(source_onnx: str | Path, out_stem: str | Path, gains=None,
                  lift_gains=None, t_r=None, shift=None, adapt=None,
                  stand=None, periods=None, excitation_seen=None,
                  target_lead=None) -> tuple[Path, Path]:
    """Write ``<out_stem>.onnx`` (the source's network, byte for byte) and ``<out_stem>.json``
    (the source's, with other deploy gains or excitation speed) for a policy whose
    checkpoints are gone.

    gains: (kp, kd) of the joints the policy commands (its JSON's ``kp`` / ``kd``, the PD law
    deploy sends and the evaluation plays), N m/rad and N m s/rad, each one value for every
    joint or three, (hip, thigh, calf), the same on every leg; lift_gains: the lifted leg's,
    as :func:`export_policy`; t_r: the excitation's time constant (s, the JSON's
    ``lift_schedule``), inside the range the policy was trained against (its
    ``train_config``'s ``t_r_range``: it never balanced against other speeds); periods: the
    excitation's steady periods (the JSON's ``lift_schedule``; with a faster ``t_r``, more of
    them keep the record as long), no longer in all (``periods`` x 8 ``t_r``) than the longest
    excitation the training played (its most ``train_periods`` at its slowest ``t_r``); shift: the
    shift phase (s, the JSON's ``lift_schedule``: the policy alone, every foot down, moving the
    body over the three feet it will stand on), at least the training's ``shift_s`` (the policy
    never lifted sooner) and at most 5 s: one value for every leg, or {leg: s} for those legs'
    lifts (the JSON's ``shift_by_leg``; the other legs keep theirs); adapt: whether the lifted
    leg's tracking adapter runs (the JSON's ``lift_schedule.adapt``;
    :mod:`deploy.tracking_adapter`: the network never sees the lifted leg's motors, so any
    policy may have it); stand: the JSON's ``stand`` (:func:`policy_train.stand.stand_spec`,
    ``home`` or ``hold``): what the graph plays while no leg is lifted, instead of the network's
    own four-leg stand (the only change to the ONNX: nodes after the network);
    excitation_seen: the fraction (in [0, 1]) of the lifted leg's excursion from its plan's
    start pose (plan.q0) that the policy observes while it excites (the JSON's
    ``lift_schedule.excitation_seen``, :func:`deploy.observation.observe_lifted_leg`);
    target_lead: ``"torque"``, each joint's target held within ``effort / kp`` of the joint
    (the JSON's ``action.target_lead_max``, :mod:`deploy.action`: no further does the motor
    give more torque), ``"off"`` no bound, None the source's (recomputed for new gains).
    The JSON's ``derived_from`` names the source, its commit, the gains, t_r, periods, shift (and
    ``shift_by_leg``), adapt, excitation_seen, stand and target lead bound it had; its
    evaluation figures are dropped (they were measured with the source's settings).
    ValueError on a source that is not an exported policy or on gains deploy refuses."""
    from deploy.policy import PolicyMeta

    src = Path(source_onnx)
    src_json = src.with_suffix(".json")
    try:
        meta = json.loads(src_json.read_text())
        data = src.read_bytes()
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{src_json if isinstance(e, json.JSONDecodeError) else src}: "
                         f"not an exported policy ({e})") from None
    sched = PolicyMeta.from_dict(meta, src_json).schedule  # ValueError unless deploy reads it
    out_stem = Path(out_stem)
    name = out_stem.name.removesuffix(".onnx")
    meta["derived_from"] = {"policy": src.name, "commit": meta.get("commit"),
                            "kp": meta["kp"], "kd": meta["kd"],
                            "lift_gains": [sched.kp, sched.kd], "t_r": sched.t_r,
                            "periods": sched.periods,
                            "shift": sched.shift,
                            **({"shift_by_leg": sched.shift_by_leg} if sched.shift_by_leg
                               else {}),
                            "adapt": sched.adapt,
                            "excitation_seen": sched.excitation_seen,
                            "stand": meta.get("stand", {"mode": "network"}),
                            "target_lead_max": meta["action"].get("target_lead_max")}
    if stand is not None:
        from policy_train.stand import apply_stand, stand_spec

        # a stand in the graph without one in the JSON is refused by apply_stand
        if meta.get("stand", {"mode": "network"}) != {"mode": "network"}:
            raise ValueError("the graph already has a stand; derive from its source instead")
        meta["stand"] = stand_spec(stand.get("mode"), stand.get("gain"))
        data = apply_stand(data, meta)
    if gains is not None:
        kp, kd = (_per_joint(g, name) for g, name in zip(gains, ("kp", "kd"), strict=True))
        if not (np.all(np.isfinite(kp + kd)) and np.all(kp > 0) and np.all(kd >= 0)):
            raise ValueError(f"gains must be kp > 0, kd >= 0, got {kp[:3]}, {kd[:3]}")
        meta["kp"], meta["kd"] = kp.tolist(), kd.tolist()
    if lift_gains is not None:
        kp, kd = (float(g) for g in lift_gains)
        meta["lift_schedule"] = {**(meta.get("lift_schedule") or {}), "kp": kp, "kd": kd}
        LiftSchedule.from_metadata(meta["lift_schedule"])  # deploy's rule for the gains
    if t_r is not None:
        lo, hi = meta["train_config"]["env"].get("t_r_range", (sched.t_r, sched.t_r))
        if not (np.isfinite(t_r) and lo <= t_r <= hi):
            raise ValueError(f"t_r {t_r} s is outside the {lo}-{hi} s the policy was trained "
                             "against")
        meta["lift_schedule"] = {**meta["lift_schedule"], "t_r": float(t_r)}
    if periods is not None:
        env = meta["train_config"]["env"]
        longest = (max(np.atleast_1d(env.get("train_periods", sched.periods)))
                   * max(env.get("t_r_range", (sched.t_r, sched.t_r))))
        t_r_now = meta["lift_schedule"]["t_r"]
        if not (int(periods) == periods and periods >= 1):
            raise ValueError(f"periods must be a whole number >= 1, got {periods}")
        if periods * t_r_now > longest + 1e-9:
            raise ValueError(f"{periods} periods at t_r {t_r_now:g} s last "
                             f"{8 * periods * t_r_now:g} s, longer than the {8 * longest:g} s "
                             "excitation the policy was trained against")
        meta["lift_schedule"] = {**meta["lift_schedule"], "periods": int(periods)}
    if shift is not None:
        lo = meta["train_config"]["env"].get("shift_s", sched.shift)
        by_leg = dict(shift) if isinstance(shift, Mapping) else {"": shift}
        for leg, v in by_leg.items():
            if not (np.isfinite(v) and lo <= v <= 5.0):
                raise ValueError(f"shift {v} s{f' of {leg}' if leg else ''} is outside {lo}-5 s "
                                 f"(the policy trained with a shift of {lo} s and never lifted "
                                 "sooner)")
        ls = dict(meta["lift_schedule"])
        if isinstance(shift, Mapping):
            ls["shift_by_leg"] = {**(ls.get("shift_by_leg") or {}),
                                  **{check_leg(g): float(v) for g, v in shift.items()}}
        else:  # every leg
            ls["shift"] = float(shift)
            ls.pop("shift_by_leg", None)
        meta["lift_schedule"] = ls
    if target_lead not in (None, "torque", "off"):
        raise ValueError(f"target_lead must be 'torque' or 'off', got {target_lead!r}")
    if target_lead is None and gains is not None and "target_lead_max" in meta["action"]:
        target_lead = "torque"  # the source's bound, for the new gains
    if target_lead == "torque":
        meta["action"] = {**meta["action"],
                          "target_lead_max": lead_max_for_torque(meta["kp"]).tolist()}
    elif target_lead == "off":
        meta["action"] = {k: v for k, v in meta["action"].items() if k != "target_lead_max"}
    if adapt is not None:
        meta["lift_schedule"] = {**meta["lift_schedule"], "adapt": bool(adapt)}
    if excitation_seen is not None:
        meta["lift_schedule"] = {**meta["lift_schedule"], "excitation_seen": float(excitation_seen)}
    meta.update(name=name, onnx=f"{name}.onnx", commit=git_commit(), evaluation={},
                created_utc=datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"))
    meta.pop("evaluation_nominal", None)
    onnx_path, json_path = out_stem.with_name(name + ".onnx"), out_stem.with_name(name + ".json")
    PolicyMeta.from_dict(meta, json_path)  # as deploy will read it: ValueError before writing
    if stand is not None:
        _check_stand(meta, data)
    onnx_path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(onnx_path, data)
    write_text_atomic(json_path, json.dumps(meta, indent=1) + "\n")
    return onnx_path, json_path


def _check_stand(meta: dict, data: bytes) -> None:
    """ValueError unless the policy's stand settles (:func:`policy_train.stand.settle`)."""
    import tempfile

    from policy_train.stand import SETTLE_S, settle

    with tempfile.TemporaryDirectory() as d:
        json_path = Path(d) / (meta["name"] + ".json")
        json_path.with_name(meta["onnx"]).write_bytes(data)
        json_path.write_text(json.dumps(meta))
        s = settle(json_path)
    if not s.settled:
        raise ValueError(f"the {s.mode} stand does not settle at these gains in {SETTLE_S:g} s on "
                         f"the simulator: {s.why_not()}; give damped --gains"
                         + (" or a lower gain" if s.mode == "home" else ""))


def _per_joint(gain, name: str) -> np.ndarray:
    """(12,) SDK order from one gain or (hip, thigh, calf): the joint types repeat on every
    leg in both joint orders, so the tiling needs no reordering."""
    g = np.atleast_1d(np.asarray(gain, dtype=float))
    if g.shape not in ((1,), (3,)):
        raise ValueError(f"{name}: give one gain or three (hip, thigh, calf), got {g.shape[0]}")
    return np.resize(g, 12)


def train_state_path(onnx_path: str | Path) -> Path:
    """``<name>.train.pt`` beside ``<name>.onnx``: the checkpoint ``a2i-train tripod --resume``
    continues the exported policy from."""
    p = Path(onnx_path)
    return p.with_name(p.name.removesuffix(".onnx") + ".train.pt")
