"""CalibrationResult: JSON schema, validation, atomic write, report."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calib.metrics import rotation_from_rpy_deg
from calib.result import REQUIRED_FIELDS, CalibrationResult, format_report
from calib.solver import CalibrationRefused, solve
from calib.synthetic import make_case


@pytest.fixture(scope="module")
def solved():
    case = make_case(21, time_offset=0.0123, noise_density=1e-3)
    return case, solve(case.t_enc, case.omega_foot, case.t_imu, case.omega_imu)


def _example() -> CalibrationResult:
    return CalibrationResult(
        leg="fl", rotation_matrix=rotation_from_rpy_deg(10, -5, 90), time_offset_s=0.0123,
        condition_number=1.7, correlation=0.998, rotation_std_deg=0.02,
        time_offset_std_s=2e-5, samples=6000, min_eigenvalue=0.3,
        created_utc="2025-01-01T00:00:00+00:00",
    )


def test_dict_has_exact_field_names_and_round_trips():
    res = _example()
    d = res.to_dict()
    assert set(REQUIRED_FIELDS) <= set(d)
    assert d["version"] == 1 and d["leg"] == "FL" and d["foot_frame"] == "FL_foot"
    assert np.asarray(d["rotation_matrix"]).shape == (3, 3)
    np.testing.assert_allclose(d["rpy_deg"], [10, -5, 90], atol=1e-9)
    back = CalibrationResult.from_dict(json.loads(json.dumps(d)))
    np.testing.assert_allclose(back.rotation_matrix, res.rotation_matrix)
    assert back.to_dict() == d


def test_write_read_atomic(tmp_path):
    res = _example()
    path = res.write(tmp_path / "calibration" / "FL.json")
    assert path.exists() and not list(path.parent.glob(".*.tmp"))
    back = CalibrationResult.read(path)
    assert back.to_dict() == res.to_dict()
    assert json.loads(path.read_text())["time_offset_s"] == pytest.approx(0.0123)


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda d: d.pop("time_offset_s"), "lacks field"),
        (lambda d: d.update(version=2), "schema version"),
        (lambda d: d.update(rotation_matrix=[[1, 0, 0], [0, 1, 0], [0, 0, 1.01]]),
         "not orthonormal"),
        (lambda d: d.update(rotation_matrix=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]), "reflection"),
        (lambda d: d.update(rotation_matrix=[[1, 0], [0, 1]]), "3x3"),
        (lambda d: d.update(quaternion_wxyz=[1, 0, 0, 0]), "quaternion_wxyz disagrees"),
        (lambda d: d.update(rpy_deg=[0, 0, 0]), "rpy_deg disagrees"),
        (lambda d: d.update(leg="XX"), "unknown leg"),
        (lambda d: d.update(samples="many"), "invalid calibration result"),
    ],
)
def test_from_dict_rejects_bad_files(mutate, match):
    d = _example().to_dict()
    mutate(d)
    with pytest.raises(ValueError, match=match):
        CalibrationResult.from_dict(d)


def test_read_rejects_non_json(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        CalibrationResult.read(p)
    p.write_text("[1, 2]")
    with pytest.raises(ValueError, match="JSON object"):
        CalibrationResult.read(p)


def test_from_solver_and_report_with_truth(solved):
    case, sres = solved
    res = CalibrationResult.from_solver("RL", sres)
    assert res.accepted and res.foot_frame == "RL_foot" and res.samples == sres.samples
    np.testing.assert_allclose(res.rotation_matrix, sres.rotation)
    text = format_report(res, truth=(case.rotation, case.time_offset))
    for label in ("R_I^F", "roll / pitch / yaw (deg", "time offset", " ms", "condition number",
                  "correlation (CC)", "rotation std", "verdict: accepted", "geodesic",
                  "Euler RE", "time offset error"):
        assert label in text
    assert f"{sres.time_offset * 1e3:+.3f} ms" in text


def test_refused_run_still_reportable():
    case = make_case(1, motion="planar", noise_density=1e-3)
    with pytest.raises(CalibrationRefused) as exc:
        solve(case.t_enc, case.omega_foot, case.t_imu, case.omega_imu)
    res = CalibrationResult.from_solver("FR", exc.value.diagnostics, foot_frame="FR_calf")
    assert not res.accepted and res.verdict.startswith("refused: ")
    assert "smallest eigenvalue" in res.verdict
    d = res.to_dict()
    assert d["condition_number"] is None or d["condition_number"] > 20  # inf -> null
    back = CalibrationResult.from_dict(json.loads(json.dumps(d)))
    assert back.verdict == res.verdict and back.foot_frame == "FR_calf"
    assert "verdict: refused" in format_report(back)
