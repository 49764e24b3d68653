"""policy_train.distill: the student starts as the committed teacher (v7), learns from the
teacher's actions on clean frames, checkpoints, resumes and exports a history policy that the
on-board runner stacks frames for."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from policy_train.distill import DistillConfig, Distiller, widen_hidden, widen_history

TEACHER = str(Path(__file__).resolve().parents[1] / "policies" / "tripod_go2_v7.onnx")


@pytest.fixture(scope="module")
def distiller(tmp_path_factory):
    cfg = DistillConfig(teacher=TEACHER, history=3, num_envs=6, steps_per_iteration=4,
                        buffer_samples=200, updates_per_iteration=3, batch_size=16)
    return Distiller(cfg, tmp_path_factory.mktemp("distill"), seed=2, threads=1)


def test_student_starts_as_the_teacher(distiller):
    """On the lifts the teacher's network makes itself (FL, RL) the untrained student is the
    teacher on the newest frame, whatever the older frames hold."""
    d = distiller
    assert d.env.num_obs == 147
    rng = np.random.default_rng(0)
    x = rng.normal(0, 0.5, (20, 147)).astype(np.float32)
    scale = d.meta["observation"]["terms"][-1]["scale"]
    x[:, 48] = rng.choice([0, d.meta["lift_command"]["FL"], d.meta["lift_command"]["RL"]],
                          20) * scale
    with torch.no_grad():
        student = d.student(torch.from_numpy(x)).numpy()
    teacher = d.teacher.run(None, {d.teacher_in: x[:, :49]})[0]
    np.testing.assert_allclose(student, teacher, atol=1e-5)
    assert set(np.flatnonzero(d.env.leg_p)) == {0, 2}  # FL and RL (model order FL FR RL RR)


def test_labels_are_the_teachers_actions_on_clean_frames_and_learning_fits_them(distiller):
    d = distiller
    obs = d.env.observations()
    clean = obs["critic"][:, :49]
    _, stats = d._collect(obs)
    assert d.buf_n == 6 * 4 and stats["episodes_ended"] >= 0
    # the first step's samples: the noisy history in, the teacher's action on the clean frame
    np.testing.assert_array_equal(d.buf_x[:6], obs["policy"])
    np.testing.assert_allclose(d.buf_y[:6], d.teacher.run(None, {d.teacher_in: clean})[0],
                               atol=1e-6)
    assert not np.allclose(d.buf_y[:6], d.teacher.run(None, {d.teacher_in: d.buf_x[:6, :49]})[0],
                           atol=1e-3)  # not its action on the noisy frame
    first = d._update()
    for _ in range(30):
        loss = d._update()
    assert np.isfinite(first) and loss < 0.5 * first


def test_actuation_labels_are_the_teachers_actions_where_the_action_takes_effect(tmp_path):
    """labels="actuation": each sample's label is the teacher's action on the clean frame of
    the state at which the student's action reaches the motors; with no latency that is the
    frame the student acted on."""
    cfg = DistillConfig(teacher=TEACHER, history=2, num_envs=4, steps_per_iteration=1,
                        buffer_samples=20, updates_per_iteration=1, batch_size=4,
                        labels="actuation")
    d = Distiller(cfg, tmp_path, seed=3, threads=1)
    d.env.latency[:] = [0, 1, 2, 4]
    obs = d.env.observations()
    now = d.teacher.run(None, {d.teacher_in: obs["critic"][:, :49]})[0]
    d._collect(obs)
    later = d.teacher.run(None, {d.teacher_in: d.env.actuation_frames})[0]
    np.testing.assert_allclose(d.buf_y[:4], later, atol=1e-6)
    np.testing.assert_allclose(d.buf_y[0], now[0], atol=1e-6)
    assert not np.allclose(d.buf_y[3], now[3], atol=1e-3)
    with pytest.raises(ValueError, match="labels"):
        Distiller(DistillConfig(teacher=TEACHER, num_envs=2, labels="later"), tmp_path)


def test_a_teacher_shown_part_of_its_leg_is_refused(tmp_path):
    """A teacher whose JSON shows the policy part of the lifted leg's excursion (stop 67) is
    refused: the labels would be its actions on frames it never sees on board."""
    from policy_train.export import derive_policy

    onnx, _ = derive_policy(TEACHER, tmp_path / "half", excitation_seen=0.5)
    with pytest.raises(ValueError, match="excitation_seen"):
        Distiller(DistillConfig(teacher=str(onnx), num_envs=2), tmp_path / "run")


def _stepped_student(n_in: int):
    """A small student (hidden 16, 8) after three Adam steps, so its optimiser has moments;
    returns the network, the optimiser and the ``mlp.*`` state dict of a checkpoint."""
    from rsl_rl.modules import MLP

    torch.manual_seed(0)
    small = MLP(n_in, 12, [16, 8], "elu")
    opt = torch.optim.Adam(small.parameters(), lr=1e-3)
    for _ in range(3):
        opt.zero_grad()
        small(torch.randn(32, n_in)).square().mean().backward()
        opt.step()
    return small, opt, {f"mlp.{k}": v for k, v in small.state_dict().items()}


def test_widened_history_acts_as_before_and_adam_takes_no_sign_steps():
    """widen_history (a resume with a longer --history): the student's outputs are unchanged
    whatever the older frames hold; the new columns' first moments are zero and their second
    moments the oldest saved frame's, so Adam's first step on them is not a sign step."""
    from rsl_rl.modules import MLP

    small, opt, actor = _stepped_student(98)
    saved = {k: v.clone() for k, v in actor.items()}
    wide_actor, wide_opt = widen_history(actor, opt.state_dict(), 2, 5)
    big = MLP(49 * 5, 12, [16, 8], "elu")
    big.load_state_dict({k[len("mlp."):]: v for k, v in wide_actor.items()})
    x = torch.randn(10, 49 * 5)
    with torch.no_grad():
        np.testing.assert_allclose(big(x).numpy(), small(x[:, :98]).numpy(), atol=1e-6)
    st = wide_opt["state"][0]
    assert st["exp_avg"].shape == (16, 245) and not st["exp_avg"][:, 98:].any()
    old_v = opt.state_dict()["state"][0]["exp_avg_sq"]
    for k in range(2, 5):
        torch.testing.assert_close(st["exp_avg_sq"][:, 49 * k:49 * (k + 1)], old_v[:, 49:])
    assert all(torch.equal(actor[k], saved[k]) for k in actor)  # the inputs are untouched
    big_opt = torch.optim.Adam(big.parameters(), lr=1e-3)
    big_opt.load_state_dict(wide_opt)  # shapes fit the widened student
    with pytest.raises(ValueError, match="only grow"):
        widen_history(actor, opt.state_dict(), 2, 1)


def test_widened_hidden_layers_act_as_before_and_the_added_units_learn():
    """widen_hidden (a resume with a wider --hidden): the outputs are unchanged; the added
    units' outgoing weights are zero and learn from the first step; Adam's moments fit the
    widened tensors, the added entries' second moments the tensor's saved mean."""
    from rsl_rl.modules import MLP

    small, opt, actor = _stepped_student(20)
    saved = {k: v.clone() for k, v in actor.items()}
    wide_actor, wide_opt = widen_hidden(actor, opt.state_dict(), (24, 11), seed=3)
    assert all(torch.equal(actor[k], saved[k]) for k in actor)  # the inputs are untouched
    big = MLP(20, 12, [24, 11], "elu")
    big.load_state_dict({k[len("mlp."):]: v for k, v in wide_actor.items()})
    x = torch.randn(50, 20)
    with torch.no_grad():
        np.testing.assert_allclose(big(x).numpy(), small(x).numpy(), atol=1e-6)
    assert wide_actor["mlp.0.weight"][16:].abs().sum() > 0  # the added units see the input
    assert not wide_actor["mlp.2.weight"][:8, 16:].any()   # and feed nothing yet
    assert not wide_actor["mlp.4.weight"][:, 8:].any()
    old_v = opt.state_dict()["state"][2]["exp_avg_sq"]     # mlp.2.weight's
    st = wide_opt["state"][2]
    assert st["exp_avg_sq"].shape == (11, 24) and not st["exp_avg"][8:].any()
    torch.testing.assert_close(st["exp_avg_sq"][:8, :16], old_v)
    torch.testing.assert_close(st["exp_avg_sq"][8:, 16:], torch.full((3, 8), float(old_v.mean())))
    big_opt = torch.optim.Adam(big.parameters(), lr=1e-3)
    big_opt.load_state_dict(wide_opt)
    big_opt.zero_grad()
    big(x).square().mean().backward()
    assert big[4].weight.grad[:, 8:].abs().sum() > 0  # the zero outgoing weights get gradients
    assert widen_hidden(actor, None, (16, 8))[1] is None
    with pytest.raises(ValueError, match="only grow"):
        widen_hidden(actor, opt.state_dict(), (16, 7))
    with pytest.raises(ValueError, match="hidden layers"):
        widen_hidden(actor, opt.state_dict(), (16, 8, 4))


def test_cli_trains_resumes_and_exports_a_history_policy(tmp_path):
    from deploy.policy import PolicyMeta, PolicyRunner

    run = tmp_path / "run"
    base = [sys.executable, "-m", "policy_train.cli", "distill", "--num-envs", "4",
            "--threads", "1", "--run-dir", str(run)]
    p = subprocess.run(base + ["--history", "2", "--iterations", "2", "--save-interval", "1",
                               "--dr", "noise_scale=0,1", "--export", str(tmp_path / "pol")],
                       capture_output=True, text=True, timeout=300, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert "it     1" in p.stdout and "it     2" in p.stdout and "loss" in p.stdout
    assert (run / "model_1.pt").exists() and (run / "model_2.pt").exists()
    ckpt = torch.load(run / "model_2.pt", weights_only=False)
    assert tuple(ckpt["distill"]["dr"]["noise_scale"]) == (0.0, 1.0)
    assert tuple(ckpt["train_config"]["env"]["dr"]["noise_scale"]) == (0.0, 1.0)
    meta = json.loads((tmp_path / "pol.json").read_text())
    teacher = json.loads(Path(TEACHER).with_suffix(".json").read_text())
    assert meta["observation"]["history"] == 2 and meta["observation"]["size"] == 98
    assert meta["mirrored_legs"] == teacher["mirrored_legs"]
    assert meta["lift_schedule"] == teacher["lift_schedule"]
    assert meta["distilled_from"]["teacher_name"] == "tripod_go2_v7.onnx"
    assert meta["distilled_from"]["labels"] == "now"
    # on board: the runner feeds the network its last two frames, newest first
    runner = PolicyRunner(PolicyMeta.load(tmp_path / "pol.json"))
    sess = ort.InferenceSession(str(tmp_path / "pol.onnx"), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(1)
    f = rng.normal(0, 0.3, (3, 49)).astype(np.float32)
    runner.reset(runner.meta.default_pose)
    for k, want_in in enumerate((np.r_[f[0], f[0]], np.r_[f[1], f[0]], np.r_[f[2], f[1]])):
        want = sess.run(None, {"obs": want_in[None]})[0][0]
        np.testing.assert_allclose(runner.act(f[k]), want, atol=1e-6)
    runner.reset(runner.meta.default_pose)  # a restart begins a new history
    np.testing.assert_allclose(runner.act(f[2]), sess.run(None, {"obs": np.r_[f[2], f[2]][None]})[0][0],
                               atol=1e-6)
    # resume continues the run's iterations, at the learning rate asked for (the optimiser's
    # saved state carries the old one); its history may grow, not shrink. --calf-margin moves
    # the student's calf clamp, and the export carries it to deploy
    p = subprocess.run(base + ["--resume", str(run / "model_2.pt"), "--iterations", "1",
                               "--learning-rate", "5e-5", "--calf-margin", "0.01",
                               "--export", str(tmp_path / "moved")],
                       capture_output=True, text=True, timeout=300, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert "resumed at iteration 2" in p.stdout and "it     3" in p.stdout
    ckpt = torch.load(run / "model_3.pt", weights_only=False)
    assert [g["lr"] for g in ckpt["optimizer_state_dict"]["param_groups"]] == [5e-5]
    assert ckpt["distill"]["calf_upper_margin"] == 0.01
    assert ckpt["train_config"]["env"]["calf_upper_margin"] == 0.01
    moved = PolicyMeta.load(tmp_path / "moved.json")
    calves = [2, 5, 8, 11]
    np.testing.assert_allclose(moved.soft_upper[calves], runner.meta.soft_upper[calves] + 0.04)
    np.testing.assert_allclose(np.delete(moved.soft_upper, calves),
                               np.delete(runner.meta.soft_upper, calves))
    assert ckpt["distill"]["learning_rate"] == 5e-5
    p = subprocess.run(base + ["--resume", str(run / "model_2.pt"), "--history", "1"],
                       capture_output=True, text=True, timeout=300, check=False)
    assert p.returncode != 0 and "--history" in p.stderr.strip().splitlines()[-1]
    p = subprocess.run(base + ["--resume", str(run / "model_3.pt"), "--history", "3",
                               "--iterations", "1"],
                       capture_output=True, text=True, timeout=300, check=False)
    assert p.returncode == 0 and "3 frames" in p.stdout, p.stdout[-2000:] + p.stderr[-2000:]
    ckpt = torch.load(run / "model_4.pt", weights_only=False)
    assert ckpt["distill"]["history"] == 3
    assert ckpt["actor_state_dict"]["mlp.0.weight"].shape[1] == 147
    # a wider student: the checkpoint and the export carry its widths; they may not shrink
    p = subprocess.run(base + ["--resume", str(run / "model_4.pt"), "--hidden", "260,130,66",
                               "--iterations", "1", "--export", str(tmp_path / "wide")],
                       capture_output=True, text=True, timeout=300, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    ckpt = torch.load(run / "model_5.pt", weights_only=False)
    assert tuple(ckpt["train_config"]["ppo"]["actor_hidden"]) == (260, 130, 66)
    assert tuple(ckpt["distill"]["hidden"]) == (260, 130, 66)
    assert ckpt["actor_state_dict"]["mlp.4.weight"].shape == (66, 130)
    sess = ort.InferenceSession(str(tmp_path / "wide.onnx"), providers=["CPUExecutionProvider"])
    assert sess.run(None, {"obs": np.zeros((2, 147), np.float32)})[0].shape == (2, 12)
    p = subprocess.run(base + ["--resume", str(run / "model_5.pt"), "--hidden", "256,128,64"],
                       capture_output=True, text=True, timeout=300, check=False)
    assert p.returncode != 0 and "only grow" in p.stderr.strip().splitlines()[-1]


@pytest.mark.parametrize(("args", "hint"), [
    (["--teacher", "nope.onnx"], "nope"),
    (["--history", "0"], "--history"),
    (["--num-envs", "x"], "--num-envs"),
    (["--dr", "nope=1"], "--dr"),
    (["--labels", "later"], "--labels"),
    (["--hidden", "512,x"], "--hidden"),
    (["--calf-margin", "-1"], "--calf-margin"),
])
def test_bad_inputs_exit_nonzero_with_one_line(tmp_path, args, hint):
    p = subprocess.run([sys.executable, "-m", "policy_train.cli", "distill", "--iterations", "1",
                        "--run-dir", str(tmp_path / "r"), *args],
                       capture_output=True, text=True, timeout=120, check=False)
    assert p.returncode != 0
    lines = p.stderr.strip().splitlines()
    assert hint in lines[-1] and "Traceback" not in p.stderr
