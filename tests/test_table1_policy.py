"""Free-base Table I: the policy-driven A2I run, the open-loop free-base runner, their records
(the same MotionRun as the held-base table), scoring, and the page/JSON round trip."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")
pytest.importorskip("onnxruntime")

from calib.joints import LEGS, model_indices
from calib.kinematics import LegKinematics
from calib.motions import walk_motion, wave_motion
from cli.calib import main
from policy_train.policy_motion import load_policy, run_policy_a2i
from sim.free_base_run import RunHealth, naive_wave_free, run_motion_free
from sim.table1 import (
    FreeRun,
    FreeTable,
    Table1Row,
    beats_paper_a2i,
    render_page,
    run_table1_free,
    score_run,
)

POLICY = Path(__file__).resolve().parents[1] / "policies" / "tripod_go2_v1.onnx"
SETTLE = 0.4


@pytest.fixture(scope="module")
def policy_run():
    if not POLICY.is_file():
        pytest.skip("no shipped policy")
    pb = load_policy(POLICY)
    run, health = run_policy_a2i(pb, "FL", settle_s=SETTLE, periods=1, after_s=0.0)
    return pb, run, health


@pytest.fixture(scope="module")
def walk_run():
    return run_motion_free(walk_motion(5.0, 200.0, 0), settle_s=0.3)


def _check_shapes(run, dt=0.002):
    n = len(run.t)
    assert n > 100
    assert run.q.shape == (n, 12) and run.dq.shape == (n, 12)
    assert run.base_gyro.shape == (n, 3)
    assert run.foot_omega.shape == (4, n, 3) and run.foot_sf.shape == (4, n, 3)
    assert run.tracking_rmse.shape == (12,)
    np.testing.assert_allclose(np.diff(run.t), dt, atol=1e-9)
    for a in (run.q, run.dq, run.base_gyro, run.foot_omega, run.foot_sf):
        assert np.all(np.isfinite(a))


def _check_foot_truth(run, legs=LEGS):
    """The recorded foot gyro truth (MuJoCo's sensor) equals forward kinematics of the
    recorded joints plus the recorded body gyro, leg by leg (so no leg or frame is swapped)."""
    for i, leg in enumerate(LEGS):
        if leg not in legs:
            continue
        q, dq = run.leg_joints(leg)
        fk = LegKinematics.from_urdf(leg=leg).foot_angular_velocity(q, dq, run.base_gyro)
        truth = run.foot_omega[i]
        scale = np.sqrt(np.mean(truth**2))
        assert scale > 0.05, leg
        assert np.sqrt(np.mean((fk - truth) ** 2)) < 0.01 * scale, leg


def test_policy_run_records_the_excitation_on_the_floor(policy_run):
    pb, run, health = policy_run
    _check_shapes(run)
    sched = dataclasses.replace(pb.meta.schedule, periods=1)
    d = sched.durations("FL")
    # recorded: the excitation phase, stamped in sim time after settle + shift + lift + hold
    assert run.t[0] == pytest.approx(SETTLE + d[:3].sum(), abs=0.005)
    assert run.t[-1] - run.t[0] == pytest.approx(d[3], abs=0.005)
    assert run.motion_name == "a2i_FL"
    # standing on the floor, not held up and not lying on it
    assert 0.15 < health.min_base_z < 0.45 and 0.15 < health.final_base_z < 0.45
    assert health.lifted_leg == "FL" and isinstance(health.lifted_foot_touched, bool)
    assert health.duration_s == pytest.approx(d[2] + d[3], abs=0.01)
    # the lifted leg follows the schedule's trajectory (its own PD, not the policy)
    assert np.all(run.tracking_rmse[:3] < 0.1)


def test_policy_run_foot_truth_is_the_simulators(policy_run):
    _check_foot_truth(policy_run[1], legs=("FL",))


def test_score_run_works_on_the_policy_run(policy_run):
    rows = score_run(policy_run[1], "a2i", ["FL"], [0.03], 0)
    assert [(r.pipeline, r.motion, r.leg) for r in rows] == [("paper", "a2i", "FL"),
                                                            ("ours", "a2i", "FL")]
    for r in rows:
        assert np.isfinite([r.cn, r.cc, r.re_euler_deg, r.offset_error_s]).all()
        assert r.cn >= 1.0
    ours = rows[1]
    assert ours.geodesic_deg < 1.0 and ours.offset_error_s < 1e-3


def test_open_loop_walk_on_the_floor(walk_run):
    run, health = walk_run
    _check_shapes(run)
    # only the motion is recorded, after the settling
    assert run.t[0] == pytest.approx(0.3 + 0.002, abs=1e-6)
    assert run.t[-1] == pytest.approx(0.3 + 5.0, abs=0.003)
    assert 0.15 < health.min_base_z < 0.45
    assert health.lifted_leg is None and health.lifted_foot_touched is None
    assert np.isnan(health.lifted_foot_min_z)
    _check_foot_truth(run)
    rows = score_run(run, "walk", ["RR"], [0.006], 1)
    assert len(rows) == 2 and all(np.isfinite(r.re_euler_deg) for r in rows)


def test_motions_are_scored_on_records_of_one_length(walk_run):
    run = walk_run[0]
    head = run.head(2.0)
    assert head.t[-1] - head.t[0] == pytest.approx(2.0, abs=1e-9)
    assert head.foot_omega.shape == (4, len(head.t), 3) and head.q.shape == (len(head.t), 12)
    np.testing.assert_array_equal(head.base_gyro, run.base_gyro[:len(head.t)])
    with pytest.raises(ValueError):
        run.head(0.0)
    # a leg scored on its record length: exactly the rows of the cropped run
    cut = score_run(run, "walk", ["FL", "RR"], [0.03], 0, record_s={"FL": 3.5, "RR": 4.0})
    assert cut[:2] == score_run(run.head(3.5), "walk", ["FL"], [0.03], 0)
    assert cut[2:] == score_run(run.head(4.0), "walk", ["RR"], [0.03], 0)
    assert cut[0] != score_run(run, "walk", ["FL"], [0.03], 0)[0]
    with pytest.raises(ValueError, match="positive"):
        run_table1_free(None, {"FL": 0.0}, legs=["FL"])
    with pytest.raises(ValueError, match="no record length for RR"):
        run_table1_free(None, {"FL": 14.8}, legs=["FL", "RR"])


def test_naive_wave_watches_the_lifted_foot():
    run, health = run_motion_free(wave_motion("RL", 3.0, 200.0, 0, ramp=0.5), lifted_leg="RL",
                                  settle_s=0.2, blend_s=0.5)
    assert run.t[0] == pytest.approx(0.7 + 0.002, abs=1e-6)
    assert health.lifted_leg == "RL" and isinstance(health.lifted_foot_touched, bool)
    assert np.isfinite(health.lifted_foot_min_z)
    with pytest.raises(ValueError):
        run_motion_free(wave_motion("RL", 3.0, 200.0, 0, ramp=0.5), record_every=0)


def test_the_naive_wave_shifts_its_weight_first_and_stays_up():
    """Blended straight from the stand to the lifted pose the robot tipped over at the lift and
    the table scored it lying on its back; the naive wave now moves the body over the three
    other feet first (open loop), lifts and waves without falling."""
    _, fell = run_motion_free(wave_motion("FL", 3.0, 200.0, 0, ramp=0.5),
                              lifted_leg="FL", settle_s=0.2)
    assert fell.fell
    wave, via = naive_wave_free("FL", 3.0, seed=0)
    assert len(via) == 1 and via[0][1] == 2.0
    # wave_motion's trajectory about the static stance's targets: a constant offset, which
    # moves the stance legs (the body's shift) and not the lifted leg's swing
    moved = wave.q - wave_motion("FL", 3.0, 200.0, 0).q
    np.testing.assert_allclose(moved, np.tile(moved[0], (len(moved), 1)), atol=1e-12)
    stance = [j for j in range(12) if j not in model_indices("FL")]
    assert np.abs(moved[0, stance]).max() > 0.02
    run, health = run_motion_free(wave, lifted_leg="FL", via=via, settle_s=0.2)
    assert not health.fell and not health.lifted_foot_touched and not health.body_contacts
    assert health.max_tilt_deg < 5.0
    assert run.t[0] == pytest.approx(0.2 + 2.0 + 1.0 + 0.002, abs=1e-6)


def test_a_fallen_baseline_run_is_listed_not_scored(monkeypatch):
    import sim.table1 as t1

    fallen = RunHealth(170.0, 160.0, 0.07, 0.07, ("base",), "RL", True, 0.01, True, 3.0)
    monkeypatch.setattr(t1, "run_motion_free", lambda *a, **k: (None, fallen))
    rows, runs = t1._free_job(("wave", 0, "RL", ("RL",), (0.03,), (0,), None, {"RL": 3.0}))
    assert rows == [] and runs == [FreeRun("wave", "RL", 0, fallen)]
    # and an A2I run that did not hold the tripod stops the table instead of being scored
    with pytest.raises(RuntimeError, match="did not hold the tripod"):
        t1._free_job(("a2i", None, "RL", ("RL",), (0.03,), (0,), lambda leg: ("run", fallen),
                      {"RL": 3.0}))


def test_a_failed_a2i_run_is_a_one_line_error(tmp_path, capsys, monkeypatch):
    import sim.table1 as t1

    def failed(*a, **k):
        raise RuntimeError("the A2I run of FL did not hold the tripod (fell True, ...)")

    monkeypatch.setattr(t1, "run_table1_free", failed)
    assert main(["bench", "--policy", str(POLICY), "--legs", "FL", "--seeds", "1",
                 "--out", str(tmp_path / "t.md")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "did not hold the tripod" in err[-1] and not (tmp_path / "t.md").exists()


def test_missing_policy_is_one_line_error(tmp_path, capsys):
    with pytest.raises(ValueError, match="not found"):
        load_policy(tmp_path / "none.onnx")
    assert main(["bench", "--policy", str(tmp_path / "none.onnx"),
                 "--out", str(tmp_path / "t.md")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "policy file not found" in err[0]
    assert not (tmp_path / "t.md").exists()


def _row(motion, pipeline, cn, cc, re, leg="FL", noise=0.03):
    return Table1Row(leg, noise, motion, pipeline, 0, cn, cc, re, re, 1e-5, motion == "a2i")


def test_free_table_json_and_page(tmp_path):
    held = [_row(m, p, cn, cc, re) for m, cn, cc, re in
            (("walk", 900.0, 0.9, 30.0), ("spin", 400.0, 0.9, 20.0), ("wave", 60.0, 0.8, 40.0),
             ("a2i", 1.1, 0.999, 0.01)) for p in ("paper", "ours")]
    # free base: A2I loses to spin on CN in "ours", beats the paper's A2I except on CC
    free_rows = [_row(m, p, cn, cc, re) for m, cn, cc, re in
                 (("walk", 70.0, 0.99, 0.2), ("spin", 1.02, 0.99, 0.3), ("wave", 100.0, 0.9, 9.0),
                  ("a2i", 1.05, 0.985, 0.1)) for p in ("paper", "ours")]
    health = RunHealth(16.7, 15.5, 0.22, 0.23, (), "FL", True, 0.021, False, 18.5)
    free = FreeTable(free_rows, [FreeRun("a2i", "FL", None, health)], [0], "p/x.onnx", 3.0)
    back = FreeTable.from_json(free.to_json())
    assert back == free
    assert beats_paper_a2i(free_rows, "ours")[("FL", 0.03)] == (True, False, True)
    page = render_page(held, [0], None, free)
    assert page.index("## The paper's pipeline") < page.index("## Free base")
    section = page.split("## Free base", 1)[1]
    assert "| a2i | FL | all | 16.7 | 15.5 | 0.220 | yes | 0.021 | none | no |" in section
    assert "| ours | 0/1 | 0/1 | 1/1 |" in section  # spin's CN 1.02 < 1.05, CC 0.99 > 0.985
    assert "| ours | FL | 0.03 | no / no / yes | yes / no / yes |" in section
    # the CLI re-renders both sections from the two JSON files
    src = tmp_path / "t1.json"
    src.write_text(json.dumps([dataclasses.asdict(r) for r in held]))
    (tmp_path / "t1_policy.json").write_text(free.to_json())
    out = tmp_path / "t1.md"
    assert main(["bench", "--from-json", str(src), "--out", str(out)]) == 0
    assert out.read_text() == page
    (tmp_path / "t1_policy.json").write_text("[]")
    assert main(["bench", "--from-json", str(src), "--out", str(out)]) == 2


def test_feedforward_schedule_tracks_closer_on_the_floor(policy_run):
    _, run, _ = policy_run
    ff = load_policy(POLICY)
    ff.meta.schedule = dataclasses.replace(ff.meta.schedule, feedforward=True)
    run_ff, health = run_policy_a2i(ff, "FL", settle_s=SETTLE, periods=1, after_s=0.0)
    assert not health.fell
    assert np.all(run_ff.tracking_rmse[:3] < 0.5 * run.tracking_rmse[:3])


@pytest.mark.parametrize("effect", ["damping", "latency"])
def test_adapt_tracks_closer_on_the_floor(effect):
    """``adapt`` (the JSON's, or the keyword): from its fit 2 s into the excitation on, the
    lifted leg lags its plan less (over the whole excitation, the first 2.5 s unadapted
    included). ``damping``: 2 N m s/rad on the joints, as MuJoCo Menagerie's Go2 has.
    ``latency``: 30 ms of actuation latency (the mock's effect), which the adapter finds from
    the torque the motors report and leads the plan by, through the end of the lowering (whose
    last rows, led past, would be the table's target-less done rows: ``after_s`` keeps some)."""
    if not POLICY.is_file():
        pytest.skip("no shipped policy")
    from sim.effects import ActuationLatency, ViscousFriction

    pb = load_policy(POLICY)
    idx = model_indices("FL")
    track = {}
    for adapt in (False, True):
        plant = ViscousFriction(2.0) if effect == "damping" else ActuationLatency(0.03)
        run, health = run_policy_a2i(pb, "FL", settle_s=SETTLE, periods=1, after_s=0.2,
                                     effects=[plant], adapt=adapt)
        assert not health.fell and not health.lifted_foot_touched
        track[adapt] = run.tracking_rmse[idx]
    assert np.all(track[True] < 0.8 * track[False]), track


def test_the_lifted_leg_moves_on_deploys_frames_not_once_per_tick():
    """run_policy_a2i plays deploy's five LowCmd_ frames per tick: with one frame per tick (the
    target held 20 ms) the kp-80 lifted leg of v17 lags its plan in a staircase that shakes
    the tripod (docs/deploy.md)."""
    v17 = POLICY.with_name("tripod_go2_v17.onnx")
    if not v17.is_file():
        pytest.skip("no v17")
    pb = load_policy(v17)
    idx = model_indices("FL")
    out = {}
    for n in (1, 5):
        run, health = run_policy_a2i(pb, "FL", settle_s=SETTLE, periods=1, after_s=0.0,
                                     commands_per_tick=n)
        assert not health.fell and not health.lifted_foot_touched
        track = float(np.sqrt(np.mean(run.tracking_rmse[idx] ** 2)))
        rate = float(np.sqrt(np.mean(np.sum(run.base_gyro ** 2, axis=1))))
        out[n] = track, rate
    assert out[1][0] > 2 * out[5][0], out
    assert out[1][1] > 1.2 * out[5][1], out
    with pytest.raises(ValueError, match="commands_per_tick"):
        run_policy_a2i(pb, "FL", commands_per_tick=3)  # 20 physics steps do not split in 3


def test_a_lift_the_tip_guard_calls_off_gives_no_run_and_the_robot_stands():
    """run_policy_a2i plays deploy's tip guard (deploy.tip_guard): a limit no lift can keep
    calls this one off in its lift; the leg goes back down and the robot stays up. (v1 levels
    the body as it lifts; v26 tips it by a tenth of a degree.)"""
    v26 = POLICY.with_name("tripod_go2_v26.onnx")
    if not v26.is_file():
        pytest.skip("no v26")
    pb = load_policy(v26)
    run, health = run_policy_a2i(pb, "FL", settle_s=SETTLE, periods=1, after_s=0.0,
                                 max_tip=0.01)
    assert run is None
    assert "tipped" in health.aborted and "in lift" in health.aborted
    assert not health.fell and health.body_contacts == ()


def test_a_knee_on_the_floor_before_the_hold_fails_the_run(monkeypatch):
    """Bodies other than the feet are watched over the whole run, as the evaluation watches a
    training episode: a thigh on the floor while the body shifts (here a simulator that reports
    one for the first 0.1 s) is in the run's health, though tilt and the lifted foot are judged
    over hold and excitation only."""
    from sim.go2 import Go2Sim

    if not POLICY.is_file():
        pytest.skip("no shipped policy")
    real = Go2Sim.body_contacts
    monkeypatch.setattr(Go2Sim, "body_contacts",
                        lambda self: ["RR_thigh"] if self.time < 0.1 else real(self))
    _, health = run_policy_a2i(load_policy(POLICY), "FL", settle_s=SETTLE, periods=1,
                               after_s=0.0)
    assert "RR_thigh" in health.body_contacts  # (v1's rear calves brush the floor beside
    assert not health.lifted_foot_touched      # their feet as it shifts, 20 mm from them)


@pytest.mark.parametrize("seen", [1.0, 0.0])
def test_excitation_seen_0_shows_the_policy_the_lifted_leg_held(monkeypatch, seen):
    """run_policy_a2i plays the schedule's ``excitation_seen`` as deploy does: at 0, over the
    excitation's ticks (and only there) the policy observes the lifted leg at the plan's ``q0``,
    still; at 1 never."""
    if not POLICY.is_file():
        pytest.skip("no shipped policy")
    import policy_train.policy_motion as pm
    from calib.joints import sdk_indices

    pb = load_policy(POLICY)
    pb.meta.schedule = dataclasses.replace(pb.meta.schedule, excitation_seen=seen)
    idx, q0 = sdk_indices("FL"), pb.meta.schedule.plan("FL").q0
    held = []
    build = pm.build_observation

    def watch(terms, signals, *a, **kw):
        held.append(np.array_equal(signals["joint_pos"][idx], q0)
                    and not np.any(signals["joint_vel"][idx]))
        return build(terms, signals, *a, **kw)

    monkeypatch.setattr(pm, "build_observation", watch)
    _, health = run_policy_a2i(pb, "FL", settle_s=SETTLE, periods=1, after_s=0.0)
    assert not health.fell
    excite_ticks = dataclasses.replace(pb.meta.schedule, periods=1).plan("FL").duration * 50
    assert abs(sum(held) - (excite_ticks if seen == 0 else 0)) <= 2, (sum(held), excite_ticks)
