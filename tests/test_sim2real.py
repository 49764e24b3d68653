"""Sim-to-real diagnosis: readers (CSV, MCAP), replay, a latency and a null case, the CLI's
JSON schema and report."""

import dataclasses
import json

import numpy as np
import pytest

from sim.effects import ActuationLatency
from sim2real import metrics as mt
from sim2real.cli import main
from sim2real.diagnose import DiagnoseConfig, diagnose
from sim2real.recording import read_csv, read_mcap_recording, write_csv
from sim2real.replay import Replayer, make_windows
from sim2real.synth import SynthConfig, synthesize, write_mcap_recording


@pytest.fixture(scope="module")
def short_null():
    return synthesize([], SynthConfig(mount="suspended", duration=3.0, seed=5))


@pytest.fixture(scope="module")
def short_latency():
    return synthesize([ActuationLatency(0.015)],
                      SynthConfig(mount="suspended", duration=3.0, seed=6))


# ---------------------------------------------------------------------------- CSV reader
def _write(tmp_path, rec, name="rec"):
    return write_csv(rec, tmp_path / f"{name}.csv")


def _one_line_error(path, match, **kw):
    with pytest.raises(ValueError, match=match) as exc:
        read_csv(path, **kw)
    assert "\n" not in str(exc.value)


def test_csv_round_trip(tmp_path, short_null):
    p = _write(tmp_path, short_null)
    back = read_csv(p)
    np.testing.assert_allclose(back.q, short_null.q, atol=1e-8)
    np.testing.assert_allclose(back.cmd_t, short_null.cmd_t, atol=1e-9)
    assert back.mount == "suspended"
    assert json.loads(p.with_suffix(".json").read_text()) == {"mount": "suspended"}


def test_csv_errors_are_one_line(tmp_path, short_null):
    p = _write(tmp_path, short_null)
    text = p.read_text().splitlines()
    # missing json
    p.with_suffix(".json").unlink()
    _one_line_error(p, "mount")
    p.with_suffix(".json").write_text('{"mount": "table"}')
    _one_line_error(p, "suspended")
    p.with_suffix(".json").write_text('{"mount": "ground"}')
    # missing column
    header = text[0].split(",")
    k = header.index("cmd_kp_FR_hip")
    bad = tmp_path / "bad.csv"
    bad.with_suffix(".json").write_text('{"mount": "ground"}')
    bad.write_text("\n".join(",".join(c for i, c in enumerate(r.split(",")) if i != k)
                             for r in text) + "\n")
    _one_line_error(bad, "cmd_kp_FR_hip")
    # non-numeric value
    rows = list(text)
    rows[5] = rows[5].replace(rows[5].split(",")[3], "abc", 1)
    bad.write_text("\n".join(rows) + "\n")
    _one_line_error(bad, "non-numeric")
    # time not increasing
    rows = list(text)
    rows[3], rows[4] = rows[4], rows[3]
    bad.write_text("\n".join(rows) + "\n")
    _one_line_error(bad, "increasing")
    _one_line_error(tmp_path / "nope.csv", "no such file")
    assert main(["diagnose", str(tmp_path / "nope.csv"), "--quiet"]) == 2


