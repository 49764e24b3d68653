"""The A2I calibration of one leg executed by the tripod policy on the free-base Go2, recorded as
:func:`sim.calibration_run.run_motion` records a motion (for the free-base Table I,
:func:`sim.table1.run_table1_free`).

The policy runs as on board (``deploy``'s TRIPOD / CALIBRATE states), on the simulator of
:mod:`sim.go2` (free base on the floor, the motor PD law every physics step, 1 kHz):

* the robot starts standing at the policy's ``default_pose`` (feet on the floor); the policy
  runs from the first tick with no lift command for ``settle_s`` s, its target starting at the
  joints' positions;
* every ``control_dt`` (50 Hz) the observation is built by :func:`deploy.observation.
  build_observation` from the JSON's terms (body gyro, projected gravity, joints in SDK order,
  previous raw actions, zero commands, the JSON's ``lift_command`` value while the schedule
  runs; ``base_lin_vel`` zero-filled as its ``source`` says), ONNX Runtime gives the actions,
  ``target += scale * clip(a)`` clamped to the soft limits; the nine other joints get that
  target with the JSON's kp / kd;
* after ``settle_s`` the lift command: :class:`deploy.lift_schedule.LiftSchedule` from the
  JSON (shift, lift, hold, excite, lower); while it gives targets the lifted leg's three motors
  get its ``q_des`` / ``dq_des`` with its own kp / kd, evaluated at each of deploy's
  ``commands_per_tick`` LowCmd_ frames and held in between, as the motors hold them (every
  4 ms; the training environment moves them every 5 ms substep); ``q_start`` is latched at
  the first step of ``lift``; when the schedule is done the policy's target of the leg
  restarts from the leg's position and the lift command is cleared (as in training and
  deploy).

Recorded: the excitation phase only (what deploy's SOLVE calibrates from). Watched for
:class:`sim.free_base_run.RunHealth`: hold and excitation (tilt, lifted-foot touchdowns), and
the whole run for falls and for bodies other than the feet on the floor (as the evaluation
judges a training episode).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.joints import (
    EFFORT_LIMIT,
    LEGS,
    check_leg,
    model_indices,
    model_to_sdk,
    sdk_indices,
    sdk_to_model,
)
from calib.support import go2_support
from deploy.lift_gate import LiftGate
from deploy.lift_schedule import (
    COMMANDS_PER_TICK,
    PHASES,
    abort_targets,
    blend_accelerations,
    blend_targets,
)
from deploy.observation import build_observation, observe_lifted_leg, projected_gravity
from deploy.policy import PolicyMeta, PolicyRunner
from deploy.tip_guard import TipGuard
from deploy.tracking_adapter import TrackingAdapter
from policy_train.config import OBS_NOISE
from sim.calibration_run import MotionRun
from sim.free_base_run import (
    FALL_HEIGHT,
    FALL_TILT,
    HealthTracker,
    RunHealth,
    RunRecorder,
    free_base_sim,
    push_record,
)
from sim.sensors import BodyImuModel, EncoderModel

__all__ = ["Disturbance", "load_policy", "run_policy_a2i", "run_policy_a2i_per_leg"]

_EXCITE = PHASES.index("excite")
_DONE = PHASES.index("done")
_LOWER = PHASES.index("lower")
_WATCH_AFTER_ABORT_S = 1.0  # s simulated once an aborted leg is down (watched for a fall)


@dataclass(frozen=True)
class Disturbance:
    """What a free-base run adds to the simulator's own effects, drawn the way the training's
    randomisation draws it (:class:`policy_train.config.DRConfig`; the noise fields are named as
    its own, and :data:`policy_train.config.OBS_NOISE` maps them to the observation terms).

    Observation noise, uniform in +- the amplitude and new every policy step: ``noise_ang_vel``
    (body gyro, rad/s), ``noise_gravity`` (projected gravity, unitless), ``noise_joint_pos``
    (rad), ``noise_joint_vel`` (rad/s). Pushes: every ``push_interval`` s (uniform in the
    range) the base's horizontal velocity changes by a uniform +-``push_vel`` m/s per world axis
    (0: no pushes). seed: the draws.

    The body IMU as mounted, before the noise: ``imu_tilt`` (rad, rotation vector, base frame)
    turns the IMU's frame from the base's, so it reads the body's rate and gravity in that
    frame (the policy's ``base_ang_vel`` and ``projected_gravity``, and the gravity the lifted
    leg's feed-forward is computed with, as on board); ``gyro_bias`` (rad/s, IMU frame) is added
    to its rate.
    """

    noise_ang_vel: float = 0.0
    noise_gravity: float = 0.0
    noise_joint_pos: float = 0.0
    noise_joint_vel: float = 0.0
    push_vel: float = 0.0
    push_interval: tuple[float, float] = (4.0, 8.0)
    seed: int = 0
    imu_tilt: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        for k in ("imu_tilt", "gyro_bias"):
            v = np.asarray(getattr(self, k), dtype=float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"{k} must be 3 finite numbers, got {getattr(self, k)!r}")
        if np.linalg.norm(self.imu_tilt) >= 0.5:
            raise ValueError("imu_tilt must turn the IMU by less than 0.5 rad, got "
                             f"{self.imu_tilt!r}")
        for k in ("noise_ang_vel", "noise_gravity", "noise_joint_pos", "noise_joint_vel",
                  "push_vel"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{k} must be a finite amplitude >= 0, got {v!r}")
        lo, hi = self.push_interval
        if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= hi):
            raise ValueError(f"push_interval must be 0 < lo <= hi s, got {self.push_interval!r}")

    @functools.cached_property
    def _imu_rotation(self) -> np.ndarray | None:
        """R of ``imu_tilt`` (None when level), built once: the feed-forward asks every step."""
        if not any(self.imu_tilt):
            return None
        from scipy.spatial.transform import Rotation

        return Rotation.from_rotvec(self.imu_tilt).as_matrix()

    def imu_frame(self, v_base: np.ndarray) -> np.ndarray:
        """A base-frame vector (3,) as the body IMU, turned by ``imu_tilt``, reads it: R.T @ v,
        as :class:`sim.effects.ImuMisalignment` turns its readings."""
        r = self._imu_rotation
        return np.asarray(v_base, dtype=float) if r is None else np.asarray(v_base) @ r

    def noisy(self, signals: dict, rng: np.random.Generator) -> dict:
        """``signals`` (deploy.observation names) as the robot senses them: the body IMU's
        mounting and bias, then this noise added to the sensed terms."""
        out = dict(signals)
        if any(self.imu_tilt) or any(self.gyro_bias):
            out["base_ang_vel"] = self.imu_frame(out["base_ang_vel"]) + np.asarray(self.gyro_bias)
            out["projected_gravity"] = self.imu_frame(out["projected_gravity"])
        for key, fld in OBS_NOISE:
            a = getattr(self, fld)
            if a > 0:
                x = np.asarray(signals[key], dtype=float)
                out[key] = x + rng.uniform(-a, a, x.shape)
        return out


def load_policy(onnx_path) -> PolicyRunner:
    """The on-board policy runner (:class:`deploy.policy.PolicyRunner`: ONNX Runtime on one
    thread, the ``delta_target`` action state) of ``<name>.onnx`` and the ``<name>.json``
    beside it. ValueError (one line) on a missing or malformed file; ImportError without
    onnxruntime."""
    p = Path(onnx_path)
    if not p.is_file():
        raise ValueError(f"policy file not found: {p}")
    return PolicyRunner(PolicyMeta.load(p.with_suffix(".json")))


def policy_signals(sim, runner: PolicyRunner, lift_value: float) -> dict:
    """The signals of :func:`deploy.observation.build_observation` as the robot gives them on
    the simulator ``sim`` (:class:`sim.go2.Go2Sim`), true (no noise or mounting): body gyro,
    projected gravity, joints in SDK order, ``runner``'s previous raw actions, zero commands,
    ``base_lin_vel`` zero-filled (the only source deploy has), and ``lift_value``."""
    zeros3 = np.zeros(3)
    return {"base_lin_vel": zeros3, "base_ang_vel": sim.base_ang_vel,
            "projected_gravity": projected_gravity(sim.base_quat_wxyz),
            "joint_pos": sim.q_sdk, "joint_vel": sim.dq_sdk,
            "previous_actions": runner.prev_actions, "commands": zeros3,
            "lift_command": lift_value}


def run_policy_a2i(
    policy,
    leg: str,
    *,
    settle_s: float = 1.0,
    periods: int | None = None,
    after_s: float = 0.5,
    timestep: float = 0.001,
    record_every: int = 2,
    encoder: EncoderModel | None = None,
    body_imu: BodyImuModel | None = None,
    effects=(),
    disturbance: Disturbance | None = None,
    progress=None,
    commands_per_tick: int = COMMANDS_PER_TICK,
    model_xml: str | None = None,
    adapt: bool | None = None,
    max_tip=None,
    lift_gate=None,
    extra_shift_s: float = 0.0,
) -> tuple[MotionRun | None, RunHealth]:
    """The A2I calibration of ``leg`` by the tripod policy on the free-base simulated Go2.

    policy: a :class:`deploy.policy.PolicyRunner` or the ``.onnx`` path (its ``.json`` beside
    it).
    settle_s: s of policy standing before the lift command. periods: excitation periods
    (None: the JSON's ``lift_schedule.periods``; fewer gives a shorter run, for tests).
    after_s: s simulated after the schedule ends (watched for falls only). timestep: physics
    step, s; record_every: physics steps per recorded sample (2 at 1 kHz = 500 Hz encoders).
    effects: :class:`sim.effects.Effect` objects of this run's simulator (fresh ones per run;
    e.g. latency, motor strength, masses, friction). disturbance: observation noise and pushes
    (:class:`Disturbance`; None: neither). commands_per_tick: LowCmd_ frames per policy tick,
    each carrying the lifted leg's schedule at its time (deploy's
    :data:`deploy.lift_schedule.COMMANDS_PER_TICK`; must divide the tick's physics steps).
    model_xml: another MJCF model of the Go2 to run on (:mod:`sim.external_model`; None: the
    URDF's). adapt: the tracking adapter on or off (None: the JSON's). max_tip: deploy's tip
    guard's limits (:class:`deploy.tip_guard.TipLimits`, a number or a (lift, hold) pair, deg;
    None: off, the policy alone): a lift or hold that tips the body past its limit is called
    off as the session does, the leg brought back down over the schedule's ``abort_lower`` from
    the next tick, with the policy balancing.
    lift_gate: deploy's lift gate (:class:`deploy.lift_gate.GateLimits`, a margin in m or a
    (margin m, wait s) pair; None: off, the lift on time): the shift is held longer, tick by
    tick, until the centre of mass estimated from the joints and the body IMU stands that far
    inside the stance triangle, as the session does; a margin that does not come calls the lift
    off before the foot leaves the floor (the lift command dropped).
    extra_shift_s: s added to the leg's shift (the second try of a lift the guard called off,
    as deploy makes it).

    Returns the :class:`MotionRun` of the excitation phase (sim-time stamps; motion name
    ``a2i_<leg>``) and the :class:`RunHealth` of hold + excitation (``fell`` covers the whole
    run). A lift the tip guard called off returns None for the run and a health with its
    ``aborted`` cause, watched up to the abort (``fell``: until 1 s after the foot is down).
    progress(fraction): optional, about 20 calls.
    """
    leg = check_leg(leg)
    if record_every < 1:
        raise ValueError(f"record_every must be >= 1, got {record_every}")
    if not (settle_s >= 0 and after_s >= 0):
        raise ValueError("settle_s and after_s must be >= 0 s")
    runner = policy if isinstance(policy, PolicyRunner) else load_policy(policy)
    pb = runner.meta
    sched = pb.schedule if periods is None else dataclasses.replace(pb.schedule,
                                                                    periods=int(periods))
    if extra_shift_s:
        sched = sched.with_shift(leg, sched.shift_of(leg) + float(extra_shift_s))
    n_ctrl = round(pb.control_dt / timestep)
    if n_ctrl < 1 or abs(n_ctrl * timestep - pb.control_dt) > 1e-9:
        raise ValueError(f"control_dt {pb.control_dt} s is not a multiple of the "
                         f"physics step {timestep} s")
    if isinstance(commands_per_tick, bool) or not isinstance(commands_per_tick, int) \
            or commands_per_tick < 1 or n_ctrl % commands_per_tick:
        raise ValueError(f"commands_per_tick must divide the {n_ctrl} physics steps of a "
                         f"tick, got {commands_per_tick!r}")
    n_frame = n_ctrl // commands_per_tick
    plan = sched.plan(leg)
    dur = sched.durations(leg)
    ends = np.cumsum(dur)
    lift_value = pb.lift_value(leg)
    none_value = pb.lift_value(None)
    idx_m = model_indices(leg)
    idx_s = sdk_indices(leg)

    sim = free_base_sim(timestep, sdk_to_model(pb.default_pose), effects,
                        0 if disturbance is None else disturbance.seed, model_xml)
    rng = None if disturbance is None else np.random.default_rng(disturbance.seed)
    pushing = disturbance is not None and disturbance.push_vel > 0
    next_push = rng.uniform(*disturbance.push_interval) if pushing else np.inf

    def sensed_gravity(quat_wxyz):  # as the body IMU reads it (deploy's feed-forward uses it)
        g = projected_gravity(quat_wxyz)
        return g if disturbance is None else disturbance.imu_frame(g)

    # the lift command comes on a policy tick, as on board
    n_settle = round(settle_s / pb.control_dt) * n_ctrl
    n_total = n_settle + int(np.ceil((ends[-1] + after_s) / timestep))
    n_exc = int(np.ceil(dur[3] / timestep)) + 1
    rec = RunRecorder(n_exc // record_every + 2)
    health = HealthTracker(leg)
    kp_m, kd_m = sdk_to_model(pb.kp), sdk_to_model(pb.kd)
    runner.reset(model_to_sdk(sim.q))  # the target starts at the joints (deploy, training)
    zeros3 = np.zeros(3)
    lift_on = False
    q_start = None
    # the schedule per physics step from the latch on
    sched_q = sched_dq = sched_ddq = sched_phase = sched_tau = None
    k_latch = 0
    fell = False
    phase = -1
    q_cmd = sdk_to_model(runner.target)
    dq_cmd = np.zeros(12)
    kp_c, kd_c = kp_m.copy(), kd_m.copy()
    tau_c = 0.0
    adapt = sched.adapt if adapt is None else bool(adapt)
    adapter = TrackingAdapter(sched.kp, sched.kd) if adapt else None
    t_exc0 = float(dur[:3].sum())
    applied = np.zeros(3)  # the adapter's torque in the frame the motors hold
    guard = TipGuard(max_tip)

    def ahead(j: int) -> int:
        """The schedule's row commanded at its row ``j``: as far ahead as the adapter's lead
        (the command delay it found), so that the motors play the plan on time."""
        if adapter is None or sched_q is None:
            return j
        lead = adapter.lead((k_latch + j - k0) * timestep - t_exc0)[0]
        # not past the lowering's last row: the table's rows after it (done) have no targets
        last = int(np.searchsorted(sched_phase, _DONE)) - 1
        return max(min(j + round(lead / timestep), last), j)
    gate = LiftGate(lift_gate)
    support = go2_support() if gate.limits is not None else None
    stance = [g for g in LEGS if g != leg]
    k0 = n_settle  # the step of the lift command; the lift gate moves it later
    dropped = False  # the lift gate called the lift off: no lift command from then on
    aborted = None
    abort_pending = False
    k_stop = None
    tilt_sq, n_tilt = 0.0, 0  # the body's tilt over the excitation (rad^2), as the evaluation
    pushes = []  # PushRecord of every shove
    fall_time = None
    k = -1
    while True:
        k += 1
        if k >= n_total or (k_stop is not None and k >= k_stop):
            break
        t_lift = (k - k0) * timestep  # s since the lift command (< 0: settling)
        if (support is not None and not dropped and q_start is None and k % n_ctrl == 0
                and t_lift + (n_ctrl - 1) * timestep >= ends[0] - 1e-9):
            # the tick the foot would leave the floor: the session's lift gate
            verdict = gate.check(support.margin(sim.q, sensed_gravity(sim.base_quat_wxyz),
                                                stance), pb.control_dt)
            if verdict != "go":  # this tick stays in the shift
                k0 += n_ctrl
                n_total += n_ctrl
                t_lift -= n_ctrl * timestep
            if verdict not in ("go", "wait"):
                aborted, dropped = verdict, True
                health.update(sim)  # the state it was called off in
                k_stop = k + round(_WATCH_AFTER_ABORT_S / timestep)
        if dropped:
            phase = _DONE
        elif t_lift >= 0:
            phase = int((t_lift >= ends - 1e-9).sum())
            if phase >= 1 and q_start is None:
                # latch at the first step of lift, tabulate the schedule from here on
                q_start = sim.q[idx_m]
                k_latch = k
                tt = (np.arange(k, n_total) - k0) * timestep
                te = tt - dur[:3].sum()
                sched_q, sched_dq, sched_phase = blend_targets(
                    tt, dur, q_start[None], plan.q0[None], plan.positions(te),
                    plan.velocities(te))
                sched_ddq = np.nan_to_num(blend_accelerations(
                    tt, dur, q_start[None], plan.q0[None], plan.accelerations(te)))
                if sched.feedforward:
                    sched_tau = sched.feedforward_table(leg, sched_q, sched_dq, sched_ddq)
            if sched_phase is not None:
                phase = int(sched_phase[k - k_latch])
        if k % n_ctrl == 0 and abort_pending:
            # the session's abort: from the last target back to where the leg stood
            abort_pending = False
            i = k - k_latch
            n_low = round(sched.abort_lower / timestep)
            m = min(n_low, len(sched_q) - i)
            sched_q[i:i + m], sched_dq[i:i + m] = abort_targets(
                np.arange(m) * timestep, sched.abort_lower, q_cmd[idx_m], q_start)
            sched_phase[i:i + m] = _LOWER
            sched_phase[i + m:] = _DONE
            sched_tau = adapter = None
            tau_c = 0.0
            phase = _LOWER
            k_stop = k + n_low + round(_WATCH_AFTER_ABORT_S / timestep)
        if k % n_ctrl == 0:
            if adapter is not None and phase == _EXCITE:
                # a tick's measurement against the plan commanded at this instant, as on board
                i = ahead(k - k_latch)
                g = sensed_gravity(sim.base_quat_wxyz)
                model = sched_tau.at(i, g) if sched_tau is not None else zeros3
                adapter.observe(t_lift - t_exc0, sched_q[i], sched_dq[i], sched_ddq[i],
                                sim.q[idx_m], sim.dq[idx_m], model, applied,
                                tau_motor=sim.tau[idx_m])
            handback = phase == _DONE and lift_on
            lift_on = 0 <= phase < _DONE
            signals = policy_signals(sim, runner, lift_value if lift_on else none_value)
            if disturbance is not None:
                signals = disturbance.noisy(signals, rng)
            q_measured = signals["joint_pos"]  # the encoders', before what the policy is shown
            if sched.excitation_seen != 1.0 and phase == _EXCITE:
                signals = observe_lifted_leg(signals, idx_s, plan.q0, sched.excitation_seen)
            obs = build_observation(pb.observation, signals)
            runner.step(runner.act(obs), q_measured)
            if handback:
                # the leg's policy target restarts from where the leg is, after this tick's
                # action, as deploy and training do: the first command is the joints themselves
                runner.target[idx_s] = model_to_sdk(sim.q)[idx_s]
            q_cmd = sdk_to_model(runner.target)
            dq_cmd = np.zeros(12)
            kp_c, kd_c = kp_m.copy(), kd_m.copy()
            if aborted is None and 0 <= phase < _DONE:
                aborted = guard.check(PHASES[phase], sim.base_quat_wxyz)
                if aborted is not None:
                    abort_pending = True
                    health.update(sim)  # the state it was called off in
        if sched_phase is not None and 1 <= phase <= 4:
            # the schedule at the time of this step's frame, held until the next frame (a latch
            # mid-frame starts the lift's first frame at the latch)
            j_frame = max(k - k % n_frame - k_latch, 0)
            j = ahead(j_frame)
            q_cmd = q_cmd.copy()
            dq_cmd = dq_cmd.copy()
            q_cmd[idx_m] = sched_q[j]
            dq_cmd[idx_m] = sched_dq[j]
            kp_c[idx_m] = sched.kp
            kd_c[idx_m] = sched.kd
            model = zeros3
            if sched_tau is not None:
                model = sched_tau.at(j, sensed_gravity(sim.base_quat_wxyz))
            if adapter is not None and phase >= _EXCITE:
                applied = adapter.torque((k_latch + j_frame - k0) * timestep - t_exc0,
                                         sched_dq[j], sched_ddq[j], model)[0]
            if sched_tau is not None or adapter is not None:
                tau_c = np.zeros(12)
                tau_c[idx_m] = np.clip(model + applied, -EFFORT_LIMIT, EFFORT_LIMIT)
        elif phase == _DONE:
            kp_c[idx_m], kd_c[idx_m] = kp_m[idx_m], kd_m[idx_m]
            tau_c = 0.0
        sim.set_command(q_cmd, dq_cmd, kp_c, kd_c, tau_c)
        if sim.time >= next_push:
            v = disturbance.push_vel
            dv = [rng.uniform(-v, v), rng.uniform(-v, v), 0.0]
            lifted = 1 <= phase <= _LOWER
            pushes.append(push_record(sim, PHASES[phase] if phase >= 0 else "settle", dv,
                                      [g for g in LEGS if g != leg] if lifted else LEGS))
            sim.push(dv)
            next_push += rng.uniform(*disturbance.push_interval)
        sim.step()
        # the phase of the state reached after this step
        t_next = t_lift + timestep
        ph_next = int((t_next >= ends - 1e-9).sum()) if t_next >= 0 else -1
        if ph_next in (2, 3) and aborted is None:
            health.update(sim)
        elif aborted is None:
            # a knee or thigh on the floor fails the run in any phase, as in the evaluation
            health.watch_contacts(sim)
        if ph_next == _EXCITE and aborted is None and (k + 1 - k0) % record_every == 0:
            # tracking against the plan at the instant of this state (the frame held 4 ms
            # behind it: five times the evaluation's figure on the URDF's model)
            plan_now = q_cmd.copy()
            plan_now[idx_m] = sched_q[min(k + 1 - k_latch, len(sched_q) - 1)]
            rec.record(sim, plan_now)
            tilt_sq += sim.base_tilt ** 2
            n_tilt += 1
        if (k + 1) % 10 == 0 and not fell:
            fell = sim.base_tilt > FALL_TILT or sim.base_pos[2] < FALL_HEIGHT
            fall_time = sim.time if fell else None
        if progress is not None and k % max(1, n_total // 20) == 0:
            progress(k / n_total)
    if progress is not None:
        progress(1.0)
    h = health.result()
    h = dataclasses.replace(h, fell=h.fell or bool(fell), aborted=aborted,
                            lift_wait_s=gate.waited_s,
                            fall_time_s=fall_time, pushes=tuple(pushes),
                            excite_tilt_rms_deg=float(np.degrees(np.sqrt(tilt_sq / n_tilt)))
                            if n_tilt else None)
    if dropped:  # no leg was lifted: its foot stood on the floor by design
        h = dataclasses.replace(h, lifted_foot_touched=None)
    if aborted is not None:
        return None, h
    return rec.finish(f"a2i_{leg}", encoder, body_imu), h


def run_policy_a2i_per_leg(policies, leg: str, **kwargs) -> tuple[MotionRun, RunHealth]:
    """:func:`run_policy_a2i` of ``leg`` with ``policies[leg]`` (leg -> ``.onnx`` path; a
    picklable callable for the free-base Table I's worker processes)."""
    return run_policy_a2i(policies[check_leg(leg)], leg, **kwargs)
