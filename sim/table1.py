"""The paper's Table I in MuJoCo: calibration accuracy of walk, spin, wave and A2I motions.

4 legs x gyro noise {0.006, 0.03, 0.06} deg/s/sqrt(Hz) x motions {walk, spin, wave, A2I} x
seeds. Each (motion, seed) is simulated once (:func:`sim.calibration_run.run_motion`, base held
on the motion's prescribed trajectory, joints under PD at 1 kHz, encoders at 500 Hz); the foot
IMUs are then applied to the recorded truth with each noise level, so every motion is judged on
the same hidden mountings, and on records of one length (the A2I excitation's: with white
gyro noise the rotation error falls as the square root of the record's length, so a longer
record would buy a baseline accuracy its motion does not earn).

Two pipelines are scored on the same data:

* ``paper``: the paper's method as published: foot angular velocity from forward kinematics
  relative to the base (still-base assumption) and the rotation from the SVD of
  S_FF^-1 S_FI; no observability gates.
* ``ours``: this toolkit: base rotation compensated with the body gyro, Procrustes rotation,
  sub-sample offset; the authors' gates (``SolverConfig.paper_gates()``: kappa < 20,
  lambda_min > 0.015, r > 0.9, plus our uncertainty gates) are evaluated and their verdict
  counted (the estimate is still scored, to compare like with like).

The free-base table (:func:`run_table1_free`, ``a2i-calib bench --policy``) scores the same way
runs where nothing holds the base (:mod:`sim.free_base_run`): walk and spin are their joint
trajectories played open-loop on the floor, wave is the naive waving (stand, lift and wave one
leg, no balance controller), and A2I is executed by the tripod policy (a picklable callable
``leg -> (MotionRun, RunHealth)`` given by the caller, e.g. ``policy_train.policy_motion``,
which this module cannot import). Each run also reports how upright the robot stayed.
"""

from __future__ import annotations

import dataclasses
import json
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from calib.excitation import ExcitationConfig, plan_excitation
from calib.joints import LEGS
from calib.kinematics import LegKinematics
from calib.metrics import euler_rotation_error_deg, geodesic_error_deg
from calib.motions import a2i_motion, spin_motion, walk_motion, wave_motion
from calib.solver import CalibrationRefused, SolverConfig, solve
from sim.calibration_run import MotionRun, run_motion
from sim.free_base_run import RunHealth, naive_wave_free, run_motion_free
from sim.sensors import PAPER_GYRO_NOISE_DEG, random_mounting

MOTIONS = ("walk", "spin", "wave", "a2i")
PIPELINES = ("paper", "ours")
IMU_RATE = 400.0
"""Foot-IMU rate of the study, Hz."""

# Scoring configuration: no gate may stop an estimate (the gates are evaluated separately).
_UNGATED = SolverConfig(min_eigenvalue=0.0, max_condition_number=np.inf, min_correlation=0.0,
                        max_rotation_std_deg=np.inf, max_time_offset_std_s=np.inf,
                        ambiguity_ratio=0.0, edge_margin=0, rotation_method="procrustes")
_PAPER = dataclasses.replace(_UNGATED, rotation_method="paper")

