"""`a2i-train tripod --iterations 2` trains, checkpoints and exports a loadable ONNX + JSON
(tiny env); `a2i-train eval` runs it through onnxruntime."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from deploy.lift_schedule import PHASES, LiftSchedule
from deploy.observation import build_observation


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    d = tmp_path_factory.mktemp("tripod")
    cmd = [sys.executable, "-m", "policy_train.cli", "tripod", "--iterations", "2",
           "--num-envs", "8", "--plans-per-leg", "1", "--steps-per-env", "8",
           "--save-interval", "1", "--run-dir", str(d / "run"), "--export", str(d / "pol")]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert "it     1" in p.stdout and "it     2" in p.stdout
    return d, p.stdout


def test_checkpoints_and_progress(exported):
    d, out = exported
    assert (d / "run" / "model_1.pt").exists() and (d / "run" / "model_2.pt").exists()
    assert "steps/s" in out


def test_resume_in_phase_2_stays_there(exported):
    """A planned total that puts phase 2 later than the checkpoint must not send a run that
    was already playing calibration motions back to tripod-only training."""
    d, out = exported
    assert "stage 2" in next(x for x in out.splitlines() if x.startswith("it     2"))
    cmd = [sys.executable, "-m", "policy_train.cli", "tripod", "--resume", str(d / "run" / "model_2.pt"),
           "--iterations", "1", "--total-iterations", "40", "--num-envs", "8",
           "--plans-per-leg", "1", "--steps-per-env", "8", "--run-dir", str(d / "resumed")]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    line = next(x for x in p.stdout.splitlines() if x.startswith("it     3"))
    assert "stage 2" in line


def test_export_averages_the_checkpoints_of_one_run(exported, tmp_path):
    """Several checkpoints export as one policy whose weights are their mean."""
    import torch

    from policy_train.config import TrainConfig
    from policy_train.export import _actor_from_checkpoint, average_checkpoints

    d, _ = exported
    ckpts = [str(d / "run" / f"model_{i}.pt") for i in (1, 2)]
    p = subprocess.run([sys.executable, "-m", "policy_train.cli", "export", *ckpts,
                        "--out", str(tmp_path / "avg")], capture_output=True, text=True,
                       timeout=240, check=False)
    assert p.returncode == 0, p.stderr[-2000:]
    meta = json.loads((tmp_path / "avg.json").read_text())
    assert meta["averaged_iterations"] == [1, 2] and meta["iterations"] == 2
    loaded = [torch.load(c, weights_only=False, map_location="cpu") for c in ckpts]
    w = [c["actor_state_dict"]["mlp.0.weight"] for c in loaded]
    assert not torch.equal(w[0], w[1])  # two PPO updates apart: the mean is a third network
    mean = average_checkpoints(loaded)
    assert torch.allclose(mean["actor_state_dict"]["mlp.0.weight"], (w[0] + w[1]) / 2)
    x = np.random.default_rng(3).normal(0, 1, (4, 49)).astype(np.float32)
    y = ort.InferenceSession(str(tmp_path / "avg.onnx"),
                             providers=["CPUExecutionProvider"]).run(None, {"obs": x})[0]
    actor = _actor_from_checkpoint(mean, TrainConfig.from_dict(mean["train_config"]))
    with torch.no_grad():
        assert np.allclose(y, actor(torch.from_numpy(x)).numpy(), atol=1e-5)
    other = dict(loaded[0], train_config=json.loads(json.dumps(loaded[0]["train_config"])))
    other["train_config"]["ppo"]["actor_hidden"] = [8]
    with pytest.raises(ValueError, match="one run only"):
        average_checkpoints([other, loaded[1]])
    # a run resumed with another save interval is still one run (v7's 3800-4069 and 4100-4550)
    resaved = dict(loaded[0], train_config={**loaded[0]["train_config"], "ppo": {
        **loaded[0]["train_config"]["ppo"], "save_interval": 7}})
    average_checkpoints([resaved, loaded[1]])


def test_onnx_single_file_dynamic_batch(exported):
    d, _ = exported
    m = onnx.load(str(d / "pol.onnx"))
    assert not any(t.data_location == onnx.TensorProto.EXTERNAL for t in m.graph.initializer)
    assert [i.name for i in m.graph.input] == ["obs"] and [o.name for o in m.graph.output] == ["actions"]
    s = ort.InferenceSession(str(d / "pol.onnx"), providers=["CPUExecutionProvider"])
    for n in (1, 5):
        y = s.run(None, {"obs": np.zeros((n, 49), np.float32)})[0]
        assert y.shape == (n, 12)


def test_json_meets_the_contract(exported):
    d, _ = exported
    meta = json.loads((d / "pol.json").read_text())
    for k in ("schema_version", "name", "onnx", "created_utc", "commit", "seed", "iterations",
              "train_config", "control_dt", "physics_dt", "decimation", "joint_order",
              "default_pose", "kp", "kd", "action", "soft_limits", "observation",
              "lift_command", "lift_schedule", "evaluation"):
        assert k in meta, k
    assert meta["schema_version"] == 1 and meta["onnx"] == "pol.onnx" and meta["iterations"] == 2
    assert meta["joint_order"][0] == "FR_hip" and len(meta["default_pose"]) == 12
    assert meta["control_dt"] == pytest.approx(0.02) and meta["decimation"] == 4
    assert meta["action"]["mode"] == "delta_target"
    lin = meta["observation"]["terms"][0]
    assert lin["name"] == "base_lin_vel" and lin["source"] == "zero"
    sched = LiftSchedule.from_metadata(meta["lift_schedule"])
    assert sched.periods >= 1
    # deploy plays the excitation with the clearance the policy was trained on
    assert sched.ground_clearance == meta["train_config"]["env"]["ground_clearance"]
    sig = {t["name"]: np.zeros(t["size"]) for t in meta["observation"]["terms"]}
    assert build_observation(meta["observation"], sig).shape == (49,)


def test_eval_runs_on_export(exported, tmp_path):
    d, _ = exported
    from policy_train.evaluate import evaluate_policy

    out = tmp_path / "policy.md"
    r = evaluate_policy(d / "pol.onnx", episodes=1, legs=("FL",), results_path=out,
                        log=lambda s: None)
    assert set(r["legs"]) == {"FL"} and 0.0 <= r["legs"]["FL"]["success"] <= 1.0
    x = r["legs"]["FL"]
    failed = round((1 - x["success"]) * x["episodes"])
    assert sum(x["first_failure"].values()) == sum(x["first_failure_phase"].values()) == failed
    assert len(x["calf_clearance_mm"]) == 2
    assert out.exists() and "| FL |" in out.read_text()
    assert json.loads((d / "pol.json").read_text())["evaluation"]["legs"]["FL"]["episodes"] == 1


def test_eval_refuses_a_json_that_stands_elsewhere_than_training(exported, tmp_path, capsys):
    """Deploy stands the robot at the JSON's default_pose, the evaluation at the training's: a
    JSON moved off it is refused with one line, before any episode is played."""
    import shutil

    from policy_train.cli import main

    d, _ = exported
    meta = json.loads((d / "pol.json").read_text())
    meta["default_pose"][1] += 0.1  # FR's thigh, SDK order
    (tmp_path / "moved.json").write_text(json.dumps(meta))
    shutil.copy(d / "pol.onnx", tmp_path / "moved.onnx")
    assert main(["eval", str(tmp_path / "moved.onnx"), "--episodes", "1", "--no-write"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "default_pose" in err[0] and "deploy" in err[0]


def test_eval_page_of_a_candidate_leaves_the_deploy_policys_page_alone(exported, tmp_path,
                                                                      monkeypatch):
    """policy.md is the page of the policy deploy picks (the newest in policies/); any other
    policy's page is policy_<name>.md."""
    from policy_train.evaluate import results_page

    d, _ = exported
    monkeypatch.chdir(tmp_path)
    (tmp_path / "policies" / "candidates").mkdir(parents=True)
    meta = json.loads((d / "pol.json").read_text())
    for where, name, created in [("policies", "tripod_go2_v2", "2026-01-02T00:00:00Z"),
                                 ("policies", "tripod_go2_v1", "2026-01-01T00:00:00Z"),
                                 ("policies/candidates", "tripod_go2_v3", "2026-01-03T00:00:00Z")]:
        (tmp_path / where / f"{name}.json").write_text(json.dumps(
            {**meta, "name": name, "onnx": f"{name}.onnx", "created_utc": created}))
    assert results_page("policies/tripod_go2_v2.onnx") == Path("docs/results/policy.md")
    assert results_page(tmp_path / "policies/tripod_go2_v1.onnx") == Path(
        "docs/results/policy_v1.md")
    assert results_page("policies/candidates/tripod_go2_v3.onnx") == Path(
        "docs/results/policy_v3.md")
    assert results_page(d / "pol.onnx") == Path("docs/results/policy_pol.md")


