"""Hardware-in-the-loop: the deploy program against the lockstep mock robot over real Zenoh
loopback and real pty serial ports (deterministic: the mock advances one 4 ms quantum per
LowCmd_, and the loop ticks on the LowState of the expected tick).

Two robots: a hung-up Go2 (``base: fixed``) driven by the hold policy (the stand-in network of
the exact file contract, ``deploy/hold_policy.py``), which runs everywhere; and the Go2 on the
floor driven by the trained tripod policy from ``policies/``, skipped only while that file is
missing. Short excitations (1 period) keep the suite fast; users get the policy's own plan.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import itertools
import json

import numpy as np
import pytest

pytest.importorskip("mujoco")
pytest.importorskip("onnx")

from calib.metrics import geodesic_error_deg
from calib.result import CalibrationResult
from deploy.cli import ALL_LEGS_ORDER
from deploy.hold_policy import write_hold_policy
from deploy.lift_schedule import COMMANDS_PER_TICK, LiftSchedule
from deploy.policy import PolicyMeta, policies_for_legs
from deploy.runtime import DeployConfig, DeployError, DeployRunner, ImuPort
from deploy.session import SessionConfig, State
from deploy.simulate import free_tcp_port, truth_tuples
from hw.mock.config import MockConfig
from hw.mock.robot import MockRobot

# hung up, the body cannot move over the tripod: the lift gate is off (a2i-deploy --lift-gate off)
FAST = SessionConfig(passive_s=0.2, stand_s=1.0, stand_settle_s=0.4, lift_gate=None)
ROT_TOL_DEG = 0.5
OFFSET_TOL_S = 1e-3


@pytest.fixture(scope="module")
def policies(tmp_path_factory):
    d = tmp_path_factory.mktemp("policies")
    sched = LiftSchedule(periods=1)
    return {"hold": write_hold_policy(d, "hold", schedule=sched),
            "nan": write_hold_policy(d, "nan", action_value=float("nan"), schedule=sched)}


def start_mock(seed: int, **extra) -> MockRobot:
    cfg = {"listen": [f"tcp/127.0.0.1:{free_tcp_port()}"], "clock": "lockstep", "seed": seed,
           "base": "fixed", **extra}
    robot = MockRobot(MockConfig.from_dict(cfg))
    robot.start()
    return robot


def deploy(robot: MockRobot, policy_json, legs, out, on_tick=None, session=FAST, periods=None):
    """policy_json None: each leg's newest committed policy (as a2i-deploy without --policy)."""
    metas = policies_for_legs(legs, policy_json)
    if periods is not None:
        from dataclasses import replace

        for m in {id(m): m for m in metas.values()}.values():
            m.schedule = replace(m.schedule, periods=periods)
    cfg = DeployConfig(
        legs=list(legs), out_dir=out, connect=list(robot.config.listen),
        imus=[ImuPort(leg, port) for leg, port in robot.imu_ports.items()], clock="lockstep",
        record_seconds=150.0, session=session, truth=truth_tuples(robot.truth()))
    return DeployRunner(cfg, metas, on_tick=on_tick).run()


def check_against_truth(result, robot, out, legs):
    truth = truth_tuples(robot.truth())
    assert [o.leg for o in result.outcomes] == list(legs)
    for o in result.outcomes:
        assert o.ok, f"{o.leg}: {o.error}"
        res = CalibrationResult.read(out / f"{o.leg}.json")
        assert res.accepted
        r_true, t_true = truth[o.leg]
        rot = geodesic_error_deg(res.rotation_matrix, r_true)
        dt = abs(res.time_offset_s - t_true)
        assert rot < ROT_TOL_DEG, f"{o.leg}: rotation error {rot:.3f} deg"
        assert dt < OFFSET_TOL_S, f"{o.leg}: offset error {dt * 1e3:.3f} ms"
        assert (out / f"{o.leg}.png").stat().st_size > 10_000


HUNG_SEED = 11


@contextlib.contextmanager
def solver_input_digests():
    """{leg: sha256 of every array SOLVE handed the solver} for the legs solved meanwhile."""
    import deploy.solve as solve_mod

    digests: dict[str, str] = {}
    extract = solve_mod.extract_leg_data

    def recording(snapshot, leg, *a, **k):
        data = extract(snapshot, leg, *a, **k)
        h = hashlib.sha256()
        for f in dataclasses.fields(data):
            h.update(np.ascontiguousarray(getattr(data, f.name)).tobytes())
        digests[leg] = h.hexdigest()
        return data

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(solve_mod, "extract_leg_data", recording)
        yield digests