# Paper Table I (Gazebo): {leg: {noise: {motion: (CN, CC, RE deg)}}}.
PAPER_TABLE1 = {
    "FL": {0.006: {"walk": (413.53, 0.89, 50.04), "spin": (618.81, 0.83, 78.37),
                   "wave": (75.39, 0.81, 48.33), "a2i": (1.17, 0.99, 6.74)},
           0.03: {"walk": (217.54, 0.93, 29.28), "spin": (442.97, 0.83, 71.20),
                  "wave": (72.52, 0.80, 56.50), "a2i": (1.23, 0.99, 7.35)},
           0.06: {"walk": (270.14, 0.93, 27.48), "spin": (468.26, 0.82, 283.22),
                  "wave": (53.27, 0.75, 63.90), "a2i": (1.25, 0.99, 6.97)}},
    "FR": {0.006: {"walk": (345.46, 0.92, 62.53), "spin": (99.70, 0.89, 26.27),
                   "wave": (52.70, 0.67, 238.61), "a2i": (1.25, 0.99, 1.03)},
           0.03: {"walk": (307.42, 0.93, 22.72), "spin": (79.59, 0.85, 20.66),
                  "wave": (50.33, 0.68, 241.12), "a2i": (1.60, 0.99, 1.47)},
           0.06: {"walk": (326.18, 0.93, 38.03), "spin": (88.65, 0.82, 41.41),
                  "wave": (55.44, 0.65, 236.92), "a2i": (1.52, 0.99, 1.41)}},
    "RL": {0.006: {"walk": (198.00, 0.93, 55.61), "spin": (254.77, 0.92, 60.96),
                   "wave": (66.05, 0.75, 98.83), "a2i": (1.28, 0.99, 2.33)},
           0.03: {"walk": (182.10, 0.93, 38.24), "spin": (193.00, 0.92, 8.89),
                  "wave": (52.83, 0.71, 76.60), "a2i": (1.51, 0.99, 2.02)},
           0.06: {"walk": (192.24, 0.93, 43.53), "spin": (194.55, 0.92, 64.05),
                  "wave": (73.90, 0.73, 89.80), "a2i": (1.54, 0.99, 1.47)}},
    "RR": {0.006: {"walk": (125.23, 0.94, 74.99), "spin": (82.91, 0.91, 75.46),
                   "wave": (23.08, 0.80, 16.74), "a2i": (1.21, 0.99, 2.04)},
           0.03: {"walk": (108.78, 0.95, 50.95), "spin": (77.46, 0.90, 38.89),
                  "wave": (35.69, 0.82, 158.39), "a2i": (1.29, 0.99, 2.61)},
           0.06: {"walk": (115.97, 0.95, 62.94), "spin": (75.37, 0.90, 91.07),
                  "wave": (26.09, 0.81, 55.20), "a2i": (1.37, 0.99, 1.44)}},
}


@dataclass
class Table1Row:
    """One scored calibration. Angles in degrees, offsets in seconds. gates_pass: whether the
    authors' gates (:meth:`SolverConfig.paper_gates`) accept our pipeline's solve; None on the
    paper pipeline's rows, which run without gates and are not judged by them."""

    leg: str
    noise_deg: float
    motion: str
    pipeline: str
    seed: int
    cn: float
    cc: float
    re_euler_deg: float
    geodesic_deg: float
    offset_error_s: float
    gates_pass: bool | None


def _mounting_seed(seed: int, leg: str) -> int:
    return 1000 * seed + LEGS.index(leg)


def held_record_s() -> float:
    """Length of every held-base record, s: the A2I plan's (the generator's defaults, ramps
    included, the same for every leg and seed), which walk, spin and wave are given too, so
    that the motions are compared on records of one length."""
    return ExcitationConfig(leg=LEGS[0]).duration


def _make_motion(name: str, seed: int, leg: str | None, duration: float):
    """The motion ``name``; walk, spin and wave last ``duration`` s, A2I its plan."""
    if name == "walk":
        return walk_motion(duration, 200.0, seed)
    if name == "spin":
        return spin_motion(duration, 200.0, seed)
    if name == "wave":
        return wave_motion(leg, duration, 200.0, seed)
    if name == "a2i":
        return a2i_motion(plan_excitation(ExcitationConfig(leg=leg, seed=seed)), 200.0)
    raise ValueError(f"unknown motion {name!r}: expected one of {', '.join(MOTIONS)}")