def test_nominal_eval_goes_to_the_json_then_the_report(exported, tmp_path):
    d, _ = exported
    from policy_train.evaluate import evaluate_policy

    out = tmp_path / "policy.md"
    r = evaluate_policy(d / "pol.onnx", episodes=1, legs=("RR",), results_path=out,
                        log=lambda s: None, nominal=True)
    assert r["domain_randomisation"] is False and not out.exists()
    meta = json.loads((d / "pol.json").read_text())
    assert meta["evaluation_nominal"]["legs"]["RR"]["episodes"] == 1
    evaluate_policy(d / "pol.onnx", episodes=1, legs=("RR",), results_path=out, log=lambda s: None)
    text = out.read_text()
    # the randomised evaluation, its failures, the nominal one
    assert "Without domain randomisation" in text and text.count("| RR |") == 3


def test_dr_off_evaluates_without_the_group_and_writes_nothing(exported, tmp_path):
    d, _ = exported
    from policy_train.config import DRConfig
    from policy_train.evaluate import evaluate_policy

    dr = DRConfig().without("pushes", "obs_noise")
    assert dr.push_vel == 0.0 and dr.noise_joint_vel == 0.0 and dr.latency_steps == (0, 4)
    with pytest.raises(ValueError, match="unknown randomisation group"):
        DRConfig().without("wind")
    before = (d / "pol.json").read_text()
    out = tmp_path / "policy.md"
    r = evaluate_policy(d / "pol.onnx", episodes=1, legs=("FL",), results_path=out,
                        log=lambda s: None, dr_off=("latency",))
    assert r["dr_off"] == ["latency"] and not out.exists()
    assert (d / "pol.json").read_text() == before


def test_dr_settings_apply_over_the_randomisation_and_write_nothing(exported, tmp_path):
    d, _ = exported
    from policy_train.config import DRConfig
    from policy_train.evaluate import WEAK_STIFFNESS, evaluate_policy, evaluation_env

    dr = DRConfig().with_settings({"motor_strength": [0.7, 0.8], "push_vel": 0.0})
    assert dr.motor_strength == (0.7, 0.8) and dr.push_vel == 0.0 and dr.friction == (0.4, 1.25)
    with pytest.raises(ValueError, match="unknown randomisation field"):
        DRConfig().with_settings({"wind": 1.0})
    import argparse

    from policy_train.cli import _dr_setting
    assert _dr_setting("floor_tilt_deg=0,5") == ("floor_tilt_deg", (0.0, 5.0))
    for bad in ("floor_tilt_deg=0,45", "floor_tilt_deg=5,2", "floor_tilt_deg=3"):
        with pytest.raises(argparse.ArgumentTypeError, match="floor_tilt_deg"):
            _dr_setting(bad)
    assert _dr_setting("floor_timeconst=0.03,0.045") == ("floor_timeconst", (0.03, 0.045))
    assert _dr_setting("floor_timeconst=0,0") == ("floor_timeconst", (0.0, 0.0))
    for bad in ("floor_timeconst=0.005,0.03", "floor_timeconst=0.03,0.2", "floor_timeconst=0,0.03"):
        with pytest.raises(argparse.ArgumentTypeError, match="floor_timeconst"):
            _dr_setting(bad)
    assert _dr_setting("default_cone=0.5") == ("default_cone", 0.5)
    for bad in ("default_cone=1.5", "default_cone=-0.1", "default_cone=0,1"):
        with pytest.raises(argparse.ArgumentTypeError, match="default_cone"):
            _dr_setting(bad)
    meta = json.loads((d / "pol.json").read_text())
    env, _ = evaluation_env(meta, ("FL",), 8, seed=1, dr_set={"motor_strength": (0.7, 0.8)})
    assert np.all((env.strength >= 0.7) & (env.strength <= 0.8))
    before = (d / "pol.json").read_text()
    out = tmp_path / "policy.md"
    # kp scale <= 1.15 times strength <= 0.78: every episode's motors are soft
    r = evaluate_policy(d / "pol.onnx", episodes=2, legs=("FL",), results_path=out,
                        log=lambda s: None, dr_set={"motor_strength": (0.7, 0.78)})
    assert 1.15 * 0.78 < WEAK_STIFFNESS
    assert r["dr_set"] == {"motor_strength": [0.7, 0.78]} and not out.exists()
    assert (d / "pol.json").read_text() == before
    x = r["legs"]["FL"]
    assert x["success_weak"] == {"episodes": 2, "success": x["success"]}
    assert 0.0 <= x["stance_calves_on_clamp"] <= 1.0
    with pytest.raises(ValueError, match="need the randomisation on"):
        evaluate_policy(d / "pol.onnx", episodes=1, legs=("FL",), nominal=True,
                        dr_set={"push_vel": 0.0}, write=False, log=lambda s: None)


def test_evaluation_draws_the_standard_ranges_unless_asked_for_the_training_ones(exported,
                                                                                  tmp_path):
    """A policy trained on wider ranges is evaluated on ``DRConfig``'s defaults, as every other
    policy; ``randomisation="training"`` draws its own and writes nothing."""
    d, _ = exported
    from policy_train.config import DRConfig
    from policy_train.evaluate import evaluate_policy, evaluation_env

    meta = json.loads((d / "pol.json").read_text())
    meta["train_config"]["env"]["dr"].update(latency_steps=[0, 6], joint_friction=[0.1, 0.4])
    std, _ = evaluation_env(meta, ("FL",), 4, seed=1)
    assert std.cfg.dr == DRConfig() and np.all(std.batch.expanded("dof_frictionloss") == 0)
    own, _ = evaluation_env(meta, ("FL",), 4, seed=1, randomisation="training")
    assert own.cfg.dr.latency_steps == (0, 6) and own.cfg.dr.joint_friction == (0.1, 0.4)
    assert np.all(own.batch.expanded("dof_frictionloss")[:, 6:] >= 0.1)
    with pytest.raises(ValueError, match="unknown randomisation"):
        evaluation_env(meta, ("FL",), 1, seed=1, randomisation="wide")
    before = (d / "pol.json").read_text()
    out = tmp_path / "policy.md"
    r = evaluate_policy(d / "pol.onnx", episodes=1, legs=("FL",), results_path=out,
                        log=lambda s: None, randomisation="training")
    assert r["randomisation"] == "training" and not out.exists()
    assert (d / "pol.json").read_text() == before


def test_table_shows_the_held_figures_and_reads_older_evaluations():
    from policy_train.evaluate import format_table

    row = {"episodes": 100, "success": 0.8, "falls": 10, "other_contact": 12,
           "lifted_foot_touch": 4, "tilt_rms_deg": 2.5, "ang_rate_rms": 0.45, "track_rmse": 0.02,
           "cn_median": 1.15, "cn_p90": 1.25}
    new = format_table({"legs": {"FL": {**row, "tilt_rms_deg_held": 1.9,
                                        "ang_rate_rms_held": 0.081}}})
    assert "| 2.50 ok (1.90) | 0.450 MISS (0.081) |" in new
    old = format_table({"legs": {"FL": row}})  # stored before the held figures existed
    assert "| 2.50 ok | 0.450 MISS |" in old


def test_failures_name_the_first_cause_and_older_evaluations_have_none():
    from policy_train.evaluate import failure_cause, format_failures

    assert failure_cause(True, ["RL_calf_col1"], "FL", True) == "fall"
    assert failure_cause(False, ["FL_calf_col0", "RL_calf_col1"], "FL", False) == "stance calf"
    assert failure_cause(False, ["FL_calf_col0", "base_col0"], "FL", False) == "lifted leg"
    assert failure_cause(False, ["RR_hip_col0"], "FL", True) == "stance hip/thigh"
    assert failure_cause(False, ["base_col0"], "RL", False) == "body"
    assert failure_cause(False, [], "RL", True) == "lifted foot down"
    row = {"first_failure": {"stance calf": 9, "fall": 1}, "first_failure_phase": {"excite": 10},
           "calf_clearance_mm": [2.7, -1.5]}
    t = format_failures({"legs": {"FL": row}})  # stored before the clamp and soft motors
    assert "| FL | 10 | stance calf 9, fall 1 | excite 10 | 2.7 (-1.5) |  |  |" in t
    t = format_failures({"legs": {"FL": {**row, "stance_calves_on_clamp": 0.984,
                                         "success_weak": {"episodes": 26, "success": 0.8846}},
                                  "RL": {**row, "stance_calves_on_clamp": 0.5,
                                         "success_weak": {"episodes": 0, "success": float("nan")}}}})
    assert "| 2.7 (-1.5) | 98 % | 88 % of 26 |" in t and "| 2.7 (-1.5) | 50 % | - |" in t
    assert format_failures({"legs": {"FL": {"success": 0.8}}}) == ""


