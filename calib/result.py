"""The calibration result type and its JSON file (schema version 1), read by other tools.

File fields (exact names): ``leg``, ``rotation_matrix`` (R_I^F as a 3x3 nested list: maps
IMU-frame vectors into the ``foot_frame`` of the URDF, ``omega_F = R @ omega_I``),
``quaternion_wxyz`` and ``rpy_deg`` (the same rotation; roll, pitch, yaw in degrees with
R = Rz Ry Rx), ``time_offset_s`` (t_d = t_I - t_E, s), ``condition_number`` (kappa of S_FF),
``correlation`` (CC), ``rotation_std_deg``, ``time_offset_std_s``, ``samples``, ``version`` (1),
plus ``min_eigenvalue`` ((rad/s)^2), ``foot_frame``, ``created_utc`` (ISO 8601) and ``verdict``
("accepted" or "refused: <reasons>").
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from calib.atomic import write_text_atomic
from calib.joints import check_leg
from calib.metrics import (
    euler_rotation_error_deg,
    geodesic_error_deg,
    offset_error_s,
    quaternion_wxyz,
    rotation_from_rpy_deg,
    rpy_deg,
)

SCHEMA_VERSION = 1
REQUIRED_FIELDS = (
    "leg", "rotation_matrix", "quaternion_wxyz", "rpy_deg", "time_offset_s",
    "condition_number", "correlation", "rotation_std_deg", "time_offset_std_s", "samples",
    "version",
)
OPTIONAL_FIELDS = ("min_eigenvalue", "foot_frame", "created_utc", "verdict")
_ORTHO_TOL = 1e-6


@dataclass
class CalibrationResult:
    """One leg's foot-IMU calibration. SI units, except the fields named ``_deg``."""

    leg: str
    rotation_matrix: np.ndarray  # R_I^F (3, 3)
    time_offset_s: float
    condition_number: float
    correlation: float
    rotation_std_deg: float
    time_offset_std_s: float
    samples: int
    min_eigenvalue: float = float("nan")
    foot_frame: str = ""
    created_utc: str = ""
    verdict: str = "accepted"
    version: int = SCHEMA_VERSION
    quaternion_wxyz: np.ndarray = field(init=False)
    rpy_deg: np.ndarray = field(init=False)

    def __post_init__(self):
        self.leg = check_leg(self.leg)
        self.rotation_matrix = _check_rotation(self.rotation_matrix)
        self.quaternion_wxyz = quaternion_wxyz(self.rotation_matrix)
        self.rpy_deg = rpy_deg(self.rotation_matrix)
        if not self.foot_frame:
            self.foot_frame = f"{self.leg}_foot"

    @property
    def accepted(self) -> bool:
        return self.verdict == "accepted"

    @classmethod
    def from_solver(cls, leg: str, solver_result, foot_frame: str | None = None,
                    created_utc: str | None = None) -> CalibrationResult:
        """Wrap a :class:`calib.solver.SolverResult` (accepted, or the diagnostics of a refusal:
        then ``verdict`` records the reasons)."""
        reasons = list(getattr(solver_result, "reasons", []) or [])
        leg = check_leg(leg)
        return cls(
            leg=leg,
            rotation_matrix=solver_result.rotation,
            time_offset_s=float(solver_result.time_offset),
            condition_number=float(solver_result.condition_number),
            correlation=float(solver_result.correlation),
            rotation_std_deg=float(solver_result.rotation_std_deg),
            time_offset_std_s=float(solver_result.time_offset_std_s),
            samples=int(solver_result.samples),
            min_eigenvalue=float(solver_result.min_eigenvalue),
            foot_frame=foot_frame or f"{leg}_foot",
            created_utc=created_utc or datetime.now(UTC).isoformat(timespec="seconds"),
            verdict="accepted" if not reasons else "refused: " + "; ".join(reasons),
        )

    def to_dict(self) -> dict:
        """JSON-ready dict (non-finite floats become null)."""
        return {
            "version": self.version,
            "leg": self.leg,
            "foot_frame": self.foot_frame,
            "rotation_matrix": [[float(v) for v in row] for row in self.rotation_matrix],
            "quaternion_wxyz": [float(v) for v in self.quaternion_wxyz],
            "rpy_deg": [float(v) for v in self.rpy_deg],
            "time_offset_s": _num(self.time_offset_s),
            "condition_number": _num(self.condition_number),
            "correlation": _num(self.correlation),
            "min_eigenvalue": _num(self.min_eigenvalue),
            "rotation_std_deg": _num(self.rotation_std_deg),
            "time_offset_std_s": _num(self.time_offset_std_s),
            "samples": int(self.samples),
            "created_utc": self.created_utc,
            "verdict": self.verdict,
        }

    @classmethod
    def from_dict(cls, d: dict) -> CalibrationResult:
        """Validate and build; ValueError (one line) on a missing field, a wrong version, a
        non-orthonormal matrix or a quaternion / RPY that disagrees with the matrix."""
        if not isinstance(d, dict):
            # ValueError on purpose: callers treat every malformed file alike
            raise ValueError(  # noqa: TRY004
                f"calibration result must be a JSON object, got {type(d).__name__}"
            )
        missing = [k for k in REQUIRED_FIELDS if k not in d]
        if missing:
            raise ValueError(f"calibration result lacks field(s): {', '.join(missing)}")
        if d["version"] != SCHEMA_VERSION:
            raise ValueError(
                f"calibration result schema version {d['version']!r} unsupported "
                f"(this reader knows version {SCHEMA_VERSION})"
            )
        try:
            res = cls(
                leg=d["leg"],
                rotation_matrix=d["rotation_matrix"],
                time_offset_s=_float(d["time_offset_s"]),
                condition_number=_float(d["condition_number"]),
                correlation=_float(d["correlation"]),
                rotation_std_deg=_float(d["rotation_std_deg"]),
                time_offset_std_s=_float(d["time_offset_std_s"]),
                samples=int(d["samples"]),
                min_eigenvalue=_float(d.get("min_eigenvalue")),
                foot_frame=str(d.get("foot_frame") or ""),
                created_utc=str(d.get("created_utc") or ""),
                verdict=str(d.get("verdict") or "accepted"),
            )
        except (TypeError, ValueError) as e:
            raise ValueError(f"invalid calibration result: {e}") from None
        q = np.asarray(d["quaternion_wxyz"], dtype=float)
        if q.shape != (4,) or min(np.linalg.norm(q - res.quaternion_wxyz),
                                  np.linalg.norm(q + res.quaternion_wxyz)) > 1e-6:
            raise ValueError("quaternion_wxyz disagrees with rotation_matrix")
        rpy = np.asarray(d["rpy_deg"], dtype=float)
        if rpy.shape != (3,) or euler_rotation_error_deg(
            rotation_from_rpy_deg(*rpy), res.rotation_matrix
        ) > 1e-4:
            raise ValueError("rpy_deg disagrees with rotation_matrix")
        return res

    def write(self, path: str | os.PathLike) -> Path:
        """Write the JSON file atomically (temp file + rename)."""
        return write_text_atomic(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def read(cls, path: str | os.PathLike) -> CalibrationResult:
        """Read and validate a file written by :meth:`write`."""
        try:
            d = json.loads(Path(path).read_text(encoding="utf-8"))
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: not valid JSON ({e.msg} at line {e.lineno})") from None
        return cls.from_dict(d)


def _check_rotation(r) -> np.ndarray:
    try:
        m = np.asarray(r, dtype=float)
    except (TypeError, ValueError):
        raise ValueError("rotation_matrix is not a numeric 3x3 array") from None
    if m.shape != (3, 3):
        raise ValueError(f"rotation_matrix must be 3x3, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError("rotation_matrix has non-finite entries")
    err = float(np.abs(m.T @ m - np.eye(3)).max())
    if err > _ORTHO_TOL:
        raise ValueError(f"rotation_matrix is not orthonormal (|R^T R - I| = {err:.2g})")
    if np.linalg.det(m) < 0:
        raise ValueError("rotation_matrix is a reflection (det = -1), not a rotation")
    return m


def _num(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _float(x) -> float:
    return float("nan") if x is None else float(x)


def format_report(result: CalibrationResult, truth=None) -> str:
    """Human-readable report. ``truth``: optional (R_I^F true (3, 3), t_d true (s)); then the
    errors (geodesic, the paper's Euler RE, offset) are printed too."""
    r = result.rotation_matrix
    lines = [
        f"Foot-IMU calibration, leg {result.leg} (IMU frame -> {result.foot_frame})",
        "  R_I^F (omega_F = R omega_I):",
        *[f"    [{row[0]:+.6f} {row[1]:+.6f} {row[2]:+.6f}]" for row in r],
        "  roll / pitch / yaw (deg, R = Rz Ry Rx): "
        + " / ".join(f"{v:+.3f}" for v in result.rpy_deg),
        "  quaternion (w, x, y, z): " + ", ".join(f"{v:+.6f}" for v in result.quaternion_wxyz),
        (
            f"  time offset t_d = t_I - t_E: {result.time_offset_s * 1e3:+.3f} ms"
            f" (std {result.time_offset_std_s * 1e3:.3f} ms)"
        ),
        f"  rotation std: {result.rotation_std_deg:.4f} deg",
        (
            f"  condition number (CN) of Sigma_FF: {result.condition_number:.3f}"
            f"   smallest eigenvalue: {result.min_eigenvalue:.4g} (rad/s)^2"
        ),
        f"  correlation (CC): {result.correlation:.5f}   samples: {result.samples}",
        f"  verdict: {result.verdict}",
    ]
    if truth is not None:
        r_true, t_true = truth
        lines += [
            "  against truth:",
            f"    geodesic rotation error: {geodesic_error_deg(r, r_true):.4f} deg",
            f"    Euler RE (paper):        {euler_rotation_error_deg(r, r_true):.4f} deg",
            "    time offset error:       "
            + f"{offset_error_s(result.time_offset_s, t_true) * 1e3:.4f} ms",
        ]
    return "\n".join(lines)
