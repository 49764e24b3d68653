"""The documented CSV input pair of ``a2i-calib solve``: encoders and foot IMU.

Both files: UTF-8 text (a BOM is tolerated), comma-separated, first non-blank, non-``#`` line
is the header of exact, case-sensitive column names; blank lines and lines starting with ``#``
are skipped anywhere; one sample per row; every row has as many fields as the header. Columns
may come in any order; columns not named below are ignored (they may hold anything).

Encoders CSV
    ``t``                      stamp, s (float; any origin, e.g. boot or Unix time)
    ``q_<LEG>_<JOINT>``        joint position, rad; LEG in FR, FL, RR, RL, JOINT in hip,
                               thigh, calf (SDK names and signs). Only the calibrated leg's
                               three columns are required.
    ``dq_<LEG>_<JOINT>``       optional joint velocity, rad/s: all three of the leg or none;
                               when absent, positions are differentiated (see below).
    ``base_wx,base_wy,base_wz`` optional base angular velocity in the base frame, rad/s (the
                               body gyro): used to make the foot angular velocity absolute.
    ``base_qw,base_qx,base_qy,base_qz`` optional base orientation R_W^B (scalar first); used,
                               differentiated, only when the gyro columns are absent.

IMU CSV (the foot IMU)
    ``t``                      the IMU's own stamps, s
    ``wx,wy,wz``               angular velocity in the IMU frame, rad/s
    ``ax,ay,az``               optional specific force in the IMU frame, m/s^2 (all or none)

Validation: every problem raises :class:`CalibInputError` (a ValueError) with a one-line
message naming the file and, where it applies, the line number (1-based, as an editor shows
it) and the column. Timestamp policy: a row whose used values (stamp included) are exactly
those of the row before is a logger's double write and is dropped (counted in
``duplicates_dropped``); after that stamps must strictly increase. A repeated stamp with
different values, or a stamp going back, is refused and never re-sorted: out-of-order
samples mean a merged or broken log whose time base cannot be trusted, and the temporal
calibration would silently absorb the damage. At least ``MIN_ROWS`` samples must remain, and
the median step must be below ``MAX_MEDIAN_STEP_S`` (catches stamps not in seconds).

Velocity from positions (no ``dq`` columns): :func:`smooth_derivative`, a local quadratic
least-squares fit around each sample on its own stamps (Savitzky-Golay generalised to
irregular sampling), over a time window of ``DEFAULT_DIFF_WINDOW_S`` (20 ms) but never fewer
than one neighbour per side. Why this one: it is exact for quadratics whatever the stamp
spacing (irregular sampling costs no bias); at 1 kHz it averages encoder quantisation over
~20 samples (about 20x less error than a central difference on a quantised 1 Hz sine); at
100 Hz it falls back to the three-point non-uniform central difference (wider windows cost
more bias than they remove noise there); its lag is zero (symmetric window, which matters
because the calibration estimates a time offset). A smoothing spline would need a noise level
to pick its smoothing; a fixed time window does not. It assumes the stamps are the sampling
instants: stamps with their own jitter (host receive times) add v * jitter of error to the
positions, which no differentiator can remove; log ``dq`` or device stamps then.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.atomic import write_text_atomic
from calib.joints import JOINTS, LEGS, SDK_LEGS
from calib.kinematics import base_angular_velocity_from_quaternions

__all__ = [
    "DEFAULT_DIFF_WINDOW_S",
    "MAX_MEDIAN_STEP_S",
    "MIN_ROWS",
    "CalibInputError",
    "EncoderLog",
    "ImuLog",
    "encoder_columns",
    "read_encoders_csv",
    "read_imu_csv",
    "smooth_derivative",
    "write_encoders_csv",
    "write_imu_csv",
]

MIN_ROWS = 50
"""Fewest samples a file may hold (after dropping duplicate rows)."""
DEFAULT_DIFF_WINDOW_S = 0.02
"""Width of the differentiation window, s (+-10 ms around each sample)."""
MAX_MEDIAN_STEP_S = 0.05
"""A median stamp step above this (slower than 20 Hz) means the ``t`` column is not in
seconds: milliseconds at 1 kHz step by 1.0, and were read as seconds, the offset 1000 times too
large; no log that slow could be calibrated to milliseconds anyway."""
BASE_GYRO_COLUMNS = ("base_wx", "base_wy", "base_wz")
BASE_QUAT_COLUMNS = ("base_qw", "base_qx", "base_qy", "base_qz")
IMU_GYRO_COLUMNS = ("wx", "wy", "wz")
IMU_ACCEL_COLUMNS = ("ax", "ay", "az")


class CalibInputError(ValueError):
    """Bad calibration input file; the message is one line naming the file (and line/column)."""


@dataclass
class EncoderLog:
    """One leg's encoder log. Joint arrays are (hip, thigh, calf) in SDK names and signs."""

    t: np.ndarray
    """(N,) stamps, s, strictly increasing."""
    q: np.ndarray
    """(N,3) joint positions, rad."""
    dq: np.ndarray
    """(N,3) joint velocities, rad/s (from the file, or differentiated from ``q``)."""
    dq_measured: bool
    """True when ``dq`` came from the file's dq columns."""
    base_omega: np.ndarray | None
    """(N,3) base angular velocity in the base frame, rad/s, or None (no base columns)."""
    leg: str = ""
    base_omega_source: str | None = None
    """"gyro" (base_w* columns), "quaternion" (differentiated base_q*) or None."""
    path: str = ""
    duplicates_dropped: int = 0