def test_cli_missing_inputs_exit_2_with_one_line(tmp_path):
    from policy_train.cli import main

    for argv in (["eval", str(tmp_path / "none.onnx")],
                 ["export", str(tmp_path / "none.pt"), "--out", str(tmp_path / "p")],
                 ["tripod", "--resume", str(tmp_path / "none.pt"), "--iterations", "1"],
                 # a save interval of 0 divided by zero after the first iteration; nan minutes
                 # meant no limit
                 ["tripod", "--save-interval", "0"], ["tripod", "--max-minutes", "nan"],
                 ["tripod", "--num-envs", "-4"], ["distill", "--max-minutes", "-1"],
                 ["tripod", "--excitation-seen", "2"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2
    assert not list(tmp_path.iterdir())


def test_tripod_device_is_checked_before_anything_is_built(tmp_path):
    """--device: cpu, or a GPU this machine has; anything else exits 1 with one line and
    writes nothing."""
    import torch

    from policy_train.cli import main
    from policy_train.runner import check_device

    assert check_device("cpu") == "cpu"
    bad = ["tpu", "cuda:7"] + ([] if torch.cuda.is_available() else ["cuda"])
    for dev in bad:
        with pytest.raises(SystemExit) as exc:
            main(["tripod", "--device", dev, "--iterations", "1", "--run-dir", str(tmp_path / "r")])
        assert str(exc.value).startswith("a2i-train tripod: ") and "\n" not in str(exc.value)
    assert not list(tmp_path.iterdir())


def test_mirrored_legs_export_plays_the_other_side_mirrored(exported, tmp_path):
    """`export --mirror-legs FR`: the graph answers an FR lift with the mirror image of what
    the network does for the mirrored (FL) observation, and anything else unchanged."""
    import torch

    from policy_train.cli import main
    from policy_train.symmetry import ActionMirror, Mirror, policy_terms

    d, _ = exported
    assert main(["export", str(d / "run" / "model_2.pt"), "--out", str(tmp_path / "m"),
                 "--mirror-legs", "FR"]) == 0
    meta = json.loads((tmp_path / "m.json").read_text())
    assert meta["mirrored_legs"] == {"FR": "FL"}
    plain = ort.InferenceSession(str(d / "pol.onnx"), providers=["CPUExecutionProvider"])
    mirr = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    terms, scale = policy_terms(meta["observation"]["terms"])
    m_obs, m_act = Mirror(terms, scale), ActionMirror()
    rng = np.random.default_rng(2)
    x = rng.normal(size=(5, 49)).astype(np.float32)
    run = lambda s, o: s.run(None, {"obs": o})[0]
    for leg, value in meta["lift_command"].items():
        x[:, -1] = value * scale
        got = run(mirr, x)
        if leg == "FR":
            mo = m_obs(torch.from_numpy(x)).numpy()
            want = m_act(torch.from_numpy(run(plain, mo))).numpy()
        else:
            want = run(plain, x)
        np.testing.assert_allclose(got, want, atol=1e-5, err_msg=leg)
    with pytest.raises(SystemExit):
        main(["export", str(d / "run" / "model_2.pt"), "--out", str(tmp_path / "x"),
              "--mirror-legs", "XX"])


def test_lift_gains_go_to_the_json_and_the_evaluation_plays_them(exported, tmp_path):
    """`export --lift-gains 80,2`: the JSON's lift_schedule carries them, the rest as the
    training's, and the evaluation's lifted leg is driven with them."""
    from policy_train.cli import main
    from policy_train.evaluate import evaluation_env

    d, _ = exported
    assert main(["export", str(d / "run" / "model_2.pt"), "--out", str(tmp_path / "g"),
                 "--lift-gains", "80,2"]) == 0
    meta = json.loads((tmp_path / "g.json").read_text())
    plain = json.loads((d / "pol.json").read_text())
    assert (meta["lift_schedule"]["kp"], meta["lift_schedule"]["kd"]) == (80.0, 2.0)
    assert {**meta["lift_schedule"], "kp": 40.0, "kd": 1.0} == plain["lift_schedule"]
    assert LiftSchedule.from_metadata(meta["lift_schedule"]).kp == 80.0
    env, _ = evaluation_env(meta, ("FL",), 1, seed=1)
    assert (env.cfg.lift_kp, env.cfg.lift_kd) == (80.0, 2.0)
    # the page says which gains it played, and that they are not the training's
    from policy_train.evaluate import evaluate_policy
    out = tmp_path / "policy.md"
    evaluate_policy(tmp_path / "g.onnx", episodes=1, legs=("FL",), results_path=out,
                    log=lambda s: None)
    assert "lifted leg at kp 80 / kd 2; trained at 40 / 1" in out.read_text()
    evaluate_policy(d / "pol.onnx", episodes=1, legs=("FL",), results_path=out,
                    log=lambda s: None)
    assert "lifted leg at kp 40 / kd 1)" in out.read_text()


def test_derive_sets_the_deploy_gains_and_the_evaluation_plays_them(exported, tmp_path):
    """`derive --gains 23,0.575`: the same network byte for byte, the JSON's kp / kd (what
    deploy sends) set, its source named, its evaluation dropped; the evaluation plays those
    gains and says they are not the training's."""
    from policy_train.cli import main
    from policy_train.evaluate import evaluate_policy, evaluation_env

    d, _ = exported
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "g"),
                 "--gains", "23,0.575"]) == 0
    assert (tmp_path / "g.onnx").read_bytes() == (d / "pol.onnx").read_bytes()
    meta = json.loads((tmp_path / "g.json").read_text())
    src = json.loads((d / "pol.json").read_text())
    assert meta["kp"] == [23.0] * 12 and meta["kd"] == [0.575] * 12
    assert meta["derived_from"]["policy"] == "pol.onnx" and meta["derived_from"]["kp"] == src["kp"]
    assert (meta["name"], meta["onnx"], meta["evaluation"]) == ("g", "g.onnx", {})
    assert meta["lift_schedule"] == src["lift_schedule"]
    env, _ = evaluation_env(meta, ("FL",), 1, seed=1)
    assert (env.cfg.kp, env.cfg.kd) == (23.0, 0.575)
    plain, _ = evaluation_env(src, ("FL",), 1, seed=1)
    assert (plain.cfg.kp, plain.cfg.kd) == (20.0, 0.5)
    out = tmp_path / "policy.md"
    evaluate_policy(tmp_path / "g.onnx", episodes=1, legs=("FL",), results_path=out,
                    log=lambda s: None)
    assert "joint gains (kp 23 / kd 0.575; trained at 20 / 0.5)" in " ".join(
        out.read_text().split())
    # a source deploy would not read is refused, and nothing is written
    del meta["kp"]
    (tmp_path / "bad.json").write_text(json.dumps(meta))
    (tmp_path / "bad.onnx").write_bytes(b"")
    assert main(["derive", str(tmp_path / "bad.onnx"), "--out", str(tmp_path / "h"),
                 "--gains", "23,0.575"]) == 2
    assert not (tmp_path / "h.json").exists()


def test_derive_sets_gains_per_joint_type_and_the_evaluation_plays_each_joints(exported,
                                                                            tmp_path):
    """`derive --gains 29,0.725/29,0.725/23,0.575`: hips, thighs and calves of every leg get
    their own gains; the evaluation's environment drives each joint with its own (the JSON's
    SDK order put into the model's), and the page names them."""
    from calib.joints import sdk_to_model
    from policy_train.cli import main
    from policy_train.evaluate import evaluate_policy, evaluation_env

    d, _ = exported
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "g"),
                 "--gains", "29,0.725/29,0.725/23,0.575"]) == 0
    meta = json.loads((tmp_path / "g.json").read_text())
    assert meta["kp"] == [29.0, 29.0, 23.0] * 4 and meta["kd"] == [0.725, 0.725, 0.575] * 4
    # twelve different gains: each reaches its own joint's actuator
    meta["kp"] = [20.0 + i for i in range(12)]
    env, _ = evaluation_env(meta, ("FL",), 2, seed=1, nominal=True)
    want = sdk_to_model(np.asarray(meta["kp"]))
    np.testing.assert_array_equal(env._kp, want)
    env.step(np.zeros((env.N, 12), dtype=np.float32))
    stance = np.arange(3, 12)  # model order FL, FR, RL, RR: the lifted FL may be on its schedule
    np.testing.assert_allclose(env.gainprm[:, stance, 0], np.broadcast_to(want[stance], (2, 9)))
    np.testing.assert_allclose(env.biasprm[:, stance, 2], np.broadcast_to(
        -sdk_to_model(np.asarray(meta["kd"]))[stance], (2, 9)))
    out = tmp_path / "policy.md"
    evaluate_policy(tmp_path / "g.onnx", episodes=1, legs=("FL",), results_path=out,
                    log=lambda s: None)
    assert ("joint gains (hip / thigh / calf kp 29 / 29 / 23, kd 0.725 / 0.725 / 0.575; "
            "trained at 20 / 0.5)") in " ".join(out.read_text().split())


