"""``a2i-train``: train, export and evaluate the tripod calibration-action policy.

  a2i-train tripod [--iterations N] [--seed S] [--num-envs N] [--resume CKPT [CKPT ...]
                   | --from-policy policies/NAME.onnx [--init-std S] [--critic-warmup N]]
                   [--new-rewards]
                   [--lift-leg-weights FL,FR,RL,RR] [--[no-]mirror-augmentation] [--run-dir D]
                   [--dr FIELD=VALUE ...] [--reward TERM=WEIGHT ...]
                   [--gains KP,KD[/KP,KD/KP,KD]] [--lift-gains KP,KD] [--device cpu|cuda]
                   [--excitation-seen F] [--export policies/NAME]
  a2i-train export CHECKPOINT [CHECKPOINT ...] --out policies/NAME [--legs RL,RR]
                   [--mirror-legs FR,RR]   (several checkpoints of one run: weights averaged)
  a2i-train eval policies/NAME.onnx [--episodes 100] [--legs FL,FR,RL,RR] [--no-write]
                 [--nominal | --dr-off GROUP[,GROUP] --dr FIELD=VALUE ...]
                 [--randomisation standard|training]
  a2i-train transfer policies/NAME.onnx [--scenarios training,heavy,...] [--episodes 20]
                 [--legs FL,FR,RL,RR] [--out docs/results/policy_transfer.md] [--append]
                 [--model-xml MJCF] (the calibration re-run on sim.go2 under perturbations;
                                    on another model of the Go2: sim to sim)
  a2i-train compare A.json B.json  (two transfer runs on the same draws, episode by episode)
  a2i-train derive policies/NAME.onnx --out policies/OTHER [--gains KP,KD[/KP,KD/KP,KD]] [--lift-gains KP,KD]
                   [--t-r S] [--periods N] [--shift S|LEG=S[,LEG=S]] [--[no-]adapt]
                   [--excitation-seen F]
                                   (the same network with other deploy gains, excitation speed
                                    or length, or time to shift the body before the lift, every leg's
                                    or some legs', the lifted leg's tracking adapter, or how much
                                    of the lifted leg's excursion the policy observes while it
                                    excites)
  a2i-train refine policies/NAME.onnx --out policies/OTHER [--generations 40] [--leg FL]
                   [--pairs 4] [--episodes 24] [--fail-cost 0.1] [--dr FIELD=VALUE ...]
                   [--margin-cost C] [--margin-target 0.08] [--tilt-cost C] [--tilt-target 1]
                   [--clearance-cost C] [--clearance-target 0.008] [--velocity]
                   [--seed 1000] [--state F] [--resume]
                                   (a linear residual on the body's rate and tilt, by ES;
                                    of a refined policy: goes on from its residual)
  a2i-train pack OUTDIR            (compiled model, plan pool and leg dynamics for a machine
                                    without the URDF)

Checkpoints go to ``runs/<run>/model_<it>.pt`` (``runs/`` is not committed).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from policy_train.config import DR_GROUPS, RANDOMISATIONS, DRConfig, EnvConfig
from policy_train.distill import LABELS

__all__ = ["main"]


def _tripod(a) -> int:
    import torch

    from deploy.action import lead_max_for_torque
    from policy_train.config import DRConfig, EnvConfig, RewardConfig, TrainConfig
    from policy_train.runner import Trainer, check_device

    if a.iterations < 1:
        raise SystemExit("--iterations must be >= 1")
    try:
        check_device(a.device)
    except ValueError as e:
        raise SystemExit(f"a2i-train tripod: {e}") from None
    cfg = TrainConfig()
    if a.resume:
        ckpts = [torch.load(c, weights_only=False, map_location="cpu") for c in a.resume]
        if len(ckpts) == 1:
            start = ckpts[0]
        else:  # the newest one, its actor the mean of all (as export averages)
            from policy_train.export import average_checkpoints

            start = average_checkpoints(ckpts)
        cfg = TrainConfig.from_dict(start["train_config"])
    elif a.from_policy:
        from policy_train.warm_start import policy_start

        start = policy_start(a.from_policy)
        cfg = TrainConfig.from_dict(start["train_config"])
        # the compiled model and plan pool it trained from were scratch files of that machine
        # (the pool is rebuilt from the policy's seed below, unless --plan-pool names one)
        cfg.env.model_file = cfg.env.plan_pool_file = None
    if (a.resume or a.from_policy) and a.new_rewards:
        # continue the weights under this code's rewards and episodes
        fresh = EnvConfig()
        cfg.env.rewards = RewardConfig()
        cfg.env.dr = DRConfig()
        for k in ("terminate_on_contact", "p_reference_start", "reference_margin_m",
                  "reference_joint_noise", "p_reference_shift", "lift_leg_weights",
                  "ground_clearance", "train_periods"):
            setattr(cfg.env, k, getattr(fresh, k))
    overrides = {"num_envs": (cfg.env, "num_envs"), "plans_per_leg": (cfg.env, "plans_per_leg"),
                 "save_interval": (cfg.ppo, "save_interval"),
                 "model_file": (cfg.env, "model_file"), "plan_pool": (cfg.env, "plan_pool_file"),
                 "leg_dynamics": (cfg.env, "leg_dynamics_file"),
                 "steps_per_env": (cfg.ppo, "num_steps_per_env"),
                 "entropy_coef": (cfg.ppo, "entropy_coef"),
                 "lift_leg_weights": (cfg.env, "lift_leg_weights"),
                 "threads": (cfg.env, "threads"), "blocks": (cfg.env, "blocks"),
                 "excitation_seen": (cfg.env, "excitation_seen"),
                 "learning_rate": (cfg.ppo, "learning_rate")}
    for arg, (section, field) in overrides.items():
        if getattr(a, arg) is not None:
            setattr(section, field, getattr(a, arg))
    if a.mirror_augmentation is not None:
        cfg.ppo.mirror_augmentation = a.mirror_augmentation
    cfg.env.dr = cfg.env.dr.with_settings(dict(a.dr))
    cfg.env.rewards = cfg.env.rewards.with_settings(dict(a.reward))
    if a.gains is not None:  # one value for every joint, or (hip, thigh, calf) on each leg
        cfg.env.kp, cfg.env.kd = (g[0] if len(g) == 1 else tuple(float(x) for x in g * 4)
                                  for g in a.gains)
    if a.lift_gains is not None:
        cfg.env.lift_kp, cfg.env.lift_kd = a.lift_gains
    if a.target_lead is not None:  # model order, as the run's gains
        cfg.env.target_lead_max = None if a.target_lead == "off" else tuple(
            float(x) for x in lead_max_for_torque(cfg.env.kp))
    if a.calf_margin is not None:
        cfg.env.calf_upper_margin = a.calf_margin
    if a.calf_margin_ramp is not None:
        target, n = a.calf_margin_ramp
        e = cfg.env
        now = e.soft_limit_margin if e.calf_upper_margin is None else e.calf_upper_margin
        e.calf_margin_target, e.calf_margin_step = target, abs(target - now) / n
    run_dir = Path(a.run_dir or f"runs/tripod_s{a.seed}_{time.strftime('%Y%m%d_%H%M%S')}")
    t0 = time.time()
    if a.from_policy and cfg.env.plan_pool_file is None:
        from policy_train.warm_start import policy_plan_pool

        cfg.env.plan_pool_file = str(policy_plan_pool(cfg.env, start["seed"],
                                                      run_dir / "pool.npz"))
    tr = Trainer(cfg, run_dir, seed=a.seed, log=lambda s: print(s, flush=True),
                 device=a.device)
    if a.resume:
        tr.load(start)
        print(f"resumed from {' '.join(a.resume)} at iteration {tr.iteration}"
              + (" (actor weights averaged)" if len(a.resume) > 1 else ""), flush=True)
    elif a.from_policy:
        tr.load_policy(start, a.init_std)
        print(f"started from the policy {a.from_policy} (iteration {tr.iteration}): its actor, "
              f"exploration std {a.init_std}, a new critic trained alone for "
              f"{a.critic_warmup} iterations first", flush=True)
        given = {"--gains": a.gains, "--lift-gains": a.lift_gains,
                 "--excitation-seen": a.excitation_seen, "--target-lead": a.target_lead}
        apart = {k: v for k, v in start["deploy_flags"].items() if given[k] is None}
        if apart:
            print(f"note: {Path(a.from_policy).name} deploys at other settings than it trained "
                  f"at, and this run trains at its training configuration's; to train as it "
                  f"deploys, give {' '.join(f'{k} {v}' for k, v in apart.items())}", flush=True)
    if a.learning_rate is not None:  # over the rate a checkpoint's schedule had reached
        tr.set_learning_rate(a.learning_rate)
    tr.total_iterations = a.total_iterations or (tr.iteration + a.iterations)
    print(f"tripod: {cfg.env.num_envs} envs, run dir {run_dir}, setup {time.time() - t0:.1f} s",
          flush=True)
    deadline = None if a.max_minutes is None else time.time() + 60 * a.max_minutes
    if a.from_policy and a.critic_warmup:
        tr.learn(a.critic_warmup, max_seconds=None if deadline is None else deadline - time.time(),
                 critic_only=True)
    tr.learn(a.iterations, max_seconds=None if deadline is None else deadline - time.time())
    ckpt = run_dir / f"model_{tr.iteration}.pt"
    print(f"saved {ckpt}", flush=True)
    if a.export:
        from policy_train.export import export_policy, train_state_path

        onnx_path, json_path = export_policy(ckpt, a.export)
        print(f"exported {onnx_path}, {json_path} and {train_state_path(onnx_path)}", flush=True)
    return 0


def _distill(a) -> int:
    import torch

    from policy_train.distill import DistillConfig, Distiller

    resume = None
    if a.resume:
        resume = torch.load(a.resume, weights_only=False, map_location="cpu")
        if "distill" not in resume:
            raise SystemExit(f"{a.resume}: not a distillation checkpoint")
        saved = {k: tuple(v) if isinstance(v, list) else v for k, v in resume["distill"].items()
                 if k in DistillConfig.__dataclass_fields__}
        cfg = DistillConfig(**saved)
    else:
        cfg = DistillConfig(teacher=a.teacher)
    for arg in ("history", "num_envs", "learning_rate", "save_interval", "labels"):
        if getattr(a, arg) is not None:
            setattr(cfg, arg, getattr(a, arg))
    if a.lift_leg_weights is not None:
        cfg.lift_leg_weights = a.lift_leg_weights
    if a.hidden is not None:
        cfg.hidden = a.hidden
    if a.calf_margin is not None:
        cfg.calf_upper_margin = a.calf_margin
    cfg.dr = {**cfg.dr, **dict(a.dr)}
    if resume is not None and cfg.history < int(resume["distill"]["history"]):
        raise SystemExit(f"--history can only grow on --resume (the checkpoint sees "
                         f"{resume['distill']['history']} frames)")
    run_dir = Path(a.run_dir or f"runs/distill_s{a.seed}_{time.strftime('%Y%m%d_%H%M%S')}")
    t0 = time.time()
    try:
        d = Distiller(cfg, run_dir, seed=a.seed, threads=a.threads or 0,
                      log=lambda s: print(s, flush=True), resume=resume)
    except (OSError, ValueError) as e:
        raise SystemExit(f"a2i-train distill: {e}") from None
    print(f"distill: teacher {cfg.teacher}, {cfg.history} frames, {cfg.num_envs} envs, run dir "
          f"{run_dir}, setup {time.time() - t0:.1f} s"
          + (f", resumed at iteration {d.iteration}" if resume is not None else ""), flush=True)
    ckpt = d.learn(a.iterations, a.max_minutes)
    print(f"saved {ckpt}", flush=True)
    if a.export:
        from policy_train.export import export_policy

        onnx_path, json_path = export_policy(ckpt, a.export)  # mirrored as the teacher
        print(f"exported {onnx_path} and {json_path}", flush=True)
    return 0


def _export(a) -> int:
    from policy_train.export import export_policy, train_state_path

    onnx_path, json_path = export_policy(a.checkpoint, a.out, a.legs, a.mirror_legs,
                                         lift_gains=a.lift_gains)
    print(f"exported {onnx_path}, {json_path} and {train_state_path(onnx_path)}")
    return 0


def _derive(a) -> int:
    from policy_train.export import derive_policy

    if (a.gains, a.lift_gains, a.t_r, a.periods, a.shift, a.adapt, a.stand,
            a.excitation_seen, a.target_lead) == (None,) * 9:
        raise SystemExit("a2i-train derive: give --gains, --lift-gains, --t-r, --periods, "
                         "--shift, --[no-]adapt, --excitation-seen, --stand and/or --target-lead")
    onnx_path, json_path = derive_policy(a.onnx, a.out, a.gains, a.lift_gains, a.t_r, a.shift,
                                         a.adapt, a.stand, a.periods, a.excitation_seen,
                                         a.target_lead)
    print(f"wrote {onnx_path} and {json_path} (the network of {a.onnx})")
    return 0


def _refine(a) -> int:
    from policy_train.refine import RefineConfig, refine

    state = Path(a.state or Path(a.out).with_name(Path(a.out).name.removesuffix(".onnx")
                                                  + ".refine.json"))
    if a.resume_state and not state.is_file():
        raise ValueError(f"--resume: no state {state}")
    cfg = RefineConfig(leg=a.leg, pairs=a.pairs, episodes=a.episodes, step=a.step,
                       fail_cost=a.fail_cost, seed=a.seed, dr=dict(a.dr),
                       margin_cost=a.margin_cost, margin_target=a.margin_target,
                       tilt_cost=a.tilt_cost, tilt_target_deg=a.tilt_target,
                       velocity=a.velocity, clearance_cost=a.clearance_cost,
                       clearance_target=a.clearance_target)
    print(f"refine: {a.onnx}, {a.generations} generations of {2 * cfg.pairs + 1} candidates x "
          f"{cfg.episodes} episodes per leg, state {state}", flush=True)
    onnx_path, json_path = refine(a.onnx, a.out, a.generations, cfg, state, resume=a.resume_state,
                                  log=lambda s: print(s, flush=True))
    print(f"wrote {onnx_path} and {json_path}; evaluate it with a2i-train eval {onnx_path}")
    return 0


def _transfer(a) -> int:
    from policy_train.transfer import (
        SCENARIOS,
        load_results,
        merge_results,
        model_identity,
        physics_rates,
        summarise,
        timed_run,
        write_results,
    )

    if a.list:
        for s in SCENARIOS.values():
            print(f"{s.name:15s} {s.description}")
        return 0
    import json

    model = model_identity(a.model_xml)  # a file that is no Go2 model is refused at once
    meta = json.loads(Path(a.onnx).with_suffix(".json").read_text())
    physics_rates(a.timestep, float(meta["control_dt"]))  # and a step that splits no tick
    page = None
    if a.append:  # checked before the run: a page it cannot join is refused at once
        from calib.joints import LEGS

        page = load_results(Path(a.out).with_suffix(".json"))
        run_legs = a.legs or meta.get("legs", list(LEGS))
        merge_results(page, [], a.onnx, a.seed, run_legs, a.episodes, model, a.max_tip,
                      a.lift_gate, a.timestep)
    n = a.episodes * len(a.scenarios) * len(a.legs or (1, 1, 1, 1))
    on = "" if model is None else f" on {a.model_xml}"
    print(f"transfer: {a.onnx}{on}, scenarios {', '.join(a.scenarios)}, about {n} episodes",
          flush=True)
    res, elapsed = timed_run(a.onnx, a.scenarios, a.legs, a.episodes, a.seed, a.workers,
                             log=lambda s: print(s, flush=True), model_xml=a.model_xml,
                             max_tip=a.max_tip, lift_gate=a.lift_gate, timestep=a.timestep)
    for s, x in summarise(res).items():
        legs = " ".join(f"{g} {100 * v:.0f} %" for g, v in x["legs"].items())
        print(f"{s:15s} success {100 * x['success']:5.1f} % ({legs}); rate "
              f"{x['rate_rms']:.3f} rad/s, tilt {x['tilt_rms_deg']:.2f} deg, CN p90 "
              f"{x['cn_p90']:.3f}")
    if not a.no_write:
        if page is not None:
            res = merge_results(page, res, a.onnx, a.seed, run_legs, a.episodes, model,
                                a.max_tip, a.lift_gate, a.timestep)
            elapsed += page[0]["elapsed_s"] or 0.0
        write_results(res, a.out, a.onnx, a.seed, elapsed, model, a.max_tip, a.lift_gate,
                      a.timestep)
        print(f"wrote {a.out} and {Path(a.out).with_suffix('.json')}")
    return 0


def _compare(a) -> int:
    from policy_train.transfer import compare, load_results, render_comparison

    (meta_a, eps_a), (meta_b, eps_b) = (load_results(f) for f in a.episodes_files)
    if meta_a["seed"] != meta_b["seed"]:
        raise ValueError(f"the runs drew with different seeds ({meta_a['seed']} and "
                         f"{meta_b['seed']}): their episodes are not the same draws")
    names = [Path(m["policy"]).stem for m in (meta_a, meta_b)]
    if names[0] == names[1]:  # one policy on two models (sim to sim), or twice
        names = [f"{Path(m['model']['path']).parent.name}/{Path(m['model']['path']).stem}"
                 if m["model"] else "URDF" for m in (meta_a, meta_b)]
        if meta_a["timestep"] != meta_b["timestep"]:  # one model at two physics steps
            names = [f"{n} at {1e3 * m['timestep']:g} ms" for n, m in zip(names, (meta_a, meta_b))]
        if names[0] == names[1]:
            names = ["A", "B"]
    print(render_comparison(compare(eps_a, eps_b), *names), end="")
    return 0


def _scenario_list(text: str) -> tuple[str, ...]:
    from policy_train.transfer import SCENARIOS

    names = tuple(x.strip() for x in text.split(",") if x.strip())
    bad = [x for x in names if x not in SCENARIOS]
    if bad or not names:
        raise argparse.ArgumentTypeError(
            f"unknown scenario(s) {', '.join(bad) or '(none)'}; known: {', '.join(SCENARIOS)}")
    return names


def _positive(text: str, least: int = 1) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if v < least:
        raise argparse.ArgumentTypeError(f"must be >= {least}, got {v}")
    return v


def _count(text: str) -> int:
    return _positive(text, 0)


def _number(lo: float, hi: float, what: str):
    """argparse type: a float in [lo, hi) (hi may be inf)."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not lo <= v < hi:
            raise argparse.ArgumentTypeError(f"{what}, got {v}")
        return v
    return parse