@dataclass
class ImuLog:
    """A foot IMU log in the IMU's own frame and clock."""

    t: np.ndarray
    """(M,) the IMU's stamps, s, strictly increasing."""
    gyro: np.ndarray
    """(M,3) angular velocity, IMU frame, rad/s."""
    accel: np.ndarray | None
    """(M,3) specific force, IMU frame, m/s^2, or None."""
    path: str = ""
    duplicates_dropped: int = 0


def encoder_columns(leg: str, velocities: bool = False) -> tuple[str, ...]:
    """Position (or velocity) column names of ``leg``: ``q_FL_hip, q_FL_thigh, q_FL_calf``."""
    prefix = "dq" if velocities else "q"
    return tuple(f"{prefix}_{leg}_{j}" for j in JOINTS)


# ---------------------------------------------------------------------------------- parsing
class _Table:
    """Header and data lines of a CSV file, parsed lazily per column set."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.name = str(path)
        p = self.path
        if not p.exists():
            raise self.error("file not found")
        if not p.is_file():
            raise self.error("not a regular file")
        try:
            raw = p.read_bytes()
        except OSError as e:
            raise self.error(f"cannot read it ({e.strerror or e})") from None
        if not raw or raw.isspace():
            raise self.error("file is empty")
        try:
            text = raw.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise self.error(f"not UTF-8 text (byte {exc.start})") from None
        lines = text.splitlines()
        # Fast path for plain logger output (no '#', no empty line): every line is content.
        # Anything else, or a whitespace-only line found by the field counts, is filtered line
        # by line. Every row's field count is checked either way (np.loadtxt's usecols would
        # read a row with a field too many and another one too few, shifted).
        plain = "#" not in text and "" not in lines and not lines[0].isspace()
        content = np.arange(len(lines)) if plain else self._content(lines)
        if content.size == 0:
            raise self.error("file is empty (only blank or comment lines)")
        n_fields = self._read_header(lines, int(content[0]))
        counts = self._field_counts(lines, content)
        if plain and np.any(counts != n_fields - 1):
            content = self._content(lines)
            if int(content[0]) != self.header_line - 1:  # the header was a blank line
                n_fields = self._read_header(lines, int(content[0]))
            counts = self._field_counts(lines, content)
        self.lines = [lines[i] for i in content[1:]]
        self.line_numbers = content[1:] + 1
        bad = np.flatnonzero(counts != n_fields - 1)
        if bad.size:
            i = bad[0]
            raise self.error(
                f"line {self.line_numbers[i]}: {counts[i] + 1} fields, the header has {n_fields}"
            )

    def _read_header(self, lines: list[str], h: int) -> int:
        """Read line ``h`` (0-based) as the header row; its field count."""
        self.header_line = h + 1
        self.columns = [c.strip() for c in lines[h].split(",")]
        if all(_is_number(c) for c in self.columns if c):
            raise self.error(
                f"line {h + 1}: no header row (the first line holds numbers); "
                "the first line must name the columns, e.g. t,q_FL_hip,..."
            )
        seen: set[str] = set()
        dups = sorted({c for c in self.columns if c and (c in seen or seen.add(c))})
        if dups:
            raise self.error(f"line {h + 1}: duplicate column name(s) {', '.join(dups)}")
        self.index = {c: i for i, c in enumerate(self.columns) if c}
        return len(self.columns)

    @staticmethod
    def _field_counts(lines: list[str], content: np.ndarray) -> np.ndarray:
        """Commas in each content line after the header."""
        rows = content[1:]
        return np.fromiter((lines[i].count(",") for i in rows), dtype=np.int64, count=rows.size)

    @staticmethod
    def _content(lines: list[str]) -> np.ndarray:
        """Indices of the lines that are neither blank nor comments."""
        return np.array(
            [i for i, s in enumerate(lines) if s.strip() and not s.lstrip().startswith("#")],
            dtype=np.int64,
        )

    def error(self, msg: str) -> CalibInputError:
        return CalibInputError(f"{self.name}: {msg}")

    def require(self, cols, what: str = "") -> None:
        missing = [c for c in cols if c not in self.index]
        if missing:
            lower = {c.lower(): c for c in self.index}
            hints = [f"{lower[m.lower()]!r}" for m in missing if m.lower() in lower]
            hint = f" (found {', '.join(hints)}: names are case-sensitive)" if hints else ""
            raise self.error(f"missing column(s) {', '.join(missing)}{what}{hint}")

    def group(self, cols, what: str) -> bool:
        """True if all of ``cols`` are present, False if none; error if only some are."""
        present = [c for c in cols if c in self.index]
        if present and len(present) != len(cols):
            missing = [c for c in cols if c not in self.index]
            raise self.error(
                f"has {', '.join(present)} but not {', '.join(missing)}: "
                f"give all {len(cols)} {what} columns or none"
            )
        return bool(present)

    def numbers(self, cols) -> np.ndarray:
        """(rows, len(cols)) float array of the named columns, finite, else CalibInputError."""
        cols = list(cols)
        if len(self.lines) < MIN_ROWS:
            raise self.error(f"{len(self.lines)} data rows, need at least {MIN_ROWS}")
        use = [self.index[c] for c in cols]
        try:
            a = np.loadtxt(
                self.lines, delimiter=",", usecols=use, dtype=float, ndmin=2, comments=None
            )
        except ValueError as exc:
            raise self._locate_bad_cell(cols, use, exc) from None
        bad = ~np.isfinite(a)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise self.error(
                f"line {self.line_numbers[r]}, column {cols[c]}: "
                f"non-finite value {float(a[r, c])!r}"
            )
        return a

    def _locate_bad_cell(self, cols, use, exc: ValueError) -> CalibInputError:
        # Slow path, only on failure: find the first cell that does not parse.
        for r, s in enumerate(self.lines):
            fields = s.split(",")
            for name, i in zip(cols, use):
                cell = fields[i].strip()
                if not _is_number(cell):
                    what = "empty cell" if not cell else f"cannot read {cell!r} as a number"
                    return self.error(f"line {self.line_numbers[r]}, column {name}: {what}")
        return self.error(f"unreadable numbers ({str(exc).splitlines()[0]})")


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return "_" not in s  # Python accepts 1_000, numpy does not


def _check_time(tab: _Table, a: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Drop exact duplicate rows, then require strictly increasing stamps (column 0 of a).

    Returns (a without duplicates, their line numbers, number dropped).
    """
    lines = tab.line_numbers
    same = np.all(a[1:] == a[:-1], axis=1)
    n_dup = int(same.sum())
    if n_dup:
        keep = np.concatenate([[True], ~same])
        a, lines = a[keep], lines[keep]
    t = a[:, 0]
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        i = bad[0]
        if dt[i] == 0:
            raise tab.error(
                f"line {lines[i + 1]}: timestamp {float(t[i + 1])!r} s repeats line {lines[i]} "
                "with different values; stamps must strictly increase"
            )
        raise tab.error(
            f"line {lines[i + 1]}: timestamp {float(t[i + 1])!r} s goes back from "
            f"{float(t[i])!r} s "
            f"(line {lines[i]}); stamps must strictly increase (the file is not re-sorted)"
        )
    if t.size < MIN_ROWS:
        raise tab.error(
            f"{t.size} samples after dropping {n_dup} duplicate row(s), need at least {MIN_ROWS}"
        )
    med = float(np.median(dt))
    if med > MAX_MEDIAN_STEP_S:
        raise tab.error(
            f"column t: median step {med:.6g} s is above {MAX_MEDIAN_STEP_S:g} s; "
            "t must be in seconds"
        )
    return a, lines, n_dup