def test_derive_sets_the_excitation_speed_within_the_trained_range(exported, tmp_path, capsys):
    """`derive --t-r 0.6`: the JSON's lift schedule plays the excitation at that time constant
    (the evaluation's plans last longer), the source's t_r named in
    ``derived_from``; a t_r outside the training's ``t_r_range`` is refused, nothing written."""
    from policy_train.cli import main
    from policy_train.evaluate import evaluation_env

    d, _ = exported
    src = json.loads((d / "pol.json").read_text())
    lo, hi = src["train_config"]["env"]["t_r_range"]
    assert lo < 0.6 < hi and src["lift_schedule"]["t_r"] < 0.6
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "g"),
                 "--t-r", "0.6"]) == 0
    meta = json.loads((tmp_path / "g.json").read_text())
    assert meta["lift_schedule"] == {**src["lift_schedule"], "t_r": 0.6}
    assert meta["derived_from"]["t_r"] == src["lift_schedule"]["t_r"]
    assert (meta["kp"], meta["kd"]) == (src["kp"], src["kd"])
    slow, _ = evaluation_env(meta, ("FL",), 1, seed=1, nominal=True)
    fast, _ = evaluation_env(src, ("FL",), 1, seed=1, nominal=True)
    # the periods stretch with t_r; the ramps into and out of them do not
    ratio = slow.lift_dur[0, 3] / fast.lift_dur[0, 3]
    assert 1.0 + 0.8 * (0.6 / src["lift_schedule"]["t_r"] - 1.0) < ratio < 0.6 / src[
        "lift_schedule"]["t_r"]
    capsys.readouterr()
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "h"),
                 "--t-r", str(hi + 0.05)]) == 2
    assert "outside" in capsys.readouterr().err and not (tmp_path / "h.json").exists()


def test_derive_sets_the_periods_no_longer_than_trained(exported, tmp_path, capsys):
    """`derive --t-r T --periods N`: a faster excitation with more periods, in the JSON's lift
    schedule (the evaluation's plans last N periods of 8 T), the source's periods named in
    ``derived_from``; an excitation longer than the training's longest (its most periods at
    its slowest t_r) is refused, nothing written."""
    from policy_train.cli import main
    from policy_train.evaluate import evaluation_env

    d, _ = exported
    src = json.loads((d / "pol.json").read_text())
    env = src["train_config"]["env"]
    lo, hi = env["t_r_range"]
    most = max(np.atleast_1d(env["train_periods"]))
    t_r = lo
    n = int(np.floor(most * hi / t_r))  # the most periods that fit at the fastest t_r
    assert n > src["lift_schedule"]["periods"]
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "g"),
                 "--t-r", str(t_r), "--periods", str(n)]) == 0
    meta = json.loads((tmp_path / "g.json").read_text())
    assert meta["lift_schedule"] == {**src["lift_schedule"], "t_r": t_r, "periods": n}
    assert meta["derived_from"]["periods"] == src["lift_schedule"]["periods"]
    more, _ = evaluation_env(meta, ("FL",), 1, seed=1, nominal=True)
    base, _ = evaluation_env(src, ("FL",), 1, seed=1, nominal=True)
    ramps = base.lift_dur[0, 3] - 8 * src["lift_schedule"]["t_r"] * src["lift_schedule"]["periods"]
    assert more.lift_dur[0, 3] == pytest.approx(ramps + 8 * t_r * n, abs=0.05)
    capsys.readouterr()
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "h"),
                 "--t-r", str(t_r), "--periods", str(n + 1)]) == 2
    assert "trained against" in capsys.readouterr().err and not (tmp_path / "h.json").exists()


def _derive_shift(d: Path, tmp_path: Path, shift: str) -> tuple[dict, float, dict]:
    """`derive --shift SHIFT` of the exported policy in ``d`` to ``tmp_path / "g"``: (the
    source's JSON, its training's shift, the derived JSON)."""
    from policy_train.cli import main

    src = json.loads((d / "pol.json").read_text())
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "g"),
                 "--shift", shift]) == 0
    return src, src["train_config"]["env"]["shift_s"], json.loads((tmp_path / "g.json").read_text())


def test_derive_sets_the_shift_no_shorter_than_trained(exported, tmp_path, capsys):
    """`derive --shift 2`: the JSON's lift schedule gives the policy 2 s to move the body before
    the lift (the evaluation plays it), the source's shift named in ``derived_from``; a shift
    shorter than the training's is refused, nothing written."""
    from policy_train.cli import main
    from policy_train.evaluate import evaluation_env

    d, _ = exported
    src, trained, meta = _derive_shift(d, tmp_path, "2")
    assert meta["lift_schedule"] == {**src["lift_schedule"], "shift": 2.0}
    assert meta["derived_from"]["shift"] == src["lift_schedule"]["shift"] == trained
    env, _ = evaluation_env(meta, ("FL",), 1, seed=1, nominal=True)
    assert env.lift_dur[0, 0] == 2.0
    from policy_train.evaluate import _derived  # the evaluation page says what derive changed

    assert _derived(meta).endswith(f"`pol.onnx`: a shift of 2 s (was {trained:g})")
    capsys.readouterr()
    for bad in (trained - 0.1, 6.0):
        assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "h"),
                     "--shift", str(bad)]) == 2
        assert "outside" in capsys.readouterr().err and not (tmp_path / "h.json").exists()


def test_derive_sets_a_shift_per_leg(exported, tmp_path, capsys):
    """`derive --shift FL=2,FR=2` (v25): those legs' lifts get 2 s, the others keep the JSON's
    shift; the evaluation plays each leg's, the page says so; a later `--shift 3` sets every
    leg's again; a leg's shift shorter than the training's, or an unknown leg, is refused."""
    from policy_train.cli import main
    from policy_train.evaluate import _derived, evaluation_env

    d, _ = exported
    src, trained, meta = _derive_shift(d, tmp_path, "FL=2,FR=2")
    assert meta["lift_schedule"] == {**src["lift_schedule"],
                                     "shift_by_leg": {"FL": 2.0, "FR": 2.0}}
    sched = LiftSchedule.from_metadata(meta["lift_schedule"])
    assert [sched.shift_of(g) for g in ("FL", "FR", "RL", "RR")] == [2.0, 2.0, trained, trained]
    env, _ = evaluation_env(meta, ("FL", "RL"), 2, seed=1, nominal=True)
    assert env.lift_dur[:, 0].tolist() == [2.0, 2.0, trained, trained]
    assert _derived(meta).endswith(f"a shift of {trained:g} s (FL 2 s, FR 2 s) (was {trained:g})")
    assert main(["derive", str(tmp_path / "g.onnx"), "--out", str(tmp_path / "h"),
                 "--shift", "3"]) == 0
    again = json.loads((tmp_path / "h.json").read_text())
    assert "shift_by_leg" not in again["lift_schedule"] and again["lift_schedule"]["shift"] == 3.0
    assert again["derived_from"]["shift_by_leg"] == {"FL": 2.0, "FR": 2.0}
    capsys.readouterr()
    argv = ["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "k"), "--shift"]
    assert main([*argv, f"RL={trained - 0.1}"]) == 2  # the policy's limit
    assert "shift 0.9 s of RL is outside" in capsys.readouterr().err
    for bad, why in (("XX=2", "unknown leg 'XX'"), ("FL=2,RR", "expected seconds")):
        with pytest.raises(SystemExit) as exc:  # argparse's
            main([*argv, bad])
        assert exc.value.code == 2 and why in capsys.readouterr().err
    assert not (tmp_path / "k.json").exists()


def test_derive_turns_the_tracking_adapter_on_and_off(exported, tmp_path):
    """`derive --adapt` (v26): the JSON's lift schedule runs the lifted leg's tracking adapter,
    the evaluation plays it and its page says so, ``derived_from`` records that the source had
    none; `--no-adapt` of the result turns it off again, the network byte for byte."""
    from policy_train.cli import main
    from policy_train.evaluate import _derived, evaluation_env

    d, _ = exported
    src = json.loads((d / "pol.json").read_text())
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "g"), "--adapt"]) == 0
    meta = json.loads((tmp_path / "g.json").read_text())
    assert meta["lift_schedule"] == {**src["lift_schedule"], "adapt": True}
    assert meta["derived_from"]["adapt"] is False
    assert _derived(meta).endswith("`pol.onnx`: the lifted leg's tracking adapter on")
    env, _ = evaluation_env(meta, ("FL",), 1, seed=1, nominal=True)
    assert env.adapter is not None
    assert main(["derive", str(tmp_path / "g.onnx"), "--out", str(tmp_path / "h"),
                 "--no-adapt"]) == 0
    off = json.loads((tmp_path / "h.json").read_text())
    assert off["lift_schedule"]["adapt"] is False and off["derived_from"]["adapt"] is True
    assert (tmp_path / "h.onnx").read_bytes() == (d / "pol.onnx").read_bytes()
    assert evaluation_env(off, ("FL",), 1, seed=1, nominal=True)[0].adapter is None