def score_run(run: MotionRun, motion: str, legs, noises, seed: int,
              record_s: dict[str, float] | None = None) -> list[Table1Row]:
    """Score every (leg, noise, pipeline) calibration from one simulated motion.
    record_s: {leg: s}, score that leg on the first s of the record (None: all of it)."""
    rows = []
    for leg in legs:
        rec = run if record_s is None else run.head(record_s[leg])
        kin = LegKinematics.from_urdf(leg=leg)
        q, dq = rec.leg_joints(leg)
        omega_rel = kin.foot_angular_velocity(q, dq)
        omega_abs = kin.foot_angular_velocity(q, dq, rec.base_gyro)
        for noise in noises:
            mount = random_mounting(_mounting_seed(seed, leg), gyro_noise_deg=noise,
                                    rate=IMU_RATE)
            imu = rec.foot_imu(leg, mount)
            for pipeline in PIPELINES:
                omega, cfg = (omega_rel, _PAPER) if pipeline == "paper" else (omega_abs, _UNGATED)
                sol = solve(rec.t, omega, imu.stamps, imu.gyro, cfg)
                gates_pass = None
                if pipeline == "ours":
                    gates_pass = True
                    try:
                        solve(rec.t, omega, imu.stamps, imu.gyro, SolverConfig.paper_gates())
                    except CalibrationRefused:
                        gates_pass = False
                rows.append(Table1Row(
                    leg, noise, motion, pipeline, seed, float(sol.condition_number),
                    float(sol.correlation),
                    float(euler_rotation_error_deg(sol.rotation, mount.rotation)),
                    float(geodesic_error_deg(sol.rotation, mount.rotation)),
                    float(abs(sol.time_offset - mount.time_offset)), gates_pass))
    return rows


def _job(args) -> list[Table1Row]:
    motion, seed, leg, legs, noises = args
    run = run_motion(_make_motion(motion, seed, leg, held_record_s()))
    return score_run(run, motion, legs if leg is None else [leg], noises, seed)


def run_table1(seeds=(0, 1, 2), legs=LEGS, noises=PAPER_GYRO_NOISE_DEG, workers=None,
               progress=None) -> list[Table1Row]:
    """All rows of the study. workers: processes (None: all cores). progress(done, total)."""
    jobs = []
    for seed in seeds:
        for motion in ("walk", "spin"):
            jobs.append((motion, seed, None, tuple(legs), tuple(noises)))
        for motion in ("wave", "a2i"):
            for leg in legs:
                jobs.append((motion, seed, leg, tuple(legs), tuple(noises)))
    rows: list[Table1Row] = []
    workers = workers or os.cpu_count() or 1
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for i, r in enumerate(pool.map(_job, jobs), 1):
            rows.extend(r)
            if progress is not None:
                progress(i, len(jobs))
    return rows


@dataclass
class FreeRun:
    """How one free-base run fared. leg None: a gait scored on every leg; seed None: the
    policy's A2I run, deterministic, scored with every seed's mountings."""

    motion: str
    leg: str | None
    seed: int | None
    health: RunHealth

    def to_dict(self) -> dict:
        return {"motion": self.motion, "leg": self.leg, "seed": self.seed,
                "health": self.health.to_dict()}

    @classmethod
    def from_dict(cls, d: dict) -> FreeRun:
        return cls(d["motion"], d["leg"], d["seed"], RunHealth.from_dict(d["health"]))


@dataclass
class FreeTable:
    """The free-base Table I: scored rows, the runs' health, the seeds, the policy file name,
    wall time (s), and each leg's record length (s; None in files written before it was
    kept)."""

    rows: list[Table1Row]
    runs: list[FreeRun]
    seeds: list[int]
    policy: str
    elapsed_s: float | None = None
    record_s: dict[str, float] | None = None

    def to_json(self) -> str:
        return json.dumps({"policy": self.policy, "seeds": list(self.seeds),
                           "elapsed_s": self.elapsed_s, "record_s": self.record_s,
                           "rows": [dataclasses.asdict(r) for r in self.rows],
                           "runs": [r.to_dict() for r in self.runs]}, indent=0)

    @classmethod
    def from_json(cls, text: str) -> FreeTable:
        d = json.loads(text)
        if not isinstance(d, dict) or "rows" not in d or "runs" not in d:
            raise ValueError("not a free-base table (expected an object with rows and runs)")
        return cls([Table1Row(**r) for r in d["rows"]], [FreeRun.from_dict(r) for r in d["runs"]],
                   [int(s) for s in d["seeds"]], str(d["policy"]), d.get("elapsed_s"),
                   d.get("record_s"))


