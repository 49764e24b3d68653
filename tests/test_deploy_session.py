"""The calibration state machine on fake inputs: a robot that follows its commands exactly."""

import dataclasses
from dataclasses import dataclass

import numpy as np
import pytest

from calib.joints import LIE_POSE_LEG, full_pose, sdk_indices
from deploy.lift_schedule import COMMANDS_PER_TICK, LiftSchedule
from deploy.policy import PolicyMeta, PolicyRunner
from deploy.report import leg_summary
from deploy.session import Session, SessionConfig, State, TickInput
from deploy.supervisor import SafetySupervisor, SupervisorConfig
from deploy.tip_guard import DEFAULT_TIP_LIMITS, TipLimits

pytest.importorskip("onnx")

# the lift gate off: the hold policy never moves the body over the tripod (its tests below)
CFG = SessionConfig(passive_s=0.1, stand_s=0.4, stand_settle_s=0.2, sit_s=0.2, sit_hold_s=0.1,
                    lift_gate=None)


@pytest.fixture(scope="module")
def meta_paths(tmp_path_factory):
    from deploy.hold_policy import write_hold_policy

    d = tmp_path_factory.mktemp("pol")
    sched = LiftSchedule(shift=0.2, lift=0.2, hold=0.2, lower=0.2, periods=1)
    return (write_hold_policy(d, "hold", schedule=sched),
            write_hold_policy(d, "nan", action_value=float("nan"), schedule=sched))


@dataclass
class FakeJob:
    accepted: bool = True
    error: str | None = None
    polls: int = 0

    def done(self):
        self.polls += 1
        return self.polls > 3  # the worker takes a few ticks

    def outcome(self):
        return self


class Rig:
    """A session plus a perfect robot: q follows the commanded targets one tick later."""

    def __init__(self, meta_path, legs=("FL",), joystick=False, config=CFG, available_legs=None):
        meta = PolicyMeta.load(meta_path)
        for leg in legs or ("FL",):
            meta.schedule.plan(leg)
        self.meta = meta
        sup = SafetySupervisor(SupervisorConfig(), meta.soft_lower, meta.soft_upper, 0.02)
        self.transitions = []
        self.reports = []
        self.solves = []
        self.s = Session(PolicyRunner(meta), sup, 0.02, self._solve, legs=legs,
                         joystick=joystick, config=config, available_legs=available_legs,
                         on_transition=lambda a, b, c: self.transitions.append((a, b, c)),
                         on_report=self.reports.append)
        self.q = full_pose(LIE_POSE_LEG, order="sdk")
        self.quat = np.array([1.0, 0, 0, 0])
        self.k = 0

    def _solve(self, leg, window):
        self.solves.append((leg, window))
        return FakeJob()

    def tick(self, **kw):
        inp = TickInput(q=self.q.copy(), dq=np.zeros(12), quat=self.quat.copy(),
                        gyro=np.zeros(3), window_mark=self.k, **kw)
        cmd = self.s.step(inp)
        self.k += 1
        if cmd.kp.max() > 0:
            self.q = cmd.q.copy()
        return cmd

    def run_until(self, state, max_ticks=5000):
        for _ in range(max_ticks):
            if self.s.state is state:
                return
            self.tick()
        raise AssertionError(f"never reached {state}; now {self.s.state}")

    @property
    def states(self):
        return [b for _, b, _ in self.transitions]


def test_full_calibration_sequence(meta_paths):
    rig = Rig(meta_paths[0], legs=("FL",))
    rig.run_until(State.DONE)
    assert rig.states == [State.STAND, State.TRIPOD, State.CALIBRATE, State.LOWER, State.STAND,
                          State.SOLVE, State.REPORT, State.SIT, State.DONE]
    assert len(rig.solves) == 1
    leg, (w0, w1) = rig.solves[0]
    plan = rig.meta.schedule.plan("FL")
    # The window spans the excitation: its length in ticks is the plan's duration.
    assert leg == "FL" and abs((w1 - w0) * 0.02 - plan.duration) <= 0.021
    assert len(rig.reports) == 1 and rig.reports[0].ok
    assert rig.s.finished