@pytest.fixture(scope="module")
def hung_all_legs(policies, tmp_path_factory):
    """The hung robot calibrating all four legs in turn: (result, stopped robot, out dir,
    digests of each leg's solver inputs)."""
    out = tmp_path_factory.mktemp("hung_all_legs")
    robot = start_mock(seed=HUNG_SEED)
    try:
        with solver_input_digests() as inputs:
            result = deploy(robot, policies["hold"], ["FL", "FR", "RL", "RR"], out)
    finally:
        robot.stop()
    return result, robot, out, inputs


def test_hung_robot_all_legs_recover_mounting_and_every_lowstate_recorded(hung_all_legs):
    result, robot, out, _ = hung_all_legs
    # Both counts read once the robot's thread has stopped: an idle repeat of the last
    # LowState can come between two reads made while it runs (CI once counted 1 too few).
    published, repeated = robot.lowstates_published, robot.lowstates_repeated
    assert result.fault is None and result.final_state is State.DONE
    check_against_truth(result, robot, out, ["FL", "FR", "RL", "RR"])
    # The session file holds every LowState the robot sent (500 Hz, not just 1 in 10).
    from hw.mcap_io import read_mcap

    snap = read_mcap(result.mcap_path)
    ticks = np.unique(snap.lowstate["tick"])
    # (the last tick's five quanta answer after the loop has stopped ticking: the runtime
    # records them until the lockstep robot falls quiet, so none is lost, not even those)
    assert len(ticks) == published - repeated
    assert np.all(np.diff(ticks) == 2)  # 2 ms apart, none missing
    # every LowCmd_ frame recorded: five per tick, and the lockstep quantum check's one
    assert len(snap.imu["FL"]) > 1000
    assert len(snap.lowcmd) == result.ticks * COMMANDS_PER_TICK + 1
    events = [text for _, _, text in snap.events_text()]
    assert any("CALIBRATE -> LOWER" in e for e in events)


def test_cli_sim_with_garbage_on_the_serial_line(policies, tmp_path):
    """`a2i-deploy --leg FR --sim` end to end, with random bytes between the IMU frames."""
    from deploy.cli import main

    cfg = tmp_path / "mock.json"
    cfg.write_text(json.dumps({"base": "fixed", "foot_imus": {
        "FR": {"garbage_prob": 0.3, "garbage_max_bytes": 40}}}))
    out = tmp_path / "out"
    code = main(["--leg", "FR", "--sim", "--sim-seed", "5", "--sim-config", str(cfg),
                 "--policy", str(policies["hold"]), "--periods", "1", "--lift-gate", "off",
                 "--out", str(out)])
    assert code == 0
    truth = json.loads((out / "sim_truth.json").read_text())
    assert set(truth) == {"FL", "FR", "RL", "RR"}
    res = CalibrationResult.read(out / "FR.json")
    assert geodesic_error_deg(res.rotation_matrix, truth["FR"]["rotation_matrix"]) < ROT_TOL_DEG
    assert abs(res.time_offset_s - truth["FR"]["time_offset_s"]) < OFFSET_TOL_S
    assert len(list(out.glob("session-*.mcap"))) == 1


def _at(state: State, after_s: float, action):
    """on_tick hook: run ``action(runner)`` once, ``after_s`` into ``state``."""
    fired = []

    def hook(runner):
        s = runner.session
        if not fired and s.state is state and s.t_state >= after_s:
            fired.append(runner.ticks)
            action(runner)
    hook.fired = fired
    return hook


def test_mock_dies_mid_motion_damps_and_writes_nothing(policies, tmp_path):
    robot = start_mock(seed=3)
    try:
        hook = _at(State.CALIBRATE, 1.0, lambda r: robot.kill())
        result = deploy(robot, policies["hold"], ["FL"], tmp_path, on_tick=hook)
    finally:
        robot.stop()
    assert hook.fired
    assert result.final_state is State.DAMP and "stale LowState" in result.fault
    assert not (tmp_path / "FL.json").exists()
    assert not result.ok and "aborted: stale" in result.outcomes[0].error


def test_imu_port_closing_is_a_clear_error(policies, tmp_path):
    robot = start_mock(seed=4)
    try:
        hook = _at(State.CALIBRATE, 1.0, lambda r: robot.close_imu_port("FL"))
        result = deploy(robot, policies["hold"], ["FL"], tmp_path, on_tick=hook)
    finally:
        robot.stop()
    assert hook.fired
    port = robot.imu_ports["FL"]
    err = result.outcomes[0].error
    assert "foot IMU FL failed" in err and port in err
    assert "FL" in result.imu_errors and port in result.imu_errors["FL"]
    assert result.fault is None and result.final_state is State.DONE  # lowered, sat down
    assert not (tmp_path / "FL.json").exists() and not result.ok