def _free_job(args) -> tuple[list[Table1Row], list[FreeRun]]:
    motion, seed, leg, legs, noises, seeds, a2i_run, record_s = args
    if motion == "a2i":
        run, health = a2i_run(leg)
        if run is None:
            raise RuntimeError(f"the A2I run of {leg} was called off: {health.aborted}")
        if health.fell or health.lifted_foot_touched or health.body_contacts:
            raise RuntimeError(f"the A2I run of {leg} did not hold the tripod (fell "
                               f"{health.fell}, lifted foot down {health.lifted_foot_touched}, "
                               f"other bodies on the floor {list(health.body_contacts)}): the "
                               "table would score a failed calibration")
        rows = [r for s in seeds for r in score_run(run, motion, [leg], noises, s)]
        return rows, [FreeRun(motion, leg, None, health)]
    scored = legs if leg is None else (leg,)
    duration = max(record_s[g] for g in scored)
    if motion == "wave":
        wave, via = naive_wave_free(leg, duration, seed)
        run, health = run_motion_free(wave, lifted_leg=leg, via=via)
    else:
        run, health = run_motion_free(_make_motion(motion, seed, leg, duration))
    # a robot that fell records no calibration anyone would keep (the naive wave once lay on
    # its back, rocking, and scored well): its run is listed in the health table, not scored
    rows = [] if health.fell else score_run(run, motion, scored, noises, seed, record_s)
    return rows, [FreeRun(motion, leg, seed, health)]


def run_table1_free(a2i_run, record_s, seeds=(0, 1, 2), legs=LEGS,
                    noises=PAPER_GYRO_NOISE_DEG, workers=None,
                    progress=None) -> tuple[list[Table1Row], list[FreeRun]]:
    """Rows and run health of the free-base study (see the module docstring).

    a2i_run: picklable ``leg -> (MotionRun, RunHealth)`` executing the A2I calibration of
    ``leg`` (run once per leg; its mountings come from each seed as for the other motions).
    record_s: s, the length of each leg's A2I record (its excitation phase, ramps included), a
    number or {leg: s}: walk, spin and wave are scored over records that long, so that every
    motion of a leg is judged on as much data.
    Same legs, noise levels, seeds, pipelines and scoring as :func:`run_table1`.
    workers: processes (None: all cores). progress(done, total).
    """
    legs, noises, seeds = tuple(legs), tuple(noises), tuple(seeds)
    if not isinstance(record_s, dict):
        record_s = dict.fromkeys(legs, record_s)
    missing = [g for g in legs if g not in record_s]
    if missing:
        raise ValueError(f"no record length for {', '.join(missing)}")
    record_s = {g: float(record_s[g]) for g in legs}
    if not all(np.isfinite(v) and v > 0 for v in record_s.values()):
        raise ValueError(f"record lengths must be positive seconds, got {record_s}")
    jobs = [("a2i", None, leg, legs, noises, seeds, a2i_run, record_s) for leg in legs]
    for seed in seeds:
        for motion in ("walk", "spin"):
            jobs.append((motion, seed, None, legs, noises, seeds, None, record_s))
        for leg in legs:
            jobs.append(("wave", seed, leg, legs, noises, seeds, None, record_s))
    rows: list[Table1Row] = []
    runs: list[FreeRun] = []
    workers = workers or os.cpu_count() or 1
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for i, (r, h) in enumerate(pool.map(_free_job, jobs), 1):
            rows.extend(r)
            runs.extend(h)
            if progress is not None:
                progress(i, len(jobs))
    return rows, runs