def test_derive_bounds_the_targets_lead_at_the_motors_torque(exported, tmp_path):
    """`derive --target-lead torque` (stop 75): the JSON's action holds each joint's target
    within effort / kp of its joint, the evaluation's env plays it (model order) and its page
    says so; new --gains recompute it; `--target-lead off` drops it; the network byte for byte."""
    from calib.joints import EFFORT_LIMIT, sdk_to_model
    from policy_train.cli import main
    from policy_train.evaluate import _derived, evaluation_env

    d, _ = exported
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "g"),
                 "--target-lead", "torque"]) == 0
    meta = json.loads((tmp_path / "g.json").read_text())
    want = np.tile(EFFORT_LIMIT, 4) / np.asarray(meta["kp"])
    np.testing.assert_allclose(meta["action"]["target_lead_max"], want)
    assert meta["derived_from"]["target_lead_max"] is None
    assert "target held within effort / kp" in _derived(meta)
    env, _ = evaluation_env(meta, ("FL",), 1, seed=1, nominal=True)
    np.testing.assert_allclose(env.cfg.target_lead_max, sdk_to_model(want))
    assert main(["derive", str(tmp_path / "g.onnx"), "--out", str(tmp_path / "h"),
                 "--gains", "29,8/29,8/26,1.2"]) == 0
    h = json.loads((tmp_path / "h.json").read_text())
    np.testing.assert_allclose(h["action"]["target_lead_max"][:3],
                               [23.7 / 29, 23.7 / 29, 45.43 / 26])
    assert main(["derive", str(tmp_path / "h.onnx"), "--out", str(tmp_path / "k"),
                 "--target-lead", "off"]) == 0
    k = json.loads((tmp_path / "k.json").read_text())
    assert "target_lead_max" not in k["action"]
    assert evaluation_env(k, ("FL",), 1, seed=1, nominal=True)[0].cfg.target_lead_max is None
    assert (tmp_path / "k.onnx").read_bytes() == (d / "pol.onnx").read_bytes()


def test_training_at_an_excitation_seen_and_a_target_lead_bound_exports_them(tmp_path):
    """`tripod --excitation-seen 0.5 --target-lead torque`: the run trains with the lifted leg
    half shown and each target within effort / kp of its joint (its configuration says so), and
    the export's lift schedule and action carry them, so deploy and the evaluation play the
    policy as training did."""
    from calib.joints import EFFORT_LIMIT
    from policy_train.config import TrainConfig

    cmd = [sys.executable, "-m", "policy_train.cli", "tripod", "--iterations", "1",
           "--num-envs", "8", "--plans-per-leg", "1", "--steps-per-env", "4",
           "--excitation-seen", "0.5", "--target-lead", "torque", "--run-dir",
           str(tmp_path / "run"), "--export", str(tmp_path / "pol")]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    meta = json.loads((tmp_path / "pol.json").read_text())
    assert meta["lift_schedule"]["excitation_seen"] == 0.5
    env = TrainConfig.from_dict(meta["train_config"]).env
    assert env.excitation_seen == 0.5
    np.testing.assert_allclose(meta["action"]["target_lead_max"],
                               np.tile(EFFORT_LIMIT, 4) / np.asarray(meta["kp"]))
    np.testing.assert_allclose(env.target_lead_max, np.tile(EFFORT_LIMIT, 4) / env.kp)


def test_derive_sets_how_much_of_the_excitation_is_seen(exported, tmp_path, capsys):
    """`derive --excitation-seen 0.5` (stop 67): the JSON's lift schedule shows the policy half
    of its lifted leg's excursion while it excites, the evaluation's env plays it and its page
    says so, ``derived_from`` records the source's 1; the network byte for byte; outside
    [0, 1] argparse refuses it."""
    from policy_train.cli import main
    from policy_train.evaluate import _derived, evaluation_env

    d, _ = exported
    src = json.loads((d / "pol.json").read_text())
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "v"),
                 "--excitation-seen", "0.5"]) == 0
    meta = json.loads((tmp_path / "v.json").read_text())
    assert meta["lift_schedule"] == {**src["lift_schedule"], "excitation_seen": 0.5}
    assert meta["derived_from"]["excitation_seen"] == 1.0
    assert _derived(meta).endswith("observed at 0.5 of its excursion while it excites")
    assert (tmp_path / "v.onnx").read_bytes() == (d / "pol.onnx").read_bytes()
    assert evaluation_env(meta, ("FL",), 1, seed=1, nominal=True)[0].cfg.excitation_seen == 0.5
    assert main(["derive", str(tmp_path / "v.onnx"), "--out", str(tmp_path / "w"),
                 "--excitation-seen", "1"]) == 0
    off = json.loads((tmp_path / "w.json").read_text())
    assert off["lift_schedule"]["excitation_seen"] == 1.0
    assert evaluation_env(off, ("FL",), 1, seed=1, nominal=True)[0].cfg.excitation_seen == 1.0
    capsys.readouterr()
    for bad in ("1.5", "-0.1", "x"):
        with pytest.raises(SystemExit) as exc:
            main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "z"),
                  "--excitation-seen", bad])
        assert exc.value.code == 2 and "--excitation-seen" in capsys.readouterr().err
    assert not (tmp_path / "z.json").exists()


@pytest.mark.parametrize(("extra", "hint"), [
    ([], "--gains"), (["--shift", "0"], "--shift"), (["--gains", "0,0.5"], "--gains"), (["--gains", "20"], "--gains"),
    (["--gains", "nan,1"], "--gains"), (["--gains", "29,0.7/23,0.5"], "--gains"),
    (["--gains", "29,0.7/29,0.7/0,0.5"], "--gains"), (["--lift-gains", "0,2"], "--lift-gains"),
    (["--t-r", "0"], "--t-r"), (["--t-r", "x"], "--t-r"), (["--stand", "0"], "--stand"),
    (["--stand", "5"], "--stand"), (["--stand", "x"], "--stand"),
    (["--stand", "Hold"], "--stand"), (["--target-lead", "on"], "--target-lead")])
def test_bad_derive_exits_with_one_line(extra, hint, exported, tmp_path, capsys):
    from policy_train.cli import main

    d, _ = exported
    with pytest.raises(SystemExit) as exc:
        main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "g"), *extra])
    assert exc.value.code not in (0, None)
    # argparse: exit 2 and one "error:" line; a missing choice: SystemExit with its line
    err = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    lines = err if exc.value.code == 2 else [str(exc.value.code)]
    assert len(lines) == 1 and hint in lines[0]
    assert not (tmp_path / "g.json").exists()


@pytest.mark.parametrize("value", ["80", "0,2", "80,-1", "a,b", "nan,1", "inf,2"])
def test_bad_lift_gains_exit_2_with_one_line(value, exported, tmp_path, capsys):
    from policy_train.cli import main

    d, _ = exported
    with pytest.raises(SystemExit) as exc:
        main(["export", str(d / "run" / "model_2.pt"), "--out", str(tmp_path / "g"),
              f"--lift-gains={value}"])
    assert exc.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(err) == 1 and "--lift-gains" in err[0]
    assert not (tmp_path / "g.json").exists()


@pytest.mark.parametrize(("option", "value", "hint"), [
    *[("--lift-leg-weights", w, "FL,FR,RL,RR") for w in ("1,2", "1,1,1,-1", "0,0,0,0", "a,b,c,d")],
    *[("--dr", v, "--dr") for v in ("joint_friction", "nope=1", "joint_friction=0.4,0.1",
                                     "latency_steps=0,1.5", "push_vel=-1", "friction=0.3",
                                     "enabled=0")],
    ("--threads", "0", "--threads"), ("--critic-warmup", "-1", "--critic-warmup"),
    ("--init-std", "0", "--init-std"), ("--learning-rate", "0", "--learning-rate"),
    ("--calf-margin", "-0.5", "--calf-margin"),
    *[("--reward", v, "--reward") for v in ("ang_vel_xy", "nope=1", "ang_vel_xy=x",
                                             "ang_vel_xy=nan", "track_sigma=0")],
    *[("--gains", v, "--gains") for v in ("29", "29,8/29,8", "0,1", "29,-1")],
    ("--lift-gains", "80", "--lift-gains"),
    *[("--calf-margin-ramp", v, "--calf-margin-ramp") for v in ("-0.1", "-0.1,0", "x,3",
                                                                 "0.6,3", "-0.1,2.5")]])
def test_bad_tripod_option_exits_2_with_one_line(option, value, hint, capsys):
    from policy_train.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["tripod", option, value, "--iterations", "1"])
    assert exc.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(err) == 1 and hint in err[0]


@pytest.mark.parametrize(("extra", "hint"), [
    (["--dr", "nope=1"], "--dr"), (["--dr", "motor_strength=0.8"], "--dr"),
    (["--nominal", "--dr", "push_vel=0"], "--nominal"),
    (["--nominal", "--dr-off", "latency"], "--nominal")])
def test_bad_eval_option_exits_2_with_one_line(extra, hint, exported, capsys):
    from policy_train.cli import main

    d, _ = exported
    with pytest.raises(SystemExit) as exc:
        main(["eval", str(d / "pol.onnx"), "--episodes", "1", *extra])
    assert exc.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(err) == 1 and hint in err[0]