def test_lifted_leg_follows_schedule_with_its_gains(meta_paths):
    rig = Rig(meta_paths[0], legs=("RR",))
    rig.run_until(State.CALIBRATE)
    cmd = rig.tick()
    idx = sdk_indices("RR")
    sched = rig.meta.schedule
    assert cmd.kp[idx].tolist() == [sched.kp] * 3 and cmd.kd[idx].tolist() == [sched.kd] * 3
    others = np.setdiff1d(np.arange(12), idx)
    np.testing.assert_allclose(cmd.kp[others], rig.meta.kp[others])
    np.testing.assert_allclose(cmd.q[idx], sched.plan("RR").q0, atol=0.05)
    assert cmd.source == "policy:excite"


def test_lifted_leg_moves_between_ticks_in_the_substep_frames(meta_paths):
    """Each tick carries the rest of its LowCmd_ frames: the lifted leg's schedule at
    t + i dt / n (position, velocity, gains), every other motor as the tick's frame."""
    rig = Rig(meta_paths[0], legs=("FL",))
    rig.run_until(State.CALIBRATE)
    for _ in range(5):
        rig.tick()
    t = rig.s._lift_time()
    cmd = rig.tick()
    n = CFG.commands_per_tick
    assert n == COMMANDS_PER_TICK == 5 and len(cmd.substeps) == n - 1
    idx = sdk_indices("FL")
    others = np.setdiff1d(np.arange(12), idx)
    sched = rig.meta.schedule
    q_start = rig.s._q_start
    frames = [cmd, *cmd.substeps]
    for i, f in enumerate(frames):
        lt = sched.targets("FL", t + i * 0.02 / n, q_start)
        assert lt.phase == "excite"
        np.testing.assert_allclose(f.q[idx], lt.q_des, atol=1e-12)
        np.testing.assert_allclose(f.dq[idx], lt.dq_des, atol=1e-12)
        assert f.kp[idx].tolist() == [sched.kp] * 3 and f.kd[idx].tolist() == [sched.kd] * 3
        np.testing.assert_array_equal(f.q[others], cmd.q[others])
        np.testing.assert_array_equal(f.kp[others], cmd.kp[others])
    # the target moves within the tick (the plan is not at rest mid-excitation)
    assert np.max(np.abs(frames[-1].q[idx] - frames[0].q[idx])) > 1e-4
    # the next tick's rate limit starts from the last frame sent
    np.testing.assert_array_equal(rig.s._prev_target, frames[-1].q)


def test_frames_without_a_lifted_leg_are_repeats(meta_paths):
    rig = Rig(meta_paths[0], legs=("FL",))
    rig.run_until(State.STAND)
    assert rig.tick().substeps == ()  # the runtime sends the tick's frame n times


def test_commands_per_tick_must_be_a_positive_integer():
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="commands_per_tick"):
            SessionConfig(commands_per_tick=bad)


def test_hand_back_restarts_the_policy_target_from_the_leg(meta_paths):
    rig = Rig(meta_paths[0], legs=("FL",))
    rig.run_until(State.LOWER)
    idx = sdk_indices("FL")
    while rig.s.phase != "done":
        q_before = rig.q.copy()
        cmd = rig.tick()
    # first tick of "done": the leg's target is where the leg was, with the policy's gains
    np.testing.assert_allclose(cmd.q[idx], q_before[idx])
    np.testing.assert_allclose(cmd.kp[idx], rig.meta.kp[idx])
    assert cmd.obs[-1] == 0.0  # lift_command back to none


def test_the_stand_takes_over_the_tick_the_foot_is_down(meta_paths):
    # the policy alone with the lift command cleared spun the body after FR lifts (v17-v20)
    rig = Rig(meta_paths[0], legs=("FL",))
    rig.run_until(State.LOWER)
    idx = sdk_indices("FL")
    free = 0  # LOWER ticks whose lifted leg the policy drove, off the schedule
    while rig.s.state is State.LOWER:
        cmd = rig.tick()
        free += rig.s.phase == "done" and np.allclose(cmd.kp[idx], rig.meta.kp[idx])
    assert rig.s.state is State.STAND and rig.transitions[-1][2] == "foot down"
    assert free <= 1


