"""``a2i-train eval``: the exported policy (ONNX through onnxruntime, plus its JSON) under domain
randomisation, per leg, each episode holding the tripod through one full calibration motion.

Per episode: the lift command at t = 0, then the JSON's schedule (shift, lift, hold, the
anti-noise excitation with the JSON's ``t_r`` / ``n_basis`` / ``periods``, lower) and 0.5 s
after. Success: no fall, no contact of anything but the feet, the lifted foot never touching
during hold and excitation. During the excitation (steady window for CN): base tilt RMS, base
angular-rate RMS (norm), lifted-leg joint tracking RMSE (all three joints, the joints at the end
of each policy step against the plan at that instant; the motors get the plan through the drawn
actuation latency, as on the robot), and the condition number of the executed foot angular
velocity (body gyro rotated into the foot frame plus the leg's relative rate, at 50 Hz). Each
failed episode is counted by its first cause (:func:`failure_cause`) and phase, and the stance
calves' lowest approach to the floor during the excitation is reported (``calf_clearance_mm``),
with how much of the excitation their targets sit on the soft limit that caps their extension
(``stance_calves_on_clamp``: there a calf is a kp spring about that limit, and a weaker motor
lets it fold) and the success of the episodes drawn with soft motors (``success_weak``: kp scale
times motor strength below :data:`WEAK_STIFFNESS`).
"""

from __future__ import annotations

import json
import time
from collections import Counter
from pathlib import Path

import numpy as np

from calib.atomic import write_text_atomic
from calib.excitation import base_to_foot, foot_omega
from calib.joints import MODEL_LEGS, default_crouch, model_to_sdk, sdk_to_model
from calib.metrics import condition_number
from deploy.lift_schedule import PHASES, LiftSchedule
from policy_train.config import RANDOMISATIONS, DRConfig, TrainConfig
from policy_train.env import PlanPool, TripodEnv

__all__ = ["TARGETS", "WEAK_STIFFNESS", "evaluate_policy", "evaluation_env", "failure_cause", "foot_angular_velocity",
           "format_failures", "format_table"]

TARGETS = {"success": 0.99, "tilt_rms_deg": 3.0, "ang_rate_rms": 0.1, "track_rmse": 0.05,
           "cn": 1.2}
WEAK_STIFFNESS = 0.9
"""kp scale x motor strength below which an episode's motors count as soft (``success_weak``)."""
_CALVES = 3 * np.arange(4) + 2  # model order: hip, thigh, calf per leg


def foot_angular_velocity(q_leg: np.ndarray, dq_leg: np.ndarray, omega_base: np.ndarray):
    """Foot (calf) frame angular velocity, rad/s, (N, 3): base rate rotated into the foot frame
    (calib.excitation.base_to_foot) plus the leg's relative rate (calib.excitation.foot_omega)."""
    return base_to_foot(omega_base, q_leg) + foot_omega(q_leg, dq_leg)