def test_silent_imu_port_aborts_the_leg_before_solve(policies, tmp_path):
    """A port that opens but carries nothing (wrong port, IMU off): the leg is aborted while
    lifted, lowered, reported; nothing is written."""
    from hw.pty_link import PtyPair

    robot = start_mock(seed=9)
    silent = PtyPair()
    meta = PolicyMeta.load(policies["hold"])
    cfg = DeployConfig(legs=["FL"], out_dir=tmp_path, connect=list(robot.config.listen),
                       imus=[ImuPort("FL", silent.port_path)], clock="lockstep", session=FAST)
    try:
        result = DeployRunner(cfg, meta).run()
    finally:
        robot.stop()
        silent.close()
    err = result.outcomes[0].error
    assert "foot IMU FL failed: no data on " + silent.port_path in err
    assert result.fault is None and result.final_state is State.DONE
    assert "SOLVE" not in [t[2] for t in result.transitions]
    assert not (tmp_path / "FL.json").exists()


def test_lockstep_mock_waits_for_a_slow_imu_reader_and_drops_no_frame(policies, tmp_path,
                                                                   monkeypatch):
    """A reader thread short of CPU (each sample takes 1 ms to record: 8 ms per 20 ms tick,
    slower than this loop ticks): the lockstep mock waits for its ports to take the frames, so
    none is lost (a mock that drops them, ``lockstep_port_wait_s`` 0, lost some 1 500 per port
    here)."""
    import time

    record = DeployRunner._imu_recorder

    def slow_recorder(self, default_leg):
        on_sample = record(self, default_leg)

        def slow(s):
            time.sleep(0.001)
            on_sample(s)
        return slow

    monkeypatch.setattr(DeployRunner, "_imu_recorder", slow_recorder)
    robot = start_mock(seed=21)
    try:
        result = deploy(robot, policies["hold"], ["FL"], tmp_path)
        dropped = {leg: c.frames_dropped for leg, c in robot.channels.items()}
    finally:
        robot.stop()
    assert result.outcomes[0].ok, result.outcomes[0].error
    assert dropped == {leg: 0 for leg in dropped}
    from hw.mcap_io import read_mcap

    # what the session recorded runs without a gap (the slow reader still had a backlog when
    # the loop stopped, so its last frames are not in the file)
    seq = read_mcap(result.mcap_path).imu["FL"]["seq"].astype(int)
    assert len(seq) > 2000 and np.all(np.diff(seq) % 65536 == 1)


def test_lockstep_runs_do_not_depend_on_how_fast_the_host_solves(policies, hung_all_legs,
                                                                  tmp_path, monkeypatch):
    """The all-leg run's seed again, its first two legs with a solver 1 s slower: the robot
    waits for it, so the second leg starts from the same state, both legs hand the solver the
    same arrays and come out bit for bit as in that run (a leg's result depends on nothing
    after its own motion)."""
    import time

    import deploy.solve as solve_mod

    _, _, fast_out, fast_inputs = hung_all_legs
    solve_leg = solve_mod.solve_leg

    def slow_solve_leg(*a, **k):
        time.sleep(1.0)
        return solve_leg(*a, **k)

    monkeypatch.setattr(solve_mod, "solve_leg", slow_solve_leg)
    robot = start_mock(seed=HUNG_SEED)
    try:
        with solver_input_digests() as slow_inputs:
            result = deploy(robot, policies["hold"], ["FL", "FR"], tmp_path)
    finally:
        robot.stop()
    assert [o.ok for o in result.outcomes] == [True, True]
    # First what reached the solver (the recording, cut to the window), then what it made of it:
    # a failure says which of the two was not reproduced.
    for leg in ("FL", "FR"):
        assert slow_inputs[leg] == fast_inputs[leg], (leg, "solver inputs")
    for leg in ("FL", "FR"):
        slow = json.loads((tmp_path / f"{leg}.json").read_text())
        fast = json.loads((fast_out / f"{leg}.json").read_text())
        for key in ("rotation_matrix", "time_offset_s"):
            assert slow[key] == fast[key], (leg, key, "from the same inputs, ulps apart:", _ulps(
                slow[key], fast[key]))