@pytest.mark.parametrize("state", [State.PASSIVE, State.STAND, State.TRIPOD, State.CALIBRATE,
                                   State.LOWER, State.SOLVE])
def test_l2_b_damps_within_the_tick_from_any_state(meta_paths, state):
    rig = Rig(meta_paths[0], legs=("FL",))
    rig.run_until(state)
    cmd = rig.tick(combos=("damp",))
    assert rig.s.state is State.DAMP
    assert np.all(cmd.kp == 0) and np.all(cmd.kd > 0)
    assert rig.transitions[-1][2] == "operator: L2+B"
    assert rig.s.finished  # command-line mode: final
    for _ in range(5):
        assert np.all(rig.tick(combos=("stand",)).kp == 0)


def test_supervisor_fault_damps_and_is_final(meta_paths):
    rig = Rig(meta_paths[0], legs=("FL",))
    rig.run_until(State.CALIBRATE)
    cmd = rig.tick(fault="tilt 35.0 deg > 30 deg")
    assert rig.s.state is State.DAMP and np.all(cmd.kp == 0)
    assert rig.s.fault == "tilt 35.0 deg > 30 deg"
    rig.tick()
    assert rig.s.state is State.DAMP and rig.solves == []
    assert rig.s.outcomes[0].error.startswith("aborted: tilt")


def test_nan_policy_damps_on_its_first_tick(meta_paths):
    rig = Rig(meta_paths[1], legs=("FL",))
    rig.run_until(State.TRIPOD)
    rig.tick()  # TRIPOD's first tick runs the policy
    assert rig.s.state is State.DAMP
    assert "non-finite policy action" in rig.s.fault
    assert np.all(rig.s.last_command.kp == 0)


def test_non_finite_observation_damps(meta_paths):
    rig = Rig(meta_paths[0], legs=("FL",))
    rig.run_until(State.TRIPOD)
    inp = TickInput(q=rig.q.copy(), dq=np.zeros(12), quat=np.array([1.0, 0, 0, 0]),
                    gyro=np.array([np.nan, 0, 0]))
    cmd = rig.s.step(inp)
    assert rig.s.state is State.DAMP and "non-finite observation" in rig.s.fault
    assert np.all(cmd.kp == 0)


def test_imu_failure_aborts_lowers_and_reports_without_solving(meta_paths):
    rig = Rig(meta_paths[0], legs=("FL",))
    rig.run_until(State.CALIBRATE)
    for _ in range(10):
        rig.tick()
    rig.tick(imu_errors={"FL": "serial port /dev/pts/9 failed"})
    assert rig.s.state is State.LOWER
    rig.run_until(State.DONE)
    assert rig.solves == []
    assert State.REPORT in rig.states and State.SOLVE not in rig.states
    assert not rig.reports[0].ok and "foot IMU FL failed" in rig.reports[0].error
    # the leg came back down smoothly to where it stood before the lift
    assert rig.s.fault is None


def _roll(deg):
    a = np.radians(deg) / 2
    return np.array([np.cos(a), np.sin(a), 0.0, 0.0])


def test_a_lift_that_tips_the_body_is_called_off_and_the_foot_put_down(meta_paths):
    rig = Rig(meta_paths[0], legs=("FL",),
              config=dataclasses.replace(CFG, tip_retry_shift_s=None))  # the default limits
    rig.quat = _roll(3.0)  # a floor tilted 3 deg: the guard measures from the lift's start
    rig.run_until(State.TRIPOD)
    while rig.s.phase != "lift":
        rig.tick()
    q_start = rig.s._q_start.copy()
    rig.quat = _roll(7.5)  # 4.5 deg more: inside the limit
    rig.tick()
    assert rig.s.state is State.TRIPOD and rig.s._abort is None
    rig.quat = _roll(8.5)
    rig.tick()  # seen on this tick, the foot goes down from the next
    assert "tipped 5.50 deg in lift" in rig.s._abort
    rig.tick()
    assert rig.s.state is State.LOWER
    rig.quat = _roll(3.0)
    rig.run_until(State.STAND)
    # back where it stood when the lift began
    np.testing.assert_allclose(rig.q[sdk_indices("FL")], q_start, atol=1e-9)
    rig.run_until(State.DONE)
    assert rig.solves == [] and State.CALIBRATE not in rig.states
    assert not rig.reports[0].ok and "tipped" in rig.reports[0].error
    assert rig.s.fault is None