def evaluation_env(meta: dict, legs, episodes: int, seed: int, nominal: bool = False,
                   dr_off: tuple[str, ...] = (), randomisation: str = "standard",
                   dr_set: dict | None = None) -> tuple[TripodEnv, np.ndarray]:
    """The evaluation's environment for a policy's JSON: ``episodes`` per leg of ``legs``, each
    with the lift command at t = 0 and the JSON's schedule and plans, running to its end (no
    terminations, no reference starts), under the ``randomisation`` (of
    :data:`config.RANDOMISATIONS`), ``dr_off``'s groups held nominal and ``dr_set``'s fields
    (``DRConfig`` names) set over it. Returns the env and each episode's model leg index.
    ValueError for a JSON whose ``default_pose`` is not the training's stand (the environment
    stands every episode there, deploy at the JSON's)."""
    if randomisation not in RANDOMISATIONS:
        raise ValueError(f"unknown randomisation {randomisation!r}; known: "
                         f"{', '.join(RANDOMISATIONS)}")
    # deploy stands the robot at the JSON's default_pose and the environment at the training's:
    # a JSON moved off it would be scored standing where it never stands on board
    if not np.allclose(meta["default_pose"], default_crouch("sdk"), rtol=0.0, atol=1e-6):
        raise ValueError(f"{meta.get('name', 'this policy')}'s default_pose is not the training "
                         f"environment's stand, {np.round(default_crouch('sdk'), 4).tolist()} "
                         "(SDK order): the evaluation cannot stand it where deploy would")
    cfg = TrainConfig.from_dict(meta["train_config"]).env
    cfg.model_file = None
    cfg.plan_pool_file = None
    cfg.num_envs = episodes * len(legs)
    cfg.seed = seed
    if randomisation == "standard":
        cfg.dr = DRConfig()
    cfg.dr = cfg.dr.without(*dr_off).with_settings(dr_set or {})
    cfg.dr.enabled = not nominal
    # every episode starts on four legs and runs to its end: failures are counted, not ended
    cfg.p_reference_start = 0.0
    cfg.terminate_on_contact = False
    cfg.command_resample_s = 1e6
    cfg.episode_s = 1e6  # episodes end with the motion, not by time-out
    cfg.action_scale = float(meta["action"]["scale"])
    cfg.action_clip = float(meta["action"]["clip"])
    lead = meta["action"].get("target_lead_max")  # SDK order in the JSON
    cfg.target_lead_max = None if lead is None else tuple(
        map(float, sdk_to_model(np.asarray(lead, dtype=float))))
    # the JSON's joint gains, as deploy sends them (the randomisation scales them from there)
    kp, kd = (sdk_to_model(np.asarray(meta[k], dtype=float)) for k in ("kp", "kd"))
    cfg.kp, cfg.kd = (float(g[0]) if not np.ptp(g) else tuple(map(float, g)) for g in (kp, kd))
    sched = LiftSchedule.from_metadata(meta["lift_schedule"])
    cfg.shift_s, cfg.lift_s, cfg.hold_s, cfg.lower_s = sched.shift, sched.lift, sched.hold, sched.lower
    cfg.shift_by_leg = sched.shift_by_leg
    cfg.lift_kp, cfg.lift_kd, cfg.lift_feedforward = sched.kp, sched.kd, sched.feedforward
    cfg.lift_adapt, cfg.excitation_seen = sched.adapt, sched.excitation_seen
    pool = PlanPool.from_plans([sched.plan(leg) for leg in MODEL_LEGS], cfg.physics_dt)
    env = TripodEnv(cfg, plan_pool=pool)
    env.obs_terms = meta["observation"]["terms"]  # the JSON's terms, as on board
    leg_of = np.repeat([MODEL_LEGS.index(leg) for leg in legs], episodes)
    env.p_excite = 1.0
    env._sample_commands(np.arange(env.N), legs=leg_of)
    env.lift_plan[:] = leg_of  # pool index == model leg index
    env.lift_dur[:, 3] = pool.duration[leg_of]
    return env, leg_of


def results_page(onnx_path, results_dir="docs/results") -> Path:
    """Where ``a2i-train eval`` writes a policy's page by default: ``policy.md`` for the policy
    deploy picks (:func:`deploy.policy.default_policy_path` from the working directory), else
    ``policy_<name>.md`` (``tripod_go2_v28`` -> ``policy_v28.md``), so that evaluating a
    candidate leaves the deploy policy's page alone."""
    from deploy.policy import default_policy_path

    json_path = Path(onnx_path).with_suffix(".json").resolve()
    try:
        deployed = default_policy_path().resolve() == json_path
    except ValueError:  # no policies/ here
        deployed = False
    name = "" if deployed else "_" + json_path.stem.removeprefix("tripod_go2_")
    return Path(results_dir) / f"policy{name}.md"


