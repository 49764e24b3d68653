"""Continue training from an exported policy (``<name>.onnx`` + ``<name>.json``), not a checkpoint.

Checkpoints (``runs/``) are scratch and do not outlive the machine that wrote them; the exported
policy is what is committed. Its ONNX holds the actor's mean weights as named initializers
(``mlp.*``, or ``actor.mlp.*`` inside the mirrored-legs graph, the same weights for both sides)
and its JSON the training configuration, iteration and seed. What it lacks is the rest of a
PPO state: the critic, the optimiser and the action noise. So a warm start loads the actor
exactly, sets the exploration std to a given value, and first trains the critic alone for a
number of iterations with the actor frozen (``Trainer.learn(..., critic_only=True)``): a random
critic would otherwise give PPO advantages that are noise and pull a converged actor off
its optimum in the first updates.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["deploy_flags", "policy_plan_pool", "policy_start"]


def policy_start(onnx_path: str | Path) -> dict:
    """A start point from an exported policy: ``{"actor_mlp": {name: tensor}, "train_config",
    "deploy_flags", "iter", "seed", "history", "warm_start": {"policy", "averaged_iterations"}}``
    (``deploy_flags``: :func:`deploy_flags`).

    The actor MLP's state dict uses rsl-rl's ``MLP`` names (``0.weight``, ``0.bias``, ...).
    ``history`` is the JSON's training curve, its records marked ``from_policy`` (already
    thinned: :func:`policy_train.export.export_policy` keeps them as they are); its last stage
    is where training goes on, so a policy trained into phase 2 (calibration motions) stays
    there.
    Raises ValueError if the files are not an exported tripod policy.
    """
    import onnx
    import torch
    from onnx import numpy_helper

    onnx_path = Path(onnx_path)
    meta_path = onnx_path.with_suffix(".json")
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{meta_path}: no readable policy metadata ({e})") from e
    for key in ("train_config", "iterations"):
        if key not in meta:
            raise ValueError(f"{meta_path}: no {key!r}: not an exported training policy")
    if meta.get("refined_from"):  # its residual (policy_train.refine) is not the MLP's
        # PPO trains the MLP alone: a start from the network drops the residuals, which
        # a2i-train refine then tunes again over the new network
        raise ValueError(f"{onnx_path}: a refined policy (a residual over "
                         f"{meta['refined_from']['policy']}'s network); start from that network "
                         f"and refine the result again")
    try:
        graph = onnx.load(str(onnx_path)).graph
    except Exception as e:  # protobuf's DecodeError and the like: not an ONNX model
        raise ValueError(f"{onnx_path}: not a readable ONNX model ({type(e).__name__})") from e
    weights = {}
    for init in graph.initializer:
        for prefix in ("actor.mlp.", "mlp."):
            if init.name.startswith(prefix):
                weights[init.name[len(prefix):]] = torch.from_numpy(
                    np.array(numpy_helper.to_array(init), dtype=np.float32))
                break
    if not weights:
        raise ValueError(f"{onnx_path}: no actor weights (mlp.*) among the graph's initializers")
    # the policy's own curve (its JSON keeps every 10th iteration) goes on as it is; a JSON
    # without one still says the stage the policy ended in (phase 2: calibration motions)
    history = [{**h, "from_policy": True} for h in meta.get("training_history") or []]
    if not history:
        history = [{"iteration": int(meta["iterations"]), "stage": 2, "from_policy": True}]
    return {
        "actor_mlp": weights,
        "train_config": meta["train_config"],
        "deploy_flags": deploy_flags(meta),
        "iter": int(meta["iterations"]),
        "seed": int(meta.get("seed", 0)),
        "history": history,
        "warm_start": {"policy": onnx_path.name,
                       "averaged_iterations": meta.get("averaged_iterations")},
    }


def _gains_flag(kp, kd) -> str | None:
    """``--gains`` text for 12 joint gains (N m/rad, N m s/rad) that repeat hip, thigh, calf on
    every leg (either joint order); None where they do not."""
    kp, kd = (np.broadcast_to(np.asarray(g, dtype=float), (12,)).reshape(4, 3) for g in (kp, kd))
    if not (np.all(kp == kp[0]) and np.all(kd == kd[0])):
        return None
    pairs = [f"{p:g},{d:g}" for p, d in zip(kp[0], kd[0], strict=True)]
    return pairs[0] if len(set(pairs)) == 1 else "/".join(pairs)


def deploy_flags(meta: dict) -> dict[str, str]:
    """``{flag: value}``: the ``a2i-train tripod`` flags under which a run trains as the exported
    policy ``meta`` (its JSON) deploys, where that differs from its training configuration.

    A derived policy (``a2i-train derive``) deploys the same network at other gains, lift gains,
    ``excitation_seen`` or target lead bound than it trained at, and ``--from-policy`` trains at
    the training configuration's (as v21 was trained from v20 with ``--gains``): a fine-tune of
    such a policy that forgets the flags learns on joints its deploy never plays."""
    env = meta["train_config"]["env"]
    sched = meta.get("lift_schedule") or {}
    out = {}
    if _gains_flag(meta["kp"], meta["kd"]) != _gains_flag(env["kp"], env["kd"]):
        out["--gains"] = _gains_flag(meta["kp"], meta["kd"]) or "per joint, as its JSON's kp, kd"
    if "kp" in sched and (float(sched["kp"]), float(sched["kd"])) != (
            float(env["lift_kp"]), float(env["lift_kd"])):
        out["--lift-gains"] = f"{float(sched['kp']):g},{float(sched['kd']):g}"
    seen = float(sched.get("excitation_seen", 1.0))
    if seen != float(env.get("excitation_seen", 1.0)):
        out["--excitation-seen"] = f"{seen:g}"
    lead = (meta.get("action") or {}).get("target_lead_max")
    if (lead is None) != (env.get("target_lead_max") is None):
        out["--target-lead"] = "off" if lead is None else "torque"
    return out


def policy_plan_pool(env_cfg, policy_seed: int, path: str | Path) -> Path:
    """Write (``.npz``) the plan pool the policy most likely trained on, and return its path.

    A policy learns the few excitation plans of its pool (``plans_per_leg`` per leg); a
    continuation on other plans first adapts to them. The pool file a policy names is a
    scratch file of its training machine, but the pool is a function of its seed:
    ``TripodEnv`` without a pool file draws it from ``default_rng(seed + 1)``, and
    ``a2i-train pack`` (default ``--seed 1``) from ``default_rng(1)``, the same pool for the
    seed-0 runs the committed policies come from. env_cfg: the policy's ``EnvConfig``.
    """
    from policy_train.env import PlanPool

    c = env_cfg
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    PlanPool(c.plans_per_leg, c.t_r_range, c.n_basis, c.train_periods, c.physics_dt,
             np.random.default_rng(int(policy_seed) + 1), c.ground_clearance).save(path)
    return path