def _tip_in_lift(rig, deg=8.0):
    rig.run_until(State.TRIPOD)
    while rig.s.phase != "lift":
        rig.tick()
    rig.quat = _roll(deg)
    rig.tick()
    rig.quat = _roll(0.0)
    rig.tick()
    assert rig.s.state is State.LOWER


def test_a_tipped_lift_is_tried_once_more_after_replant_with_a_longer_shift(meta_paths):
    rig = Rig(meta_paths[0], legs=("FL", "RL"))
    _tip_in_lift(rig)
    rig.run_until(State.CALIBRATE)
    # down, sat, stood, and FL again before RL, its shift 1 s longer
    assert rig.states == [State.STAND, State.TRIPOD, State.LOWER, State.STAND, State.REPLANT,
                          State.STAND, State.TRIPOD, State.CALIBRATE]
    assert rig.s.leg == "FL" and "again with a 1.2 s shift" in rig.transitions[6][2]
    sched = rig.s.meta.schedule
    assert sched.shift_of("FL") == pytest.approx(1.2) and sched.shift_of("RL") == 0.2
    assert sched.plan("FL") is rig.meta.schedule.plan("FL")  # not optimised again
    # RL's lift has the policy's own schedule; it tips, and so does its retry: reported
    for shift in (0.2, 1.2):
        _tip_in_lift(rig)
        assert rig.s.leg == "RL" and rig.s.meta.schedule.shift_of("RL") == pytest.approx(shift)
        assert "tipped" in rig.s._abort
        assert rig.s.meta.schedule.shift_of("FL") == 0.2
    rig.run_until(State.DONE)
    fl, rl = rig.reports
    assert fl.leg == "FL" and fl.ok and fl.error is None and "tipped" in fl.retried
    assert rl.leg == "RL" and not rl.ok and "tipped" in rl.error and "tipped" in rl.retried
    assert rig.s.outcomes == [fl, rl] and len(rig.solves) == 1


def test_the_hold_has_its_own_limit(meta_paths):
    rig = Rig(meta_paths[0], legs=("FL",), config=dataclasses.replace(CFG, tip_retry_shift_s=None))
    rig.run_until(State.TRIPOD)
    while rig.s.phase != "hold":
        rig.tick()
    rig.quat = _roll(7.5)  # past the lift's 5 deg, within the hold's 8: a planned lean
    rig.tick()
    assert rig.s.state is State.TRIPOD and rig.s._abort is None
    rig.quat = _roll(8.5)
    rig.tick()
    assert "tipped 8.50 deg in hold" in rig.s._abort and "limit 8" in rig.s._abort


def test_the_tip_guard_watches_lift_and_hold_only_and_none_is_off(meta_paths):
    assert CFG.max_tip == DEFAULT_TIP_LIMITS  # on unless turned off
    assert dataclasses.replace(CFG, max_tip=6.0).max_tip == TipLimits(6.0, 6.0)
    with pytest.raises(ValueError, match="tip limit"):
        dataclasses.replace(CFG, max_tip=(5.0, -1.0))
    rig = Rig(meta_paths[0], legs=("FL",))
    rig.run_until(State.CALIBRATE)
    rig.quat = _roll(12.0)  # the excitation's sway is not the guard's
    rig.run_until(State.DONE)
    assert rig.reports[0].ok
    off = Rig(meta_paths[0], legs=("FL",), config=dataclasses.replace(CFG, max_tip=None))
    off.run_until(State.TRIPOD)
    while off.s.phase != "lift":
        off.tick()
    off.quat = _roll(12.0)
    off.run_until(State.DONE)
    assert off.reports[0].ok


def _pitch(deg):
    a = np.radians(deg) / 2
    return np.array([np.cos(a), 0.0, np.sin(a), 0.0])