def _ulps(a, b) -> int:
    """Largest distance in units in the last place between two equally shaped float arrays."""
    a, b = (np.asarray(x, dtype=np.float64).view(np.int64) for x in (a, b))
    return int(np.max(np.abs(a - b)))


def test_l2_b_mid_motion_damps_within_one_tick(policies, tmp_path):
    robot = start_mock(seed=5)
    try:
        hook = _at(State.CALIBRATE, 1.0, lambda r: robot.press("L2+B", 0.3))
        result = deploy(robot, policies["hold"], ["FL"], tmp_path, on_tick=hook)
    finally:
        robot.stop()
    (press_tick,) = hook.fired
    damp = [t for t in result.transitions if t[2] == "DAMP"]
    assert damp and damp[0][3] == "operator: L2+B"
    # The tick right after the press was published (the first to see it) damped.
    assert round(damp[0][0] / 0.02) == press_tick
    assert result.final_state is State.DAMP and not (tmp_path / "FL.json").exists()


def test_a_crash_in_the_loop_damps_the_robot_before_the_error_propagates(policies, tmp_path):
    robot = start_mock(seed=10)

    def boom(r):
        raise RuntimeError("boom")

    try:
        with pytest.raises(RuntimeError, match="boom"):
            deploy(robot, policies["hold"], ["FL"], tmp_path,
                   on_tick=_at(State.TRIPOD, 0.2, boom))
        import time

        deadline = time.monotonic() + 5.0  # the mock applies commands on its own thread
        while time.monotonic() < deadline and np.any(robot.sim.command.kp != 0):
            time.sleep(0.05)
        cmd = robot.sim.command  # what the motors obey
        assert np.all(cmd.kp == 0) and np.all(cmd.kd > 0)
    finally:
        robot.stop()


def test_nan_policy_damps(policies, tmp_path):
    robot = start_mock(seed=6)
    try:
        result = deploy(robot, policies["nan"], ["FL"], tmp_path)
    finally:
        robot.stop()
    assert result.final_state is State.DAMP and "non-finite policy action" in result.fault
    assert [t[1] for t in result.transitions][-1] == "TRIPOD"
    assert not (tmp_path / "FL.json").exists()


def test_refuses_to_start_while_another_lowcmd_publisher_is_present(policies, tmp_path):
    from hw.go2_msgs import LowCmdBuffer
    from hw.transport import KEY_LOWCMD, Transport, TransportConfig

    robot = start_mock(seed=7)
    other = Transport(TransportConfig(connect=list(robot.config.listen))).open()
    try:
        other.publisher(KEY_LOWCMD).put(LowCmdBuffer().finalize())
        with pytest.raises(DeployError, match="refusing to publish 'rt/lowcmd'"):
            deploy(robot, policies["hold"], ["FL"], tmp_path)
    finally:
        other.close()
        robot.stop()


def test_a_lockstep_robot_on_another_quantum_is_refused(policies, tmp_path):
    """A lockstep mock that advances 20 ms per LowCmd_ would play five times too fast for a
    loop that sends five frames per 20 ms tick: refused at start with a one-line reason."""
    robot = start_mock(seed=9, lockstep_quantum_s=0.02)
    try:
        with pytest.raises(DeployError, match="advanced 20 ms on one LowCmd_.*must advance 4 ms"):
            deploy(robot, policies["hold"], ["FL"], tmp_path)
    finally:
        robot.stop()


def test_joystick_mode_stand_then_calibrate_by_combo(policies, tmp_path):
    """No --leg: L2+A stands, R1+Down calibrates RR (the remote's bytes in LowState), then a
    stop request (Ctrl-C) damps and ends the run."""
    robot = start_mock(seed=8, joystick=[[0.3, "L2+A"], [2.5, "R1+Down"]])
    meta = PolicyMeta.load(policies["hold"])

    def stop_after_report(r):
        if r.session.outcomes and r.session.outcomes[0].payload is not None:
            r.request_stop()

    cfg = DeployConfig(legs=[], joystick=True, out_dir=tmp_path,
                       connect=list(robot.config.listen),
                       imus=[ImuPort(leg, p) for leg, p in robot.imu_ports.items()],
                       clock="lockstep", session=FAST, truth=truth_tuples(robot.truth()))
    try:
        result = DeployRunner(cfg, meta, on_tick=stop_after_report).run()
    finally:
        robot.stop()
    causes = [t[3] for t in result.transitions]
    assert causes[0] == "operator: L2+A" and "operator: calibrate RR" in causes
    assert causes[-1] == "operator: stop (Ctrl-C)" and result.final_state is State.DAMP
    assert result.fault is None and result.ok
    assert [o.leg for o in result.outcomes] == ["RR"]
    assert (tmp_path / "RR.json").exists()