def beats_baselines(rows: list[Table1Row], pipeline: str) -> dict:
    """{(leg, noise): (wins on CN, on CC, on RE)}: A2I's median against every baseline's."""
    out = {}
    for leg in sorted({r.leg for r in rows}):
        for noise in sorted({r.noise_deg for r in rows}):
            med = {}
            for motion in MOTIONS:
                sel = [r for r in rows if r.leg == leg and r.noise_deg == noise
                       and r.motion == motion and r.pipeline == pipeline]
                if sel:
                    med[motion] = (np.median([r.cn for r in sel]), np.median([r.cc for r in sel]),
                                   np.median([r.re_euler_deg for r in sel]))
            if "a2i" not in med:
                continue
            a = med["a2i"]
            base = [v for k, v in med.items() if k != "a2i"]
            out[(leg, noise)] = (all(a[0] < b[0] for b in base), all(a[1] > b[1] for b in base),
                                 all(a[2] < b[2] for b in base))
    return out


def beats_paper_a2i(rows: list[Table1Row], pipeline: str) -> dict:
    """{(leg, noise): (CN lower, CC higher, RE lower)}: A2I's median against the paper's A2I
    figures (Table I, Gazebo) for the same leg and noise."""
    out = {}
    for leg in sorted({r.leg for r in rows}):
        for noise in sorted({r.noise_deg for r in rows}):
            sel = [r for r in rows if r.leg == leg and r.noise_deg == noise and r.motion == "a2i"
                   and r.pipeline == pipeline]
            p = PAPER_TABLE1.get(leg, {}).get(noise, {}).get("a2i")
            if not sel or p is None:
                continue
            out[(leg, noise)] = (np.median([r.cn for r in sel]) < p[0],
                                 np.median([r.cc for r in sel]) > p[1],
                                 np.median([r.re_euler_deg for r in sel]) < p[2])
    return out


def rows_from_json(text: str) -> list[Table1Row]:
    """Rows saved by ``a2i-calib bench`` (the JSON beside the table)."""
    return [Table1Row(**d) for d in json.loads(text)]


def _agg(vals):
    a = np.asarray(vals, dtype=float)
    return float(np.median(a)), float(np.max(a))


def _fmt(x: float) -> str:
    if not np.isfinite(x):
        return "inf"
    if abs(x) >= 1e4:
        return f"{x:.1e}"
    return f"{x:.3g}" if abs(x) < 100 else f"{x:.0f}"


def _pipeline_title(pipeline: str) -> str:
    return {"paper": "The paper's pipeline (relative FK, S_FF^-1 S_FI rotation, no gates)",
            "ours": "This toolkit (base rotation compensated, Procrustes rotation)"}[pipeline]


def _metric_table(rows: list[Table1Row], pipeline: str) -> list[str]:
    """Per leg, noise and motion: median (worst) of each metric, and the paper's figures."""
    head = "| leg | noise °/s/√Hz | motion | CN | CC | RE ° | geo ° | Δt ms |"
    if pipeline == "ours":
        head += " paper gates pass |"
    head += " paper CN / CC / RE |"
    out = [head, "|" + "---|" * (head.count("|") - 1)]
    for leg in LEGS:
        for noise in sorted({r.noise_deg for r in rows}):
            for motion in MOTIONS:
                sel = [r for r in rows if r.leg == leg and r.noise_deg == noise
                       and r.motion == motion and r.pipeline == pipeline]
                if not sel:
                    continue
                cn = _agg([r.cn for r in sel])
                cc = _agg([-r.cc for r in sel])  # worst = lowest correlation
                re = _agg([r.re_euler_deg for r in sel])
                geo = _agg([r.geodesic_deg for r in sel])
                dt = _agg([r.offset_error_s * 1e3 for r in sel])
                line = (f"| {leg} | {noise:g} | {motion} | {_fmt(cn[0])} ({_fmt(cn[1])}) "
                        f"| {-cc[0]:.4f} ({-cc[1]:.4f}) | {_fmt(re[0])} ({_fmt(re[1])}) "
                        f"| {_fmt(geo[0])} ({_fmt(geo[1])}) | {_fmt(dt[0])} ({_fmt(dt[1])}) |")
                if pipeline == "ours":
                    line += f" {sum(r.gates_pass for r in sel)}/{len(sel)} |"
                p = PAPER_TABLE1.get(leg, {}).get(noise, {}).get(motion)
                line += f" {p[0]:g} / {p[1]:g} / {p[2]:g} |" if p else " |"
                out.append(line)
    return out