def test_the_foot_leaves_the_floor_only_once_the_body_stands_over_the_tripod(meta_paths):
    from calib.joints import LEGS, sdk_to_model
    from calib.support import go2_support
    from deploy.observation import projected_gravity

    rig = Rig(meta_paths[0], legs=("FL",), config=dataclasses.replace(CFG, lift_gate=(0.02, 1.0)))
    stand = sdk_to_model(rig.meta.default_pose)
    tripod = [g for g in LEGS if g != "FL"]
    # the hold policy's stand: 4 mm short of the FL tripod; nose up 10 deg, 29 mm inside
    assert go2_support().margin(stand, projected_gravity(rig.quat), tripod) < 0
    assert go2_support().margin(stand, projected_gravity(_pitch(-10.0)), tripod) > 0.02
    rig.run_until(State.TRIPOD)
    shift_ticks = round(rig.meta.schedule.shift_of("FL") / 0.02)
    for _ in range(shift_ticks + 7):  # the shift, then 7 ticks held for the margin
        rig.tick()
        assert rig.s.phase == "shift" and rig.s._q_start is None
    assert rig.s._gate.waited_s == pytest.approx(7 * 0.02)
    rig.quat = _pitch(-10.0)
    rig.tick()
    assert rig.s.phase == "lift" and rig.s._q_start is not None
    rig.quat = _pitch(0.0)  # lifted: the foot is the tip guard's, not the gate's (2 deg)
    rig.run_until(State.DONE)
    assert rig.reports[0].ok and rig.reports[0].retried is None and len(rig.solves) == 1
    assert rig.reports[0].lift_wait_s == pytest.approx(7 * 0.02)
    # the leg's report says so (a fake solve: its result block is "no result")
    text = leg_summary(rig.reports[0])
    assert "its shift was held 0.14 s longer, until the centre of mass stood" in text


def test_a_body_that_never_stands_over_the_tripod_is_not_lifted_and_tried_again(meta_paths):
    rig = Rig(meta_paths[0], legs=("FL",), config=dataclasses.replace(CFG, lift_gate=(0.02, 0.2)))
    phases = set()
    for _ in range(3000):
        if rig.s.state is State.DONE:
            break
        rig.tick()
        phases.add(rig.s.phase)
    assert phases <= {"", "shift", "done"}  # the foot never left the floor
    assert rig.states.count(State.REPLANT) == 1 and rig.states.count(State.TRIPOD) == 2
    assert "again with a 1.2 s shift" in [c for _, b, c in rig.transitions
                                          if b is State.TRIPOD][1]
    (fl,) = rig.reports
    assert not fl.ok and rig.solves == []
    for why in (fl.error, fl.retried):
        assert why.startswith("centre of mass -4 mm in the stance triangle after 0.2 s")
    assert rig.s.fault is None


def test_a_gate_the_body_passes_changes_nothing(meta_paths):
    runs = []
    for gate in (None, (0.0, 2.0)):  # RL's tripod: 4 mm inside at the hold policy's stand
        rig = Rig(meta_paths[0], legs=("RL",), config=dataclasses.replace(CFG, lift_gate=gate))
        cmds = []
        while rig.s.state is not State.DONE:
            cmds.append(rig.tick().q)
        runs.append((rig.transitions, np.array(cmds)))
    assert runs[0][0] == runs[1][0]
    np.testing.assert_array_equal(runs[0][1], runs[1][1])


def test_two_legs_in_turn(meta_paths):
    rig = Rig(meta_paths[0], legs=("FR", "RL"))
    rig.run_until(State.REPORT)
    hold = rig.tick()  # REPORT holds the default pose, then re-plants for RL
    assert rig.s.state is State.REPLANT and rig.transitions[-1][2] == ("re-planting the feet "
                                                                       "before RL")
    first = rig.tick()
    assert np.abs(first.q - hold.q).max() < 0.05  # from the hold's target: no torque step
    rig.run_until(State.STAND)
    np.testing.assert_allclose(rig.q, rig.s.lie_pose, atol=1e-9)  # sat all the way down
    rig.run_until(State.DONE)
    assert [leg for leg, _ in rig.solves] == ["FR", "RL"]
    assert rig.states == [State.STAND, State.TRIPOD, State.CALIBRATE, State.LOWER, State.STAND,
                          State.SOLVE, State.REPORT, State.REPLANT, State.STAND, State.TRIPOD,
                          State.CALIBRATE, State.LOWER, State.STAND, State.SOLVE, State.REPORT,
                          State.SIT, State.DONE]
    # without re-planting the next lift starts from the stance the last one left
    rig = Rig(meta_paths[0], legs=("FR", "RL"), config=SessionConfig(
        **{**CFG.__dict__, "replant": False}))
    rig.run_until(State.DONE)
    assert State.REPLANT not in rig.states and rig.states.count(State.TRIPOD) == 2