# ---------------------------------------------------------------------------------- readers
def read_encoders_csv(
    path: str | os.PathLike, leg: str, diff_window_s: float = DEFAULT_DIFF_WINDOW_S
) -> EncoderLog:
    """Read one leg's encoders (and base rotation, if logged) from the encoders CSV.

    ``leg``: FL, FR, RL or RR (case-insensitive). Velocities come from the ``dq`` columns when
    present, else from :func:`smooth_derivative` of the positions with ``diff_window_s``.
    The base angular velocity comes from the gyro columns, else from the quaternion columns
    (differentiated), else is None. Raises :class:`CalibInputError`.
    """
    up = str(leg).strip().upper()
    if up not in LEGS:
        raise CalibInputError(f"{path}: unknown leg {leg!r}: expected one of {', '.join(SDK_LEGS)}")
    tab = _Table(path)
    qcols = encoder_columns(up)
    dqcols = encoder_columns(up, velocities=True)
    tab.require(("t", *qcols), f" (leg {up})")
    has_dq = tab.group(dqcols, f"velocity (leg {up})")
    has_gyro = tab.group(BASE_GYRO_COLUMNS, "base gyro")
    has_quat = (not has_gyro) and tab.group(BASE_QUAT_COLUMNS, "base quaternion")

    cols = ["t", *qcols]
    if has_dq:
        cols += dqcols
    if has_gyro:
        cols += BASE_GYRO_COLUMNS
    elif has_quat:
        cols += BASE_QUAT_COLUMNS
    a, lines, n_dup = _check_time(tab, tab.numbers(cols))

    t = a[:, 0].copy()
    q = a[:, 1:4].copy()
    k = 4
    if has_dq:
        dq = a[:, k : k + 3].copy()
        k += 3
    else:
        dq = smooth_derivative(t, q, diff_window_s)
    base_omega, source = None, None
    if has_gyro:
        base_omega, source = a[:, k : k + 3].copy(), "gyro"
    elif has_quat:
        quat = a[:, k : k + 4]
        zero = np.flatnonzero(np.linalg.norm(quat, axis=1) < 1e-9)
        if zero.size:
            raise tab.error(f"line {lines[zero[0]]}, columns base_q*: zero quaternion")
        base_omega, source = base_angular_velocity_from_quaternions(t, quat), "quaternion"
    return EncoderLog(
        t=t,
        q=q,
        dq=dq,
        dq_measured=has_dq,
        base_omega=base_omega,
        leg=up,
        base_omega_source=source,
        path=str(path),
        duplicates_dropped=n_dup,
    )