def _summary_table(rows: list[Table1Row]) -> list[str]:
    out = ["| pipeline | motion | CN | CC | RE ° | geo ° | Δt ms |", "|---|---|---|---|---|---|---|"]
    for pipeline in PIPELINES:
        for motion in MOTIONS:
            sel = [r for r in rows if r.pipeline == pipeline and r.motion == motion]
            if sel:
                out.append(
                    f"| {pipeline} | {motion} | {_fmt(np.median([r.cn for r in sel]))} "
                    f"| {np.median([r.cc for r in sel]):.4f} "
                    f"| {_fmt(np.median([r.re_euler_deg for r in sel]))} "
                    f"| {_fmt(np.median([r.geodesic_deg for r in sel]))} "
                    f"| {_fmt(np.median([r.offset_error_s for r in sel]) * 1e3)} |")
    return out


def _wins_table(rows: list[Table1Row], verdicts=None,
                what: str = "A²I wins") -> list[str]:
    """Per pipeline, the (leg, noise) cells where ``verdicts(rows, pipeline)`` (default
    :func:`beats_baselines`) holds on CN, CC and RE."""
    verdicts = verdicts or beats_baselines
    out = [f"| pipeline | cells where {what} on CN | on CC | on RE |", "|---|---|---|---|"]
    for pipeline in PIPELINES:
        wins = verdicts(rows, pipeline)
        n = len(wins)
        out.append(f"| {pipeline} | {sum(bool(w[0]) for w in wins.values())}/{n} "
                   f"| {sum(bool(w[1]) for w in wins.values())}/{n} "
                   f"| {sum(bool(w[2]) for w in wins.values())}/{n} |")
    return out


def render_markdown(rows: list[Table1Row], seeds, elapsed_s: float | None = None) -> str:
    """The result page: per pipeline, per leg and noise, median (worst) of each metric."""
    out = [
        "# Table I in MuJoCo: calibration motions compared",
        "",
        "Produced by `a2i-calib bench` (`sim/table1.py`); seeds "
        + ", ".join(str(s) for s in seeds)
        + f"; foot IMU at {IMU_RATE:.0f} Hz, random mounting per leg and seed (any rotation, "
        "offset within ±0.2 s); encoders at 500 Hz from 1 kHz physics. The noise levels are "
        "the foot IMU's; the body gyro, which our pipeline uses to take the base's rotation out, "
        "reads without noise or bias in both tables, which favours the motions that turn the "
        "body (walk and spin) over A²I, whose body stays still.",
        "",
        ("**Base held.** In this table every motion runs with the base *held* "
        "on the motion's prescribed trajectory (walk: trot with body sway; spin: yawing at "
        "0.5 rad/s; wave and A²I: still base). The A²I motion is the anti-noise excitation "
        "(`calib.excitation`, κ(Σ_FF) = 1 planned over its steady periods; the 1 s ramps in and "
        "out, part of every scored record, put the whole plan's at 1.12-1.13), played by joint "
        "PD (kp 60, kd 2) with velocity feed-forward; CN below is of the *executed* motion. "
        "Every motion is scored "
        f"on a record of the same length, {held_record_s():g} s (the A²I plan's, ramps "
        "included): the motions are compared on as much data. The free-base table, "
        "with A²I executed by the tripod policy, is the last section (`a2i-calib bench "
        "--policy`) when it has been run."),
        "",
        ("Cells: median over seeds (worst in brackets). CN: condition number of Σ_FF. CC: trace "
        "correlation. RE: the paper's Euler-angle error (deg). geo: geodesic rotation error "
        "(deg). Δt: time-offset error (ms). Paper: the paper's Table I (Gazebo) figures."),
        "",
    ]
    for pipeline in PIPELINES:
        out += [f"## {_pipeline_title(pipeline)}", ""]
        out += _metric_table(rows, pipeline)
        out.append("")
    out += ["## Summary (median over legs, noise levels and seeds)", ""]
    out += _summary_table(rows)
    out += ["", "## Does A²I beat every baseline?", "",
            ("Per (leg, noise) cell, on medians over seeds: lower CN, higher CC, lower RE than each "
            "of walk, spin and wave."), ""]
    out += _wins_table(rows)
    if elapsed_s is not None:
        out += ["", f"Wall time: {elapsed_s:.0f} s."]
    return "\n".join(out) + "\n"