def test_joystick_mode(meta_paths):
    rig = Rig(meta_paths[0], legs=(), joystick=True)
    for _ in range(50):
        rig.tick()
    assert rig.s.state is State.PASSIVE  # waits for L2+A
    rig.tick(combos=("calibrate_FL",))  # ignored outside STAND
    rig.tick(combos=("stand",))
    rig.run_until(State.STAND)
    for _ in range(60):
        rig.tick()
    assert rig.s.state is State.STAND
    rig.tick(combos=("calibrate_RR",))
    rig.run_until(State.REPORT)
    assert rig.s.leg == "RR"
    rig.tick()
    assert rig.s.state is State.STAND  # back to waiting, not sitting
    for _ in range(60):
        rig.tick()
    rig.tick(combos=("calibrate_FL",))  # a second lift: re-planted first
    rig.run_until(State.TRIPOD)
    assert rig.states[-3:] == [State.REPLANT, State.STAND, State.TRIPOD] and rig.s.leg == "FL"
    rig.run_until(State.REPORT)
    rig.tick()
    assert rig.s.state is State.STAND
    rig.tick(combos=("damp",))
    assert rig.s.state is State.DAMP and not rig.s.finished  # the operator can stand again
    rig.tick(combos=("stand",))
    assert rig.s.state is State.STAND
    rig.tick(combos=("damp",))
    rig.tick(fault="motor 3 over temperature (95 C >= 90 C)")  # a fault while damped by hand
    assert rig.s.finished and rig.s.fault.startswith("motor 3")
    rig.tick(combos=("stand",))
    assert rig.s.state is State.DAMP  # final now


def _stand_by_joystick(rig):
    rig.tick(combos=("stand",))
    rig.run_until(State.STAND)
    for _ in range(60):
        rig.tick()


def test_joystick_without_foot_imus_lifts_no_leg(meta_paths):
    rig = Rig(meta_paths[0], legs=(), joystick=True, available_legs=[])
    _stand_by_joystick(rig)
    rig.tick(combos=("calibrate_FL",))
    for _ in range(20):
        rig.tick()
    assert rig.s.state is State.STAND and State.TRIPOD not in rig.states


def test_a_combo_before_the_damp_is_no_order_after_it(meta_paths):
    rig = Rig(meta_paths[0], legs=(), joystick=True)
    rig.tick(combos=("stand",))
    rig.run_until(State.STAND)
    rig.tick(combos=("calibrate_FL",))  # still standing up: kept for when it stands
    rig.tick(combos=("damp",))
    _stand_by_joystick(rig)  # L2+A stands the robot up, and only that
    assert rig.s.state is State.STAND and State.TRIPOD not in rig.states
    # a called-off lift waiting for its second try: the damp ends it, and says so
    rig.tick(combos=("calibrate_FL",))
    _tip_in_lift(rig)
    rig.run_until(State.REPLANT)
    rig.tick(combos=("damp",))
    _stand_by_joystick(rig)
    assert rig.s.state is State.STAND and rig.states.count(State.TRIPOD) == 1
    (fl,) = rig.s.outcomes
    assert not fl.ok and fl.retried is None
    assert "tipped" in fl.error and "not lifted again: operator: L2+B" in fl.error


def test_a_solve_that_ends_after_a_stop_keeps_its_result(meta_paths):
    rig = Rig(meta_paths[0], legs=("FL",))
    rig.run_until(State.SOLVE)
    rig.tick(combos=("stop",))  # Ctrl-C while the worker solves: it writes the file all the same
    (fl,) = rig.s.outcomes
    assert rig.s.state is State.DAMP and fl.error == "aborted: operator: stop (Ctrl-C)"
    late = []
    for _ in range(5):  # the run joins its jobs, then takes their outcomes
        late += rig.s.adopt_late_results()
    assert late == [fl] and fl.ok and fl.error is None and fl.payload is not None
    assert rig.s.adopt_late_results() == []


