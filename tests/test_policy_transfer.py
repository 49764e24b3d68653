"""Transfer check (policy_train.transfer): scenarios draw the effects and disturbances they name,
the disturbance reaches the policy's observation and the base, an episode on sim.go2 is scored
as the evaluation scores, the CLI writes its page, and two runs compare episode by episode."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("mujoco")
pytest.importorskip("onnxruntime")

from calib.joints import LEGS
from policy_train.cli import main
from policy_train.config import DRConfig
from policy_train.policy_motion import Disturbance
from policy_train.transfer import (
    SCENARIOS,
    EpisodeResult,
    Scenario,
    compare,
    load_results,
    merge_results,
    physics_rates,
    push_summary,
    render_markdown,
    run_episode,
    summarise,
    write_results,
)
from sim.effects import (
    ActuationLatency,
    Armature,
    Backlash,
    CoulombFriction,
    FloorSlope,
    FloorSoftness,
    FootFriction,
    FootPayload,
    LinkMass,
    MotorStrength,
    ViscousFriction,
)
from sim.free_base_run import PushRecord, RunHealth, free_base_sim, push_record
from sim.go2 import Go2Sim, SimConfig

POLICY = Path(__file__).resolve().parents[1] / "policies" / "tripod_go2_v7.onnx"


def test_a_payload_adds_its_kilograms_and_moves_the_centre_of_mass_as_drawn():
    """On the compiled base, which holds the bodies fused into it (the URDF's hip rotors):
    scaling the spec's base by 1 + m / 7.277 added 0.951 m kg and moved the centre of mass 5 %
    short of the draw."""
    plain = free_base_sim().model.body("base")
    for add, shift in ((4.0, (0.03, -0.02, 0.01)), (-1.0, (0.0, 0.0, 0.0))):
        loaded = Go2Sim(SimConfig(base="free", effects=[LinkMass(1.0, "base", shift,
                                                                  add_kg=add)])).model.body("base")
        assert loaded.mass[0] - plain.mass[0] == pytest.approx(add, abs=1e-9)
        np.testing.assert_allclose(loaded.ipos - plain.ipos, shift, atol=1e-9)
    with pytest.raises(ValueError, match="payload"):
        LinkMass(1.1, "base", add_kg=1.0)


def test_training_scenario_draws_the_training_ranges():
    dr = DRConfig()
    for seed in range(20):
        effects, dist = SCENARIOS["training"].draw(np.random.default_rng(seed))
        kinds = {type(e): e for e in effects}
        assert set(kinds) == {LinkMass, FootFriction, MotorStrength, ActuationLatency}
        add = kinds[LinkMass].add_kg
        assert kinds[LinkMass].scale == 1.0
        assert dr.base_mass_add[0] - 1e-9 <= add <= dr.base_mass_add[1] + 1e-9
        assert np.all(np.abs(kinds[LinkMass].com_shift) <= np.array(dr.base_com_offset) + 1e-12)
        assert dr.friction[0] <= kinds[FootFriction].mu <= dr.friction[1]
        assert 0 <= kinds[ActuationLatency].seconds <= 0.020 + 1e-12
        assert dist.noise_joint_vel == dr.noise_joint_vel and dist.push_vel == dr.push_vel
    # the scenarios beyond the training change what they say and keep the rest
    effects, dist = SCENARIOS["joint_friction"].draw(np.random.default_rng(0))
    f = [e for e in effects if isinstance(e, CoulombFriction)]
    assert len(f) == 1 and np.all((f[0].value >= 0.2) & (f[0].value <= 0.6))
    effects, _ = SCENARIOS["damped_joints"].draw(np.random.default_rng(0))
    joint = {type(e): float(np.unique(e.value).item()) for e in effects
             if isinstance(e, (ViscousFriction, Armature, CoulombFriction))}
    assert joint == {ViscousFriction: 2.0, Armature: 0.01, CoulombFriction: 0.2}  # Menagerie's
    slopes = [e for e in SCENARIOS["slope"].draw(np.random.default_rng(0))[0]
              if isinstance(e, FloorSlope)]
    assert len(slopes) == 1 and np.radians(2) <= slopes[0].angle <= np.radians(5)
    soft = [e for e in SCENARIOS["soft_floor"].draw(np.random.default_rng(0))[0]
            if isinstance(e, FloorSoftness)]
    assert len(soft) == 1 and 0.03 <= soft[0].timeconst <= 0.045
    nodes = [e for e in SCENARIOS["foot_imus"].draw(np.random.default_rng(0))[0]
             if isinstance(e, FootPayload)]
    assert sorted(n.leg for n in nodes) == sorted(LEGS)
    assert all(0.03 <= n.kg <= 0.08 for n in nodes) and len({n.kg for n in nodes}) == 4
    effects = SCENARIOS["backlash"].draw(np.random.default_rng(0))[0]
    assert isinstance(effects[-1], Backlash) and len(effects[-1].indices) == 12
    assert np.all((effects[-1].half_width >= 0.003) & (effects[-1].half_width <= 0.01))
    dist = SCENARIOS["body_imu"].draw(np.random.default_rng(0))[1]
    assert 1.0 <= np.degrees(np.linalg.norm(dist.imu_tilt)) <= 2.0
    assert np.all(np.abs(dist.gyro_bias) <= 0.02) and np.any(dist.gyro_bias)
    # all at once: every one of those effects, each within the lower half of its own range,
    # on top of the training's
    effects, dist = SCENARIOS["all_at_once"].draw(np.random.default_rng(0))
    kinds = {type(e) for e in effects}
    assert {CoulombFriction, ViscousFriction, Armature, FloorSlope, FootPayload, Backlash,
            ActuationLatency, MotorStrength} <= kinds and FloorSoftness not in kinds
    assert isinstance(effects[-1], Backlash) and np.all(effects[-1].half_width <= 0.0065)
    assert np.radians(2) <= next(e for e in effects if isinstance(e, FloorSlope)).angle \
        <= np.radians(3.5)
    assert all(0.03 <= e.kg <= 0.055 for e in effects if isinstance(e, FootPayload))
    assert 1.0 <= np.degrees(np.linalg.norm(dist.imu_tilt)) <= 1.5
    assert np.all(np.abs(dist.gyro_bias) <= 0.01) and dist.push_vel == dr.push_vel
    assert SCENARIOS["training"].draw(np.random.default_rng(0))[1].imu_tilt == (0.0, 0.0, 0.0)
    assert SCENARIOS["quiet"].draw(np.random.default_rng(0))[1].noise_joint_vel == 0.0
    assert SCENARIOS["noisy"].draw(np.random.default_rng(0))[1].noise_joint_vel == 2 * 1.5
    effects, dist = SCENARIOS["nominal"].draw(np.random.default_rng(0))
    assert effects == [] and dist.push_vel == 0 and dist.noise_ang_vel == 0
    # the same generator state draws the same episode
    a = SCENARIOS["training"].draw(np.random.default_rng(5))
    b = SCENARIOS["training"].draw(np.random.default_rng(5))
    assert repr(a[0]) == repr(b[0]) and a[1] == b[1]


def test_scenarios_keep_their_places():
    # an episode's draws are seeded by its scenario's place: the committed results of earlier
    # policies are paired with new runs (compare) only while the places stay put
    assert list(SCENARIOS)[:11] == ["nominal", "training", "heavy", "slippery", "late", "weak",
                                    "joint_friction", "shoves", "noisy", "quiet", "damped_joints"]
    assert list(SCENARIOS)[11:] == ["slope", "soft_floor", "foot_imus", "backlash",
                                     "body_imu", "all_at_once", "rotor_joints",
                                     "default_cone", "weak_default_cone"]


def test_a_body_imu_mounted_off_reads_the_body_in_its_own_frame():
    """Disturbance.imu_tilt turns what the policy and the feed-forward sense: a level body on an
    IMU rolled 2 deg reads gravity rolled the other way; a yaw turn leaves gravity alone but
    moves the rate between axes; the bias is added after."""
    tilt = np.radians(2.0)
    d = Disturbance(imu_tilt=(tilt, 0.0, 0.0), gyro_bias=(0.0, 0.0, 0.01))
    s = d.noisy({"base_ang_vel": np.array([0.0, 0.0, 0.1]),
                 "projected_gravity": np.array([0.0, 0.0, -1.0])}, np.random.default_rng(0))
    np.testing.assert_allclose(s["projected_gravity"], [0.0, -np.sin(tilt), -np.cos(tilt)],
                               atol=1e-12)
    np.testing.assert_allclose(s["base_ang_vel"], [0.0, 0.1 * np.sin(tilt),
                                                   0.1 * np.cos(tilt) + 0.01], atol=1e-12)
    yaw = Disturbance(imu_tilt=(0.0, 0.0, 0.3))
    np.testing.assert_allclose(yaw.imu_frame(np.array([0.0, 0.0, -1.0])), [0.0, 0.0, -1.0])
    np.testing.assert_allclose(yaw.imu_frame(np.array([1.0, 0.0, 0.0])),
                               [np.cos(0.3), -np.sin(0.3), 0.0], atol=1e-12)
    # the same reading as the effect library's IMU effects give the diagnoser and the mock
    from deploy.observation import projected_gravity
    from sim.effects import ImuBias, ImuMisalignment, apply_imu_effects

    rv, bias = (0.01, -0.02, 0.03), (0.004, -0.002, 0.001)
    q = np.array([[np.cos(0.1), np.sin(0.1), 0.0, 0.0]])  # the body rolled 11.5 deg
    w = np.array([[0.1, -0.2, 0.3]])
    gyro, _, q_imu = apply_imu_effects([ImuMisalignment(rv), ImuBias(bias)], np.zeros(1), w,
                                       np.zeros((1, 3)), q)
    true = {"base_ang_vel": w[0], "projected_gravity": projected_gravity(q[0])}
    s = Disturbance(imu_tilt=rv, gyro_bias=bias).noisy(true, np.random.default_rng(0))
    np.testing.assert_allclose(s["base_ang_vel"], gyro[0], atol=1e-12)
    np.testing.assert_allclose(s["projected_gravity"], projected_gravity(q_imu[0]), atol=1e-12)
    with pytest.raises(ValueError, match="imu_tilt"):
        Disturbance(imu_tilt=(0.6, 0.0, 0.0))
    with pytest.raises(ValueError, match="gyro_bias"):
        Disturbance(gyro_bias=(0.0, np.nan, 0.0))


def test_disturbance_noise_is_bounded_and_only_on_sensed_terms():
    d = Disturbance(noise_ang_vel=0.2, noise_gravity=0.05, noise_joint_pos=0.01,
                    noise_joint_vel=1.5)
    rng = np.random.default_rng(0)
    sig = {"base_ang_vel": np.zeros(3), "projected_gravity": np.array([0, 0, -1.0]),
           "joint_pos": np.ones(12), "joint_vel": np.zeros(12), "commands": np.zeros(3)}
    outs = [d.noisy(sig, rng) for _ in range(200)]
    for key, a in (("base_ang_vel", 0.2), ("projected_gravity", 0.05), ("joint_pos", 0.01),
                   ("joint_vel", 1.5)):
        dev = np.array([o[key] - sig[key] for o in outs])
        assert np.abs(dev).max() <= a and np.abs(dev).max() > 0.9 * a
    assert all(o["commands"] is sig["commands"] for o in outs)
    with pytest.raises(ValueError, match="noise_joint_vel"):
        Disturbance(noise_joint_vel=-1.0)
    with pytest.raises(ValueError, match="push_interval"):
        Disturbance(push_interval=(5.0, 1.0))


def test_push_changes_the_free_base_velocity_only():
    sim = free_base_sim()
    v0 = sim.data.qvel[:6].copy()
    sim.push([0.3, -0.2, 0.0])
    np.testing.assert_allclose(sim.data.qvel[:3] - v0[:3], [0.3, -0.2, 0.0])
    np.testing.assert_allclose(sim.data.qvel[3:6], v0[3:6])
    sim.step(5)  # and the physics goes on from it
    assert sim.data.qvel[0] > 0.2
    with pytest.raises(ValueError, match="free base"):
        Go2Sim(SimConfig(base="fixed", floor=False)).push([0.1, 0, 0])


def test_a_push_record_puts_the_capture_point_where_the_pendulum_says():
    sim = free_base_sim()  # standing at rest on four feet
    qvel = sim.data.qvel.copy()
    still = push_record(sim, "settle", [0.0, 0.0, 0.0], LEGS)
    assert still.capture_margin_m == pytest.approx(still.com_margin_m, abs=1e-9)
    assert 0.08 < still.com_margin_m < 0.2 and still.stance == tuple(LEGS)
    com, _ = sim.com_state()
    feet = sim.foot_positions  # FL, FR, RL, RR
    # the right edge (FR-RR): the centre of mass's distance to it, by hand
    a, b = feet[1, :2], feet[3, :2]
    e = (b - a) / np.linalg.norm(b - a)
    d_right = abs(e[0] * (com[1] - a[1]) - e[1] * (com[0] - a[0]))
    w0 = np.sqrt(9.81 / (com[2] - (feet[:, 2].mean() - 0.022)))
    right = push_record(sim, "settle", [0.0, -0.5, 0.0], LEGS)
    assert right.capture_margin_m == pytest.approx(d_right - 0.5 / w0, abs=2e-3)
    assert right.dv == (0.0, -0.5) and right.t_s == sim.time
    # on three feet the margin is the triangle's, smaller; a hard shove leaves it
    tri = push_record(sim, "excite", [0.0, 0.0, 0.0], ["FR", "RL", "RR"])
    assert tri.com_margin_m < still.com_margin_m and tri.stance == ("FR", "RL", "RR")
    assert push_record(sim, "excite", [0.0, -1.5, 0.0], ["FR", "RL", "RR"]).capture_margin_m < 0
    np.testing.assert_array_equal(sim.data.qvel, qvel)  # recorded, not given
    with pytest.raises(ValueError, match="three feet"):
        push_record(sim, "excite", [0.0, 0.0, 0.0], ["FR", "RR"])
    # and it goes through the episodes file with its run
    h = RunHealth(3.0, 1.0, 0.3, 0.3, (), "FL", False, 0.1, False, 20.0, fall_time_s=None,
                  pushes=(right,))
    assert RunHealth.from_dict(json.loads(json.dumps(h.to_dict()))) == h


def _push(t, margin, phase="excite", com=0.08):
    return PushRecord(t, phase, (0.1, -0.5), ("FR", "RL", "RR"), com, margin).to_dict()


def test_push_summary_puts_each_fall_down_to_the_push_before_it():
    eps = [
        # a push outside, the fall 0.8 s later; the push after the fall is not counted
        EpisodeResult("shoves", "FL", 0, False, ["fall"], fall_time_s=7.9,
                      pushes=[_push(7.1, -0.03), _push(12.0, -0.5)]),
        # held: one push just outside, one inside; one before the lift is not on three feet
        EpisodeResult("shoves", "FL", 1, True, pushes=[_push(2.0, -0.2, "shift"),
                                                       _push(9.0, -0.006), _push(15.0, 0.04)]),
        # a fall 3 s after a push inside: no push in the 1.5 s before it
        EpisodeResult("shoves", "FL", 2, False, ["fall"], fall_time_s=8.0,
                      pushes=[_push(5.0, 0.05)]),
        # a fall 1 s after a push inside
        EpisodeResult("shoves", "FR", 0, False, ["fall"], fall_time_s=10.0,
                      pushes=[_push(9.0, 0.01)]),
        # a push that met the centre of mass already outside: it was falling, no push's doing
        EpisodeResult("shoves", "FR", 1, False, ["fall"], fall_time_s=4.6,
                      pushes=[_push(4.2, -0.07, com=-0.02)]),
        EpisodeResult("nominal", "FL", 0, True),  # no pushes: no row
    ]
    s = push_summary(eps)
    assert list(s) == ["shoves"]
    x = s["shoves"]
    assert (x["pushes"], x["outside"], x["outside_fell"]) == (6, 3, 2)
    assert (x["falls"], x["falls_outside"], x["falls_inside"], x["falls_unpushed"]) == (4, 1, 1, 2)
    assert x["held_min_cm"] == pytest.approx(-0.6)
    page = render_markdown(eps, "p.onnx", 1)
    assert "| shoves | 6 | 3 (2) | 1 / 1 / 2 | -0.6 |" in page
    # not every scenario ran: the line that produced the page names the ones that did
    assert "`a2i-train transfer p.onnx --scenarios shoves,nominal --episodes" in page
    assert "| nominal |" in page.split("capture region")[0]
    assert "| nominal |" not in page.split("capture region")[1]


def test_progress_speaks_every_minute_on_a_slow_run_and_says_what_is_left(monkeypatch):
    from policy_train import transfer

    clock = iter([0.0, 30.0, 70.0, 80.0, 100.0, 1000.0, 1000.0])  # t0, one per call, the end
    # the module's own clock only: pytest's goes on
    monkeypatch.setattr(transfer, "time", SimpleNamespace(time=lambda: next(clock)))

    def fake_run(*args):
        progress = args[7]
        for done in (1, 2, 3, 7, 40):
            progress(done, 40)
        return []

    monkeypatch.setattr(transfer, "run_transfer", fake_run)
    lines = []
    transfer.timed_run("p.onnx", ["nominal"], ["FL"], 40, 1, 1, log=lines.append)
    # 1/40 (30 s): under 10 % and a minute; 2/40 speaks by the minute (70 s); 3/40 does not
    # (10 s and 2.5 % on); 7/40 by the 10 % (12.5 % on, 30 s later); 40/40 always, nothing left
    assert lines == ["  2/40 episodes, 70 s, about 1330 s left",
                     "  7/40 episodes, 100 s, about 471 s left", "  40/40 episodes, 1000 s"]


@pytest.fixture(scope="module")
def episodes():
    if not POLICY.is_file():
        pytest.skip("no shipped policy")
    nominal = run_episode(str(POLICY), SCENARIOS["nominal"], "FL", 0, periods=1)
    late = run_episode(str(POLICY), SCENARIOS["late"], "FL", 0, periods=1)
    return nominal, late


def test_nominal_episode_holds_the_tripod_with_the_evaluations_figures(episodes):
    nominal, _ = episodes
    assert nominal.success and nominal.causes == []
    assert 0 < nominal.tilt_rms_deg < 3
    assert 0 < nominal.rate_rms < 0.2
    assert 0 < nominal.track_rmse < 0.05
    assert 1.0 <= nominal.cn < 1.3


def test_perturbed_episode_differs_and_summarises(episodes):
    nominal, late = episodes
    # 20-40 ms of latency and the training's noise move the base much more than nothing does
    assert (not late.success) or late.rate_rms > 2 * nominal.rate_rms
    # the training's pushes, each recorded with the feet it met (three while FL is up)
    assert nominal.pushes == [] and late.pushes
    for p in late.pushes:
        lifted = p["phase"] in ("lift", "hold", "excite", "lower")
        assert p["stance"] == (["FR", "RL", "RR"] if lifted else list(LEGS))
        assert max(abs(v) for v in p["dv"]) <= DRConfig().push_vel
    assert late.fall_time_s is None or "fall" in late.causes
    failed = EpisodeResult("late", "RL", 1, False, ["fall", "RR_calf on floor"])
    brushed = EpisodeResult("soft_floor", "FL", 0, False, ["FR_calf on floor"],
                            calf_reach_mm={"FR": 24.6})
    s = summarise([nominal, late, failed, brushed])
    assert s["nominal"]["success"] == 1.0 and s["nominal"]["legs"] == {"FL": 1.0}
    assert s["late"]["episodes"] == 2 and s["late"]["causes"]["fall"] >= 1
    assert s["late"]["legs"]["RL"] == 0.0
    assert s["soft_floor"]["calf_reach_mm"] == {"FR_calf on floor": 24.6}
    page = render_markdown([nominal, late, failed, brushed], "p.onnx", 1)
    assert "| nominal | no perturbation | 1 | 100 % |" in page
    assert "| FR_calf on floor 1 (25 mm) |" in page  # where the calf touched, from its foot
    # the counted causes: the made-up failure's plus whatever the simulated episode had
    assert f"RR_calf on floor {1 + late.causes.count('RR_calf on floor')}" in page


def test_cli_writes_page_and_episodes(tmp_path, capsys):
    if not POLICY.is_file():
        pytest.skip("no shipped policy")
    out = tmp_path / "transfer.md"
    rc = main(["transfer", str(POLICY), "--scenarios", "nominal", "--legs", "RR",
               "--episodes", "1", "--workers", "1", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "1/1 episodes" in text and "nominal" in text
    page = out.read_text()
    assert "| nominal |" in page and "RR" in page
    rows = json.loads(out.with_suffix(".json").read_text())["episodes"]
    assert len(rows) == 1 and rows[0]["leg"] == "RR" and rows[0]["success"] is True
    # one scenario of all: the line names it, and re-runs what the page holds
    assert (f"`a2i-train transfer {POLICY} --scenarios nominal --episodes 1 --seed 1 --legs RR`"
            in page)
    # a scenario added to the page: both rows, as one command over both would write them
    rc = main(["transfer", str(POLICY), "--scenarios", "slope", "--legs", "RR", "--episodes",
               "1", "--workers", "1", "--out", str(out), "--append"])
    assert rc == 0
    rows = json.loads(out.with_suffix(".json").read_text())["episodes"]
    assert [r["scenario"] for r in rows] == ["nominal", "slope"]
    page = out.read_text()
    assert "| nominal |" in page and "| slope |" in page
    assert f"`a2i-train transfer {POLICY} --scenarios nominal,slope --episodes 1" in page
    # a page of another seed is refused before anything runs
    rc = main(["transfer", str(POLICY), "--scenarios", "slope", "--legs", "RR", "--episodes",
               "1", "--seed", "2", "--out", str(out), "--append"])
    assert rc == 2 and "the page has seed 1, not 2" in capsys.readouterr().err


def test_merge_results_adds_and_replaces_scenarios_in_their_order():
    old = _run({"weak": [True, False], "training": [True, True]})
    page = ({"policy": "p.onnx", "seed": 1, "elapsed_s": 10.0}, old)
    new = _run({"nominal": [False, False], "weak": [True, True]})
    merged = merge_results(page, new, "p.onnx", 1, ["FL"], 2)
    assert [(r.scenario, r.success) for r in merged] == [
        ("nominal", False), ("nominal", False), ("training", True), ("training", True),
        ("weak", True), ("weak", True)]
    for args, what in [(("q.onnx", 1, ["FL"], 2), "policy"), (("p.onnx", 2, ["FL"], 2), "seed"),
                       (("p.onnx", 1, ["FL", "RR"], 2), "legs"),
                       (("p.onnx", 1, ["FL"], 3), "episodes"),
                       (("p.onnx", 1, ["FL"], 2, None, 5.0), "tip guard")]:
        with pytest.raises(ValueError, match=f"the page has {what}"):
            merge_results(page, new, *args)


def test_a_page_of_another_mujoco_is_refused_by_the_version_that_saved_its_model():
    """The model's hash is of the model as MuJoCo saves it, so another MuJoCo changes it with
    the physics unchanged: the refusal names both versions, so the reason is plain. A page
    written before the version was recorded still takes episodes of its own model's hash."""
    old = _run({"weak": [True, True]})
    was = {"path": "go2/scene.xml", "sha256": "a" * 64, "mujoco": "4.0.0"}
    page = ({"policy": "p.onnx", "seed": 1, "elapsed_s": 1.0, "model": was}, old)
    now = dict(was, sha256="b" * 64, mujoco="4.0.1")
    with pytest.raises(ValueError, match=r"\(aaaaaaaaaaaaaaaa, MuJoCo 4\.0\.0\), not "
                                         r"go2/scene\.xml \(bbbbbbbbbbbbbbbb, MuJoCo 4\.0\.1\)"):
        merge_results(page, [], "p.onnx", 1, ["FL"], 2, now)
    unversioned = {k: v for k, v in was.items() if k != "mujoco"}
    merged = merge_results(({**page[0], "model": unversioned}, old), [], "p.onnx", 1, ["FL"], 2,
                           was)
    assert len(merged) == 2
    assert "sha256 aaaaaaaaaaaaaaaa, MuJoCo 4.0.0;" in render_markdown(old, "p.onnx", 1,
                                                                       model=was)


def test_with_the_tip_guard_a_called_off_lift_is_lifted_again_and_reported():
    """--max-tip plays deploy's tip guard: a limit no lift keeps calls the first lift off, the
    episode's second lift (1 s more shift) is called off too, and the robot stays up."""
    v26 = POLICY.with_name("tripod_go2_v26.onnx")
    if not v26.is_file():
        pytest.skip("no v26")
    r = run_episode(str(v26), SCENARIOS["nominal"], "FL", 0, periods=1, max_tip=0.01)
    assert not r.success and "tipped" in r.retried
    assert r.causes == ["lift called off (tipping)"]
    page = render_markdown([r], str(v26), 1, max_tip=0.01)
    assert "--max-tip 0.01" in page and "tip guard at 0.01 deg" in page


def test_a_page_records_the_tip_limits_of_each_phase(tmp_path):
    from deploy.tip_guard import TipLimits

    res = _run({"nominal": [True, False]})
    write_results(res, tmp_path / "p.md", "p.onnx", 1, 1.0, None, (5.0, 8.0))
    text = (tmp_path / "p.md").read_text()
    assert "--max-tip 5,8" in text and "5 deg lifting, 8 deg holding" in text
    meta, eps = load_results(tmp_path / "p.json")
    assert meta["max_tip"] == TipLimits(5.0, 8.0) and len(eps) == 2
    # a page with one limit for both phases (before the phases had their own) reads the same
    merge_results((dict(meta, max_tip=TipLimits.of(5.0)), eps), [], "p.onnx", 1, ["FL"], 2,
                  None, 5.0)
    with pytest.raises(ValueError, match="the page has tip guard 5,8, not 5"):
        merge_results((meta, eps), [], "p.onnx", 1, ["FL"], 2, None, 5.0)


def test_the_lift_gate_holds_the_shift_of_a_lift_the_floor_would_tip():
    """v43's one `slope` fall of the URDF's 80 (FL, episode 7: the floor falling away towards
    the lifted corner, the centre of mass 38 mm outside the tripod when the lift began) holds
    once the gate has held its shift until the body stands over the tripod."""
    v43 = POLICY.with_name("tripod_go2_v43.onnx")
    if not v43.is_file():
        pytest.skip("no v43")
    alone = run_episode(str(v43), SCENARIOS["slope"], "FL", 7, periods=1)
    assert not alone.success and "fall" in alone.causes and alone.lift_wait_s == 0.0
    gated = run_episode(str(v43), SCENARIOS["slope"], "FL", 7, periods=1, lift_gate=0.02)
    assert gated.success and gated.retried is None and 0.2 < gated.lift_wait_s < 1.0


def test_a_lift_the_gate_never_opens_is_not_lifted_and_tried_again():
    """A margin no stance reaches: the shift is held its wait, the lift called off with the
    foot on the floor, and the episode's second lift (1 s more shift) called off too."""
    v43 = POLICY.with_name("tripod_go2_v43.onnx")
    if not v43.is_file():
        pytest.skip("no v43")
    r = run_episode(str(v43), SCENARIOS["nominal"], "FL", 0, periods=1, lift_gate=(0.15, 0.1))
    assert not r.success and r.retried.startswith("centre of mass")
    assert r.causes == ["lift called off (centre of mass)"]  # no fall, no foot down
    page = render_markdown([r], str(v43), 1, lift_gate=(0.15, 0.1))
    assert "--lift-gate 150,0.1" in page and "150 mm inside the stance triangle" in page


def test_a_page_records_its_lift_gate(tmp_path):
    from deploy.lift_gate import DEFAULT_GATE

    res = _run({"nominal": [True, False]})
    write_results(res, tmp_path / "p.md", "p.onnx", 1, 1.0, None, None, DEFAULT_GATE)
    text = (tmp_path / "p.md").read_text()
    assert "--lift-gate 20,2" in text and "held longer in 0 of 2 episodes" in text
    meta, eps = load_results(tmp_path / "p.json")
    assert meta["lift_gate"] == DEFAULT_GATE and meta["max_tip"] is None
    merge_results((meta, eps), [], "p.onnx", 1, ["FL"], 2, None, None, (0.02, 2.0))
    with pytest.raises(ValueError, match="the page has lift gate 20,2, not None"):
        merge_results((meta, eps), [], "p.onnx", 1, ["FL"], 2)
    write_results(res, tmp_path / "q.md", "p.onnx", 1, 1.0)  # the policy alone: as before
    assert "lift_gate" not in json.loads((tmp_path / "q.json").read_text())
    assert load_results(tmp_path / "q.json")[0]["lift_gate"] is None


def test_physics_rates_fit_deploys_frames_into_the_tick():
    assert physics_rates(0.001) == (5, 2)  # the mock: 5 frames a tick, 500 Hz records
    assert physics_rates(0.002) == (5, 1)
    assert physics_rates(0.0025) == (4, 1)
    assert physics_rates(0.005) == (4, 1)  # the training's 200 Hz: a frame a step
    assert physics_rates(0.02) == (1, 1)
    for bad, why in [(0.003, "does not divide the policy's 0.02 s tick"),
                     (0.0, "must be in"), (0.04, "must be in"), (float("nan"), "must be in")]:
        with pytest.raises(ValueError, match=why):
            physics_rates(bad)


def test_a_page_records_its_physics_step(tmp_path, capsys):
    res = _run({"nominal": [True, False]})
    write_results(res, tmp_path / "p.md", "p.onnx", 1, 1.0, timestep=0.005)
    text = (tmp_path / "p.md").read_text()
    assert "--timestep 0.005`" in text
    assert "(200 Hz, the motor PD law computed explicitly every step" in text
    meta, eps = load_results(tmp_path / "p.json")
    assert meta["timestep"] == 0.005
    merge_results((meta, eps), [], "p.onnx", 1, ["FL"], 2, timestep=0.005)
    with pytest.raises(ValueError, match=r"the page has physics step \(s\) 0.005, not 0.001"):
        merge_results((meta, eps), [], "p.onnx", 1, ["FL"], 2)
    write_results(res, tmp_path / "q.md", "p.onnx", 1, 1.0)  # the mock's 1 kHz: as before
    assert "timestep_s" not in json.loads((tmp_path / "q.json").read_text())
    assert "(1 kHz, free base" in (tmp_path / "q.md").read_text()
    assert load_results(tmp_path / "q.json")[0]["timestep"] == 0.001
    # the CLI refuses a step that does not divide the tick before anything runs
    if POLICY.is_file():
        assert main(["transfer", str(POLICY), "--timestep", "0.003", "--no-write"]) == 2
        assert "does not divide the policy's 0.02 s tick" in capsys.readouterr().err
    # two pages of one model at two steps compare under names that tell them apart
    write_results(res, tmp_path / "q.md", "p.onnx", 1, 1.0)
    assert main(["compare", str(tmp_path / "q.json"), str(tmp_path / "p.json")]) == 0
    assert "URDF at 1 ms" in capsys.readouterr().out


def test_the_deploy_policys_gains_need_a_short_step_or_damped_joints_at_200_hz():
    """docs/policy-format.md, "Motors": the JSON's hip and thigh kd (8) and the lifted leg's
    gains, computed explicitly every 5 ms, diverge on the URDF's bare joints (no rotor
    inertia, no damping); with Menagerie's joints (damping MuJoCo integrates implicitly, rotor
    inertia) the same 200 Hz runner holds the lift."""
    v51 = POLICY.with_name("tripod_go2_v51.onnx")
    if not v51.is_file():
        pytest.skip("no v51")
    bare = run_episode(str(v51), SCENARIOS["nominal"], "FL", 0, periods=1, timestep=0.005)
    assert not bare.success and "fall" in bare.causes
    joints = Scenario("menagerie_joints", "Menagerie's joint model", joint_damping=(2.0, 2.0),
                      armature=(0.01, 0.01), joint_friction=(0.2, 0.2))
    damped = run_episode(str(v51), joints, "FL", 0, periods=1, timestep=0.005)
    assert damped.success and damped.tilt_rms_deg < 3 and damped.rate_rms < 0.1
    assert damped.track_rmse < 0.05


def test_hips_at_kd_5_stand_a_200_hz_explicit_step_on_unitrees_joints():
    """docs/policy-format.md, "Motors": on the joints of Unitree's own MuJoCo Go2 (rotor
    inertia, next to no damping) a PD law computed explicitly every 5 ms, as unitree_rl_gym's
    sim-to-sim runner does when set to the issue's 200 Hz, drops v51 (hips at kd 8) and holds
    the candidate v54 (hips at kd 5)."""
    v51 = POLICY.with_name("tripod_go2_v51.onnx")
    v54 = POLICY.parent / "candidates" / "tripod_go2_v54.onnx"
    if not (v51.is_file() and v54.is_file()):
        pytest.skip("no v51 or v54")
    rj = SCENARIOS["rotor_joints"]  # its joints alone, none of the training's perturbations
    joints = Scenario("unitree_joints", "Unitree's joint model", joint_damping=rj.joint_damping,
                      armature=rj.armature, joint_friction=rj.joint_friction)
    fell = run_episode(str(v51), joints, "FL", 0, periods=1, timestep=0.005)
    assert not fell.success and "fall" in fell.causes
    held = run_episode(str(v54), joints, "FL", 0, periods=1, timestep=0.005)
    assert held.success and held.tilt_rms_deg < 3 and held.rate_rms < 0.1
    assert held.track_rmse < 0.05


def test_weak_motors_on_mujocos_default_cone_drop_v51_and_hold_v56_and_v57():
    """docs/policy-format.md, "Contacts": on MuJoCo's default friction cone (pyramidal,
    impratio 1) a nominal FL lift on motors at 65 % drops v51, which holds it on the model's
    elliptic cone, and holds the candidate v56 and the deploy policy v57, whose front lifts
    were refined with half their episodes on that cone."""
    v51 = POLICY.with_name("tripod_go2_v51.onnx")
    v56 = POLICY.parent / "candidates" / "tripod_go2_v56.onnx"
    v57 = POLICY.with_name("tripod_go2_v57.onnx")
    if not (v51.is_file() and v56.is_file() and v57.is_file()):
        pytest.skip("no v51, v56 or v57")
    own = Scenario("weak_motors", "motors at 65 %", motor_strength=(0.65, 0.65))
    default = dataclasses.replace(own, friction_cone="pyramidal")
    held = run_episode(str(v51), own, "FL", 0, periods=1)
    assert held.success and held.rate_rms < 0.1
    fell = run_episode(str(v51), default, "FL", 0, periods=1)
    assert not fell.success and "lifted foot down" in fell.causes
    for refined in (v56, v57):
        kept = run_episode(str(refined), default, "FL", 0, periods=1)
        assert kept.success and kept.tilt_rms_deg < 3 and kept.rate_rms < 0.1
        assert kept.track_rmse < 0.05


@pytest.mark.parametrize("argv, message", [
    (["transfer"], "needs the policy"),
    (["transfer", "POLICY", "--scenarios", "moon"], "unknown scenario(s) moon"),
    (["transfer", "POLICY", "--episodes", "0"], "must be >= 1"),
    (["transfer", "POLICY", "--max-tip", "5,x"], "tip limits are LIFT[,HOLD] deg"),
    (["transfer", "POLICY", "--max-tip", "5,95"], "(hold) must be in (0, 90) deg"),
    (["transfer", "POLICY", "--lift-gate", "20,x"], "the lift gate is MM[,S] or off"),
    (["transfer", "POLICY", "--lift-gate", "300"], "margin_m must be in [-0.2, 0.2]"),
    (["transfer", "nowhere.onnx"], "no such file"),
])
def test_cli_bad_input_is_one_line_exit_2(argv, message, capsys):
    argv = [str(POLICY) if a == "POLICY" else a for a in argv]
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1]


