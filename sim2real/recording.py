"""Recordings the diagnoser reads: the documented CSV form and the recorder's MCAP files.

One in-memory form, :class:`Recording`: every joint array is **SDK order** (FR, FL, RR, RL x
hip, thigh, calf), SI units, time in float seconds from the first state sample.

CSV form (``docs/sim2real.md``): ``RECORDING.csv`` with a header row, one row per state sample,
and ``RECORDING.json`` beside it with ``{"mount": "suspended" | "ground"}``. Columns: ``t``;
``q_<LEG>_<JOINT>``, ``dq_<LEG>_<JOINT>``, optional ``tau_<LEG>_<JOINT>``; the command in force
``cmd_q_``, ``cmd_dq_``, ``cmd_kp_``, ``cmd_kd_``, ``cmd_tau_`` + joint; the body IMU ``base_qw``
.. ``base_qz``, ``base_wx`` .. ``base_wz``, ``base_ax`` .. ``base_az``; optional ``base_px`` ..
``base_vz`` (motion capture, world frame), ``foot_force_<LEG>``, ``imu_<LEG>_wx`` .. ``_wz``.

Commands: the CSV holds the command in force at each row, so a command is taken to be sent at
the first row that shows it (the send time is known to one state period). MCAP recordings keep
the exact send times of ``rt/lowcmd``.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.atomic import write_text_atomic
from calib.joints import SDK_JOINT_NAMES, SDK_LEGS

__all__ = [
    "CMD_FIELDS",
    "MOUNTS",
    "Recording",
    "load_recording",
    "read_csv",
    "read_mcap_recording",
    "write_csv",
]

MOUNTS = ("suspended", "ground")
CMD_FIELDS = ("q", "dq", "kp", "kd", "tau")
_IMU_COLS = ("base_qw", "base_qx", "base_qy", "base_qz", "base_wx", "base_wy", "base_wz",
             "base_ax", "base_ay", "base_az")
_MOCAP_COLS = ("base_px", "base_py", "base_pz", "base_vx", "base_vy", "base_vz")


@dataclass
class Recording:
    """A robot (or simulated) recording, SDK joint order, SI units.

    t (N,) s, increasing. q, dq (N, 12) rad, rad/s; tau (N, 12) N m estimated or None.
    cmd[f] (N, 12) for f in CMD_FIELDS: the command in force at each sample. cmd_t (M,) s and
    cmd_events[f] (M, 12): the commands as sent, in send order. base_quat (N, 4) w, x, y, z
    base->world; base_gyro (N, 3) rad/s and base_acc (N, 3) m/s^2, base frame. base_pos,
    base_vel (N, 3) world frame or None. foot_force (N, 4) legs FR, FL, RR, RL or None.
    foot_gyro: {leg: (N, 3) rad/s} (may be empty). mount: "suspended" or "ground".
    """

    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    cmd: dict[str, np.ndarray]
    cmd_t: np.ndarray
    cmd_events: dict[str, np.ndarray]
    base_quat: np.ndarray
    base_gyro: np.ndarray
    base_acc: np.ndarray
    mount: str
    tau: np.ndarray | None = None
    base_pos: np.ndarray | None = None
    base_vel: np.ndarray | None = None
    foot_force: np.ndarray | None = None
    foot_gyro: dict[str, np.ndarray] = field(default_factory=dict)
    source: str = ""

    def __post_init__(self) -> None:
        if self.mount not in MOUNTS:
            raise ValueError(f"mount must be 'suspended' or 'ground', got {self.mount!r}")
        n = self.t.shape[0]
        if n < 50:
            raise ValueError(f"recording has {n} state samples; at least 50 are needed")
        if not np.all(np.diff(self.t) > 0):
            raise ValueError("recording time t must be strictly increasing")
        for name in ("q", "dq"):
            if getattr(self, name).shape != (n, 12):
                raise ValueError(f"{name} must be ({n}, 12)")
        if self.cmd_t.size == 0:
            raise ValueError("recording has no motor commands")

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    @property
    def sample_period(self) -> float:
        return float(np.median(np.diff(self.t)))


def _joint_cols(prefix: str) -> list[str]:
    return [f"{prefix}_{n}" for n in SDK_JOINT_NAMES]


def commands_from_rows(t: np.ndarray, cmd: dict[str, np.ndarray]):
    """(cmd_t, cmd_events): a command is sent at the first row where any field changes."""
    stacked = np.concatenate([cmd[f] for f in CMD_FIELDS], axis=1)
    change = np.ones(t.shape[0], bool)
    change[1:] = np.any(stacked[1:] != stacked[:-1], axis=1)
    return t[change].copy(), {f: cmd[f][change].copy() for f in CMD_FIELDS}


def read_csv(path: str | Path, mount: str | None = None) -> Recording:
    """Read ``RECORDING.csv`` (+ ``RECORDING.json`` for the mount unless ``mount`` is given)."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: no such file")
    if mount is None:
        side = p.with_suffix(".json")
        if not side.is_file():
            raise ValueError(f"{side}: missing; it must hold {{\"mount\": \"suspended\" | \"ground\"}}")
        try:
            meta = json.loads(side.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{side}: not valid JSON ({exc.msg})") from None
        if not isinstance(meta, dict) or meta.get("mount") not in MOUNTS:
            raise ValueError(f"{side}: \"mount\" must be \"suspended\" or \"ground\"")
        mount = meta["mount"]
    text = p.read_text(encoding="utf-8")
    reader = csv.reader(io.StringIO(text))
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise ValueError(f"{p}: empty file") from None
    if len(set(header)) != len(header):
        raise ValueError(f"{p}: duplicate column names in the header")
    col = {h: i for i, h in enumerate(header)}
    required = (["t"] + _joint_cols("q") + _joint_cols("dq")
                + [c for f in CMD_FIELDS for c in _joint_cols(f"cmd_{f}")] + list(_IMU_COLS))
    missing = [c for c in required if c not in col]
    if missing:
        more = f" (+{len(missing) - 3} more)" if len(missing) > 3 else ""
        raise ValueError(f"{p}: missing column(s) {', '.join(missing[:3])}{more}")
    rows = [r for r in reader if r and any(x.strip() for x in r)]
    if not rows:
        raise ValueError(f"{p}: no data rows")
    try:
        data = np.array([[float(x) if x.strip() != "" else np.nan for x in r] for r in rows])
    except ValueError as exc:
        raise ValueError(f"{p}: non-numeric value ({exc})") from None
    if data.ndim != 2 or data.shape[1] != len(header):
        bad = next(i for i, r in enumerate(rows) if len(r) != len(header))
        raise ValueError(f"{p}: row {bad + 2} has {len(rows[bad])} fields, header has {len(header)}")

    def get(names: list[str], optional: bool = False):
        if not all(n in col for n in names):
            if optional:
                return None
            raise ValueError(f"{p}: missing column {next(n for n in names if n not in col)}")
        a = data[:, [col[n] for n in names]]
        if not np.all(np.isfinite(a)):
            r = int(np.nonzero(~np.all(np.isfinite(a), axis=1))[0][0])
            raise ValueError(f"{p}: empty or non-finite value in row {r + 2} of {names[0]}..")
        return a

    t = get(["t"])[:, 0]
    if not np.all(np.diff(t) > 0):
        raise ValueError(f"{p}: column t must be strictly increasing")
    cmd = {f: get(_joint_cols(f"cmd_{f}")) for f in CMD_FIELDS}
    cmd_t, cmd_events = commands_from_rows(t, cmd)
    imu = get(list(_IMU_COLS))
    mocap = get(list(_MOCAP_COLS), optional=True)
    foot_gyro = {}
    for leg in SDK_LEGS:
        g = get([f"imu_{leg}_w{a}" for a in "xyz"], optional=True)
        if g is not None:
            foot_gyro[leg] = g
    return Recording(
        t=t - t[0], q=get(_joint_cols("q")), dq=get(_joint_cols("dq")), cmd=cmd,
        cmd_t=cmd_t - t[0], cmd_events=cmd_events, base_quat=imu[:, 0:4],
        base_gyro=imu[:, 4:7], base_acc=imu[:, 7:10], mount=mount,
        tau=get(_joint_cols("tau"), optional=True),
        base_pos=None if mocap is None else mocap[:, 0:3],
        base_vel=None if mocap is None else mocap[:, 3:6],
        foot_force=get([f"foot_force_{leg}" for leg in SDK_LEGS], optional=True),
        foot_gyro=foot_gyro, source=str(p),
    )


def write_csv(rec: Recording, path: str | Path) -> Path:
    """Write ``rec`` in the CSV form (+ the ``.json`` mount file), atomically; returns the CSV."""
    p = Path(path)
    cols: list[tuple[str, np.ndarray]] = [("t", rec.t)]
    for name, arr in (("q", rec.q), ("dq", rec.dq), ("tau", rec.tau)):
        if arr is not None:
            cols += list(zip(_joint_cols(name), arr.T, strict=True))
    for f in CMD_FIELDS:
        cols += list(zip(_joint_cols(f"cmd_{f}"), rec.cmd[f].T, strict=True))
    imu = np.concatenate([rec.base_quat, rec.base_gyro, rec.base_acc], axis=1)
    cols += list(zip(_IMU_COLS, imu.T, strict=True))
    if rec.base_pos is not None and rec.base_vel is not None:
        cols += list(zip(_MOCAP_COLS, np.concatenate([rec.base_pos, rec.base_vel], 1).T,
                         strict=True))
    if rec.foot_force is not None:
        cols += [(f"foot_force_{leg}", rec.foot_force[:, k]) for k, leg in enumerate(SDK_LEGS)]
    for leg, g in rec.foot_gyro.items():
        cols += [(f"imu_{leg}_w{a}", g[:, k]) for k, a in enumerate("xyz")]
    data = np.stack([c[1] for c in cols], axis=1)
    buf = io.StringIO()
    buf.write(",".join(c[0] for c in cols) + "\n")
    np.savetxt(buf, data, delimiter=",", fmt="%.9g")
    write_text_atomic(p.with_suffix(".json"), json.dumps({"mount": rec.mount}) + "\n")
    write_text_atomic(p, buf.getvalue())
    return p


def read_mcap_recording(path: str | Path, mount: str | None = None) -> Recording:
    """Read a recorder MCAP (``docs/recording.md``). The mount comes from ``mount``, else the
    ``a2i/session`` metadata key ``"mount"``; ValueError when neither gives it."""
    from hw.go2_msgs import get_field, lowstate_records
    from hw.mcap_io import read_mcap, read_mcap_metadata

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: no such file")
    try:
        snap = read_mcap(p)
        meta = read_mcap_metadata(p).get("a2i/session", {})
    except ValueError:
        raise
    except Exception as exc:  # noqa: BLE001 - the mcap library raises its own types
        raise ValueError(f"{p}: not a readable MCAP recording ({type(exc).__name__}: {exc})") from None
    if mount is None:
        mount = meta.get("mount")
        if mount not in MOUNTS:
            raise ValueError(f"{p}: the mount is not in the recording's metadata; "
                             "pass --mount suspended|ground")
    ls, lc = snap.lowstate, snap.lowcmd
    if ls.shape[0] < 50:
        raise ValueError(f"{p}: only {ls.shape[0]} rt/lowstate messages")
    if lc.shape[0] == 0:
        raise ValueError(f"{p}: no rt/lowcmd messages")
    order = np.argsort(ls["t_host_ns"], kind="stable")
    ls = ls[order]
    t0 = int(ls["t_host_ns"][0])
    t = (ls["t_host_ns"] - t0).astype(float) * 1e-9
    keep = np.concatenate([[True], np.diff(t) > 0])
    ls, t = ls[keep], t[keep]
    lc = lc[np.argsort(lc["t_host_ns"], kind="stable")]
    cmd_t = (lc["t_host_ns"] - t0).astype(float) * 1e-9
    ev = {"q": lc["q_des"], "dq": lc["dq_des"], "kp": lc["kp"], "kd": lc["kd"], "tau": lc["tau_ff"]}
    ev = {k: np.asarray(v, dtype=float) for k, v in ev.items()}
    idx = np.searchsorted(cmd_t, t + 1e-9, side="right") - 1
    cmd = {}
    for f in CMD_FIELDS:
        a = ev[f][np.clip(idx, 0, None)].copy()
        a[idx < 0] = 0.0  # before the first command the motors were passive
        cmd[f] = a
    foot_force = None
    raw = ls["raw"]
    if raw.shape[1] >= 1180 and np.all(ls["raw_len"] >= 1180):
        ff = get_field(lowstate_records(raw[:, :1180]), "foot_force").astype(float)
        if np.any(ff != 0):
            foot_force = ff[:, :4]
    foot_gyro = {}
    for leg, rows in snap.imu.items():
        if rows.shape[0] >= 2:
            tt = (rows["t_host_ns"] - t0).astype(float) * 1e-9
            g = rows["gyro"].astype(float)
            foot_gyro[leg] = np.stack([np.interp(t, tt, g[:, k]) for k in range(3)], axis=1)
    return Recording(
        t=t, q=ls["q"].astype(float), dq=ls["dq"].astype(float), cmd=cmd, cmd_t=cmd_t,
        cmd_events=ev, base_quat=ls["imu_quat_wxyz"].astype(float),
        base_gyro=ls["imu_gyro"].astype(float), base_acc=ls["imu_accel"].astype(float),
        mount=mount, tau=ls["tau_est"].astype(float), foot_force=foot_force,
        foot_gyro=foot_gyro, source=str(p),
    )


def load_recording(path: str | Path, mount: str | None = None) -> Recording:
    """:func:`read_mcap_recording` for ``.mcap``, :func:`read_csv` for ``.csv``."""
    suffix = Path(path).suffix.lower()
    if suffix == ".mcap":
        return read_mcap_recording(path, mount)
    if suffix == ".csv":
        return read_csv(path, mount)
    raise ValueError(f"{path}: expected a .csv or .mcap recording")