def read_imu_csv(path: str | os.PathLike) -> ImuLog:
    """Read a foot IMU CSV (``t, wx, wy, wz`` and optional ``ax, ay, az``)."""
    tab = _Table(path)
    tab.require(("t", *IMU_GYRO_COLUMNS))
    has_acc = tab.group(IMU_ACCEL_COLUMNS, "accelerometer")
    cols = ["t", *IMU_GYRO_COLUMNS] + (list(IMU_ACCEL_COLUMNS) if has_acc else [])
    a, _, n_dup = _check_time(tab, tab.numbers(cols))
    return ImuLog(
        t=a[:, 0].copy(),
        gyro=a[:, 1:4].copy(),
        accel=a[:, 4:7].copy() if has_acc else None,
        path=str(path),
        duplicates_dropped=n_dup,
    )


# ---------------------------------------------------------------------------------- writers
def _column(x, n: int, width: int, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.shape != (n, width):
        raise ValueError(f"{name} must have shape ({n}, {width}), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds non-finite values")
    return a


def _write(path, names: list[str], blocks: list[np.ndarray]) -> Path:
    data = np.hstack(blocks)
    buf = io.StringIO()
    # Stamps round-trip exactly (17 digits); 9 significant digits (float32 carries ~7) are far
    # below any encoder or gyro resolution and keep files small and quick to parse.
    fmt = ["%.17g"] + ["%.9g"] * (data.shape[1] - 1)
    np.savetxt(buf, data, fmt=fmt, delimiter=",", header=",".join(names), comments="")
    return write_text_atomic(path, buf.getvalue())


def write_encoders_csv(
    path: str | os.PathLike,
    t,
    q,
    *,
    leg: str | None = None,
    dq=None,
    base_omega=None,
    base_quat_wxyz=None,
) -> Path:
    """Write an encoders CSV atomically; returns the path.

    t: (N,) s, strictly increasing. q (and dq): (N,12) in SDK order (FR, FL, RR, RL x hip,
    thigh, calf) when ``leg`` is None, else (N,3) for that leg; rad (rad/s). base_omega: (N,3)
    base frame, rad/s; base_quat_wxyz: (N,4) R_W^B. Raises ValueError on bad shapes,
    non-finite values or non-increasing stamps.
    """
    ta = np.asarray(t, dtype=float).reshape(-1)
    n = ta.size
    if not np.all(np.isfinite(ta)) or np.any(np.diff(ta) <= 0):
        raise ValueError("t must be finite and strictly increasing")
    legs = SDK_LEGS if leg is None else (_leg(leg),)
    width = 3 * len(legs)
    names, blocks = ["t"], [ta[:, None]]
    names += [c for lg in legs for c in encoder_columns(lg)]
    blocks.append(_column(q, n, width, "q"))
    if dq is not None:
        names += [c for lg in legs for c in encoder_columns(lg, velocities=True)]
        blocks.append(_column(dq, n, width, "dq"))
    if base_omega is not None:
        names += list(BASE_GYRO_COLUMNS)
        blocks.append(_column(base_omega, n, 3, "base_omega"))
    if base_quat_wxyz is not None:
        names += list(BASE_QUAT_COLUMNS)
        blocks.append(_column(base_quat_wxyz, n, 4, "base_quat_wxyz"))
    return _write(path, names, blocks)


def write_imu_csv(path: str | os.PathLike, t, gyro, accel=None) -> Path:
    """Write a foot IMU CSV atomically: t (M,) s, gyro (M,3) rad/s, accel (M,3) m/s^2."""
    ta = np.asarray(t, dtype=float).reshape(-1)
    n = ta.size
    if not np.all(np.isfinite(ta)) or np.any(np.diff(ta) <= 0):
        raise ValueError("t must be finite and strictly increasing")
    names, blocks = ["t", *IMU_GYRO_COLUMNS], [ta[:, None], _column(gyro, n, 3, "gyro")]
    if accel is not None:
        names += list(IMU_ACCEL_COLUMNS)
        blocks.append(_column(accel, n, 3, "accel"))
    return _write(path, names, blocks)


def _leg(leg: str) -> str:
    up = str(leg).strip().upper()
    if up not in LEGS:
        raise ValueError(f"unknown leg {leg!r}: expected one of {', '.join(SDK_LEGS)}")
    return up


# ---------------------------------------------------------------------------------- derivative
_MAX_SIDE = 256  # neighbours per side considered at most (bounds memory on dense bursts)


def smooth_derivative(
    t, y, window_s: float = DEFAULT_DIFF_WINDOW_S, min_side: int = 1
) -> np.ndarray:
    """dy/dt by a local quadratic least-squares fit on irregular stamps.

    t: (N,) s, strictly increasing, N >= 3. y: (N,) or (N,k). For each sample i, a quadratic
    in (t - t_i) is fitted (uniform weights) to the samples with |t - t_i| <= h_i, where
    h_i = max(window_s / 2, distance to the ``min_side``-th neighbour on either side), so
    every fit has at least ``min_side`` neighbours per side (at the ends, the inner side
    makes up for the missing ones: at least 2*min_side+1 points); its slope at t_i is the
    derivative. Symmetric in the interior, so no lag. Cost: O(N * samples per window).
    """
    ta = np.asarray(t, dtype=float).reshape(-1)
    ya = np.asarray(y, dtype=float)
    vec = ya.ndim == 1
    y2 = ya[:, None] if vec else ya
    n = ta.size
    if y2.ndim != 2 or y2.shape[0] != n:
        raise ValueError(f"y must have {n} rows, got shape {ya.shape}")
    if n < 3:
        raise ValueError("need at least 3 samples to differentiate")
    if np.any(np.diff(ta) <= 0):
        raise ValueError("t must be strictly increasing")
    if not window_s > 0 or min_side < 1:
        raise ValueError("window_s must be > 0 and min_side >= 1")
    half = 0.5 * window_s
    idx = np.arange(n)
    # Window half-width per sample; where one side is short (the ends), the other side
    # supplies the missing neighbours so that every fit has at least 2*min_side+1 points.
    n_ahead = min_side + np.maximum(0, min_side - idx)
    n_behind = min_side + np.maximum(0, min_side - (n - 1 - idx))
    ahead = ta[np.minimum(idx + n_ahead, n - 1)] - ta
    behind = ta - ta[np.maximum(idx - n_behind, 0)]
    h = np.maximum(half, np.maximum(ahead, behind)) * (1.0 + 1e-9)
    hi = np.searchsorted(ta, ta + h, side="right") - 1 - idx
    lo = idx - np.searchsorted(ta, ta - h, side="left")
    side = int(min(max(hi.max(), lo.max()), _MAX_SIDE, n - 1))
    # Moments of x = (t_j - t_i) / h_i (scaled to [-1, 1] for conditioning) and of x^k y_j,
    # accumulated one offset o = j - i at a time over slices: no (N, window) temporaries.
    s0 = np.ones(n)
    s1, s2, s3, s4 = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    t0 = y2.copy()
    t1, t2 = np.zeros_like(y2), np.zeros_like(y2)
    for o in range(1, side + 1):
        for i_sl, j_sl in ((slice(0, n - o), slice(o, n)), (slice(o, n), slice(0, n - o))):
            x = (ta[j_sl] - ta[i_sl]) / h[i_sl]
            w = (np.abs(x) <= 1.0).astype(float)
            wx = w * x
            wx2 = wx * x
            s0[i_sl] += w
            s1[i_sl] += wx
            s2[i_sl] += wx2
            s3[i_sl] += wx2 * x
            s4[i_sl] += wx2 * x * x
            yj = y2[j_sl]
            t0[i_sl] += w[:, None] * yj
            t1[i_sl] += wx[:, None] * yj
            t2[i_sl] += wx2[:, None] * yj
    # Slope coefficient of the 3x3 normal equations by Cramer's rule (vectorised).
    det = s0 * (s2 * s4 - s3 * s3) - s1 * (s1 * s4 - s3 * s2) + s2 * (s1 * s3 - s2 * s2)
    c0 = (s3 * s2 - s1 * s4)[:, None]  # cofactors of the slope row
    c1 = (s0 * s4 - s2 * s2)[:, None]
    c2 = (s1 * s2 - s0 * s3)[:, None]
    slope = (c0 * t0 + c1 * t1 + c2 * t2) / det[:, None]
    d = slope / h[:, None]
    return d[:, 0] if vec else d