def test_adapt_schedule_adds_what_the_legs_lag_shows_from_its_fit_on(tmp_path):
    """With the schedule's ``adapt``: the lifted leg's frames carry the tracking adapter's
    torque from its first fit on (2 s into the excitation), faded in; none before, and none on
    the other joints; a new lift starts a new adapter. The rig's leg reaches each target a
    tick late, a lag the adapter reads as damping."""
    from deploy.hold_policy import write_hold_policy

    sched = LiftSchedule(shift=0.2, lift=0.2, hold=0.2, lower=0.2, periods=1, adapt=True)
    rig = Rig(write_hold_policy(tmp_path, "ad", schedule=sched), legs=("RL", "FL"))
    idx = sdk_indices("RL")
    rig.run_until(State.CALIBRATE)
    first = rig.s._adapter
    assert first is not None and not first.fitted[0]
    t0 = sched.durations("RL")[:3].sum()
    seen = []
    while rig.s.state is State.CALIBRATE:
        t = (rig.s.k - rig.s._k_lift) * 0.02 - t0  # s into the excitation at this tick
        cmd = rig.tick()
        assert not np.delete(cmd.tau, idx).any()
        frames = (cmd, *cmd.substeps)
        if t < 2.0:
            assert not any(f.tau.any() for f in frames)
        elif t > 2.6:
            lt = sched.targets("RL", t + t0, rig.s._q_start)
            want = first.torque(t, lt.dq_des, lt.ddq_des, np.zeros(3))[0]
            np.testing.assert_allclose(cmd.tau[idx], want, atol=1e-9)
            seen.append(np.abs(want).max())
    assert first.fitted[0] and max(seen) > 0.1
    damping = first.coef[0, :, 0]
    assert np.all((damping > 0.5) & (damping < 5.0)), damping  # kp 40 x 20 ms + kd 1: ~1.8
    rig.run_until(State.CALIBRATE)  # FL's lift
    assert rig.s.leg == "FL"
    assert rig.s._adapter is not first and not rig.s._adapter.fitted[0]


def test_adapt_finds_the_command_delay_from_the_reported_torque_and_leads_the_plan(tmp_path):
    """The rig's motors play each command a tick (20 ms) late and report the torque of the PD
    law they ran (LowState's ``tau_est``): the adapter finds the delay from it, and once faded
    in the lifted leg's frames are the plan 20 ms ahead, so the late leg plays it on time."""
    from deploy.hold_policy import write_hold_policy

    sched = LiftSchedule(shift=0.2, lift=0.2, hold=0.2, lower=0.2, periods=1, adapt=True)
    rig = Rig(write_hold_policy(tmp_path, "ad", schedule=sched), legs=("RL",))
    idx = sdk_indices("RL")
    rig.run_until(State.CALIBRATE)
    t0 = sched.durations("RL")[:3].sum()
    last = None  # the frame the motors hold now: the one sent a tick ago
    checked = 0
    while rig.s.state is State.CALIBRATE:
        t = (rig.s.k - rig.s._k_lift) * 0.02 - t0  # s into the excitation at this tick
        # the PD law on the held frame with the joints as they are (q is that frame's, dq 0)
        tau = None if last is None else last.kp * (last.q - rig.q) + last.kd * last.dq + last.tau
        cmd = rig.tick(tau=tau)
        last = cmd
        ad = rig.s._adapter
        if t > 3.0 and rig.s.state is State.CALIBRATE:
            lead = ad.lead(t)[0]
            want = sched.targets("RL", t + t0 + lead, rig.s._q_start)
            np.testing.assert_allclose(cmd.q[idx], want.q_des, atol=1e-9)
            checked += 1
    assert ad.delay[0] == pytest.approx(0.02)
    assert checked > 20
    # the leg's outcome keeps it, and its report says it (the hold policy names no training)
    out = rig.s.outcomes[0]
    assert out.command_delay_s == pytest.approx(0.02) and out.trained_delay_s is None
    assert "command delay 20 ms (the motors' torque against the commands)" in leg_summary(out)


