"""The documented CSV inputs: round trips, differentiation, base rotation, every error path."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.csvio import (
    MIN_ROWS,
    CalibInputError,
    EncoderLog,
    read_encoders_csv,
    read_imu_csv,
    smooth_derivative,
    write_encoders_csv,
    write_imu_csv,
)
from calib.joints import SDK_LEGS, sdk_indices

QUANT = 2 * np.pi / 2**15  # encoder resolution used in the tests, rad


def _leg_file(path, n=200, rate=500.0, leg="FL", **kw):
    t = 10.0 + np.arange(n) / rate
    q = np.stack([0.1 * np.sin(t), 0.8 + 0.2 * np.sin(2 * t), -1.5 + 0.1 * np.cos(t)], 1)
    write_encoders_csv(path, t, q, leg=leg, **kw)
    return t, q


def _write_lines(path, header: str, rows: list[str]) -> str:
    path.write_text("\n".join([header, *rows]) + "\n")
    return str(path)


def _rows(n=60, start=0.0, dt=0.01, ncols=3):
    return [
        ",".join([f"{start + i * dt:.6f}"] + [f"{0.1 * i + k:.4f}" for k in range(ncols)])
        for i in range(n)
    ]


def _error(fn, *args, **kw) -> str:
    with pytest.raises(CalibInputError) as exc:
        fn(*args, **kw)
    msg = str(exc.value)
    assert "\n" not in msg
    assert isinstance(exc.value, ValueError)
    return msg


# ------------------------------------------------------------------------------ round trips
def test_full_robot_round_trip_in_sdk_order(tmp_path):
    rng = np.random.default_rng(0)
    n = 300
    t = 1.7e9 + np.arange(n) * 0.002 + rng.uniform(0, 1e-4, n)  # Unix-time stamps
    q, dq = rng.normal(size=(n, 12)), rng.normal(size=(n, 12))
    w = rng.normal(size=(n, 3))
    path = write_encoders_csv(tmp_path / "enc.csv", t, q, dq=dq, base_omega=w)
    header = path.read_text().splitlines()[0].split(",")
    assert header[:4] == ["t", "q_FR_hip", "q_FR_thigh", "q_FR_calf"]
    assert header[13:16] == ["dq_FR_hip", "dq_FR_thigh", "dq_FR_calf"]
    assert header[-3:] == ["base_wx", "base_wy", "base_wz"]
    for leg in SDK_LEGS:
        log = read_encoders_csv(path, leg.lower())
        assert isinstance(log, EncoderLog) and log.leg == leg
        np.testing.assert_array_equal(log.t, t)  # stamps round-trip exactly
        np.testing.assert_allclose(log.q, q[:, sdk_indices(leg)], rtol=1e-8, atol=1e-9)
        np.testing.assert_allclose(log.dq, dq[:, sdk_indices(leg)], rtol=1e-8, atol=1e-9)
        assert log.dq_measured
        np.testing.assert_allclose(log.base_omega, w, rtol=1e-8, atol=1e-9)
        assert log.base_omega_source == "gyro"
        assert log.duplicates_dropped == 0


def test_imu_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    t = np.arange(100) * 0.005
    g, a = rng.normal(size=(100, 3)), rng.normal(size=(100, 3))
    log = read_imu_csv(write_imu_csv(tmp_path / "imu.csv", t, g, a))
    np.testing.assert_array_equal(log.t, t)
    np.testing.assert_allclose(log.gyro, g, rtol=1e-8)
    np.testing.assert_allclose(log.accel, a, rtol=1e-8)
    log = read_imu_csv(write_imu_csv(tmp_path / "imu2.csv", t, g))
    assert log.accel is None


def test_writers_are_atomic_and_validate(tmp_path):
    _leg_file(tmp_path / "e.csv")
    _leg_file(tmp_path / "e.csv")  # overwrite
    assert sorted(os.listdir(tmp_path)) == ["e.csv"]  # no temp file left behind
    t = np.arange(60) * 0.01
    with pytest.raises(ValueError, match=r"q must have shape \(60, 12\)"):
        write_encoders_csv(tmp_path / "x.csv", t, np.zeros((60, 3)))
    with pytest.raises(ValueError, match="strictly increasing"):
        write_encoders_csv(tmp_path / "x.csv", t[::-1], np.zeros((60, 12)))
    with pytest.raises(ValueError, match="non-finite"):
        write_imu_csv(tmp_path / "x.csv", t, np.full((60, 3), np.nan))
    with pytest.raises(ValueError, match="unknown leg"):
        write_encoders_csv(tmp_path / "x.csv", t, np.zeros((60, 3)), leg="LF")


def test_any_column_order_extra_columns_comments_bom_crlf(tmp_path):
    n = 60
    lines = [
        "\ufeff# logged by someone else's tool",
        "",
        "note,q_FL_calf,t,q_FR_hip,q_FL_hip,q_FL_thigh,mode",
    ]
    for i in range(n):
        lines.append(f"hello #{i},{-1.5 + i * 1e-3},{i * 0.01},9,{0.1},{0.2 + i * 1e-3},x")
        if i == 10:
            lines.append("# a comment in the middle")
            lines.append("   ")
    (tmp_path / "e.csv").write_bytes("\r\n".join(lines).encode("utf-8"))
    log = read_encoders_csv(tmp_path / "e.csv", "FL")
    assert log.q.shape == (n, 3)
    np.testing.assert_allclose(log.t, np.arange(n) * 0.01)
    np.testing.assert_allclose(log.q[:, 0], 0.1)
    np.testing.assert_allclose(log.q[:, 2], -1.5 + np.arange(n) * 1e-3)
    assert not log.dq_measured and log.base_omega is None and log.base_omega_source is None
    np.testing.assert_allclose(log.dq, [[0.0, 0.1, 0.1]] * n, atol=1e-9)


# ------------------------------------------------------------------------------ differentiation
@pytest.mark.parametrize("rate", [100.0, 1000.0])
def test_derivative_of_quantised_sine_on_jittered_stamps(rate):
    rng = np.random.default_rng(int(rate))
    n = int(20 * rate)
    dt = 1.0 / rate
    t = np.arange(n) * dt + rng.uniform(-0.3, 0.3, n) * dt  # irregular sampling instants
    amp, w = 1.0, 2 * np.pi * 1.0  # 1 Hz, peak rate 6.3 rad/s
    y = np.round(amp * np.sin(w * t + 0.3) / QUANT) * QUANT
    truth = amp * w * np.cos(w * t + 0.3)
    d = smooth_derivative(t, y)
    rms = np.sqrt(np.mean((d - truth) ** 2))
    naive = np.sqrt(np.mean((np.gradient(y, t) - truth) ** 2))
    assert rms < 0.01, rms  # < 0.16 % of the peak rate
    assert np.abs(d - truth)[5:-5].max() < 0.03
    assert rms <= 1.05 * naive  # never worse than a central difference
    if rate == 1000.0:
        assert rms < naive / 8, (rms, naive)  # quantisation averaged out


def test_derivative_exact_for_quadratics_on_irregular_stamps():
    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(0.2e-3, 3e-3, 3000))
    y = np.stack([1.0 + 2.0 * t - 3.0 * t**2, -t + 0.5 * t**2], 1)
    d = smooth_derivative(t, y)
    np.testing.assert_allclose(d, np.stack([2.0 - 6.0 * t, -1.0 + t], 1), atol=1e-9)
    # A gap of half a second in the middle does not break it.
    t2 = np.concatenate([t[:1000], t[1000:] + 0.5])
    np.testing.assert_allclose(smooth_derivative(t2, 3.0 * t2**2), 6.0 * t2, atol=1e-8)
    with pytest.raises(ValueError, match="strictly increasing"):
        smooth_derivative(t[::-1], y[::-1])
    with pytest.raises(ValueError, match="at least 3"):
        smooth_derivative(t[:2], y[:2])


def test_encoder_file_without_dq_is_differentiated(tmp_path):
    rng = np.random.default_rng(4)
    n = 5000
    t = np.arange(n) * 1e-3 + rng.uniform(-0.2e-3, 0.2e-3, n)
    w = 2 * np.pi * np.array([0.5, 1.0, 1.5])
    q = np.round(0.5 * np.sin(w * t[:, None]) / QUANT) * QUANT
    write_encoders_csv(tmp_path / "e.csv", t, q, leg="RR")
    log = read_encoders_csv(tmp_path / "e.csv", "RR")
    assert not log.dq_measured
    truth = 0.5 * w * np.cos(w * t[:, None])
    assert np.sqrt(np.mean((log.dq - truth) ** 2)) < 0.01


# ------------------------------------------------------------------------------ base rotation
def test_base_rotation_from_quaternions_and_gyro_preferred(tmp_path):
    n = 400
    t = np.arange(n) * 0.005
    rates = np.array([0.3, -0.2, 1.1])  # constant body rate, rad/s
    rot = Rotation.from_rotvec(t[:, None] * rates)  # R_W^B(t) = exp(t [w]) : body rate = w
    quat = rot.as_quat(scalar_first=True)
    quat[::3] *= -1  # sign flips, as some loggers do
    q = np.zeros((n, 3))
    write_encoders_csv(tmp_path / "quat.csv", t, q, leg="FR", base_quat_wxyz=quat)
    log = read_encoders_csv(tmp_path / "quat.csv", "FR")
    assert log.base_omega_source == "quaternion"
    np.testing.assert_allclose(log.base_omega, np.tile(rates, (n, 1)), atol=1e-6)
    gyro = np.tile([9.0, 8.0, 7.0], (n, 1))
    write_encoders_csv(tmp_path / "both.csv", t, q, leg="FR", base_omega=gyro, base_quat_wxyz=quat)
    log = read_encoders_csv(tmp_path / "both.csv", "FR")
    assert log.base_omega_source == "gyro"
    np.testing.assert_allclose(log.base_omega, gyro)


# ------------------------------------------------------------------------------ errors
def test_missing_file_directory_and_empty(tmp_path):
    msg = _error(read_encoders_csv, tmp_path / "nope.csv", "FL")
    assert msg == f"{tmp_path / 'nope.csv'}: file not found"
    assert "not a regular file" in _error(read_imu_csv, tmp_path)
    (tmp_path / "empty.csv").write_text("")
    assert _error(read_imu_csv, tmp_path / "empty.csv").endswith("empty.csv: file is empty")
    (tmp_path / "blank.csv").write_text("\n  \n\n")
    assert _error(read_imu_csv, tmp_path / "blank.csv").endswith(": file is empty")
    (tmp_path / "comments.csv").write_text("# only\n# comments\n")
    assert "only blank or comment lines" in _error(read_imu_csv, tmp_path / "comments.csv")
    (tmp_path / "bin.csv").write_bytes(b"t,wx\n\xff\xfe\n")
    assert "not UTF-8" in _error(read_imu_csv, tmp_path / "bin.csv")


def test_header_problems(tmp_path):
    p = _write_lines(tmp_path / "nohdr.csv", "0.0,1,2,3", _rows())
    assert "line 1: no header row" in _error(read_imu_csv, p)
    p = _write_lines(tmp_path / "dup.csv", "t,wx,wy,wx", _rows())
    assert "line 1: duplicate column name(s) wx" in _error(read_imu_csv, p)
    p = _write_lines(tmp_path / "miss.csv", "t,wx,wy,speed", _rows())
    assert _error(read_imu_csv, p) == f"{p}: missing column(s) wz"
    p = _write_lines(tmp_path / "case.csv", "t,Q_FL_HIP,q_FL_thigh,q_FL_calf", _rows())
    msg = _error(read_encoders_csv, p, "FL")
    assert "missing column(s) q_FL_hip (leg FL)" in msg and "case-sensitive" in msg
    p = _write_lines(tmp_path / "leg.csv", "t,q_FR_hip,q_FR_thigh,q_FR_calf", _rows())
    msg = _error(read_encoders_csv, p, "FL")
    assert "missing column(s) q_FL_hip, q_FL_thigh, q_FL_calf (leg FL)" in msg


def test_partial_column_groups(tmp_path):
    hdr = "t,q_FL_hip,q_FL_thigh,q_FL_calf"
    p = _write_lines(tmp_path / "dq.csv", hdr + ",dq_FL_hip,dq_FL_thigh", _rows(ncols=5))
    msg = _error(read_encoders_csv, p, "FL")
    assert "has dq_FL_hip, dq_FL_thigh but not dq_FL_calf" in msg
    assert "velocity (leg FL) columns or none" in msg
    p = _write_lines(tmp_path / "g.csv", hdr + ",base_wx,base_wz", _rows(ncols=5))
    assert "but not base_wy: give all 3 base gyro columns" in _error(read_encoders_csv, p, "FL")
    p = _write_lines(tmp_path / "qt.csv", hdr + ",base_qw,base_qx,base_qy", _rows(ncols=6))
    assert "but not base_qz: give all 4 base quaternion" in _error(read_encoders_csv, p, "FL")
    p = _write_lines(tmp_path / "a.csv", "t,wx,wy,wz,ax", _rows(ncols=4))
    assert "but not ay, az: give all 3 accelerometer" in _error(read_imu_csv, p)


def test_bad_cells_name_line_and_column(tmp_path):
    rows = _rows()
    rows[7] = "0.07,0.1,abc,0.3"
    p = _write_lines(tmp_path / "text.csv", "t,wx,wy,wz", rows)
    assert _error(read_imu_csv, p) == f"{p}: line 9, column wy: cannot read 'abc' as a number"
    rows = _rows()
    rows[3] = "0.03,0.1,0.2,"
    p = _write_lines(tmp_path / "emptycell.csv", "t,wx,wy,wz", rows)
    assert _error(read_imu_csv, p) == f"{p}: line 5, column wz: empty cell"
    rows = _rows()
    rows[20] = "0.2,nan,0.2,0.3"
    p = _write_lines(tmp_path / "nan.csv", "# comment first\nt,wx,wy,wz", rows)
    assert _error(read_imu_csv, p) == f"{p}: line 23, column wx: non-finite value nan"
    rows = _rows()
    rows[30] = "0.3,0.1,-inf,0.3"
    p = _write_lines(tmp_path / "inf.csv", "t,wx,wy,wz", rows)
    assert _error(read_imu_csv, p) == f"{p}: line 32, column wy: non-finite value -inf"
    rows = _rows()
    rows[-1] = "0.59,0.1,0.2"  # a truncated last line (logger killed mid-write)
    p = _write_lines(tmp_path / "trunc.csv", "t,wx,wy,wz", rows)
    assert _error(read_imu_csv, p) == f"{p}: line 61: 3 fields, the header has 4"
    # A row with a field too many and another with one too few: the comma total is right,
    # every row is still counted (np.loadtxt would have read the first one shifted).
    rows = _rows()
    rows[10], rows[12] = "0.1,1,999,2,3", "0.12,1,2"
    p = _write_lines(tmp_path / "shifted.csv", "t,wx,wy,wz", rows)
    assert _error(read_imu_csv, p) == f"{p}: line 12: 5 fields, the header has 4"
    # blank and whitespace-only lines are skipped, also before the header
    p = _write_lines(tmp_path / "blank.csv", "  \nt,wx,wy,wz", _rows()[:30] + ["\t"] + _rows()[30:])
    assert read_imu_csv(p).gyro.shape == (60, 3)
    # Text in an ignored column is fine; text in a used one of an encoder file is named.
    rows = [r + ",x" for r in _rows()]
    p = _write_lines(tmp_path / "ok.csv", "t,wx,wy,wz,label", rows)
    assert read_imu_csv(p).gyro.shape == (60, 3)
    rows = _rows()
    rows[0] = "0.0,0.1,0.2,1e999x"
    p = _write_lines(tmp_path / "enc.csv", "t,q_RL_hip,q_RL_thigh,q_RL_calf", rows)
    assert "line 2, column q_RL_calf: cannot read '1e999x'" in _error(read_encoders_csv, p, "RL")


def test_timestamp_policy(tmp_path):
    hdr = "t,wx,wy,wz"
    rows = _rows()
    rows.insert(11, rows[10])  # exact duplicate row: dropped
    rows.insert(30, rows[29])
    log = read_imu_csv(_write_lines(tmp_path / "dup.csv", hdr, rows))
    assert log.duplicates_dropped == 2 and log.t.size == 60
    assert np.all(np.diff(log.t) > 0)
    rows = _rows()
    rows[11] = rows[10].rsplit(",", 1)[0] + ",123"  # same stamp, different values
    p = _write_lines(tmp_path / "rep.csv", hdr, rows)
    assert _error(read_imu_csv, p) == (
        f"{p}: line 13: timestamp 0.1 s repeats line 12 with different values; "
        "stamps must strictly increase"
    )
    rows = _rows()
    rows[20], rows[21] = rows[21], rows[20]
    p = _write_lines(tmp_path / "back.csv", hdr, rows)
    msg = _error(read_imu_csv, p)
    assert msg.startswith(f"{p}: line 23: timestamp 0.2 s goes back from 0.21 s (line 22)")
    assert "not re-sorted" in msg
    p = _write_lines(tmp_path / "ns.csv", hdr, _rows(start=1.7e18, dt=2e6))
    msg = _error(read_imu_csv, p)
    assert "column t: median step 2.0" in msg and "e+06 s is above 0.05 s; t must be in seconds" in msg
    # milliseconds at 1 kHz step by 1.0: read as seconds they made a 0.3 ms offset 0.3 s
    p = _write_lines(tmp_path / "ms.csv", hdr, _rows(start=5000.0, dt=1.0))
    assert "median step 1 s is above 0.05 s" in _error(read_imu_csv, p)


def test_row_count(tmp_path):
    hdr = "t,wx,wy,wz"
    p = _write_lines(tmp_path / "49.csv", hdr, _rows(MIN_ROWS - 1))
    assert _error(read_imu_csv, p) == f"{p}: 49 data rows, need at least 50"
    assert read_imu_csv(_write_lines(tmp_path / "50.csv", hdr, _rows(MIN_ROWS))).t.size == 50
    rows = _rows(MIN_ROWS)
    rows.append(rows[-1])
    rows[1] = rows[0]
    p = _write_lines(tmp_path / "dups.csv", hdr, rows)
    assert _error(read_imu_csv, p) == (
        f"{p}: 49 samples after dropping 2 duplicate row(s), need at least 50"
    )
    p = _write_lines(tmp_path / "hdronly.csv", hdr, [])
    assert _error(read_imu_csv, p) == f"{p}: 0 data rows, need at least 50"


def test_wrong_leg_and_zero_quaternion(tmp_path):
    _leg_file(tmp_path / "e.csv")
    msg = _error(read_encoders_csv, tmp_path / "e.csv", "LF")
    assert msg == f"{tmp_path / 'e.csv'}: unknown leg 'LF': expected one of FR, FL, RR, RL"
    n = 80
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    quat[40] = 0.0
    write_encoders_csv(
        tmp_path / "z.csv", np.arange(n) * 0.01, np.zeros((n, 3)), leg="FL", base_quat_wxyz=quat
    )
    assert "line 42, columns base_q*: zero quaternion" in _error(
        read_encoders_csv, tmp_path / "z.csv", "FL"
    )


# ------------------------------------------------------------------------------ speed
def test_reads_20000_rows_quickly(tmp_path):
    rng = np.random.default_rng(5)
    n = 20000
    t = np.arange(n) * 2e-3
    write_encoders_csv(tmp_path / "e.csv", t, rng.normal(size=(n, 12)))
    write_imu_csv(tmp_path / "i.csv", t, rng.normal(size=(n, 3)))
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        read_encoders_csv(tmp_path / "e.csv", "FL")  # includes differentiating positions
        read_imu_csv(tmp_path / "i.csv")
        best = min(best, time.perf_counter() - t0)
    # Typically ~0.1 s for both on one free core; the bound only catches a per-cell Python loop
    # on a busy shared machine.
    assert best < 1.0, best