def test_resume_from_averaged_checkpoints(exported):
    """``--resume A B`` continues from the newest with the mean actor, and says so in the log
    and in the checkpoints it writes."""
    import torch

    from policy_train.export import average_checkpoints

    d, _ = exported
    ckpts = [str(d / "run" / f"model_{i}.pt") for i in (1, 2)]
    cmd = [sys.executable, "-m", "policy_train.cli", "tripod", "--resume", *ckpts,
           "--iterations", "1", "--num-envs", "8", "--plans-per-leg", "1", "--steps-per-env", "8",
           "--run-dir", str(d / "averaged")]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert "(actor weights averaged)" in p.stdout
    assert any(x.startswith("it     3") for x in p.stdout.splitlines())
    out = torch.load(d / "averaged" / "model_3.pt", weights_only=False, map_location="cpu")
    assert out["resumed_from_average"] == [1, 2]
    # the Trainer starts from the mean's actor exactly (the CLI hands it the averaged dict)
    from policy_train.config import TrainConfig
    from policy_train.runner import Trainer

    mean = average_checkpoints([torch.load(c, weights_only=False, map_location="cpu")
                                for c in ckpts])
    tr = Trainer(TrainConfig.from_dict(mean["train_config"]), d / "unused", log=lambda s: None)
    tr.load(mean)
    assert tr.iteration == 2
    for k, v in tr.alg.actor.state_dict().items():
        assert torch.equal(v, mean["actor_state_dict"][k]), k
    other = torch.load(ckpts[0], weights_only=False, map_location="cpu")
    other["train_config"]["ppo"]["actor_hidden"] = [8]
    torch.save(other, d / "other_run.pt")
    bad = subprocess.run([*cmd[:5], str(d / "other_run.pt"), ckpts[1], *cmd[7:-2], "--run-dir",
                          str(d / "bad")], capture_output=True, text=True, timeout=240, check=False)
    assert bad.returncode == 2 and "one run only" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1