@pytest.mark.parametrize(("delay", "says"), [
    (0.015, "command delay 15 ms (the motors' torque against the commands), within the 0-20 ms"),
    (0.035, "command delay 35 ms (the motors' torque against the commands): OVER the 0-20 ms"),
    (None, None)])
def test_the_report_weighs_the_command_delay_against_the_policys_training(delay, says):
    from deploy.session import LegOutcome

    o = LegOutcome("FL", error="no result", command_delay_s=delay, trained_delay_s=(0.0, 0.02))
    text = leg_summary(o)
    if says is None:
        assert "command delay" not in text
    else:
        assert says in text and ("look at the command path" in text) == (delay > 0.02)


def test_the_lift_without_a_reported_torque_leaves_the_command_delay_unread(tmp_path):
    from deploy.hold_policy import write_hold_policy

    sched = LiftSchedule(shift=0.2, lift=0.2, hold=0.2, lower=0.2, periods=1, adapt=True)
    rig = Rig(write_hold_policy(tmp_path, "ad", schedule=sched), legs=("RL",))
    rig.run_until(State.DONE)
    assert rig.s._adapter.fitted[0] and rig.s.outcomes[0].command_delay_s is None


def test_feedforward_schedule_sends_the_lifted_leg_torque(tmp_path):
    from deploy.hold_policy import write_hold_policy

    sched = LiftSchedule(shift=0.2, lift=0.2, hold=0.2, lower=0.2, periods=1, feedforward=True)
    rig = Rig(write_hold_policy(tmp_path, "ff", schedule=sched), legs=("RL",))
    rig.run_until(State.TRIPOD)
    assert not rig.tick().tau.any()  # shift: the policy alone, no torque
    rig.run_until(State.CALIBRATE)
    cmd = rig.tick()
    idx = sdk_indices("RL")
    t = (rig.s.k - 1 - rig.s._k_lift) * 0.02
    want = rig.meta.schedule.targets("RL", t, rig.s._q_start, [0.0, 0.0, -1.0]).tau
    np.testing.assert_allclose(cmd.tau[idx], want)
    assert np.abs(cmd.tau[idx]).max() > 0.1  # the leg's weight, at least
    assert not np.delete(cmd.tau, idx).any()


@pytest.mark.parametrize("seen", [1.0, 0.5, 0.0])
def test_excitation_seen_scales_the_lifted_leg_the_policy_observes(tmp_path, seen):
    """With the schedule's ``excitation_seen`` the policy observes the lifted leg at that
    fraction of its excursion from the plan's ``q0`` on every excitation tick, while its
    commands still play the plan; before and after the excitation the leg as measured."""
    from deploy.hold_policy import write_hold_policy

    sched = LiftSchedule(shift=0.2, lift=0.2, hold=0.2, lower=0.2, periods=1,
                         excitation_seen=seen)
    rig = Rig(write_hold_policy(tmp_path, "seen", schedule=sched), legs=("RL",))
    idx = sdk_indices("RL")
    q0 = sched.plan("RL").q0
    offset = np.asarray(rig.meta.observation["terms"][3]["offset"])[idx]
    rig.run_until(State.CALIBRATE)
    frames = {"excite": [], "other": []}
    while rig.s.state is State.CALIBRATE:
        q_in = rig.q[idx].copy()
        cmd = rig.tick()
        if cmd.source.startswith("policy:"):
            frames["excite" if cmd.source == "policy:excite" else "other"].append(
                (cmd.obs[9 + idx], q_in, cmd.q[idx]))
    excite = frames["excite"]
    assert len(excite) > 20 and frames["other"]
    moved = np.ptp([c for _, _, c in excite], axis=0)
    assert moved.min() > 0.05  # the leg is commanded through the plan either way
    for obs, q_in, _ in frames["other"]:
        np.testing.assert_allclose(obs, q_in - offset, atol=1e-6)
    for obs, q_in, _ in excite:
        np.testing.assert_allclose(obs, q0 + seen * (q_in - q0) - offset, atol=1e-6)