def _yes(b) -> str:
    return "-" if b is None else ("yes" if b else "no")


def _health_table(runs: list[FreeRun]) -> list[str]:
    out = [("| motion | leg | seed | max tilt ° | tilt RMS ° | min base z m "
            "| lifted foot touched | lowest lifted foot m | other bodies on the floor | fell |"),
           "|---|---|---|---|---|---|---|---|---|---|"]
    order = {m: i for i, m in enumerate(MOTIONS)}
    for r in sorted(runs, key=lambda r: (order.get(r.motion, 9), r.leg or "",
                                         -1 if r.seed is None else r.seed)):
        h = r.health
        low = "-" if not np.isfinite(h.lifted_foot_min_z) else f"{h.lifted_foot_min_z:.3f}"
        out.append(f"| {r.motion} | {r.leg or 'all'} | {'all' if r.seed is None else r.seed} "
                   f"| {h.max_tilt_deg:.1f} | {h.tilt_rms_deg:.1f} | {h.min_base_z:.3f} "
                   f"| {_yes(h.lifted_foot_touched)} | {low} "
                   f"| {', '.join(h.body_contacts) or 'none'} | {_yes(h.fell)} |")
    return out


def _verdicts(rows: list[Table1Row]) -> list[str]:
    """Per pipeline, leg and noise: the verdicts of beats_baselines and beats_paper_a2i."""
    out = [("| pipeline | leg | noise °/s/√Hz | A²I beats every baseline on CN / CC / RE "
            "| beats the paper's A²I on CN / CC / RE |"), "|---|---|---|---|---|"]
    for pipeline in PIPELINES:
        base = beats_baselines(rows, pipeline)
        paper = beats_paper_a2i(rows, pipeline)
        for (leg, noise), w in sorted(base.items()):
            p = paper.get((leg, noise))
            ps = " / ".join(_yes(bool(x)) for x in p) if p is not None else "-"
            out.append(f"| {pipeline} | {leg} | {noise:g} | "
                       + " / ".join(_yes(bool(x)) for x in w) + f" | {ps} |")
    return out


def _record_sentence(record_s: dict[str, float] | None) -> str:
    if not record_s:
        return ""
    lengths = sorted(set(record_s.values()))
    shown = (f"{lengths[0]:g} s" if len(lengths) == 1 else
             ", ".join(f"{g} {v:g} s" for g, v in record_s.items()))
    return ("Every motion of a leg is scored on a record as long as the leg's A²I excitation "
            f"(ramps included): {shown}.")