def test_dr_settings_change_a_resumed_runs_randomisation(exported):
    """``--dr FIELD=VALUE`` sets the run's ``DRConfig`` (on --resume, over the checkpoint's),
    and the checkpoints it writes carry it."""
    import torch

    d, _ = exported
    cmd = [sys.executable, "-m", "policy_train.cli", "tripod", "--resume",
           str(d / "run" / "model_2.pt"), "--iterations", "1", "--num-envs", "8",
           "--plans-per-leg", "1", "--steps-per-env", "8", "--run-dir", str(d / "wider"),
           "--dr", "joint_friction=0,0.3", "--dr", "latency_steps=0,6", "--dr", "push_vel=0.5",
           "--dr", "base_mass_add=-1,4", "--threads", "1",
           "--learning-rate", "2e-5"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    ckpt = torch.load(d / "wider" / "model_3.pt", weights_only=False, map_location="cpu")
    env = ckpt["train_config"]["env"]
    assert env["threads"] == 1
    assert ckpt["train_config"]["ppo"]["learning_rate"] == 2e-5
    # the adaptive schedule moves the rate by 1.5x per mini-batch from where it was set
    lr = ckpt["history"][-1]["learning_rate"]
    assert 2e-5 / 1.5 ** 20 <= lr <= 2e-5 * 1.5 ** 20
    dr = env["dr"]
    assert tuple(dr["joint_friction"]) == (0.0, 0.3) and tuple(dr["latency_steps"]) == (0, 6)
    assert dr["push_vel"] == 0.5 and tuple(dr["base_mass_add"]) == (-1.0, 4.0)
    before = torch.load(d / "run" / "model_2.pt", weights_only=False,
                        map_location="cpu")["train_config"]["env"]["dr"]
    assert tuple(dr["friction"]) == tuple(before["friction"])  # the rest is the run's own


def test_reward_weights_and_gains_replace_a_resumed_runs_own(exported):
    """``--reward TERM=WEIGHT``, ``--gains`` and ``--lift-gains`` set the run's rewards and PD
    gains over the checkpoint's; its checkpoints carry them and the exported JSON commands
    the joints with the new gains (SDK order, hip / thigh / calf on every leg)."""
    import torch

    d, _ = exported
    out = d / "stiff"
    cmd = [sys.executable, "-m", "policy_train.cli", "tripod", "--resume",
           str(d / "run" / "model_2.pt"), "--iterations", "1", "--num-envs", "8",
           "--plans-per-leg", "1", "--steps-per-env", "8", "--run-dir", str(out),
           "--reward", "ang_vel_xy=-8", "--reward", "track_sigma=0.1",
           "--gains", "29,8/29,8/26,1.2", "--lift-gains", "80,2", "--threads", "1",
           "--export", str(out / "pol")]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    env = torch.load(out / "model_3.pt", weights_only=False, map_location="cpu")[
        "train_config"]["env"]
    before = torch.load(d / "run" / "model_2.pt", weights_only=False,
                        map_location="cpu")["train_config"]["env"]
    assert env["rewards"]["ang_vel_xy"] == -8.0 and env["rewards"]["track_sigma"] == 0.1
    assert env["rewards"]["slip"] == before["rewards"]["slip"]  # the rest is the run's own
    assert tuple(env["kp"]) == (29.0, 29.0, 26.0) * 4 and tuple(env["kd"]) == (8.0, 8.0, 1.2) * 4
    assert (env["lift_kp"], env["lift_kd"]) == (80.0, 2.0)
    meta = json.loads((out / "pol.json").read_text())
    assert meta["kp"] == [29.0, 29.0, 26.0] * 4 and meta["kd"] == [8.0, 8.0, 1.2] * 4


def test_calf_margin_ramp_raises_the_clamp_each_iteration_and_resume_goes_on(exported,
                                                                               tmp_path):
    """``--calf-margin-ramp TARGET,N`` moves the calves' target clamp from the checkpoint's
    margin (0.05) to TARGET in N equal steps, one per PPO iteration; the checkpoints hold
    the margin reached, a resume without the option goes on to TARGET and stops there, and the
    export's soft limits are the clamp the policy ended on."""
    import torch

    from calib.joints import position_limits

    d, _ = exported
    common = ["--iterations", "2", "--num-envs", "8", "--plans-per-leg", "1",
              "--steps-per-env", "8", "--threads", "1"]
    cmd = [sys.executable, "-m", "policy_train.cli", "tripod", "--resume",
           str(d / "run" / "model_2.pt"), *common, "--run-dir", str(tmp_path / "a"),
           "--calf-margin-ramp=-0.07,3"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    ckpt = torch.load(tmp_path / "a" / "model_4.pt", weights_only=False, map_location="cpu")
    margins = [h["calf_upper_margin"] for h in ckpt["history"][-2:]]
    assert margins == pytest.approx([0.01, -0.03])
    assert ckpt["train_config"]["env"]["calf_upper_margin"] == pytest.approx(-0.03)
    cmd = [sys.executable, "-m", "policy_train.cli", "tripod", "--resume",
           str(tmp_path / "a" / "model_4.pt"), *common, "--run-dir", str(tmp_path / "b"),
           "--export", str(tmp_path / "ramped")]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    ckpt = torch.load(tmp_path / "b" / "model_6.pt", weights_only=False, map_location="cpu")
    assert [h["calf_upper_margin"] for h in ckpt["history"][-2:]] == pytest.approx([-0.07, -0.07])
    upper = json.loads((tmp_path / "ramped.json").read_text())["soft_limits"]["upper"]
    assert upper[2] == pytest.approx(position_limits("FR")[1][2] + 0.07)  # FR calf, SDK order
    assert upper[1] == pytest.approx(position_limits("FR")[1][1] - 0.05)  # its thigh: unmoved


def test_pack_trains_on_a_machine_without_the_urdf_or_pinocchio(tmp_path):
    """``a2i-train pack`` writes what training needs from the URDF (the compiled model, a plan
    pool, the lifted legs' inverse dynamics for the feed-forward); with them ``tripod`` runs in
    a process that can import no pinocchio and find no URDF, and without the dynamics it
    cannot (so the run does reach the feed-forward)."""
    from policy_train.cli import main

    assert main(["pack", str(tmp_path / "pack"), "--plans-per-leg", "1"]) == 0
    files = {f: str(tmp_path / "pack" / f) for f in ("go2_train.mjb", "pool.npz",
                                                     "leg_dynamics.npz")}
    code = ("import sys; sys.modules['pinocchio'] = None; import calib.robot\n"
            "def _none():\n    raise RuntimeError('no URDF here')\n"
            "calib.robot.go2_urdf_path = _none\n"
            "from policy_train.cli import main; sys.exit(main(sys.argv[1:]))")
    base = [sys.executable, "-c", code, "tripod", "--iterations", "1", "--num-envs", "32",
            "--steps-per-env", "8", "--threads", "1", "--model-file", files["go2_train.mjb"],
            "--plan-pool", files["pool.npz"]]
    p = subprocess.run([*base, "--run-dir", str(tmp_path / "a")], capture_output=True, text=True,
                       timeout=240, check=False)
    assert p.returncode != 0 and "pinocchio" in p.stderr
    p = subprocess.run([*base, "--leg-dynamics", files["leg_dynamics.npz"], "--run-dir",
                        str(tmp_path / "b")], capture_output=True, text=True, timeout=240,
                       check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert (tmp_path / "b" / "model_1.pt").exists()


def test_export_writes_the_training_state_that_resume_continues(exported, tmp_path):
    """``<name>.train.pt`` beside the ONNX: the averaged actor as exported, the newest
    checkpoint's critic and optimiser; ``--resume`` continues the exported policy from it."""
    import torch

    from policy_train.cli import main

    d, _ = exported
    ckpts = [str(d / "run" / f"model_{i}.pt") for i in (1, 2)]
    assert main(["export", *ckpts, "--out", str(tmp_path / "avg")]) == 0
    state = torch.load(tmp_path / "avg.train.pt", weights_only=False, map_location="cpu")
    newest = torch.load(ckpts[1], weights_only=False, map_location="cpu")
    assert state["iter"] == 2 and state["averaged_iterations"] == [1, 2]
    assert state["exported_as"] == "avg"
    for k, v in newest["critic_state_dict"].items():
        assert torch.equal(state["critic_state_dict"][k], v), k
    w = torch.load(ckpts[0], weights_only=False, map_location="cpu")["actor_state_dict"]
    assert torch.allclose(state["actor_state_dict"]["mlp.0.weight"],
                          (w["mlp.0.weight"] + newest["actor_state_dict"]["mlp.0.weight"]) / 2)
    p = subprocess.run([sys.executable, "-m", "policy_train.cli", "tripod", "--resume",
                        str(tmp_path / "avg.train.pt"), "--iterations", "1", "--num-envs", "8",
                        "--plans-per-leg", "1", "--steps-per-env", "8", "--run-dir",
                        str(tmp_path / "more")], capture_output=True, text=True, timeout=240,
                       check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    out = torch.load(tmp_path / "more" / "model_3.pt", weights_only=False, map_location="cpu")
    assert out["resumed_from_average"] == [1, 2]


def test_from_policy_continues_an_exported_policy(exported, tmp_path):
    """``--from-policy X.onnx``: the committed files are enough to continue training. The
    actor starts as the exported weights exactly (the mirrored graph's too), the critic
    alone learns for ``--critic-warmup`` iterations, then PPO moves the actor; a policy in
    phase 2 stays there; the checkpoints name the policy they started from."""
    import torch

    from policy_train.cli import main

    d, _ = exported
    src = torch.load(d / "run" / "model_2.pt", weights_only=False, map_location="cpu")
    assert main(["export", str(d / "run" / "model_2.pt"), "--out", str(tmp_path / "m"),
                 "--mirror-legs", "FR"]) == 0
    cmd = [sys.executable, "-m", "policy_train.cli", "tripod", "--from-policy",
           str(tmp_path / "m.onnx"), "--init-std", "0.3", "--critic-warmup", "2",
           "--iterations", "1", "--num-envs", "8", "--plans-per-leg", "1", "--steps-per-env",
           "8", "--save-interval", "1", "--run-dir", str(tmp_path / "run")]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    lines = [x for x in p.stdout.splitlines() if x.startswith("it ")]
    assert [x.split()[1] for x in lines] == ["3", "4", "5"]
    assert all("stage 2" in x for x in lines)
    assert "critic" in lines[1] and "critic" not in lines[2]
    warm = torch.load(tmp_path / "run" / "model_4.pt", weights_only=False, map_location="cpu")
    done = torch.load(tmp_path / "run" / "model_5.pt", weights_only=False, map_location="cpu")
    for k, v in src["actor_state_dict"].items():
        if k.startswith("mlp."):
            assert torch.equal(warm["actor_state_dict"][k], v), k
    std = [v for k, v in warm["actor_state_dict"].items() if "std" in k]
    assert std and all(torch.allclose(s, torch.full_like(s, 0.3)) for s in std)
    assert not torch.equal(done["actor_state_dict"]["mlp.0.weight"],
                           src["actor_state_dict"]["mlp.0.weight"])
    assert warm["warm_start"] == {"policy": "m.onnx", "averaged_iterations": None, "std": 0.3}
    assert [h.get("critic_only", False) for h in done["history"][-3:]] == [True, True, False]
    # the warm-up gathered the actor's Adam moments; the optimiser is one group again, so the
    # checkpoints resume into a fresh PPO; the exported curve keeps the policy's own records
    opt = warm["optimizer_state_dict"]
    assert len(opt["param_groups"]) == 1
    assert all(int(st["step"]) == 2 * 4 * 5 for st in opt["state"].values())  # 2 it x 4 mb x 5 ep
    p = subprocess.run([*cmd[:4], "--resume", str(tmp_path / "run" / "model_5.pt"),
                        "--iterations", "1", *cmd[12:-2], "--run-dir", str(tmp_path / "again")],
                       capture_output=True, text=True, timeout=240, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert main(["export", str(tmp_path / "run" / "model_5.pt"), "--out", str(tmp_path / "n")]) == 0
    curve = json.loads((tmp_path / "n.json").read_text())["training_history"]
    src_curve = json.loads((tmp_path / "m.json").read_text())["training_history"]
    assert curve[:len(src_curve)] == src_curve and curve[-1]["iteration"] == 3


def test_deploy_flags_name_what_a_derived_policy_deploys_apart_from_its_training():
    """The committed policies' networks trained at kp 20 / kd 0.5 and deploy derived gains: the
    flags that would train at the deploy's are named, joint types in hip/thigh/calf order;
    a policy deployed as trained needs none; gains that differ between legs are named as
    such, not as a flag value they are not."""
    from policy_train.warm_start import deploy_flags

    pol = Path(__file__).resolve().parents[1] / "policies"
    v43 = json.loads((pol / "tripod_go2_v43.json").read_text())
    assert deploy_flags(v43) == {"--gains": "29,8/29,8/26,1.2", "--lift-gains": "80,2"}
    assert deploy_flags(json.loads((pol / "tripod_go2_v7.json").read_text())) == {}
    seen = {**v43, "lift_schedule": {**v43["lift_schedule"], "excitation_seen": 0.5}}
    assert deploy_flags(seen)["--excitation-seen"] == "0.5"
    bound = {**v43, "action": {**v43["action"], "target_lead_max": [0.8] * 12}}
    assert deploy_flags(bound)["--target-lead"] == "torque"
    uneven = {**v43, "kp": [29.0] * 11 + [30.0]}
    assert deploy_flags(uneven)["--gains"].startswith("per joint")
    trained = {**v43, "train_config": {**v43["train_config"], "env": {
        **v43["train_config"]["env"], "kp": [29.0, 29.0, 26.0] * 4, "kd": [8.0, 8.0, 1.2] * 4,
        "lift_kp": 80.0, "lift_kd": 2.0}}}
    assert deploy_flags(trained) == {}


def test_from_policy_of_a_derived_policy_names_the_deploy_settings_it_does_not_train_at(
        exported, tmp_path):
    """``--from-policy`` trains at the policy's training configuration; a derived policy
    deploys other gains and what it is shown, so the run says which flags it was not given."""
    from policy_train.cli import main

    d, _ = exported
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "g"), "--gains",
                 "29,8/29,8/26,1.2", "--lift-gains", "80,2", "--excitation-seen", "0.5"]) == 0
    p = subprocess.run([sys.executable, "-m", "policy_train.cli", "tripod", "--from-policy",
                        str(tmp_path / "g.onnx"), "--lift-gains", "80,2", "--critic-warmup", "0",
                        "--iterations", "1", "--num-envs", "8", "--plans-per-leg", "1",
                        "--steps-per-env", "8", "--run-dir", str(tmp_path / "run")],
                       capture_output=True, text=True, timeout=240, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    note = [x for x in p.stdout.splitlines() if x.startswith("note: g.onnx deploys")]
    assert len(note) == 1, p.stdout[-2000:]
    assert note[0].endswith("give --gains 29,8/29,8/26,1.2 --excitation-seen 0.5"), note[0]


def test_from_policy_bad_inputs_exit_2_with_one_line(exported, tmp_path):
    d, _ = exported
    run = lambda *args: subprocess.run([sys.executable, "-m", "policy_train.cli", "tripod", *args],
                                       capture_output=True, text=True, timeout=120, check=False)
    (tmp_path / "lone.onnx").write_bytes((d / "pol.onnx").read_bytes())
    (tmp_path / "junk.onnx").write_bytes(b"not a graph")
    (tmp_path / "junk.json").write_bytes((d / "pol.json").read_bytes())
    for args, hint in [
            (["--from-policy", str(d / "pol.onnx"), "--resume", str(d / "run" / "model_2.pt")],
             "exclude each other"),
            (["--from-policy", str(tmp_path / "lone.onnx")], "no policy metadata"),
            (["--from-policy", str(tmp_path / "junk.onnx")], "not a readable ONNX model"),
            (["--from-policy", str(d / "pol.onnx"), "--init-std", "0", "--num-envs", "8",
              "--plans-per-leg", "1"], "std")]:
        p = run(*args)
        err = [line for line in p.stderr.splitlines() if "error:" in line]
        assert p.returncode == 2 and len(err) == 1 and hint in err[0], (args, p.stderr)


def test_a_fall_is_counted_in_the_phase_it_happened_in():
    """The env resets a fallen episode inside its step, so the phase after the step is the new
    episode's; the evaluation takes the fall's phase from before the step."""
    from deploy.policy import default_policy_path
    from policy_train.evaluate import evaluation_env, step_phase

    json_path = default_policy_path([Path(__file__).resolve().parents[1] / "policies"])
    meta = json.loads(json_path.read_text())
    onnx_path = json_path.with_name(meta["onnx"])
    env, _ = evaluation_env(meta, ("FL",), 1, seed=0, nominal=True)
    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    obs = env.observations()["policy"]
    for _ in range(200):  # the policy plays until the excitation
        obs = env.step(sess.run(None, {"obs": obs.astype(np.float32)})[0])[0]["policy"]
        if env.phase[0] == PHASES.index("excite"):
            break
    assert env.phase[0] == PHASES.index("excite")
    env.qpos[0, 3:7] = [0.0, 1.0, 0.0, 0.0]  # upside down: a fall
    before = env.phase.copy()
    _, _, _, extras = env.step(np.zeros((1, 12), dtype=np.float32))
    assert extras["terminated"][0] and env.phase[0] != PHASES.index("excite")
    assert step_phase(before, env.phase, extras["terminated"])[0] == PHASES.index("excite")
    assert step_phase(before, env.phase, ~extras["terminated"])[0] == env.phase[0]


def test_eval_names_the_training_gains_one_pair_or_per_joint():
    from policy_train.evaluate import _gains_note

    meta = {"kp": [29.0, 29.0, 23.0] * 4, "kd": [6.0, 6.0, 0.8] * 4,
            "train_config": {"env": {"kp": 20.0, "kd": 0.5}}}
    assert _gains_note(meta) == "; trained at 20 / 0.5"
    # a2i-train tripod --gains 29,6/29,6/23,0.8: twelve values in the training's config
    meta["train_config"]["env"] = {"kp": [29.0, 29.0, 23.0] * 4, "kd": [6.0, 6.0, 0.8] * 4}
    assert _gains_note(meta) == ""
    meta["kp"] = [30.0, 29.0, 23.0] * 4
    assert _gains_note(meta) == "; trained at hip / thigh / calf kp 29 / 29 / 23, kd 6 / 6 / 0.8"


def test_derive_stand_holds_the_default_pose_while_no_leg_is_lifted(exported, tmp_path, capsys):
    """`derive --stand GAIN` (v27): with the lift command none the graph plays the integral
    stand of ``policy_train.stand`` (actions -GAIN/s x the joint_pos term), any other command
    the network, whose weights stay the source's; with damped gains the stand brings the joints
    to the default pose on the free-base simulator, the PD sag taken out; at the training's
    soft gains it tips the robot and derive refuses it; a second stand is refused.
    `derive --stand hold` plays zero actions there until the network first acts: the targets
    held, the joints sagged but at rest, and refused where the soft gains leave the body
    rocking."""
    from policy_train.cli import main
    from policy_train.stand import MAX_SETTLED_ERROR, settle

    def refused(source, out, why, stand="0.2"):
        capsys.readouterr()
        assert main(["derive", str(source), "--out", str(out), "--stand", stand]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and why in err[0], err
        assert not out.with_suffix(".json").exists()

    d, _ = exported
    refused(d / "pol.onnx", tmp_path / "soft", "does not settle")
    refused(d / "pol.onnx", tmp_path / "soft", "still moved", "hold")

    damped = ["--gains", "29,8/29,8/26,1.2"]
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "s"), *damped,
                 "--stand", "0.2"]) == 0
    meta = json.loads((tmp_path / "s.json").read_text())
    assert meta["stand"] == {"mode": "home", "gain": 0.2}
    assert meta["derived_from"]["stand"] == {"mode": "network"}
    from policy_train.evaluate import _derived

    assert _derived(meta).endswith("the stand at the default pose of `policy_train.stand` "
                                   "(gain 0.2) instead of the network's")
    names = [t["name"] for t in meta["observation"]["terms"]]
    at = {n: sum(t["size"] for t in meta["observation"]["terms"][:names.index(n)]) for n in names}
    c_scale = meta["observation"]["terms"][names.index("lift_command")]["scale"]
    x = np.random.default_rng(5).normal(0, 0.5, (6, meta["observation"]["size"]))
    x = x.astype(np.float32)
    x[:, at["lift_command"]] = np.array([0, 1, 2, 3, 4, 0]) * c_scale
    run = {p: ort.InferenceSession(str(p), providers=["CPUExecutionProvider"])
           for p in (d / "pol.onnx", tmp_path / "s.onnx")}
    y_src, y = (run[p].run(["actions"], {"obs": x})[0] for p in run)
    jp = x[:, at["joint_pos"]:at["joint_pos"] + 12]
    none = x[:, at["lift_command"]] == 0
    assert np.allclose(y[none], -0.2 * jp[none], atol=1e-6)
    assert np.array_equal(y[~none], y_src[~none])
    src_w, new_w = ({i.name: onnx.numpy_helper.to_array(i) for i in onnx.load(p).graph.initializer}
                    for p in (d / "pol.onnx", tmp_path / "s.onnx"))
    assert all(np.array_equal(w, new_w[k]) for k, w in src_w.items())
    # the same gains without the stand: the network's own (here barely trained) stand
    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "n"), *damped]) == 0
    assert settle(tmp_path / "n.json").error_rad > MAX_SETTLED_ERROR
    s = settle(tmp_path / "s.json")
    assert s.settled and s.error_rad < 0.01
    refused(tmp_path / "s.onnx", tmp_path / "t", "already has a stand")

    assert main(["derive", str(d / "pol.onnx"), "--out", str(tmp_path / "h"), *damped,
                 "--stand", "hold"]) == 0
    meta = json.loads((tmp_path / "h.json").read_text())
    assert meta["stand"] == {"mode": "hold"}
    assert _derived(meta).endswith("with no leg lifted yet, the joint targets held "
                                   "(`policy_train.stand`'s hold) "
                                   "instead of the network's stand")
    # it holds while no leg is lifted and the network has not acted since the reset (the
    # previous actions all zero: rows 0 to 2), then the network plays, its stand too (row 5)
    x[:3, at["previous_actions"]:at["previous_actions"] + 12] = 0
    y_src, y = (ort.InferenceSession(str(p), providers=["CPUExecutionProvider"]).run(
        ["actions"], {"obs": x})[0] for p in (d / "pol.onnx", tmp_path / "h.onnx"))
    assert np.all(y[0] == 0) and np.array_equal(y[1:], y_src[1:]) and np.any(y_src[5] != 0)
    # fed back as deploy's runner feeds it: held from the reset, the network after a lift
    from calib.joints import sdk_to_model
    from deploy.policy import PolicyMeta, PolicyRunner
    from policy_train.policy_motion import policy_signals
    from sim.free_base_run import free_base_sim

    pm = PolicyMeta.load(tmp_path / "h.json")
    runner = PolicyRunner(pm)
    sim = free_base_sim(0.001, sdk_to_model(pm.default_pose))
    outputs = []
    for leg in [None] * 3 + ["FR"] + [None] * 3 + ["reset", None]:
        if leg == "reset":
            runner.reset(pm.default_pose)
            continue
        a = runner.act(build_observation(pm.observation,
                                         policy_signals(sim, runner, pm.lift_value(leg))))
        runner.step(a)
        outputs.append(np.abs(a).sum())
    assert outputs[:3] == [0, 0, 0] and min(outputs[3:7]) > 0 and outputs[7] == 0
    h = settle(tmp_path / "h.json")  # sagged under the PD law, at rest
    assert h.settled and h.error_rad > MAX_SETTLED_ERROR and h.drift_rad < 0.005
    refused(tmp_path / "h.onnx", tmp_path / "t", "already has a stand", "hold")


