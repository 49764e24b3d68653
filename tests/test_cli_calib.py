"""a2i-calib end to end: plan, solve (from CSV logs made here, independently of the simulator),
the refusals and input errors (exit 2, nothing written), and the simulated demo."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.csvio import write_encoders_csv, write_imu_csv
from calib.excitation import ExcitationConfig, plan_excitation
from calib.kinematics import LegKinematics
from calib.metrics import geodesic_error_deg
from cli.calib import main


@pytest.fixture(scope="module")
def fl_plan():
    return plan_excitation(ExcitationConfig(leg="FL", periods=2))


def _logs(
    tmp_path,
    plan,
    rotation,
    offset,
    *,
    noise=0.002,
    bias=(0.01, -0.02, 0.005),
    hip_still=False,
    seed=0,
):
    """Encoder CSV at 500 Hz and IMU CSV at 400 Hz (irregular) for a leg playing ``plan``."""
    rng = np.random.default_rng(seed)
    t_enc = np.arange(0.0, plan.duration, 0.002)
    q, dq = plan.positions(t_enc), plan.velocities(t_enc)
    if hip_still:
        q[:, 0], dq[:, 0] = q[0, 0], 0.0
    kin = LegKinematics.from_urdf(leg=plan.leg)
    t_imu = np.sort(rng.uniform(0.3, plan.duration - 0.3, int(400 * (plan.duration - 0.6))))
    t_true = t_imu - offset  # an IMU sample stamped t describes the motion at t - t_d
    qi = np.stack([np.interp(t_true, t_enc, q[:, j]) for j in range(3)], 1)
    dqi = np.stack([np.interp(t_true, t_enc, dq[:, j]) for j in range(3)], 1)
    omega_f = kin.foot_angular_velocity(qi, dqi)
    gyro = omega_f @ rotation + np.asarray(bias) + rng.normal(0, noise, omega_f.shape)
    full_q = np.zeros((len(t_enc), 12))
    full_dq = np.zeros((len(t_enc), 12))
    from calib.joints import sdk_indices

    full_q[:, sdk_indices(plan.leg)] = q
    full_dq[:, sdk_indices(plan.leg)] = dq
    enc, imu = tmp_path / "enc.csv", tmp_path / "imu.csv"
    write_encoders_csv(enc, t_enc, full_q, dq=full_dq)
    write_imu_csv(imu, t_imu, gyro)
    return enc, imu


def test_plan_writes_trajectory_and_reports_kappa(tmp_path, capsys):
    out = tmp_path / "traj.csv"
    assert main(["plan", "--leg", "RL", "--periods", "1", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    kappa = float(text.split("kappa(Sigma_FF) = ")[1].split()[0])
    assert kappa <= 1.02
    header = out.read_text().splitlines()[0].split(",")
    assert header == [
        "t",
        "q_RL_hip",
        "q_RL_thigh",
        "q_RL_calf",
        "dq_RL_hip",
        "dq_RL_thigh",
        "dq_RL_calf",
    ]


def test_plan_reproduces_a_policys_lift(tmp_path, capsys):
    """With the policy JSON's settings, ground clearance included, the CLI writes the plan the
    robot's lift plays (without --ground-clearance v26's differed by up to 0.46 rad)."""
    from pathlib import Path

    from deploy.lift_schedule import LiftSchedule

    meta = json.loads((Path(__file__).resolve().parents[1] / "policies"
                       / "tripod_go2_v26.json").read_text())
    ls = meta["lift_schedule"]
    out = tmp_path / "fl.csv"
    assert main(["plan", "--leg", "FL", "--offset-range", str(ls["t_r"]), "--periods",
                 str(ls["periods"]), "--basis", str(ls["n_basis"]), "--seed", str(ls["seed"]),
                 "--ground-clearance", str(ls["ground_clearance"]), "--out", str(out)]) == 0
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    plan = LiftSchedule.from_metadata({**ls, "n_basis": float(ls["n_basis"])}).plan("FL")
    np.testing.assert_allclose(data[:, 1:4], plan.positions(data[:, 0]), atol=1e-6)
    capsys.readouterr()
    with pytest.raises(SystemExit) as bad:  # argparse's one-line refusal
        main(["plan", "--leg", "FL", "--ground-clearance", "-0.1", "--out", str(out)])
    assert bad.value.code == 2


@pytest.mark.parametrize("offset", [-0.43, 0.0123, 0.31])
def test_solve_recovers_rotation_and_offset(tmp_path, fl_plan, offset, capsys):
    rot = Rotation.random(random_state=int(abs(offset) * 1e4)).as_matrix()
    enc, imu = _logs(tmp_path, fl_plan, rot, offset)
    out = tmp_path / "result.json"
    assert (
        main(["solve", "--encoders", str(enc), "--imu", str(imu), "--leg", "FL", "--out", str(out)])
        == 0
    )
    res = json.loads(out.read_text())
    assert res["leg"] == "FL" and res["version"] == 1
    assert geodesic_error_deg(np.array(res["rotation_matrix"]), rot) < 0.05
    assert abs(res["time_offset_s"] - offset) < 2e-4
    for key in (
        "quaternion_wxyz",
        "rpy_deg",
        "condition_number",
        "correlation",
        "rotation_std_deg",
        "time_offset_std_s",
        "samples",
    ):
        assert key in res
    assert "verdict: accepted" in capsys.readouterr().out


def test_solve_refuses_rank_deficient_motion_and_writes_nothing(tmp_path, fl_plan, capsys):
    rot = Rotation.random(random_state=3).as_matrix()
    enc, imu = _logs(tmp_path, fl_plan, rot, 0.05, hip_still=True)
    out = tmp_path / "result.json"
    assert (
        main(["solve", "--encoders", str(enc), "--imu", str(imu), "--leg", "FL", "--out", str(out)])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "refused" in err[0] and "eigenvalue" in err[0]
    assert not out.exists()


def test_solve_malformed_input_one_line_exit_2(tmp_path, capsys):
    enc = tmp_path / "enc.csv"
    enc.write_text("t,q_FL_hip,q_FL_thigh\n0,0,0\n")
    imu = tmp_path / "imu.csv"
    imu.write_text("t,wx,wy,wz\n0,0,0,0\n")
    out = tmp_path / "r.json"
    assert (
        main(["solve", "--encoders", str(enc), "--imu", str(imu), "--leg", "FL", "--out", str(out)])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "q_FL_calf" in err[0]
    assert not out.exists()
    assert (
        main(
            [
                "solve",
                "--encoders",
                str(tmp_path / "missing.csv"),
                "--imu",
                str(imu),
                "--leg",
                "FL",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    assert not out.exists()


def test_solve_output_problems_one_line_exit_2(tmp_path, capsys):
    (tmp_path / "outdir").mkdir()
    args = ["solve", "--encoders", str(tmp_path / "e.csv"), "--imu", str(tmp_path / "i.csv"),
            "--leg", "FL", "--out"]
    # found before the inputs are even read
    assert main([*args, str(tmp_path / "outdir")]) == 2
    assert capsys.readouterr().err.strip() == (f"a2i-calib solve: error: --out {tmp_path}/outdir: "
                                               "is a directory")
    # an output folder that cannot be made: the OSError's one line, not a traceback
    assert main(["plan", "--leg", "FL", "--out", "/proc/nope/traj.csv"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("a2i-calib plan: error: /proc/nope")


def test_bad_arguments_exit_2(capsys):
    r = subprocess.run(
        [sys.executable, "-m", "cli.calib", "plan", "--leg", "XX", "--out", "x"],
        check=False,
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "unknown leg" in r.stderr
    # once a traceback (numpy's seed) and a CSV of a few rows
    for extra, why in ((["--seed", "-1"], "seed must be an integer >= 0"),
                       (["--rate", "5"], "--rate must be >= 20 Hz")):
        assert main(["plan", "--leg", "FL", "--out", "x.csv", *extra]) == 2, extra
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and why in err[0], err
    r = subprocess.run(
        [sys.executable, "-m", "cli.calib", "--help"], check=False, capture_output=True, text=True
    )
    assert r.returncode == 0 and "solve" in r.stdout


def test_demo_recovers_hidden_mounting(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--leg", "RR", "--seed", "11", "--out", str(out)]) == 0
    res = json.loads((out / "RR.json").read_text())
    truth = json.loads((out / "sim_truth.json").read_text())["RR"]
    assert (
        geodesic_error_deg(np.array(res["rotation_matrix"]), np.array(truth["rotation_matrix"]))
        < 0.5
    )
    assert abs(res["time_offset_s"] - truth["time_offset_s"]) < 1e-3
    assert "against truth" in capsys.readouterr().out


def test_bench_renders_saved_rows_without_simulating(tmp_path):
    rows = [
        {
            "leg": "FL",
            "noise_deg": 0.03,
            "motion": m,
            "pipeline": p,
            "seed": 0,
            "cn": cn,
            "cc": cc,
            "re_euler_deg": re,
            "geodesic_deg": re,
            "offset_error_s": 1e-5,
            "gates_pass": m == "a2i",
        }
        for m, cn, cc, re in (
            ("walk", 900.0, 0.9, 30.0),
            ("spin", 400.0, 0.9, 20.0),
            ("wave", 60.0, 0.8, 40.0),
            ("a2i", 1.1, 0.999, 0.01),
        )
        for p in ("paper", "ours")
    ]
    src = tmp_path / "rows.json"
    src.write_text(json.dumps(rows))
    out = tmp_path / "t1.md"
    assert main(["bench", "--from-json", str(src), "--out", str(out)]) == 0
    text = out.read_text()
    assert "| FL | 0.03 | a2i |" in text and "| paper | 1/1 | 1/1 | 1/1 |" in text
    assert main(["bench", "--from-json", str(tmp_path / "none.json"), "--out", str(out)]) == 2