def test_outputs_and_windows_are_checked_before_the_diagnosis(tmp_path, short_null, capsys):
    p = _write(tmp_path, short_null)
    (tmp_path / "jdir").mkdir()
    assert main(["diagnose", str(p), "--quiet", "--json", str(tmp_path / "jdir")]) == 2
    assert capsys.readouterr().err.strip() == f"a2i-sim2real: error: {tmp_path / 'jdir'}: is a directory"
    # 1e-9 s windows asked numpy for 15 GiB of edges
    for w in ("1e-9", "nan"):
        assert main(["diagnose", str(p), "--quiet", "--window", w]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "window length must be at least" in err
    with pytest.raises(ValueError, match="at least"):
        make_windows(short_null, 0.0)
    # an output folder that cannot be made: one line, exit 2
    assert main(["synth", "/proc/nope/rec.csv", "--duration", "2"]) == 2
    assert capsys.readouterr().err.strip().startswith("a2i-sim2real: error: /proc/nope")


# ---------------------------------------------------------------------------- MCAP input
def test_mcap_input(tmp_path, short_latency):
    p = tmp_path / "rec.mcap"
    write_mcap_recording(short_latency, p)
    back = read_mcap_recording(p)
    assert back.mount == "suspended"
    np.testing.assert_allclose(back.q, short_latency.q, atol=1e-6)  # float32 on the wire
    np.testing.assert_allclose(back.cmd_t, short_latency.cmd_t, atol=1e-9)
    np.testing.assert_allclose(back.cmd["q"], short_latency.cmd["q"], atol=1e-6)
    assert back.mount == "suspended"
    assert read_mcap_recording(p, mount="ground").mount == "ground"


# ---------------------------------------------------------------------------- replay
def test_replay_reproduces_a_null_recording(short_null):
    p = Replayer(short_null).run([], make_windows(short_null, 0.5))
    err = np.abs(p.q[p.mask] - short_null.q[p.mask]).max()
    assert err < 2e-3  # encoder quantisation and float32 only
    lat = synthesize([ActuationLatency(0.015)], SynthConfig(mount="suspended", duration=3.0,
                                                            seed=5))
    p2 = Replayer(lat).run([], make_windows(lat, 0.5))
    assert np.abs(p2.q[p2.mask] - lat.q[p2.mask]).max() > 10 * err


# ---------------------------------------------------------------------------- diagnosis
def test_null_case_is_no_significant_gap(short_null):
    d = diagnose(short_null, DiagnoseConfig())
    assert not d.significant_gap
    assert d.to_json()["effects"] == []


def test_latency_case_via_cli_json_and_report(tmp_path, short_latency):
    csv_path = _write(tmp_path, short_latency, "lat")
    out_json = tmp_path / "out.json"
    out_html = tmp_path / "out.html"
    assert main(["diagnose", str(csv_path), "--json", str(out_json), "--report",
                 str(out_html), "--quiet"]) == 0
    doc = json.loads(out_json.read_text())
    assert set(doc) >= {"significant_gap", "gap_before", "effects"}
    assert isinstance(doc["significant_gap"], bool) and doc["significant_gap"]
    assert isinstance(doc["gap_before"], float)
    for e in doc["effects"]:
        assert set(e) >= {"name", "location", "parameters", "ci", "gap_after_heldout"}
        assert isinstance(e["location"], list)
        for k, v in e["parameters"].items():
            lo, hi = e["ci"][k]
            assert lo <= v <= hi
    top = doc["effects"][0]
    assert top["name"] == "latency" and top["location"] == ["all"]
    assert top["parameters"]["seconds"] == pytest.approx(0.015, abs=0.003)
    assert top["gap_after_heldout"] < 0.5 * doc["gap_before"]
    page = out_html.read_text()
    assert page.startswith("<!DOCTYPE html>") and "data:image/png;base64," in page
    assert "latency" in page


# ---------------------------------------------------------------------------- ground replay
def test_ground_replay_burn_in_settles_the_contacts():
    """On the ground, each window starts after a burn-in in which the base settles on its
    contacts: a null recording replays close to the recording, a 20 ms latency clearly not."""
    from sim2real import metrics as mt

    cfg = SynthConfig(mount="ground", duration=2.0, seed=3)
    null = synthesize([], cfg)
    lat = synthesize([ActuationLatency(0.02)], cfg)
    gaps = []
    for rec in (null, lat):
        cs = mt.channel_set(rec)
        windows = make_windows(rec, 0.5)
        p = Replayer(rec).run([], windows)
        assert p.failed == 0
        # the first window loses its burn-in, the others compare from their start
        assert not p.mask[: windows[0][0] + 10].any() and p.mask[windows[1][0] + 1]
        gaps.append(mt.gap(mt.normalised_residual(cs, mt.pred_matrix(p), p.mask), cs.noise))
    assert gaps[0] < 0.045  # the ground re-synchronisation floor (docs/sim2real.md)
    assert gaps[1] > 2 * gaps[0]



def test_motion_capture_does_not_take_the_attitude_from_the_diagnosed_imu():
    """With motion-capture columns the replay still tilts the base from the legs: when it took
    the body IMU's quaternion and rate, a misaligned IMU tilted the simulated robot with it (a
    gap of 0.6 that no IMU candidate explained, and "no significant gap"). The mocap replay
    keeps the burn-in, so its floor is no worse than the legs-only one."""
    from sim.effects import ImuMisalignment

    rv = np.deg2rad(4.0) * np.array([0.6, -0.8, 0.0])
    cfg = SynthConfig(mount="ground", duration=6.0, seed=5, base_truth=True)
    rec = synthesize([ImuMisalignment(rv)], cfg)
    assert rec.base_pos is not None
    d = diagnose(rec, DiagnoseConfig())
    assert d.significant_gap and d.effects[0].name == "imu_misalignment"
    fit = d.effects[0].parameters
    np.testing.assert_allclose([fit["rot_x"], fit["rot_y"]], rv[:2], atol=np.deg2rad(0.3))
    assert d.gap_after < 0.25 * d.gap_before

    null = synthesize([], cfg)
    cs = mt.channel_set(null)

    def floor(rec):
        p = Replayer(rec).run([], make_windows(rec, 0.5))
        return mt.gap(mt.normalised_residual(cs, mt.pred_matrix(p), p.mask), cs.noise)

    legs_only = floor(dataclasses.replace(null, base_pos=None, base_vel=None))
    assert floor(null) <= legs_only < 0.045

def test_torque_limit_search_stays_where_the_limit_binds():
    from sim2real.candidates import dynamic_candidates
    from sim2real.diagnose import _peak_torque

    rec = synthesize([], SynthConfig(mount="suspended", duration=1.0, seed=2))
    peak = _peak_torque(rec)
    assert peak.shape == (12,) and np.all(peak > 0)
    c = {x.name: x for x in dynamic_candidates("FL_calf", "suspended", float(peak[5]))}
    tl = c["torque_limit"]
    assert tl.hi[0] == pytest.approx(1.2 * peak[5]) and 0 < tl.lo[0] < tl.hi[0]
    assert "latency" not in c
    assert "latency" in {x.name for x in dynamic_candidates("FL_calf", "ground", 3.0)}


def test_candidates_cover_carried_links_and_log_torque_grid():
    from sim2real.candidates import dynamic_candidates

    cands = dynamic_candidates("RR_hip", "suspended", 6.0, plateau=0.7)
    assert {c.location for c in cands if c.name == "link_mass"} == {"RR_hip", "RR_thigh",
                                                                   "RR_calf"}
    assert {c.location for c in dynamic_candidates("RR_calf", "suspended", 6.0)
            if c.name == "link_mass"} == {"RR_calf"}
    tl = next(c for c in cands if c.name == "torque_limit")
    assert tl.log and tl.hints == (0.7,)


def test_outlier_windows_are_left_out_only_when_no_candidate_explains_them(short_null):
    from sim2real.diagnose import EffectFit, _outlier_windows, _Problem, _scored_windows

    ms = np.array([0.010, 0.012, 0.011, 0.30, 0.009, 0.013, 0.010])
    assert _outlier_windows(ms).tolist() == [False] * 3 + [True] + [False] * 3
    assert not _outlier_windows(np.full(7, 0.02)).any()
    pb = _Problem(short_null, DiagnoseConfig())
    c = len(pb.cs.names)
    n0 = np.full(5, 200.0)
    level = np.array([0.01, 0.01, 1.0, 0.01, 0.01])  # window 2: a residual nothing explains
    ss0 = n0[:, None] * (pb.cs.noise + level[:, None])
    outl = np.array([False, False, True, False, False])

    def fit(scale):
        f = EffectFit("x", ["all"], {}, {}, 0.0, 0.0, 1)
        f.win_ss, f.win_n = n0[:, None] * (pb.cs.noise + scale[:, None] * level[:, None]), n0
        return f

    partial = fit(np.array([0.1, 0.1, 0.95, 0.1, 0.1]))
    assert _scored_windows(pb, ss0, n0, outl, [partial]).tolist() == [1, 1, 0, 1, 1]
    full = fit(np.full(5, 0.1))
    assert _scored_windows(pb, ss0, n0, outl, [partial, full]).all()
    assert ss0.shape == (5, c)


def test_a_jointly_refitted_pair_reports_its_own_intervals():
    # armature + backlash on one thigh: the pair's refit moves both parameters, whose intervals
    # were the single fits' and held neither the estimates nor the truth
    from sim import effects as fx

    rec = synthesize([fx.Armature(0.02, joints=["RL_thigh"]), fx.Backlash(0.02, joints=["RL_thigh"])],
                     SynthConfig(mount="suspended", duration=4.0, seed=1))
    d = diagnose(rec)
    chosen = [e for e in d.effects if e.chosen]
    assert {e.name for e in chosen} == {"armature", "backlash"}
    for e in chosen:
        for k, v in e.parameters.items():
            assert e.ci[k][0] <= v <= e.ci[k][1], (e.name, v, e.ci[k])
    assert d.effects[1].ci["half_width"][0] <= 0.02 <= d.effects[1].ci["half_width"][1]


def test_packet_loss_pays_in_its_bic_for_the_drops_found_on_the_held_out_windows():
    """The held-out windows are replayed with the drops found on them (which packets a robot
    loses cannot be predicted), so those drops, one parameter each, are the BIC's; the training
    windows' drops touch no held-out window."""
    from sim.effects import PacketLoss
    from sim2real.diagnose import _detect_drops, _fit_packet_loss, _Problem

    rec = synthesize([PacketLoss(0.25)], SynthConfig(mount="suspended", duration=3.0, seed=4))
    pb = _Problem(rec, DiagnoseConfig())
    fit = _fit_packet_loss(pb)
    held_drops, _ = _detect_drops(pb, pb.held)
    train_drops, _ = _detect_drops(pb, pb.train)
    assert held_drops.size > 0 and held_drops.size != train_drops.size
    assert fit.k_bic == held_drops.size and fit.k == train_drops.size
    in_held = [any(rec.t[a] <= t < rec.t[b - 1] for a, b in pb.held) for t in fit.drop_times]
    assert sum(in_held) == held_drops.size


def test_a_foot_imu_node_s_mass_is_found_as_its_calf_s(tmp_path, capsys):
    """The node a foot IMU sits in (``sim.effects.FootPayload``, 80 g above the foot) is no
    candidate of its own: the diagnoser finds it as a heavier calf on its leg."""
    rec = tmp_path / "node.csv"
    assert main(["synth", str(rec), "--mount", "suspended", "--effect", "foot_payload=0.08@FL",
                 "--seed", "3"]) == 0
    out = tmp_path / "d.json"
    assert main(["diagnose", str(rec), "--quiet", "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    assert d["significant_gap"]
    assert (d["effects"][0]["name"], d["effects"][0]["location"]) == ("link_mass", ["FL_calf"])
    assert d["gap_after"] < 0.2 * d["gap_before"]
    capsys.readouterr()
    assert main(["synth", str(rec), "--effect", "foot_payload=0.08"]) == 2
    assert "needs its leg" in capsys.readouterr().err