def render_free_section(table: FreeTable) -> str:
    """The free-base section of the page (markdown, level-2 heading first)."""
    rows = table.rows
    pol = [r for r in table.runs if r.motion == "a2i"]
    n_touch = sum(bool(r.health.lifted_foot_touched) for r in pol)
    n_fell = sum(r.health.fell for r in pol)
    n_body = sum(bool(r.health.body_contacts) for r in pol)
    tilt = max((r.health.max_tilt_deg for r in pol), default=float("nan"))
    out = [
        "## Free base: A²I executed by the tripod policy",
        "",
        (f"Produced by `a2i-calib bench --policy {table.policy}` (`sim/table1.py`, "
         "`sim/free_base_run.py`, `policy_train/policy_motion.py`); seeds "
         + ", ".join(str(s) for s in table.seeds)
         + "; the same legs, noise levels, mountings, pipelines and scoring as above. With "
           "several policies each leg is lifted by the last one whose JSON lists it, as "
           "`a2i-deploy` picks per leg."),
        "",
        ("**Nothing holds the base.** The Go2 stands on the floor (MuJoCo, free base, 1 kHz "
         "physics, the motor PD law every step) and the base goes where the contact forces "
         "take it. *A²I*: the tripod policy (ONNX Runtime, 50 Hz, the policy JSON's observation, "
         "action and gains) holds the body on three legs while the lift schedule of its JSON "
         "drives the lifted leg (shift, lift, hold, the anti-noise excitation, lower); the robot "
         "starts standing at the policy's default pose, the policy stands 1 s, then the lift "
         "command; the excitation phase is what is recorded and scored (it does not depend on "
         "the seed: one run per leg, scored with each seed's mountings). *walk*, *spin*: the "
         "gaits' joint trajectories played open-loop (PD kp 60, kd 2, velocity feed-forward) "
         "after 1 s of standing. *wave*: the naive single-foot waving, open loop: from the "
         "stand pose the body is moved over the three other feet (2 s, to the static stance "
         "with the centre of mass 5 cm inside their triangle, `sim/tripod_pose.py`), the leg is "
         "lifted (1 s) and waved with the wave motion's joint trajectory; nothing corrects the "
         "body as it waves (lifted without the shift, the robot tipped over at the lift). A "
         "run in which the robot fell is listed below and not scored: a record of a fallen "
         "robot is no calibration. " + _record_sentence(table.record_s)),
        "",
        (f"**Did the policy's A²I stay upright?** {len(pol)} policy runs: max tilt "
         f"{tilt:.1f}°; the lifted foot touched the floor during hold or excitation in "
         f"{n_touch}; another body than a foot touched the floor in {n_body}; fell in "
         f"{n_fell}. Watched: the A²I runs over hold and excitation (tilt, the lifted foot) "
         "and over the whole run (falls, other bodies), the other motions over the recorded "
         "motion."),
        "",
        "### How the robot fared",
        "",
    ]
    out += _health_table(table.runs)
    for pipeline in PIPELINES:
        out += ["", f"### {_pipeline_title(pipeline)}", ""]
        out += _metric_table(rows, pipeline)
    out += ["", "### Summary (median over legs, noise levels and seeds)", ""]
    out += _summary_table(rows)
    out += ["", "### Does A²I beat every baseline, and the paper's A²I?", "",
            ("Per (leg, noise) cell, on medians over seeds: lower CN, higher CC, lower RE than "
             "each of walk, spin and wave; and than the paper's A²I figures (its CC is "
             "rounded to 0.99)."), ""]
    out += _wins_table(rows)
    out.append("")
    out += _wins_table(rows, beats_paper_a2i, "A²I beats the paper's A²I")
    out.append("")
    out += _verdicts(rows)
    if table.elapsed_s is not None:
        out += ["", f"Wall time: {table.elapsed_s:.0f} s."]
    return "\n".join(out) + "\n"


def render_page(held_rows: list[Table1Row] | None, held_seeds=(), held_elapsed_s=None,
                free: FreeTable | None = None) -> str:
    """The whole page: the held-base table (:func:`render_markdown`) and, when given, the
    free-base section after it."""
    if held_rows:
        page = render_markdown(held_rows, held_seeds, held_elapsed_s)
    else:
        page = ("# Table I in MuJoCo: calibration motions compared\n\n"
                "(No held-base rows: run `a2i-calib bench` for them.)\n")
    if free is not None:
        page += "\n" + render_free_section(free)
    return page
