"""`a2i-train refine`: the residual acts only on the refined lift (and its mirror), every
candidate of a generation plays the same episodes, and the refined policy exports, resumes,
refuses to be warm-started as a plain network and can itself be refined further."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from policy_train.refine import (
    BlockRNG,
    RefineConfig,
    build_actor,
    pack,
    paired_rollouts,
    refine,
    residual_columns,
    score,
    unpack,
)

V21 = Path(__file__).resolve().parents[1] / "policies" / "tripod_go2_v21.onnx"
V22 = V21.with_name("tripod_go2_v22.onnx")  # v21 refined 40 generations


def test_block_rng_repeats_each_blocks_draws_and_passes_the_rest_through():
    r = BlockRNG(np.random.default_rng(0), 3)
    for x in (r.uniform(-1, 1, (6, 2)), r.integers(0, 1000, 6), r.random(6),
              r.choice(4, 6, p=[0.1, 0.2, 0.3, 0.4]), r.uniform(size=(9, 2, 2))):
        blocks = np.split(x, 3)
        assert all(np.array_equal(blocks[0], b) for b in blocks[1:])
        assert x.shape[0] in (6, 9)
    x = r.uniform(0, 1, (2, 2))  # one env of two blocks: not a block draw
    assert x.shape == (2, 2) and not np.array_equal(x[0], x[1])
    assert np.isscalar(r.uniform(0, 1)) and r.integers(0, 5, size=4).shape == (4,)
    plain = np.random.default_rng(0)
    assert BlockRNG(plain, 2).bit_generator is plain.bit_generator


def test_residual_reads_the_newest_rate_and_tilt():
    meta = json.loads(V21.with_suffix(".json").read_text())
    cols, lift_col, scale = residual_columns(meta["observation"]["terms"])
    assert cols == [3, 4, 5, 6, 7] and lift_col == 48 and scale == 0.25
    with pytest.raises(ValueError, match="lift_command"):
        residual_columns([t for t in meta["observation"]["terms"] if t["name"] != "lift_command"])
    with pytest.raises(ValueError, match="72"):
        unpack(np.zeros(71))


def test_residual_acts_on_the_refined_lift_and_mirrors_onto_its_twin():
    """Zero residual: the source's ONNX. A residual for FL changes FL's lifts by D x + b,
    FR's (mirrored onto FL in v21's graph) by its mirror image, and nothing else."""
    from policy_train.symmetry import ActionMirror, Mirror, policy_terms

    meta, actor, res = build_actor(V21, "FL")
    sess = ort.InferenceSession(str(V21), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(3)
    x = rng.normal(0, 0.3, (6, 490)).astype(np.float32)
    values = {"none": 0.0, "FL": 0.25, "FR": 0.5, "RL": 0.75, "RR": 1.0}
    with torch.no_grad():
        for leg, v in values.items():
            x[:, 48::49] = v
            np.testing.assert_allclose(actor(torch.from_numpy(x)).numpy(),
                                       sess.run(None, {"obs": x})[0], atol=1e-4, err_msg=leg)
        D, b = rng.normal(size=(12, 5)), rng.normal(size=12)
        res.set_residual(D, b)
        terms, scale = policy_terms(meta["observation"]["terms"])
        m_obs, m_act = Mirror(terms, scale, 10), ActionMirror()
        for leg, v in values.items():
            x[:, 48::49] = v
            got = actor(torch.from_numpy(x)).numpy()
            base = sess.run(None, {"obs": x})[0]
            if leg == "FL":
                want = base + x[:, [3, 4, 5, 6, 7]] @ D.T + b
            elif leg == "FR":
                xm = m_obs(torch.from_numpy(x)).numpy()
                want = base + m_act(torch.from_numpy(xm[:, [3, 4, 5, 6, 7]] @ D.T + b)).numpy()
            else:
                want = base
            np.testing.assert_allclose(got, want, atol=1e-4, err_msg=leg)
    with pytest.raises(ValueError, match="mirror"):
        build_actor(V21, "FR")


def test_candidates_play_the_same_episodes():
    """Two equal candidates give the same figures (the same masses, friction, pushes and
    noise); a drifting one differs."""
    meta, actor, res = build_actor(V21, "FL", 3)
    zero = (np.zeros((12, 5)), np.zeros(12))
    drift = (np.zeros((12, 5)), np.full(12, 0.02))
    rows = paired_rollouts(meta, actor, res, [zero, drift, zero], ("FL",), 2, seed=5)
    # equal but for the float rounding of a row's place in the batch's matrix products, which
    # the contacts amplify over the 20 s (1e-6 rad at 4 s, 6e-3 rad by 17 s on these draws)
    a, b, c = (r["FL"]["rate"] for r in rows)
    assert abs(c - a) < 1e-2 * a and abs(b - a) > 10 * abs(c - a), (a, b, c)
    assert 0 < rows[0]["FL"]["rate"] < 1 and rows[0]["FL"]["track"] < 0.05
    # the capture point's lowest margin over the lift: inside the stance feet; the score's
    # shortfall below 8 cm is a mean over the episodes (convex: at least the median's)
    fl = rows[0]["FL"]
    assert 0 < fl["cp_min"] < 0.15 and 0.08 - fl["cp_min"] - 1e-12 <= fl["short"] <= 0.16
    assert score(rows[0], 2, 0.1, 2.0) == pytest.approx(
        score(rows[0], 2, 0.1) + 2.0 * rows[0]["FL"]["short"])
    # the tilt from the vertical over the excitation: the crouch's lean, priced beyond a target
    assert np.radians(0.1) < fl["tilt"] < np.radians(5)
    assert score(rows[0], 2, 0.1, 0.0, 3.0, 0.0) == pytest.approx(
        score(rows[0], 2, 0.1) + 3.0 * fl["tilt"])
    assert score(rows[0], 2, 0.1, 0.0, 3.0, fl["tilt"] + 1e-3) == score(rows[0], 2, 0.1)
    assert rows[1]["FL"]["tilt"] != fl["tilt"]
    # the stance calves' lowest point over the floor in the excitation: millimetres up (the
    # hulls wrap the top of the foot), the evaluation's calf_clearance_mm; the shortfall below
    # 8 mm a mean over the episodes, priced like the capture point's
    assert 0.001 < fl["calf_min"] < 0.03
    assert max(0.008 - fl["calf_min"], 0.0) - 1e-12 <= fl["calf_short"] <= 0.016
    assert score(rows[0], 2, 0.1, clearance_cost=20.0) == pytest.approx(
        score(rows[0], 2, 0.1) + 20.0 * fl["calf_short"])
    high = paired_rollouts(meta, actor, res, [zero], ("FL",), 2, seed=5,
                           clearance_target=0.03)[0]["FL"]
    assert high["calf_min"] == pytest.approx(fl["calf_min"], rel=1e-2)
    assert high["calf_short"] == pytest.approx(0.03 - fl["calf_min"], abs=5e-3)
    assert res.group is None


def test_refine_exports_resumes_and_is_no_warm_start(tmp_path):
    from deploy.policy import PolicyMeta
    from policy_train.warm_start import policy_start

    cfg = RefineConfig(pairs=1, episodes=1, seed=7)
    state = tmp_path / "s.json"
    lines = []
    onnx_path, json_path = refine(V21, tmp_path / "r", 1, cfg, state, log=lines.append)
    assert len(lines) == 1 and lines[0].startswith("generation 0: score")
    saved = json.loads(state.read_text())
    assert saved["source"] == V21.name and len(saved["history"]) == 1
    assert np.linalg.norm(saved["params"]) > 0  # one step taken
    refine(V21, tmp_path / "r", 1, RefineConfig(pairs=3), state, resume=True, log=lines.append)
    saved = json.loads(state.read_text())
    assert [h["generation"] for h in saved["history"]] == [0, 1]
    assert saved["config"]["pairs"] == 1  # the state's settings, not the new ones
    meta = json.loads(json_path.read_text())
    PolicyMeta.from_dict(meta, json_path)
    rf = meta["refined_from"]
    assert rf["policy"] == V21.name and rf["legs"] == ["FL", "FR"] and len(rf["generations"]) == 2
    assert meta["evaluation"] == {} and "evaluation_nominal" not in meta
    D, b = unpack(saved["params"])
    np.testing.assert_allclose(rf["D"], D, atol=1e-6)
    # the ONNX is the source plus the state's residual on FL's lifts
    x = np.random.default_rng(0).normal(0, 0.3, (4, 490)).astype(np.float32)
    x[:, 48::49] = 0.25
    got = ort.InferenceSession(str(onnx_path)).run(None, {"obs": x})[0]
    src = ort.InferenceSession(str(V21)).run(None, {"obs": x})[0]
    np.testing.assert_allclose(got, src + x[:, [3, 4, 5, 6, 7]] @ D.T + b, atol=1e-4)
    with pytest.raises(ValueError, match="refined"):
        policy_start(onnx_path)
    with pytest.raises(ValueError, match="refines"):
        refine(json_path.with_suffix(".onnx"), tmp_path / "q", 1, cfg, state, resume=True)


def test_a_refined_policy_goes_on_from_its_residual(tmp_path):
    with pytest.raises(ValueError, match="unknown randomisation"):
        RefineConfig(dr={"shove": 1.0})
    cfg = RefineConfig(pairs=1, episodes=1, fail_cost=0.5, dr={"push_vel": 0.5})
    state, lines = tmp_path / "s.json", []
    onnx_path, json_path = refine(V22, tmp_path / "r", 1, cfg, state, log=lines.append)
    assert lines[0].startswith("generation 40: score")  # v22's 40 generations go on
    saved = json.loads(state.read_text())
    assert saved["source"] == V21.name and saved["start"] == V22.name
    assert saved["history"][-1]["seed"] == 1040 and saved["config"]["dr"] == {"push_vel": 0.5}
    rf22 = json.loads(V22.with_suffix(".json").read_text())["refined_from"]
    moved = (np.asarray(saved["params"]) - pack(rf22["D"], rf22["b"])) / cfg.scales
    np.testing.assert_allclose(np.linalg.norm(moved), cfg.step * np.sqrt(72), rtol=1e-5)
    rf = json.loads(json_path.read_text())["refined_from"]
    assert rf["policy"] == V21.name and len(rf["generations"]) == 41
    assert rf["continued_from"]["policy"] == V22.name
    assert rf["continued_from"]["generations"] == 40 and rf["continued_from"]["config"].get("dr", {}) == {}
    # the export is v21's network under the new residual, as v22's was under its own
    x = np.random.default_rng(1).normal(0, 0.3, (2, 490)).astype(np.float32)
    x[:, 48::49] = 0.25
    D, b = unpack(saved["params"])
    got = ort.InferenceSession(str(onnx_path)).run(None, {"obs": x})[0]
    src = ort.InferenceSession(str(V21)).run(None, {"obs": x})[0]
    np.testing.assert_allclose(got, src + x[:, [3, 4, 5, 6, 7]] @ D.T + b, atol=1e-4)
    with pytest.raises(ValueError, match="refines tripod_go2_v22"):
        refine(V21, tmp_path / "q", 1, cfg, state, resume=True)


def test_another_lifts_refinement_keeps_the_first_residual(tmp_path):
    """Refining the rear lifts of a policy refined on its front ones: the front lifts' residual
    stays in the graph as it was (``kept``), the rear lifts get their own, from zero, and a
    further refinement of either goes on from its own and keeps the other."""
    cfg = RefineConfig(leg="RL", pairs=1, episodes=1, seed=7)
    onnx_path, json_path = refine(V22, tmp_path / "r", 1, cfg, tmp_path / "s.json",
                                  log=lambda s: None)
    rf = json.loads(json_path.read_text())["refined_from"]
    rf22 = json.loads(V22.with_suffix(".json").read_text())["refined_from"]
    assert rf["policy"] == V21.name and rf["leg"] == "RL" and rf["legs"] == ["RL", "RR"]
    assert len(rf["generations"]) == 1 and "continued_from" not in rf  # from zero
    assert [k["leg"] for k in rf["kept"]] == ["FL"] and rf["kept"][0]["D"] == rf22["D"]
    x = np.random.default_rng(2).normal(0, 0.3, (3, 490)).astype(np.float32)
    run = {p: ort.InferenceSession(str(p)) for p in (onnx_path, V22, V21)}
    D, b = np.asarray(rf["D"]), np.asarray(rf["b"])
    for value in (0.0, 0.25, 0.5, 0.75, 1.0):  # no lift, FL, FR, RL, RR
        x[:, 48::49] = value
        got, v22, v21 = (run[p].run(None, {"obs": x})[0] for p in (onnx_path, V22, V21))
        if value < 0.6:  # no lift and the front lifts: v22's graph
            np.testing.assert_allclose(got, v22, atol=1e-5)
        elif value == 0.75:  # RL: v21's network plus the new residual
            np.testing.assert_allclose(got, v21 + x[:, [3, 4, 5, 6, 7]] @ D.T + b, atol=1e-4)
        else:  # RR, mirrored onto RL: changed by its mirror image, the front's residual off
            assert np.abs(got - v21).max() > 1e-3 and np.abs(got - v22).max() > 1e-3
    # the front lifts again: v22's residual goes on, the rear lifts' is kept (the network
    # beside the refined policy, as in policies/)
    for f in (V21, V21.with_suffix(".json")):
        (tmp_path / f.name).write_bytes(f.read_bytes())
    again = RefineConfig(pairs=1, episodes=1, seed=7)
    _, j2 = refine(onnx_path, tmp_path / "f", 1, again, tmp_path / "f.json", log=lambda s: None)
    rf2 = json.loads(j2.read_text())["refined_from"]
    assert rf2["leg"] == "FL" and len(rf2["generations"]) == 41
    assert rf2["continued_from"]["policy"] == onnx_path.name
    assert [k["leg"] for k in rf2["kept"]] == ["RL"] and rf2["kept"][0]["D"] == rf["D"]


@pytest.mark.parametrize(("extra", "hint"), [
    (["--leg", "FL,FR"], "one leg"), (["--leg", "XX"], "XX"), (["--pairs", "0"], "pairs"),
    (["--resume", "--state", "nowhere.json"], "no state"), (["--dr", "shove=1"], "FIELD"),
    (["--fail-cost", "0"], "fail-cost"), (["--tilt-cost", "-1"], "tilt-cost"),
    (["--clearance-target", "0.2"], "clearance-target")])
def test_bad_refine_exits_with_one_line(extra, hint, tmp_path):
    p = subprocess.run([sys.executable, "-m", "policy_train.cli", "refine", str(V21), "--out",
                        str(tmp_path / "o"), "--generations", "1", *extra],
                       capture_output=True, text=True, timeout=120, check=False)
    err = [line for line in p.stderr.splitlines() if "error" in line]
    assert p.returncode == 2 and len(err) == 1 and hint in err[0], p.stderr
    assert "error: '" not in err[0] and 'error: "' not in err[0], p.stderr  # not a repr


def test_refining_a_derived_policy_keeps_its_deploy_settings(tmp_path):
    """v26 is v22's graph (v21's network and a residual) with a2i-train derive's settings (the
    front lifts' 2 s shift, the tracking adapter): refined further, the rollouts play and the
    new JSON keeps v26's, not v21's."""
    v26 = V21.with_name("tripod_go2_v26.onnx")
    _, json_path = refine(v26, tmp_path / "r", 1, RefineConfig(pairs=1, episodes=1),
                          tmp_path / "s.json", log=lambda s: None)
    src, new = (json.loads(p.with_suffix(".json").read_text()) for p in (v26, json_path))
    # one generation played on top of v26's own
    assert len(new["refined_from"]["generations"]) == len(src["refined_from"]["generations"]) + 1
    for key in ("kp", "kd", "lift_schedule"):
        assert new[key] == src[key], key
    assert new["refined_from"]["policy"] == V21.name
    assert new["refined_from"]["continued_from"]["policy"] == v26.name
    meta, _, _ = build_actor(V21, "FL", 1, v26.with_suffix(".json"))
    assert meta["lift_schedule"]["adapt"] and meta["lift_schedule"]["shift_by_leg"]["FL"] == 2
    with pytest.raises(ValueError, match="observation is not its network's"):
        build_actor(V21, "FL", 1, V21.with_name("tripod_go2_v7.json"))


def test_a_policy_derived_with_the_target_bound_refines_with_it(tmp_path):
    """v51 is v46 derived with `--target-lead torque`: its action names the bound, its network's
    (v21's) does not. The bound is deploy's, as the gains are, so the refinement takes v51 and
    plays it; any other difference in the action is still refused."""
    v51 = V21.with_name("tripod_go2_v51.json")
    meta, _, _ = build_actor(V21, "FL", 1, v51)
    assert meta["action"]["target_lead_max"] == json.loads(v51.read_text())["action"][
        "target_lead_max"]
    from policy_train.evaluate import evaluation_env
    env, _ = evaluation_env(meta, ("FL",), 1, 0)
    assert env.cfg.target_lead_max is not None  # the rollouts play the bound
    bad = json.loads(v51.read_text())
    bad["action"]["scale"] = 0.2
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="action is not its network's"):
        build_actor(V21, "FL", 1, tmp_path / "bad.json")


def test_refining_a_policy_with_a_stand_keeps_it_in_its_graph(tmp_path):
    """The candidate v27 is v26 whose graph stands at the default pose while no leg is lifted
    (`derive --stand`): refined further (beside the network its refinement names, as a
    refinement needs), the new JSON names the stand and the new graph plays it."""
    import shutil

    v27 = V21.parent / "candidates" / "tripod_go2_v27.onnx"
    for f in (V21, V21.with_suffix(".json"), v27, v27.with_suffix(".json")):
        shutil.copy(f, tmp_path / f.name)
    _, json_path = refine(tmp_path / v27.name, tmp_path / "r", 1,
                          RefineConfig(pairs=1, episodes=1), tmp_path / "s.json",
                          log=lambda s: None)
    src = json.loads(v27.with_suffix(".json").read_text())
    new = json.loads(json_path.read_text())
    assert new["stand"] == src["stand"] == {"mode": "home", "gain": 0.2}
    x = np.random.default_rng(2).normal(0, 0.3, (2, src["observation"]["size"])).astype(np.float32)
    x[:, 48] = 0.0  # lift command none (its scale 0.25: 0.25 per leg)
    y = ort.InferenceSession(str(json_path.with_suffix(".onnx"))).run(None, {"obs": x})[0]
    assert np.allclose(y, -0.2 * x[:, 9:21], atol=1e-6)


def test_stance_velocity_map_reads_the_base_velocity_from_the_stance_legs():
    """Feet still on the floor: a base moved by d over VEL_FRAMES steps bends each stance leg
    by -J^-1 d, and the map reads d / (k dt) from the joint angles; a body turning at omega
    about the feet reads -(omega x p); the lifted leg's joints and other columns do not count."""
    from calib.joints import SDK_LEGS
    from calib.kinematics import LegKinematics
    from policy_train.refine import VEL_FRAMES, stance_velocity_map

    meta = json.loads(V21.with_suffix(".json").read_text())
    terms, q0 = meta["observation"]["terms"], np.asarray(meta["default_pose"]).reshape(4, 3)
    M = stance_velocity_map(terms, meta["default_pose"], "FL", 490, 0.02)
    assert M.shape == (2, 490)
    v = np.array([0.3, -0.2])
    x = np.zeros(490)
    for i, g in enumerate(SDK_LEGS):
        kin, h = LegKinematics.from_urdf(leg=g), 1e-6
        J = np.stack([(kin.foot_position(q0[i] + h * e) - kin.foot_position(q0[i] - h * e))
                      / (2 * h) for e in np.eye(3)], 1)
        # the foot still in the world: the base moved by d, the foot by -d in the base frame
        dq = np.linalg.solve(J, -np.r_[v * VEL_FRAMES * 0.02, 0.0]) if g != "FL" \
            else np.array([0.5, -0.4, 0.3])
        x[9 + 3 * i:12 + 3 * i] = dq  # the newest frame; the frame k steps ago at q0 (0 here)
    np.testing.assert_allclose(M @ x, v, rtol=1e-6)
    w = np.zeros(490)
    w[3:3 + 49 * VEL_FRAMES:49] = 0.1 * 0.25  # roll 0.1 rad/s in the rate's scaled units
    feet = np.mean([LegKinematics.from_urdf(leg=g).foot_position(q0[i])
                    for i, g in enumerate(SDK_LEGS) if g != "FL"], 0)
    np.testing.assert_allclose(M @ w, -np.cross([0.1, 0, 0], feet)[:2], atol=1e-12)
    with pytest.raises(ValueError, match="frames"):
        stance_velocity_map(terms, meta["default_pose"], "FL", 49 * VEL_FRAMES, 0.02)


def test_a_velocity_residual_goes_on_from_one_without(tmp_path):
    """--velocity on v22 (a residual on rate and tilt): its 72 numbers go on, the two velocity
    columns start at zero; the export reads u = [rate, tilt, x @ M.T] in its graph, and a
    refinement without --velocity refuses to go on from it."""
    import shutil

    from policy_train.refine import stance_velocity_map
    from policy_train.symmetry import ActionMirror, Mirror, policy_terms

    cfg = RefineConfig(pairs=1, episodes=1, velocity=True)
    assert cfg.n_inputs == 7 and cfg.scales.shape == (96,)
    state, lines = tmp_path / "s.json", []
    onnx_path, json_path = refine(V22, tmp_path / "r", 1, cfg, state, log=lines.append)
    saved = json.loads(state.read_text())
    rf22 = json.loads(V22.with_suffix(".json").read_text())["refined_from"]
    moved = (np.asarray(saved["params"]) - pack(rf22["D"], rf22["b"], 7)) / cfg.scales
    np.testing.assert_allclose(np.linalg.norm(moved), cfg.step * np.sqrt(96), rtol=1e-5)
    meta = json.loads(json_path.read_text())
    rf = meta["refined_from"]
    assert np.shape(rf["D"]) == (12, 7) and len(rf["inputs"]) == 7 and rf["config"]["velocity"]
    D, b = unpack(saved["params"])
    M = stance_velocity_map(meta["observation"]["terms"], meta["default_pose"], "FL", 490, 0.02)
    x = np.random.default_rng(4).normal(0, 0.3, (3, 490)).astype(np.float32)
    x[:, 48::49] = 0.25
    u = np.c_[x[:, [3, 4, 5, 6, 7]], x @ M.T]
    got = ort.InferenceSession(str(onnx_path)).run(None, {"obs": x})[0]
    src = ort.InferenceSession(str(V21)).run(None, {"obs": x})[0]
    np.testing.assert_allclose(got, src + u @ D.T + b, atol=1e-4)
    # FR's lifts, mirrored onto FL's: the velocity read from the mirrored frames, mirrored back
    x[:, 48::49] = 0.5
    terms, scale = policy_terms(meta["observation"]["terms"])
    xm = Mirror(terms, scale, 10)(torch.from_numpy(x)).numpy()
    um = np.c_[xm[:, [3, 4, 5, 6, 7]], xm @ M.T]
    want = (ort.InferenceSession(str(V21)).run(None, {"obs": x})[0]
            + ActionMirror()(torch.from_numpy(um @ D.T + b)).numpy())
    np.testing.assert_allclose(ort.InferenceSession(str(onnx_path)).run(None, {"obs": x})[0],
                               want, atol=1e-4)
    for f in (V21, V21.with_suffix(".json")):  # a refinement goes on over its network, beside it
        shutil.copy(f, tmp_path / f.name)
    with pytest.raises(ValueError, match="--velocity"):
        refine(onnx_path, tmp_path / "q", 1, RefineConfig(pairs=1, episodes=1),
               tmp_path / "q.json")
    with pytest.raises(ValueError, match="velocity must be"):
        RefineConfig(velocity="yes")