def test_commit_reads_dirty_for_changed_code_not_for_a_runs_outputs(tmp_path, monkeypatch):
    from policy_train.export import git_commit

    # git must not find a repository above tmp_path (a checkout that holds /tmp, say)
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path.parent))

    def git(*args):
        subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=tmp_path,
                       check=True, capture_output=True)

    assert git_commit(tmp_path) == "unknown"  # not a repository
    git("init", "-q")
    (tmp_path / "code.py").write_text("x = 1\n")
    git("add", "code.py")
    git("commit", "-q", "-m", "c")
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=tmp_path, capture_output=True,
                          text=True, check=True).stdout.strip()
    assert git_commit(tmp_path) == head
    (tmp_path / "policies").mkdir()
    (tmp_path / "policies" / "p.onnx").write_bytes(b"\0")  # what a run writes: still clean
    (tmp_path / "p.refine.json").write_text("{}")
    assert git_commit(tmp_path) == head
    (tmp_path / "policies" / "new.py").write_text("")  # code not yet added
    assert git_commit(tmp_path) == head + "-dirty"
    (tmp_path / "policies" / "new.py").unlink()
    (tmp_path / "code.py").write_text("x = 2\n")  # tracked code changed
    assert git_commit(tmp_path) == head + "-dirty"
    # the default is this package's repository, wherever the command runs from
    assert git_commit().split("-")[0] == subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parents[1],
        capture_output=True, text=True, check=True).stdout.strip()