def _run(outcomes: dict[str, list[bool]], leg: str = "FL") -> list[EpisodeResult]:
    return [EpisodeResult(s, leg, e, ok, [] if ok else ["fall"])
            for s, oks in outcomes.items() for e, ok in enumerate(oks)]


def test_compare_pairs_the_same_draws():
    a = _run({"training": [True] * 8 + [False, False], "weak": [True, False, True, False]})
    # b ran 3 episodes of "weak" (the 4th of a has no partner) and an extra scenario
    b = _run({"training": [False] * 8 + [True, False], "weak": [True, True, False],
              "late": [True]})
    rows = {r.scenario: r for r in compare(a, b)}
    assert list(rows) == ["training", "weak", "all"]
    t = rows["training"]
    assert (t.pairs, t.both, t.only_a, t.only_b, t.neither) == (10, 0, 8, 1, 1)
    assert t.success_a == 0.8 and t.success_b == 0.1
    assert t.p == pytest.approx(2 * (1 + 9) / 2 ** 9)  # exact sign test, 8 against 1
    w = rows["weak"]
    assert (w.pairs, w.both, w.only_a, w.only_b, w.neither) == (3, 1, 1, 1, 0) and w.p == 1.0
    assert rows["all"].pairs == 13 and rows["all"].only_a == 9
    with pytest.raises(ValueError, match="share no episode"):
        compare(a, _run({"late": [True]}))


def test_cli_compare(tmp_path, capsys):
    a = _run({"training": [True, True, False]}, "RR")
    write_results(a, tmp_path / "a.md", "policies/x_v1.onnx", 1)
    write_results(_run({"training": [False, True, False]}, "RR"), tmp_path / "b.md",
                  "policies/x_v2.onnx", 1)
    assert main(["compare", str(tmp_path / "a.json"), str(tmp_path / "b.json")]) == 0
    out = capsys.readouterr().out
    assert "| scenario | pairs | x_v1 | x_v2 |" in out
    assert "| training | 3 | 67 % | 33 % | 1 / 1 / 0 / 1 | 1 |" in out
    write_results(a, tmp_path / "c.md", "policies/x_v3.onnx", 2)
    (tmp_path / "d.json").write_text("{}")
    for other, message in (("c.json", "different seeds (1 and 2)"),
                           ("d.json", "not a transfer episodes file")):
        assert main(["compare", str(tmp_path / "a.json"), str(tmp_path / other)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0]