def evaluate_policy(onnx_path, episodes: int = 100, legs=None, seed: int = 1, write: bool = True,
                    results_path=None, log=print, nominal: bool = False,
                    dr_off: tuple[str, ...] = (), randomisation: str = "standard",
                    dr_set: dict | None = None) -> dict:
    """Per-leg figures of the policy over ``episodes`` calibration motions per leg, under the
    ``randomisation`` (:data:`config.RANDOMISATIONS`; only ``standard`` is written).

    ``nominal``: no domain randomisation (nominal masses, gains, friction 0.8, no latency,
    pushes or observation noise: the deploy mock's situation); then ``write`` stores the
    figures under the JSON's ``evaluation_nominal`` only, and the DR evaluation's report (run
    after it) shows them in a second table. ``dr_off``: groups of ``config.DR_GROUPS`` held
    nominal (a diagnosis of what each costs); ``dr_set``: ``DRConfig`` fields set over the
    randomisation (``{"motor_strength": (0.7, 0.8)}``: how it does with weak motors). Either
    is a diagnosis, never written. ``write`` writes the page to ``results_path`` (None:
    :func:`results_page`) and the figures into the policy's JSON.
    """
    import onnxruntime as ort

    onnx_path = Path(onnx_path)
    meta = json.loads(onnx_path.with_suffix(".json").read_text())
    legs = tuple(legs) if legs else tuple(meta.get("legs", MODEL_LEGS))  # the legs it serves
    if episodes < 1:
        raise ValueError("episodes must be >= 1")
    if (dr_off or dr_set) and nominal:
        raise ValueError("dr_off and dr_set need the randomisation on (not nominal)")
    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    t0 = time.time()
    env, leg_of = evaluation_env(meta, legs, episodes, seed, nominal=nominal, dr_off=dr_off,
                                 randomisation=randomisation, dr_set=dr_set)
    sched = LiftSchedule.from_metadata(meta["lift_schedule"])
    N = env.N
    total = max(float(sched.total(g)) for g in legs)  # a leg's shift may be its own
    n_steps = int(np.ceil((total + 0.5) / env.dt))
    alive = np.ones(N, dtype=bool)
    touched_other = np.zeros(N, dtype=bool)
    touched_lift = np.zeros(N, dtype=bool)
    tilt2, rate2, err2, nexc = np.zeros(N), np.zeros(N), np.zeros(N), np.zeros(N)
    omega_f = [[] for _ in range(N)]
    ramp = sched.plan(legs[0]).config.ramp
    # the first failure of each episode: its cause and the schedule phase it happened in
    cause, cause_phase = [""] * N, [""] * N
    geoms = env.tm.collision_geoms
    stance = np.ones((N, 4), dtype=bool)
    stance[np.arange(N), leg_of] = False
    calf_min = np.full(N, np.inf)  # lowest a stance calf came to the floor in the excitation, m
    on_clamp = np.zeros(N)  # stance calves' targets on their upper soft limit, summed over steps
    # as drawn for the episode: an env that falls is reset with new draws
    weak = env.kp_s * env.strength < WEAK_STIFFNESS
    obs = env.observations()["policy"]
    name_in = sess.get_inputs()[0].name
    log(f"eval: {N} episodes ({', '.join(legs)}), {total + 0.5:.1f} s each")
    for k in range(n_steps):
        if k and k % max(1, n_steps // 10) == 0:
            log(f"  {k * env.dt:.1f}/{n_steps * env.dt:.1f} s simulated, "
                f"{time.time() - t0:.0f} s, {int(alive.sum())} standing")
        act = sess.run(None, {name_in: obs.astype(np.float32)})[0]
        before = env.phase.copy()
        ob, _, _, extras = env.step(act)
        obs = ob["policy"]
        term = extras["terminated"]
        phase = step_phase(before, env.phase, term)
        was_ok = alive & ~touched_other & ~touched_lift
        alive &= ~term
        touched_other |= env.other_touch & alive
        touched_lift |= env.lift_touch & alive
        for i in np.flatnonzero(was_ok & (term | env.other_touch | env.lift_touch)):
            cause[i] = failure_cause(bool(term[i]), [geoms[g] for g in np.flatnonzero(
                env.geom_touch[i])], MODEL_LEGS[leg_of[i]], bool(env.lift_touch[i]))
            cause_phase[i] = PHASES[min(phase[i], len(PHASES) - 1)]
        exc = alive & (env.phase == 3)
        if exc.any():
            calf_min[exc] = np.minimum(calf_min[exc], env.stance_calf_clearance(exc))
            pinned = np.isclose(env.target[exc][:, _CALVES], env.soft_hi[_CALVES]) & stance[exc]
            on_clamp[exc] += pinned.sum(1) / 3.0
            tilt2[exc] += env.tilt[exc] ** 2
            rate2[exc] += np.sum(env.ang_vel_b[exc] ** 2, 1)
            err2[exc] += np.nanmean(env.lift_err[exc] ** 2, 1)
            nexc[exc] += 1
            te = env.lift_t - env.lift_dur[:, :3].sum(1)
            steady = exc & (te >= ramp) & (te <= env.lift_dur[:, 3] - ramp)
            ids = np.flatnonzero(steady)
            if len(ids):
                jl = 3 * leg_of[ids, None] + np.arange(3)
                wf = foot_angular_velocity(env.q[ids[:, None], jl], env.dq[ids[:, None], jl],
                                           env.ang_vel_b[ids])
                for i, w in zip(ids, wf, strict=True):
                    omega_f[i].append(w)
    success = alive & ~touched_other & ~touched_lift
    rows = {}
    for leg in legs:
        sel = leg_of == MODEL_LEGS.index(leg)
        ok = sel & (nexc > 0)
        held = ok & success
        cn = [condition_number(np.array(omega_f[i])) for i in np.flatnonzero(ok & success)
              if len(omega_f[i]) > 10]
        rows[leg] = {
            "episodes": int(sel.sum()),
            "success": float(success[sel].mean()),
            "falls": int((~alive[sel]).sum()),
            "other_contact": int(touched_other[sel].sum()),
            "lifted_foot_touch": int(touched_lift[sel].sum()),
            "tilt_rms_deg": float(np.degrees(_rms(tilt2[ok], nexc[ok]))),
            "ang_rate_rms": _rms(rate2[ok], nexc[ok]),
            # the same over the successful episodes only: how still a held tripod is, apart
            # from the episodes that tip (their fall dominates the figure above)
            "tilt_rms_deg_held": float(np.degrees(_rms(tilt2[held], nexc[held]))),
            "ang_rate_rms_held": _rms(rate2[held], nexc[held]),
            "track_rmse": _rms(err2[ok], nexc[ok]),
            "cn_median": float(np.median(cn)) if cn else float("nan"),
            "cn_p90": float(np.percentile(cn, 90)) if cn else float("nan"),
            "first_failure": _counts(cause[i] for i in np.flatnonzero(sel & ~success)),
            "first_failure_phase": _counts(cause_phase[i] for i in np.flatnonzero(sel & ~success)),
            # median and 10th percentile over the episodes of their lowest stance calf, mm
            "calf_clearance_mm": [float(1e3 * np.percentile(calf_min[ok], p)) if ok.any()
                                  else float("nan") for p in (50, 10)],
            "stance_calves_on_clamp": float(on_clamp[ok].sum() / nexc[ok].sum())
            if ok.any() else float("nan"),
            "success_weak": {"episodes": int((sel & weak).sum()),
                             "success": float(success[sel & weak].mean())
                             if (sel & weak).any() else float("nan")},
        }
    try:  # the command as one types it in the repository
        shown = onnx_path.resolve().relative_to(Path.cwd().resolve()).as_posix()
    except ValueError:
        shown = onnx_path.as_posix()
    result = {"policy": onnx_path.name, "path": shown,
              "episodes_per_leg": episodes, "seed": seed,
              "domain_randomisation": not nominal, "dr_off": list(dr_off),
              "dr_set": {k: list(v) if isinstance(v, tuple) else v
                         for k, v in (dr_set or {}).items()},
              "randomisation": randomisation,
              "armature_kg_m2": [float(x) for x in env.cfg.dr.armature],
              "motion_s": total, "t_r": sched.t_r, "periods": sched.periods,
              "wall_s": time.time() - t0, "legs": rows, "targets": TARGETS}
    table = format_table(result)
    log(table)
    log("\n" + format_failures(result))
    # a diagnosis, not the policy's evaluation
    write = write and not dr_off and not dr_set and randomisation == "standard"
    if write and nominal:
        meta["evaluation_nominal"] = result
        write_text_atomic(onnx_path.with_suffix(".json"), json.dumps(meta, indent=1) + "\n")
    elif write:
        write_text_atomic(results_path or results_page(onnx_path), _report(result, meta, table))
        meta["evaluation"] = result
        write_text_atomic(onnx_path.with_suffix(".json"), json.dumps(meta, indent=1) + "\n")
    return result


def step_phase(before: np.ndarray, after: np.ndarray, terminated: np.ndarray) -> np.ndarray:
    """(N,) the schedule phase each env's policy step ended in: ``after``'s, but for a
    terminated env the one it started in (``before``), since the step resets it and ``after``
    is then the new episode's."""
    return np.where(terminated, before, after)


def failure_cause(fell: bool, geoms: list[str], lifted: str, lift_touch: bool) -> str:
    """What ended a successful tripod, in words, from one policy step's events.

    ``geoms``: the non-foot collision geoms on the floor (``<leg>_<part>_colN`` or
    ``base_colN``); ``lifted``: the lifted leg's name. A fall (tilt, height, body on the floor)
    comes first, then a stance calf, a stance hip or thigh, the lifted leg, the body, and
    last the lifted foot set down."""
    if fell:
        return "fall"
    kinds = set()
    for g in geoms:
        leg, _, rest = g.partition("_")
        if leg not in MODEL_LEGS:
            kinds.add("body")
        elif leg == lifted:
            kinds.add("lifted leg")
        else:
            kinds.add("stance calf" if rest.startswith("calf") else "stance hip/thigh")
    for k in ("stance calf", "stance hip/thigh", "lifted leg", "body"):
        if k in kinds:
            return k
    return "lifted foot down" if lift_touch else ""


def _counts(items) -> dict[str, int]:
    return dict(Counter(items).most_common())


def _training(meta: dict) -> str:
    """How the network was trained: PPO iterations, or distilled from a teacher."""
    d = meta.get("distilled_from")
    if d:
        when = (", labelled with the teacher's action where the student's reaches the motors"
                if d.get("labels") == "actuation" else "")
        return (f"{meta.get('iterations')} DAgger iterations distilling `{d.get('teacher_name')}` "
                f"into a policy that sees its last {d.get('history')} observation frames{when}")
    return f"{meta.get('iterations')} PPO iterations"


def _refined(meta: dict) -> str:
    """How ``a2i-train refine`` changed the network's actions, if it did."""
    r = meta.get("refined_from")
    if not r:
        return ""
    dr = r.get("config", {}).get("dr") or {}
    played = (" on episodes with " + ", ".join(f"{k} {v}" for k, v in dr.items())) if dr else ""
    c = r.get("continued_from")
    went_on = (f" (the last {len(r['generations']) - c['generations']} going on from "
               f"`{c['policy']}`'s residual{played})" if c else played)
    reads = ("rate, tilt and the stance legs' velocity" if len(r.get("inputs", ())) > 5
             else "rate and tilt")
    kept = "".join(f", over the {' and '.join(k['legs'])} lifts' residual of "
                   f"{len(k['generations'])} generations kept as it was"
                   for k in r.get("kept", []))
    return (f"; then {len(r['generations'])} generations of `a2i-train refine` on "
            f"`{r['policy']}`{went_on}: a linear residual on the body's {reads} for the "
            f"{' and '.join(r['legs'])} lifts, tuned by evolution strategies{kept}")


def _derived(meta: dict) -> str:
    """What ``a2i-train derive`` changed from its source's deploy settings, if it did."""
    d = meta.get("derived_from")
    if not d:
        return ""
    sched = meta.get("lift_schedule") or {}
    changed = []
    if d.get("kp") != meta.get("kp") or d.get("kd") != meta.get("kd"):
        changed.append("other joint gains")
    if d.get("lift_gains") not in (None, [sched.get("kp"), sched.get("kd")]):
        changed.append(f"the lifted leg at kp {sched.get('kp'):g} / kd {sched.get('kd'):g}")
    if d.get("t_r") not in (None, sched.get("t_r")):
        changed.append(f"the excitation at t_r {sched.get('t_r'):g} s (was {d['t_r']:g})")
    by_leg = sched.get("shift_by_leg") or {}
    if d.get("shift") not in (None, sched.get("shift")) or by_leg != (d.get("shift_by_leg") or {}):
        legs = ", ".join(f"{leg} {v:g} s" for leg, v in sorted(by_leg.items()))
        changed.append(f"a shift of {sched.get('shift'):g} s" + (f" ({legs})" if legs else "")
                       + f" (was {d['shift']:g}" + (" per leg" if d.get("shift_by_leg") else "")
                       + ")")
    if bool(d.get("adapt", False)) != bool(sched.get("adapt", False)):
        changed.append("the lifted leg's tracking adapter " + ("on" if sched.get("adapt")
                                                                else "off"))
    seen = float(sched.get("excitation_seen", 1.0))
    if float(d.get("excitation_seen", 1.0)) != seen:
        changed.append(f"the lifted leg observed at {seen:g} of its excursion while it excites"
                       if seen != 1.0 else "the lifted leg observed as measured while it excites")
    lead = (meta.get("action") or {}).get("target_lead_max")
    if lead != d.get("target_lead_max", lead):  # records before the bound: none then
        changed.append("every joint's target held within effort / kp of its joint "
                       "(`deploy.action`)" if lead is not None else "no target lead bound")
    stand = meta.get("stand") or {"mode": "network"}
    if stand != (d.get("stand") or {"mode": "network"}):
        if stand.get("mode") == "home":
            changed.append(f"with no leg lifted, the stand at the default pose of "
                           f"`policy_train.stand` (gain {stand['gain']:g}) instead of the "
                           "network's")
        elif stand.get("mode") == "hold":
            changed.append("with no leg lifted yet, the joint targets held (`policy_train.stand`'s "
                           "hold) instead of the network's stand")
    # no "then": a refined policy keeps the derive record of the policy it was refined from
    return (f"; its deploy settings from `a2i-train derive` on `{d.get('policy')}`: "
            f"{', '.join(changed) or 'none changed'}")


def _averaged(meta: dict) -> str:
    its = meta.get("averaged_iterations")
    return f"; the weight average of iterations {', '.join(map(str, its))}" if its else ""


def _nominal_section(meta: dict) -> str:
    n = meta.get("evaluation_nominal")
    if not n or n.get("policy") != meta.get("onnx"):
        return ""
    return f"""
## Without domain randomisation

`a2i-train eval {n.get('path', 'policies/' + n['policy'])} --nominal --episodes {n['episodes_per_leg']}`: nominal
MuJoCo model, gains and masses, friction 0.8, no latency, pushes or observation noise (the
situation of the deploy mock); the same calibration motion.

{format_table(n)}
"""


def _rms(sum_sq: np.ndarray, count: np.ndarray) -> float:
    n = float(count.sum())
    return float(np.sqrt(sum_sq.sum() / n)) if n > 0 else float("nan")


def _armature(r: dict) -> str:
    lo, hi = r.get("armature_kg_m2", (0.01, 0.01))
    return f"joint armature {lo:g} kg m^2" if lo == hi else f"joint armature {lo:g}-{hi:g} kg m^2"


def _mark(ok: bool) -> str:
    return "ok" if ok else "MISS"


def _held(x: dict, key: str, digits: int) -> str:
    v = x.get(key)  # evaluations before v7 did not store it
    return "" if v is None else f" ({v:.{digits}f})"


def format_table(r: dict) -> str:
    t = TARGETS
    lines = [("| leg | success | falls | other contact | lifted foot touch | tilt RMS (deg), all "
              "(held) | ang. rate RMS (rad/s), all (held) | tracking RMSE (rad) "
              "| CN median (p90) |"),
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for leg, x in r["legs"].items():
        lines.append(
            f"| {leg} | {100 * x['success']:.0f} % {_mark(x['success'] >= t['success'])} "
            f"| {x['falls']} | {x['other_contact']} | {x['lifted_foot_touch']} "
            f"| {x['tilt_rms_deg']:.2f} {_mark(x['tilt_rms_deg'] <= t['tilt_rms_deg'])}"
            f"{_held(x, 'tilt_rms_deg_held', 2)} "
            f"| {x['ang_rate_rms']:.3f} {_mark(x['ang_rate_rms'] <= t['ang_rate_rms'])}"
            f"{_held(x, 'ang_rate_rms_held', 3)} "
            f"| {x['track_rmse']:.3f} {_mark(x['track_rmse'] <= t['track_rmse'])} "
            f"| {x['cn_median']:.3f} ({x['cn_p90']:.3f}) {_mark(x['cn_p90'] <= t['cn'])} |")
    return "\n".join(lines)


def format_failures(r: dict) -> str:
    """The failed episodes by first cause and phase, and the stance calves' clearance; empty
    for evaluations stored before they were recorded."""
    if not all("first_failure" in x for x in r["legs"].values()):
        return ""

    def words(d: dict) -> str:
        return ", ".join(f"{k} {n}" for k, n in d.items()) or "-"

    def clamp(x: dict) -> str:  # evaluations stored before it was recorded have neither
        v = x.get("stance_calves_on_clamp")
        return "" if v is None or np.isnan(v) else f"{100 * v:.0f} %"

    def weak(x: dict) -> str:
        w = x.get("success_weak")
        if w is None:
            return ""
        return "-" if not w["episodes"] else f"{100 * w['success']:.0f} % of {w['episodes']}"

    lines = [("| leg | failed | first failure | in phase | stance-calf clearance (mm), median "
              "(p10) of the episodes' lowest | stance calves' targets on their soft limit | "
              f"success with kp x strength < {WEAK_STIFFNESS:g} |"),
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for leg, x in r["legs"].items():
        med, p10 = x["calf_clearance_mm"]
        lines.append(f"| {leg} | {sum(x['first_failure'].values())} | {words(x['first_failure'])} "
                     f"| {words(x['first_failure_phase'])} | {med:.1f} ({p10:.1f}) | {clamp(x)} "
                     f"| {weak(x)} |")
    return "\n".join(lines)


def _failures_section(r: dict) -> str:
    t = format_failures(r)
    return "" if not t else f"""
What ended the failed episodes (the first event of each: a fall, then the part that touched the
floor, then the lifted foot set down), in which phase of the schedule, and how close the
stance calves came to the floor during the excitation (the lowest point of their collision
hulls; a touch counts from 1 N); the share of the excitation's policy steps in which the
stance calves' targets sit on the clamp of their extension (the upper `soft_limits` of the JSON,
where a calf is a kp spring about that clamp: a weaker motor lets it fold); and the success of
the episodes whose motors were drawn soft (kp scale times motor strength below
{WEAK_STIFFNESS:g}):

{t}
"""


def _report(r: dict, meta: dict, table: str) -> str:
    return f"""# Tripod policy evaluation

Policy `{r['policy']}` (commit `{meta.get('commit')}`, seed {meta.get('seed')},
{_training(meta)}{_averaged(meta)}{_refined(meta)}{_derived(meta)}). Produced by
`a2i-train eval {r.get('path', 'policies/' + r['policy'])} --episodes {r['episodes_per_leg']}` (seed {r['seed']}):
the ONNX through onnxruntime, the JSON's observation terms, action, joint gains ({_gains_words(meta)}{_gains_note(meta)}) and lift schedule (the
lifted leg at kp {meta['lift_schedule']['kp']:g} / kd {meta['lift_schedule']['kd']:g}{_lift_gains_note(meta)}).

Each episode: the standard domain randomisation (`DRConfig`'s defaults, the same for
every policy whatever ranges it trained on: masses, centre of mass, {_armature(r)},
friction, kp/kd, motor strength, 0-20 ms latency, pushes, observation noise), the lift command at t = 0 and one
full calibration motion: shift, lift, hold, the anti-noise excitation (t_r = {r['t_r']} s,
{r['periods']} periods), lower; {r['motion_s']:.1f} s in all. Success = no fall, no contact but
the feet, the lifted foot never down during hold and excitation. Tilt, angular rate and
tracking are RMS over the excitation of the episodes that reached it (targets marked on
these), tilt and angular rate also over the successful episodes alone ("held"); CN over the
excitation's steady window of the successful episodes.

Targets: success >= 99 %, tilt RMS <= 3 deg, angular rate RMS <= 0.1 rad/s, tracking RMSE
<= 0.05 rad, CN <= 1.2 (p90 compared).

{table}
{_failures_section(r)}
Wall time {r['wall_s']:.0f} s.
{_nominal_section(meta)}

## Training curve

Mean per-step reward of the rollouts, mean return and length of the episodes that ended in
the iteration (20 s episodes; falls end them early). Stage 1 = tripod hold only, stage 2 = with
the calibration motions (paper's two phases).

| iteration | stage | step reward | episode return | episode length (s) |
| --- | --- | --- | --- | --- |
{_curve(meta)}
"""


def _gains_words(meta: dict) -> str:
    """The JSON's joint gains: one pair, a pair per joint type (``a2i-train derive --gains
    KP,KD/KP,KD/KP,KD``), or all twelve in SDK order."""
    kp, kd = (np.asarray(meta[k], dtype=float) for k in ("kp", "kd"))
    if not np.ptp(kp) and not np.ptp(kd):
        return f"kp {kp[0]:g} / kd {kd[0]:g}"
    if all(np.array_equal(g, np.resize(g[:3], 12)) for g in (kp, kd)):
        return (f"hip / thigh / calf kp {' / '.join(f'{g:g}' for g in kp[:3])}, "
                f"kd {' / '.join(f'{g:g}' for g in kd[:3])}")
    return f"kp {kp.tolist()}, kd {kd.tolist()} (SDK order)"


def _gains_note(meta: dict) -> str:
    """Whether the joints' gains are the training's: ``a2i-train derive`` may set others."""
    env = meta.get("train_config", {}).get("env", {})
    if env.get("kp") is None:
        return ""
    # one value, or twelve in model order (a2i-train tripod --gains KP,KD/KP,KD/KP,KD)
    trained = {k: model_to_sdk(np.broadcast_to(np.asarray(env[k], dtype=float), (12,)))
               for k in ("kp", "kd")}
    if all(np.array_equal(trained[k], np.asarray(meta[k], dtype=float)) for k in trained):
        return ""
    tk, td = trained["kp"], trained["kd"]
    if not np.ptp(tk) and not np.ptp(td):
        return f"; trained at {tk[0]:g} / {td[0]:g}"
    return f"; trained at {_gains_words(trained)}"


def _lift_gains_note(meta: dict) -> str:
    """Whether the lifted leg's gains are the training's: the export may set others."""
    env = meta.get("train_config", {}).get("env", {})
    kp, kd = env.get("lift_kp"), env.get("lift_kd")
    sched = meta["lift_schedule"]
    if kp is None or (kp == sched["kp"] and kd == sched["kd"]):
        return ""
    return f"; trained at {kp:g} / {kd:g}"


def _curve(meta: dict) -> str:
    rows = []
    for h in meta.get("training_history", [])[::5]:
        er, el = h.get("mean_episode_reward"), h.get("mean_episode_length_s")
        sr = h.get("mean_step_reward")
        rows.append(f"| {h['iteration']} | {h['stage']} | {'-' if sr is None else f'{sr:+.4f}'} | "
                    f"{'-' if er is None else f'{er:+.1f}'} | {'-' if el is None else f'{el:.1f}'} |")
    return "\n".join(rows)