# ---------------------------------------------------------------------------- trained policy
def _trained_policies():
    """Each leg's newest committed policy, or None while some leg has none."""
    try:
        return policies_for_legs(["FL", "FR", "RL", "RR"])
    except ValueError:
        return None


@pytest.mark.skipif(_trained_policies() is None,
                    reason="some leg has no trained tripod policy in policies/; the floor "
                           "test needs one for each leg to stand on three legs")
@pytest.mark.parametrize("slope_deg", [0.0, 4.0])
def test_robot_on_the_floor_all_legs_recover_mounting(tmp_path, slope_deg):
    """Flat, and on a floor falling away ahead of the robot: there, without re-planting the
    feet between lifts, the third lift (FL) tipped over, here with one period as with the
    full schedule (docs/results/replant.md)."""
    robot = start_mock(seed=21, base="free", floor_slope_deg=slope_deg)
    try:
        result = deploy(robot, None, ALL_LEGS_ORDER, tmp_path, session=SessionConfig(),
                        periods=1)
    finally:
        robot.stop()
    assert result.fault is None, result.fault
    check_against_truth(result, robot, tmp_path, ALL_LEGS_ORDER)
    # each lift read the command path's delay from the motors' torque: the mock's, within the
    # latency the policies were trained under
    for o in result.outcomes:
        assert o.command_delay_s is not None and o.trained_delay_s is not None, o.leg
        assert 0.0 <= o.command_delay_s <= o.trained_delay_s[1], (o.leg, o.command_delay_s)
    from hw.mcap_io import read_mcap_metadata

    recorded = read_mcap_metadata(result.mcap_path)["a2i/session"]["command_delay_s"]
    assert recorded == {o.leg: o.command_delay_s for o in result.outcomes}
    # every lift but the first started from a stand-up after sitting down
    states = [t[2] for t in result.transitions]
    assert states.count("REPLANT") == len(ALL_LEGS_ORDER) - 1
    assert all(b == "STAND" for a, b in itertools.pairwise(states) if a == "REPLANT")


@pytest.mark.skipif(_trained_policies() is None,
                    reason="no trained tripod policy for FL in policies/")
def test_cli_a_lift_that_tips_is_called_off_and_the_robot_stays_up(tmp_path, capsys):
    """`a2i-deploy --max-tip`: with a limit no lift keeps (0.01 deg) the FL lift is called off
    in its lift phase and the foot goes back down; the robot sits, stands and lifts FL again
    with a 1 s longer shift, which is called off too; the run ends sitting, not damped: exit 1,
    the leg reported failed, nothing written for it."""
    from deploy.cli import main

    code = main(["--leg", "FL", "--sim", "--sim-seed", "3", "--periods", "1",
                 "--max-tip", "0.01", "--out", str(tmp_path)])
    assert code == 1
    out = capsys.readouterr().out
    assert out.count("TRIPOD -> LOWER: abort: the body tipped") == 2 and "in lift" in out
    assert "REPLANT" in out and "again with a 3 s shift" in out
    assert "LOWER -> STAND: foot down" in out and "SIT -> DONE" in out and "DAMP" not in out
    assert "Leg FL: NO CALIBRATION WRITTEN" in out and "its first lift was called off" in out
    assert not (tmp_path / "FL.json").exists()


@pytest.mark.skipif(_trained_policies() is None,
                    reason="no trained tripod policy for FL in policies/")
def test_cli_a_lift_the_body_cannot_stand_for_is_not_lifted(tmp_path, capsys):
    """`a2i-deploy --lift-gate`: with a margin no stance reaches (150 mm) the shift is held its
    0.1 s and the lift called off with the foot still on the floor; the robot sits, stands and
    tries once more with a longer shift, called off too: exit 1, nothing written for FL."""
    from deploy.cli import main

    code = main(["--leg", "FL", "--sim", "--sim-seed", "3", "--periods", "1",
                 "--lift-gate", "150,0.1", "--out", str(tmp_path)])
    assert code == 1
    out = capsys.readouterr().out
    assert out.count("TRIPOD -> LOWER: abort: centre of mass") == 2
    assert "after 0.1 s more shift (needs +150)" in out
    assert "REPLANT" in out and "again with a 3 s shift" in out
    assert "SIT -> DONE" in out and "DAMP" not in out
    assert "Leg FL: NO CALIBRATION WRITTEN" in out and "its first lift was called off" in out
    assert not (tmp_path / "FL.json").exists()