_MINUTES = _number(0.0, math.inf, "must be a number of minutes >= 0")
_STAND_GAIN = _number(0.01, 5.0, "a home stand's gain must be in [0.01, 5)")
_SEEN = _number(0.0, math.nextafter(1.0, 2.0), "must be in [0, 1]")


def _stand(text: str) -> dict:
    """argparse type for derive --stand: ``hold``, or the home stand's gain."""
    if text == "hold":
        return {"mode": "hold"}
    try:
        float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected hold or a gain, got {text!r}") from None
    return {"mode": "home", "gain": _STAND_GAIN(text)}


def _tip_limits(text: str):
    """argparse type: deploy's tip guard limits, "LIFT[,HOLD]" deg ("0": off)."""
    from deploy.tip_guard import TipLimits

    try:
        return TipLimits.parse(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _lift_gate(text: str):
    """argparse type: deploy's lift gate, "MM[,S]" ("off": off)."""
    from deploy.lift_gate import GateLimits

    try:
        return GateLimits.parse(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _pack(a) -> int:
    """Write the compiled training model, a plan pool and the legs' inverse dynamics, for a
    machine without the URDF / example-robot-data / pinocchio (then train there with
    --model-file / --plan-pool / --leg-dynamics)."""
    import numpy as np

    from deploy.lift_schedule import LiftSchedule
    from policy_train.config import EnvConfig
    from policy_train.env import PlanPool
    from policy_train.model import TrainModel

    c = EnvConfig()
    out = Path(a.outdir)
    out.mkdir(parents=True, exist_ok=True)
    TrainModel(c.physics_dt, c.kp, c.kd).save(out / "go2_train.mjb")
    PlanPool(a.plans_per_leg, c.t_r_range, c.n_basis, c.train_periods, c.physics_dt,
             np.random.default_rng(a.seed), c.ground_clearance).save(out / "pool.npz")
    LiftSchedule.save_dynamics_pack(out / "leg_dynamics.npz")
    print(f"wrote {out / 'go2_train.mjb'}, {out / 'pool.npz'} and {out / 'leg_dynamics.npz'}")
    return 0


def _eval(a) -> int:
    from policy_train.evaluate import evaluate_policy

    evaluate_policy(a.onnx, episodes=a.episodes, legs=a.legs, seed=a.seed,
                    write=not a.no_write, results_path=a.results, nominal=a.nominal,
                    dr_off=a.dr_off, randomisation=a.randomisation, dr_set=dict(a.dr),
                    log=lambda s: print(s, flush=True))
    return 0


def _dr_groups(text: str) -> tuple[str, ...]:
    """argparse type: comma-separated groups of ``config.DR_GROUPS`` (checked by
    ``DRConfig.without``, the one place that knows them)."""
    groups = tuple(g.strip() for g in text.split(",") if g.strip())
    if not groups:
        raise argparse.ArgumentTypeError(f"no group in {text!r}")
    try:
        DRConfig().without(*groups)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return groups


def _leg_list(text: str) -> tuple[str, ...]:
    """argparse type: comma-separated legs, e.g. ``RL,RR``."""
    from calib.joints import check_leg

    try:
        return tuple(check_leg(g.strip()) for g in text.split(","))
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _leg(text: str) -> str:
    """argparse type: one leg, e.g. ``FL``."""
    legs = _leg_list(text)
    if len(legs) != 1:
        raise argparse.ArgumentTypeError(f"one leg, got {text!r}")
    return legs[0]


def _kp_kd(text: str, example: str) -> tuple[float, float]:
    try:
        kp, kd = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give KP,KD, e.g. {example}") from None
    return kp, kd


def _shift(text: str) -> float | dict[str, float]:
    """``2.0`` (every leg) or ``FL=2,FR=2`` (those legs), seconds >= 0.05."""
    from calib.joints import check_leg

    def seconds(v: str) -> float:
        try:
            x = float(v)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected seconds, got {v!r}") from None
        if not (x >= 0.05 and x < float("inf")):
            raise argparse.ArgumentTypeError(f"must be >= 0.05 s, got {v}")
        return x

    if "=" not in text:
        return seconds(text)
    out = {}
    for item in text.split(","):
        leg, _, v = item.partition("=")
        try:
            leg = check_leg(leg.strip())
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
        out[leg] = seconds(v)
    return out


def _gains(text: str) -> tuple[float, float]:
    """argparse type: ``KP,KD`` (N m/rad, N m s/rad), as the lift schedule accepts them."""
    from deploy.lift_schedule import LiftSchedule

    kp, kd = _kp_kd(text, "80,2")
    try:
        LiftSchedule(kp=kp, kd=kd)
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"{text!r}: {e}") from None
    return kp, kd


_CALF_MARGIN = _number(-0.3, 0.5, "must be in [-0.3, 0.5) rad")


def _ramp(text: str) -> tuple[float, int]:
    """argparse type: ``TARGET,ITERATIONS`` of the calf-clamp curriculum."""
    target, sep, n = text.partition(",")
    if not sep:
        raise argparse.ArgumentTypeError(f"{text!r}: give TARGET,ITERATIONS, e.g. -0.1,300")
    return _CALF_MARGIN(target), _positive(n)


def _joint_gains(text: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """argparse type: ``KP,KD`` of every joint, or ``KP,KD/KP,KD/KP,KD`` of the hips, thighs
    and calves (kp > 0, kd >= 0); (kp, kd), each one value or three."""
    parts = text.split("/")
    if len(parts) not in (1, 3):
        raise argparse.ArgumentTypeError(
            f"{text!r}: give KP,KD or HIP_KP,HIP_KD/THIGH_KP,THIGH_KD/CALF_KP,CALF_KD")
    pairs = [_kp_kd(p, "23,0.575 or 29,6/29,6/23,0.8") for p in parts]
    for kp, kd in pairs:
        if not (math.isfinite(kp) and math.isfinite(kd) and kp > 0 and kd >= 0):
            raise argparse.ArgumentTypeError(f"{text!r}: kp must be > 0 and kd >= 0")
    kp, kd = zip(*pairs, strict=True)
    return kp, kd


def _dr_setting(text: str) -> tuple[str, object]:
    """argparse type: ``FIELD=VALUE`` for a ``DRConfig`` field; a range as ``LO,HI``, in the
    field's units and type (``latency_steps=0,6``, ``push_vel=0.5``)."""
    from dataclasses import fields

    known = {f.name: getattr(DRConfig(), f.name) for f in fields(DRConfig) if f.name != "enabled"}
    field, sep, value = text.partition("=")
    if not sep or field not in known:
        raise argparse.ArgumentTypeError(f"{text!r}: give FIELD=VALUE, FIELD one of "
                                          f"{', '.join(known)}")
    default = known[field]
    kind = type(default[0]) if isinstance(default, tuple) else type(default)
    try:
        parts = tuple(kind(x) for x in value.split(","))
    except ValueError:
        parts = ()
    n = len(default) if isinstance(default, tuple) else 1
    if len(parts) != n or any(x < 0 for x in parts if field != "base_mass_add") or (
            n == 2 and parts[0] > parts[1]):
        raise argparse.ArgumentTypeError(
            f"{text!r}: {field} takes {n} {kind.__name__} value(s)"
            + (" LO,HI with LO <= HI" if n == 2 else "") + f", e.g. {default}")
    if field == "floor_tilt_deg" and parts[1] >= 30.0:  # a Go2 tripod slides well before
        raise argparse.ArgumentTypeError(f"{text!r}: floor_tilt_deg must stay under 30 deg")
    if field == "default_cone" and parts[0] > 1:
        raise argparse.ArgumentTypeError(f"{text!r}: default_cone is a fraction of the "
                                          "episodes, at most 1")
    if field == "floor_timeconst" and parts[1] > 0:
        from sim.effects import check_floor_timeconst

        try:
            check_floor_timeconst(parts[0], EnvConfig().physics_dt)
        except ValueError as e:
            raise argparse.ArgumentTypeError(f"{text!r}: {e}") from None
        if parts[1] > 0.08:  # the standing feet sink past their centres, every calf on it
            raise argparse.ArgumentTypeError(f"{text!r}: floor_timeconst must stay at most 0.08 s")
    return field, parts if isinstance(default, tuple) else parts[0]


def _reward_setting(text: str) -> tuple[str, float]:
    """argparse type: ``TERM=WEIGHT`` for a ``RewardConfig`` field (``ang_vel_xy=-6``)."""
    from dataclasses import fields

    from policy_train.config import RewardConfig

    known = [f.name for f in fields(RewardConfig)]
    term, sep, value = text.partition("=")
    if not sep or term not in known:
        raise argparse.ArgumentTypeError(f"{text!r}: give TERM=WEIGHT, TERM one of "
                                          f"{', '.join(known)}")
    try:
        w = float(value)
    except ValueError:
        w = math.nan
    if not math.isfinite(w) or (term.endswith("_sigma") and w <= 0):
        raise argparse.ArgumentTypeError(f"{text!r}: the weight must be a finite number"
                                          + (" > 0" if term.endswith("_sigma") else ""))
    return term, w


def _weights(text: str) -> tuple[float, ...]:
    """argparse type: four non-negative lift weights, FL,FR,RL,RR, not all zero."""
    try:
        w = tuple(float(x) for x in text.split(","))
    except ValueError:
        w = ()
    if len(w) != 4 or min(w) < 0 or sum(w) <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: give 4 non-negative weights FL,FR,RL,RR")
    return w


def _widths(text: str) -> tuple[int, ...]:
    """argparse type: hidden layer widths, e.g. 512,256,128."""
    try:
        w = tuple(int(x) for x in text.split(","))
    except ValueError:
        w = ()
    if not w or min(w) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: give positive widths, e.g. 512,256,128")
    return w


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="a2i-train", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("tripod", help="train the tripod calibration-action policy (PPO)")
    t.add_argument("--iterations", type=_count, default=600)
    t.add_argument("--total-iterations", type=_positive, default=None,
                   help="planned total (sets where phase 2 starts); default: this run's end")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--num-envs", type=_positive, default=None)
    t.add_argument("--plans-per-leg", type=_positive, default=None)
    t.add_argument("--steps-per-env", type=_positive, default=None)
    t.add_argument("--save-interval", type=_positive, default=None)
    t.add_argument("--entropy-coef", type=float, default=None, help="PPO entropy bonus")
    t.add_argument("--lift-leg-weights", type=_weights, default=None, metavar="FL,FR,RL,RR",
                   help="how often each leg is lifted, e.g. 3,3,1,1 (default 2,2,1,1)")
    t.add_argument("--dr", type=_dr_setting, action="append", default=[],
                   metavar="FIELD=VALUE", help="domain randomisation setting (repeatable), "
                   "e.g. --dr motor_strength=0.75,1.1 --dr latency_steps=0,6; on --resume it "
                   "changes the run's own")
    t.add_argument("--learning-rate", type=_number(1e-7, 1.0, "must be in [1e-7, 1)"),
                   default=None, metavar="LR",
                   help="PPO's (starting) learning rate; the adaptive schedule moves it to keep "
                        "the KL near its target. On --resume it replaces the checkpoint's")
    t.add_argument("--reward", type=_reward_setting, action="append", default=[],
                   metavar="TERM=WEIGHT", help="a reward weight (or sigma, target) of "
                   "RewardConfig (repeatable), e.g. --reward ang_vel_xy=-6; on --resume or "
                   "--from-policy it replaces the run's own")
    t.add_argument("--gains", type=_joint_gains, default=None, metavar="KP,KD[/KP,KD/KP,KD]",
                   help="the PD gains (N m/rad, N m s/rad) the policy commands, as derive "
                        "--gains: KP,KD for every joint or hip/thigh/calf; on --resume or "
                        "--from-policy they replace the run's own (kp 20, kd 0.5)")
    t.add_argument("--lift-gains", type=_gains, default=None, metavar="KP,KD",
                   help="the lifted leg's PD gains in training (a new run's 40,1; on --resume "
                        "or --from-policy they replace the run's own; deploy's JSON may name "
                        "others, a2i-train export --lift-gains)")
    t.add_argument("--excitation-seen", type=_SEEN, default=None, metavar="F",
                   help="the fraction in [0, 1] of the lifted leg's excursion from its plan's "
                        "start pose (plan.q0) that the policy observes while it excites (a new "
                        "run's 1, the leg as measured; the critic always sees it so); the "
                        "export's JSON carries it, so deploy shows the leg as training did "
                        "(docs/policy-training.md, stop 67)")
    t.add_argument("--target-lead", choices=("torque", "off"), default=None,
                   help="torque: hold each joint's target within effort / kp of the joint (the "
                   "run's gains), as deploy plays a policy derived with --target-lead torque; "
                   "off: no bound (a new run's; on --resume or --from-policy the run's own)")
    t.add_argument("--threads", type=_positive, default=None,
                   help="threads of the simulation and of the update (default: all CPUs); "
                        "1 each for two runs side by side on two cores")
    t.add_argument("--blocks", type=_positive, default=None,
                   help="step the envs in this many blocks, one's numpy while another's physics "
                        "runs (EnvConfig.blocks; default: 2 with 4 threads or more, else 1)")
    t.add_argument("--device", default="cpu",
                   help="where the networks and PPO's update run: cpu (default) or cuda on a "
                        "machine with a GPU (the simulation stays on the CPU's threads)")
    t.add_argument("--max-minutes", type=_MINUTES, default=None,
                   help="stop (and save) after this")
    t.add_argument("--model-file", default=None, help="compiled training model (.mjb)")
    t.add_argument("--plan-pool", default=None, help="precomputed excitation plan pool (.npz)")
    t.add_argument("--leg-dynamics", default=None,
                   help="the legs' inverse dynamics (.npz of a2i-train pack) instead of the URDF's")
    t.add_argument("--resume", nargs="+", default=None, metavar="CKPT",
                   help="checkpoint to continue from (runs/<run>/model_<it>.pt, or an exported "
                        "policy's policies/<name>.train.pt); several of one run: from the newest "
                        "with the mean of their actor weights (as export averages)")
    t.add_argument("--from-policy", default=None, metavar="ONNX",
                   help="continue from an exported policy without a training state (its "
                        ".json beside it, no .train.pt): its actor and configuration, a new "
                        "critic")
    t.add_argument("--init-std", type=_number(1e-3, 10.0, "must be in [0.001, 10)"), default=0.3,
                   help="with --from-policy: exploration std of every action (default 0.3)")
    t.add_argument("--critic-warmup", type=_count, default=600,
                   help="with --from-policy: iterations that train the new critic alone, the "
                        "actor frozen, before PPO proper (default 600)")
    t.add_argument("--new-rewards", action="store_true",
                   help="with --resume or --from-policy: use the current reward weights, "
                        "episode settings (contact terminations, reference starts, ...) and "
                        "domain randomisation, not the checkpoint's")
    t.add_argument("--mirror-augmentation", action=argparse.BooleanOptionalAction, default=None,
                   help="train on the left-right mirrored samples too (default: on for new runs, "
                        "the checkpoint's setting with --resume; before v5 it was off). Off "
                        "pays when the exported graph mirrors the other side's legs anyway")
    t.add_argument("--calf-margin", type=_CALF_MARGIN, default=None, metavar="RAD",
                   help="clamp the calves' targets this far inside their extension limit "
                        "(< 0: beyond it; default 0.05, over a checkpoint's on --resume)")
    t.add_argument("--calf-margin-ramp", type=_ramp, default=None, metavar="TARGET,ITERATIONS",
                   help="move that clamp linearly to TARGET rad over ITERATIONS PPO iterations "
                        "(a curriculum: a policy trained on the clamp winds its stance calves "
                        "up to a clamp raised at once)")
    t.add_argument("--run-dir", default=None)
    t.add_argument("--export", default=None, help="after training, export to this path stem")
    d = sub.add_parser("distill", help="distil a policy into one that sees a history of noisy "
                       "observations (DAgger; docs/policy-training.md)")
    d.add_argument("--teacher", default="policies/tripod_go2_v7.onnx",
                   help="the exported policy to imitate (its .json beside it)")
    d.add_argument("--history", type=_positive, default=None,
                   help="frames the student sees (10); on --resume it may grow, the older "
                        "frames' weights starting at zero")
    d.add_argument("--hidden", type=_widths, default=None, metavar="H1,H2,H3",
                   help="the student's hidden layer widths (default: the teacher's); on "
                        "--resume they may grow, the added units starting with zero output "
                        "weights")
    d.add_argument("--iterations", type=_positive, default=400)
    d.add_argument("--num-envs", type=_positive, default=None)
    d.add_argument("--learning-rate", type=_number(1e-7, 1.0, "must be in [1e-7, 1)"),
                   default=None, metavar="LR",
                   help="Adam's learning rate (3e-4); on --resume it replaces the checkpoint's")
    d.add_argument("--lift-leg-weights", type=_weights, default=None, metavar="FL,FR,RL,RR")
    d.add_argument("--save-interval", type=_positive, default=None)
    d.add_argument("--calf-margin", type=_CALF_MARGIN,
                   default=None, metavar="RAD",
                   help="clamp the student's calf targets this far inside the calf's extension "
                        "limit (< 0: beyond it; default: the teacher's 0.05): a stance calf is a "
                        "kp spring about that clamp")
    d.add_argument("--dr", type=_dr_setting, action="append", default=[], metavar="FIELD=VALUE",
                   help="a DRConfig field over the teacher's, e.g. noise_scale=0,1 (repeatable)")
    d.add_argument("--labels", choices=LABELS, default=None,
                   help="the teacher's action on the clean frame of the state the student acts "
                        "in (now, v8 and v9) or of the state at which its action reaches the "
                        "motors, the actuation latency later (actuation); default: now, or the "
                        "checkpoint's with --resume")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--threads", type=_positive, default=None,
                   help="simulation and update threads (default: all CPUs)")
    d.add_argument("--max-minutes", type=_MINUTES, default=None,
                   help="stop (and save) after this")
    d.add_argument("--resume", default=None, metavar="CKPT", help="a distillation checkpoint")
    d.add_argument("--run-dir", default=None)
    d.add_argument("--export", default=None, help="after training, export to this path stem")
    e = sub.add_parser("export", help="export a checkpoint to ONNX + JSON")
    e.add_argument("checkpoint", nargs="+",
                   help="a checkpoint, or several of one run: their actor weights averaged")
    e.add_argument("--out", required=True, help="path stem, e.g. policies/tripod_v1")
    e.add_argument("--legs", type=_leg_list, default=None,
                   help="legs deploy may lift with it, e.g. RL,RR (default: all four)")
    e.add_argument("--mirror-legs", type=_leg_list, default=None,
                   help="legs played as the mirror image of the opposite side's lift, e.g. FR "
                        "(FR as FL mirrored; the robot and the task are left-right symmetric)")
    e.add_argument("--lift-gains", type=_gains, default=None, metavar="KP,KD",
                   help="the lifted leg's PD gains in the JSON's lift_schedule, KP > 0, KD >= 0 (default: the "
                        "training's, 40,1); stiffer gains track the plan through joint damping "
                        "the training did not model")
    g = sub.add_parser("derive", help="a copy of an exported policy with other deploy gains "
                       "(the network unchanged)")
    g.add_argument("onnx", help="the exported policy (its .json beside it)")
    g.add_argument("--out", required=True, help="path stem, e.g. policies/tripod_v2")
    g.add_argument("--gains", type=_joint_gains, default=None, metavar="KP,KD[/KP,KD/KP,KD]",
                   help="the PD gains (N m/rad, N m s/rad) the policy commands: KP,KD for every "
                        "joint, or HIP_KP,HIP_KD/THIGH_KP,THIGH_KD/CALF_KP,CALF_KD on every leg")
    g.add_argument("--lift-gains", type=_gains, default=None, metavar="KP,KD",
                   help="the lifted leg's gains, as export --lift-gains")
    g.add_argument("--t-r", type=_number(0.05, 5.0, "must be in [0.05, 5) s"), default=None,
                   metavar="S", help="the excitation's time constant t_r (s), inside the range "
                   "the policy trained against; slower motions shake the tripod less")
    g.add_argument("--periods", type=_count, default=None, metavar="N",
                   help="the excitation's steady periods (8 t_r s each), no longer in all than "
                   "the longest excitation the policy trained against; with a faster --t-r, "
                   "more periods keep the record as long (more signal against the gyro noise)")
    g.add_argument("--shift", type=_shift, default=None, metavar="S|LEG=S[,LEG=S]",
                   help="the shift phase (s): how long the policy has, every foot down, to "
                   "move the body over the three it will stand on; at least the training's. "
                   "One value for every leg, or per leg (FL=2,FR=2: those legs' lifts, the "
                   "others as they were)")
    g.add_argument("--adapt", action=argparse.BooleanOptionalAction, default=None,
                   help="whether the lifted leg's tracking adapter runs: from 2 s into the "
                   "excitation, the torque its tracking shows the leg's model lacks (damping, "
                   "friction, inertia, torque constant) is fed forward (default: the source's)")
    g.add_argument("--excitation-seen", type=_SEEN, default=None, metavar="F",
                   help="the fraction in [0, 1] of the lifted leg's excursion from its plan's "
                   "start pose, plan.q0 (and of its joint velocities) that the policy observes "
                   "while it excites: 1 as measured, 0 the leg still at that pose, as in the "
                   "hold before (docs/policy-training.md, stop 67; default: the source's)")
    g.add_argument("--stand", type=_stand, default=None, metavar="GAIN|hold",
                   help="while no leg is lifted, the graph stands the robot itself instead of "
                   "playing the network's own stand. GAIN (in [0.01, 5)): at the default pose, "
                   "each tick moving every joint's target by the action scale x GAIN of its "
                   "error, so the PD sag is taken out; hold: zero actions, the targets held "
                   "(the joints sag under the PD law) until the first lift, the network's own "
                   "stand after it. Refused unless it settles on the "
                   "simulator (damped gains)")
    g.add_argument("--target-lead", choices=("torque", "off"), default=None,
                   help="torque: hold each joint's target within effort / kp of the joint, "
                   "where the motor already gives its whole torque (no wound-up demand); off: "
                   "no bound (default: the source's, recomputed for new --gains)")
    r = sub.add_parser("refine", help="add a linear residual on the body's rate and tilt to an "
                       "exported policy's lifts of one leg, tuned by evolution strategies")
    r.add_argument("onnx", help="the exported policy (its .json beside it); a refined policy "
                   "goes on from its residual, over its source's network (beside it)")
    r.add_argument("--out", required=True, help="path stem, e.g. policies/tripod_v2")
    r.add_argument("--generations", type=_count, default=40,
                   help="ES generations (each about a minute on 2 cores at the defaults)")
    r.add_argument("--leg", type=_leg, default="FL",
                   help="the lift refined; legs the policy mirrors onto it follow, and a refined policy's residuals of other lifts stay in its graph as they are (default FL)")
    r.add_argument("--pairs", type=_positive, default=4, help="antithetic pairs per generation")
    r.add_argument("--episodes", type=_positive, default=24,
                   help="episodes per leg and candidate, the same draws for every candidate")
    r.add_argument("--step", type=_number(1e-3, 10.0, "must be in [0.001, 10)"), default=0.3,
                   help="the update's length, as a fraction of one perturbation's")
    r.add_argument("--fail-cost", type=_number(1e-6, 100.0, "must be in (0, 100)"), default=0.1,
                   help="the score's cost of failed episodes, rad/s per failed fraction")
    r.add_argument("--margin-cost", type=_number(0.0, 1000.0, "must be in [0, 1000)"),
                   default=0.0,
                   help="the score's cost of the capture point's shortfall inside the stance "
                   "feet, rad/s per metre (default 0: not scored)")
    r.add_argument("--margin-target", type=_number(0.0, 0.3, "must be in [0, 0.3) m"),
                   default=0.08,
                   help="m inside the stance feet's triangle the capture point should keep "
                   "(default 0.08)")
    r.add_argument("--tilt-cost", type=_number(0.0, 1000.0, "must be in [0, 1000)"), default=0.0,
                   help="the score's cost of the body's tilt RMS in the excitation beyond "
                   "--tilt-target, rad/s per rad (default 0: not scored)")
    r.add_argument("--tilt-target", type=_number(0.0, 30.0, "must be in [0, 30) deg"),
                   default=1.0, help="deg of tilt RMS the score lets pass (default 1)")
    r.add_argument("--clearance-cost", type=_number(0.0, 1000.0, "must be in [0, 1000)"),
                   default=0.0,
                   help="the score's cost of the stance calves' shortfall below "
                   "--clearance-target over the floor in the excitation, rad/s per metre "
                   "(default 0: not scored)")
    r.add_argument("--clearance-target", type=_number(0.0, 0.05, "must be in [0, 0.05) m"),
                   default=0.008,
                   help="m over the floor the stance calves' lowest point should keep "
                   "(default 0.008)")
    r.add_argument("--velocity", action="store_true",
                   help="the residual also reads the base's horizontal velocity from the stance "
                   "legs' joint angles over four policy steps (96 parameters instead of 72)")
    r.add_argument("--dr", type=_dr_setting, action="append", default=[], metavar="FIELD=VALUE",
                   help="a DRConfig field over the standard ranges for the episodes played "
                   "(repeatable), e.g. --dr push_vel=0.5 for harder shoves")
    r.add_argument("--seed", type=int, default=1000,
                   help="directions and draws: generation g plays evaluation seed SEED + g")
    r.add_argument("--state", default=None,
                   help="the ES state, saved each generation (default <out>.refine.json)")
    r.add_argument("--resume", action="store_true", dest="resume_state",
                   help="go on from --state (its source, settings and residual)")
    v = sub.add_parser("eval", help="evaluate an exported policy (onnxruntime)")
    v.add_argument("onnx")
    v.add_argument("--episodes", type=int, default=100)
    v.add_argument("--legs", type=_leg_list, default=None,
                   help="legs to evaluate, e.g. FL,RR (default: the legs its JSON lists)")
    v.add_argument("--seed", type=int, default=1)
    v.add_argument("--no-write", action="store_true", help="do not write results files")
    v.add_argument("--nominal", action="store_true",
                   help="no domain randomisation (writes only the JSON's evaluation_nominal)")
    v.add_argument("--dr-off", type=_dr_groups, default=(), metavar="GROUP[,GROUP]",
                   help="hold these randomisation groups nominal, to see what each costs "
                        f"({', '.join(DR_GROUPS)}); writes nothing")
    v.add_argument("--dr", type=_dr_setting, action="append", default=[], metavar="FIELD=VALUE",
                   help="a randomisation field set over the drawn ranges (repeatable), e.g. "
                        "--dr motor_strength=0.7,0.8 for weak motors; writes nothing")
    v.add_argument("--randomisation", choices=RANDOMISATIONS, default="standard",
                   help="standard: DRConfig's defaults, the same for every policy (written); "
                        "training: the policy's own training ranges (writes nothing)")
    v.add_argument("--results", default=None, metavar="MD",
                   help="the page to write (default: docs/results/policy.md for the policy "
                   "deploy picks, else docs/results/policy_<name>.md, e.g. policy_v28.md)")
    x = sub.add_parser("transfer", help="re-run the policy's calibrations on sim.go2 under "
                                        "perturbations it was not trained for (needs no torch)")
    x.add_argument("onnx", nargs="?", help="the policy (its .json beside it)")
    x.add_argument("--scenarios", type=_scenario_list, default=None, metavar="NAME[,NAME]",
                   help="default: all; --list names them")
    x.add_argument("--list", action="store_true", help="print the scenarios and exit")
    x.add_argument("--episodes", type=_positive, default=20, help="per leg and scenario")
    x.add_argument("--legs", type=_leg_list, default=None,
                   help="legs to lift, e.g. FL,RR (default: the legs its JSON lists)")
    x.add_argument("--seed", type=int, default=1)
    x.add_argument("--workers", type=_positive, default=None, help="processes (default: all cores)")
    x.add_argument("--no-write", action="store_true", help="print only")
    x.add_argument("--out", default="docs/results/policy_transfer.md",
                   help="markdown page; the episodes go beside it as .json")
    x.add_argument("--append", action="store_true",
                   help="add these scenarios to the page at --out (the same policy, seed, legs, "
                        "episodes and model), replacing its rows of them")
    x.add_argument("--model-xml", default=None, metavar="MJCF",
                   help="run on another MJCF model of the Go2 instead of the URDF's (e.g. MuJoCo "
                        "Menagerie's unitree_go2/scene.xml; see sim/external_model.py)")
    x.add_argument("--max-tip", type=_tip_limits, default=None, metavar="LIFT[,HOLD]",
                   help="play deploy's tip guard with these limits, deg, as a2i-deploy "
                        "--max-tip (e.g. 5,8, deploy's default; one number: both phases; "
                        "default: off, the policy alone)")
    x.add_argument("--lift-gate", type=_lift_gate, default=None, metavar="MM[,S]",
                   help="play deploy's lift gate, as a2i-deploy --lift-gate: the foot leaves "
                        "the floor once the estimated centre of mass stands MM mm inside the "
                        "stance triangle, the shift held up to S s longer for it (e.g. 20,2, "
                        "deploy's default; default: off, the lift on time)")
    x.add_argument("--timestep", type=float, default=0.001, metavar="S",
                   help="the simulator's physics step, s, dividing the policy's 20 ms tick "
                        "(default 0.001, the mock's; 0.005 is the training's 200 Hz, the motor "
                        "PD law here still computed explicitly every step, as a checker's "
                        "script may)")
    c = sub.add_parser("compare", help="two transfer runs of the same seed, paired episode by "
                                       "episode (which policy holds more of the same draws)")
    c.add_argument("episodes_files", nargs=2, metavar="EPISODES_JSON",
                   help="the .json a2i-train transfer writes beside its page")
    k = sub.add_parser("pack", help="compiled model + plan pool for a remote training machine")
    k.add_argument("outdir")
    k.add_argument("--plans-per-leg", type=_positive, default=8)
    k.add_argument("--seed", type=int, default=1)
    a = p.parse_args(argv)
    # Input files named on the command line must exist: say so in one line, exit 2.
    if a.cmd == "tripod" and a.resume and a.from_policy:
        p.error("--resume and --from-policy exclude each other: start from one")
    for name in ("checkpoint", "onnx", "resume", "episodes_files", "from_policy", "model_xml"):
        paths = getattr(a, name, None)
        for path in [paths] if isinstance(paths, str) else paths or ():
            if not Path(path).is_file():
                p.error(f"{name} {path}: no such file")
    if a.cmd == "tripod" and a.from_policy and not Path(a.from_policy).with_suffix(".json").is_file():
        p.error(f"{Path(a.from_policy).with_suffix('.json')}: no policy metadata beside the ONNX file")
    if a.cmd == "eval" and a.nominal and (a.dr_off or a.dr):
        p.error("--dr-off and --dr need the randomisation on: drop --nominal")
    if a.cmd == "transfer" and a.onnx is None and not a.list:
        p.error("transfer needs the policy's .onnx (or --list)")
    if a.cmd == "transfer" and a.append and a.no_write:
        p.error("--append writes the page: it cannot go with --no-write")
    if a.cmd == "transfer" and a.scenarios is None:
        from policy_train.transfer import SCENARIOS

        a.scenarios = tuple(SCENARIOS)
    if a.cmd in ("eval", "transfer", "derive", "refine") and a.onnx and not Path(a.onnx).with_suffix(".json").is_file():
        p.error(f"{Path(a.onnx).with_suffix('.json')}: no policy metadata beside the ONNX file")
    try:
        return {"tripod": _tripod, "distill": _distill, "export": _export, "derive": _derive, "eval": _eval,
                "refine": _refine,
                "transfer": _transfer,
                "compare": _compare, "pack": _pack}[a.cmd](a)
    except (OSError, ValueError) as e:
        # the first line of the message (an f-string's !r would quote the whole expression)
        print(f"a2i-train {a.cmd}: error: {(str(e).splitlines() or [repr(e)])[0]}",
              file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
