"""SOLVE: one leg's calibration from the recorder, on a worker thread, and its files.

The window is the CALIBRATE span, given as two :class:`WindowMark` (the newest LowState when the
excitation began and ended). The recorder snapshot is cut by host time with generous padding,
then the streams are put on the :mod:`deploy.timebase` clocks: encoders over the window plus
``pad_s`` on each side (the solver shifts the IMU by up to its ``max_offset`` against them), the
foot IMU over the window. Then :func:`calib.pipeline.calibrate_leg` (forward kinematics with
the body gyro compensating base rotation, the correlation solver, the quality gates).

Files (atomic): ``<leg>.json`` only when the gates pass; ``<leg>.png`` in both cases (the
correlation against offset and the angular velocities before and after alignment).
"""

from __future__ import annotations

import io
import logging
import queue
import threading
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.atomic import write_bytes_atomic
from calib.joints import check_leg, sdk_indices
from calib.metrics import geodesic_error_deg
from calib.pipeline import calibrate_leg
from calib.result import CalibrationResult
from calib.solver import AlignedSignals, CalibrationRefused, SolverConfig, SolverResult
from deploy.timebase import TimeBase
from hw.recorder import RecordingSnapshot

__all__ = ["LegData", "SolveJob", "SolveOutcome", "SolveWorker", "WindowMark", "extract_leg_data",
           "solve_leg"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WindowMark:
    """A point of the recording: host receive time (ns) of the newest LowState and its
    encoder time in the session's time base (s)."""

    host_ns: int
    t_enc: float


@dataclass
class LegData:
    """Inputs of the solver for one leg. t_enc (N,) s; q, dq (N, 3) rad, rad/s (hip, thigh,
    calf); base_omega (N, 3) rad/s body frame; t_imu (M,) s; gyro (M, 3) rad/s IMU frame."""

    t_enc: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    base_omega: np.ndarray
    t_imu: np.ndarray
    gyro: np.ndarray
    imu_overwritten: int = 0
    lowstate_overwritten: int = 0


@dataclass
class SolveOutcome:
    """One leg's SOLVE. ``result``: the result (accepted, or the diagnostics of a refusal, or
    None when not even diagnostics exist); ``error``: why nothing was written as a calibration;
    ``truth``: (R_I^F, t_d) of the simulated mounting, when known; ``files`` written."""

    leg: str
    accepted: bool = False
    result: CalibrationResult | None = None
    solver: SolverResult | None = None
    error: str | None = None
    truth: tuple[np.ndarray, float] | None = None
    files: list[Path] = field(default_factory=list)
    enc_samples: int = 0
    imu_samples: int = 0
    window_s: float = float("nan")
    solve_s: float = float("nan")

    def errors_vs_truth(self) -> tuple[float, float] | None:
        """(geodesic rotation error deg, |offset error| s) against the truth, if both exist."""
        if self.truth is None or self.result is None:
            return None
        r, t = self.truth
        return (geodesic_error_deg(self.result.rotation_matrix, r),
                abs(self.result.time_offset_s - t))


def _unique_sorted(t: np.ndarray) -> np.ndarray:
    """Indices that sort ``t`` and drop repeated stamps (the mock repeats its last LowState
    when idle; the robot may too)."""
    order = np.argsort(t, kind="stable")
    keep = np.ones(order.size, bool)
    keep[1:] = np.diff(t[order]) > 0
    return order[keep]


def extract_leg_data(snapshot, leg: str, time_base: TimeBase, t0: float, t1: float,
                     pad_s: float = 0.6) -> LegData:
    """Solver inputs of ``leg`` from a recorder snapshot, on ``time_base``'s clocks.

    Encoders over [t0 - pad_s, t1 + pad_s], IMU samples over [t0, t1] (s, time base)."""
    leg = check_leg(leg)
    ls = snapshot.lowstate
    if leg not in snapshot.imu:
        raise ValueError(f"no foot IMU stream for {leg} in the recording")
    imu = snapshot.imu[leg]
    te = time_base.encoder_times(ls)
    eps = 1e-9  # ms ticks as float s: 7624e-3 - 0.6 > 7024e-3, one sample lost at an edge
    sel = (te >= t0 - pad_s - eps) & (te <= t1 + pad_s + eps)
    ls, te = ls[sel], te[sel]
    o = _unique_sorted(te)
    ls, te = ls[o], te[o]
    idx = sdk_indices(leg)
    ok = time_base.imu_valid(imu)
    imu = imu[ok]
    ti = time_base.imu_times(imu)
    sel = (ti >= t0) & (ti <= t1)
    imu, ti = imu[sel], ti[sel]
    o = _unique_sorted(ti)
    imu, ti = imu[o], ti[o]
    return LegData(
        t_enc=te, q=ls["q"][:, idx].astype(float), dq=ls["dq"][:, idx].astype(float),
        base_omega=ls["imu_gyro"].astype(float), t_imu=ti, gyro=imu["gyro"].astype(float),
        imu_overwritten=int(snapshot.overwritten.get(f"imu/{leg}", 0)),
        lowstate_overwritten=int(snapshot.overwritten.get("lowstate", 0)),
    )


def _leg_snapshot(recorder, leg: str, t0_ns: int) -> RecordingSnapshot:
    """Copies of only what SOLVE reads (LowState and this leg's IMU) from ``t0_ns`` on."""
    empty = np.zeros(0, dtype=[("t_host_ns", "i8")])
    ls = recorder.ring("lowstate").read(t0_ns, None)
    try:
        im = recorder.ring(f"imu/{leg}").read(t0_ns, None)
    except ValueError:
        raise ValueError(f"no foot IMU stream for {leg} in the recording") from None
    return RecordingSnapshot(
        lowstate=ls.rows, lowcmd=empty, wireless=empty, imu={leg: im.rows}, events=empty,
        total_written={"lowstate": ls.total_written, f"imu/{leg}": im.total_written},
        overwritten={"lowstate": ls.overwritten, f"imu/{leg}": im.overwritten}, t0_ns=t0_ns)


def solve_leg(recorder, leg: str, window: tuple[WindowMark, WindowMark], time_base: TimeBase,
              out_dir: Path | None, *, kin=None, config: SolverConfig | None = None,
              truth: tuple[np.ndarray, float] | None = None, pad_s: float = 0.6,
              host_pad_s: float = 5.0) -> SolveOutcome:
    """Snapshot, extract, calibrate, write. Never raises: failures land in ``error``."""
    import time

    t_start = time.perf_counter()
    out = SolveOutcome(leg=check_leg(leg), truth=truth)
    try:
        start, end = window
        if start is None or end is None:
            raise ValueError("the calibration window was not recorded")
        snap = _leg_snapshot(recorder, leg, int(start.host_ns - host_pad_s * 1e9))
        data = extract_leg_data(snap, leg, time_base, start.t_enc, end.t_enc, pad_s)
        out.enc_samples, out.imu_samples = len(data.t_enc), len(data.t_imu)
        out.window_s = end.t_enc - start.t_enc
        if len(data.t_imu) < 2:
            raise ValueError(f"no foot-IMU samples of {leg} in the calibration window "
                             f"({len(data.t_imu)}): is the IMU on the right port?")
        if len(data.t_enc) < 10:
            raise ValueError(f"only {len(data.t_enc)} LowState samples in the window")
        # a wrapped ring no longer holds the window's start: the solve would quietly use the
        # rest (--record-seconds 12 solved 5 of an 18 s excitation and wrote it)
        wrapped = data.lowstate_overwritten > 0 or data.imu_overwritten > 0
        if wrapped and (data.t_enc[0] > start.t_enc - pad_s + 0.05
                        or data.t_imu[0] > start.t_enc + 0.05):
            raise ValueError("the recorder no longer holds the start of the calibration "
                             "window (its ring wrapped): give a larger --record-seconds")
        # Over the same rows the times were mapped from (the whole snapshot, not the window).
        imu_all = snap.imu[leg]
        clock_problems = time_base.check(snap.lowstate, imu_all[time_base.imu_valid(imu_all)])
        if clock_problems:
            raise ValueError("clock check failed: " + "; ".join(clock_problems))
        if kin is None:
            from calib.kinematics import LegKinematics

            kin = LegKinematics.from_urdf(leg=leg)
        try:
            res, sol = calibrate_leg(leg, data.t_enc, data.q, data.dq, data.t_imu, data.gyro,
                                     data.base_omega, kin=kin, config=config)
            out.result, out.solver, out.accepted = res, sol, True
        except CalibrationRefused as e:
            out.solver = e.diagnostics
            out.error = "quality gates failed: " + "; ".join(e.reasons)
            try:
                out.result = CalibrationResult.from_solver(leg, e.diagnostics,
                                                           foot_frame=kin.foot_frame)
            except ValueError:
                out.result = None  # no usable rotation in the diagnostics
        if out_dir is not None:
            out_dir = Path(out_dir)
            if out.accepted:
                out.files.append(out.result.write(out_dir / f"{leg}.json"))
            try:
                png = plot_png(out, data, kin)
                out.files.append(write_bytes_atomic(out_dir / f"{leg}.png", png))
            except Exception as e:  # noqa: BLE001 - a figure must never cost the calibration
                log.warning("figure of %s not written: %r", leg, e)
    except Exception as e:  # noqa: BLE001 - reported by the state machine, never lost
        out.accepted = False
        out.error = f"{type(e).__name__}: {e}"
        log.debug("solve of %s failed:\n%s", leg, traceback.format_exc())
    out.solve_s = time.perf_counter() - t_start
    return out


def plot_png(out: SolveOutcome, data: LegData, kin) -> bytes:
    """The figure of one leg's SOLVE as PNG bytes (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    sol = out.solver
    fig = Figure(figsize=(10, 9), dpi=100)
    axs = fig.subplots(3, 1)
    verdict = "accepted" if out.accepted else f"NOT WRITTEN ({out.error})"
    fig.suptitle(f"Foot IMU {out.leg}: {verdict}"[:140], fontsize=10)
    ax = axs[0]
    if sol is not None and sol.offsets is not None and len(sol.offsets):
        ax.plot(np.asarray(sol.offsets) * 1e3, sol.correlation_curve, lw=1)
        if np.isfinite(sol.time_offset):
            ax.axvline(sol.time_offset * 1e3, color="C1", ls="--",
                       label=f"estimate {sol.time_offset * 1e3:+.2f} ms")
    if out.truth is not None:
        ax.axvline(out.truth[1] * 1e3, color="C2", ls=":", label=f"truth {out.truth[1] * 1e3:+.2f} ms")
    ax.set_xlabel("time offset t_d = t_I - t_E (ms)")
    ax.set_ylabel("trace correlation r")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)

    # Before: the raw streams on their own stamps; frames differ, so compare magnitudes.
    omega_f = kin.foot_angular_velocity(data.q, data.dq, data.base_omega)
    t0 = data.t_imu[0]
    t_show = min(6.0, data.t_imu[-1] - t0)
    mid = t0 + 0.5 * (data.t_imu[-1] - t0 - t_show)
    si = (data.t_imu >= mid) & (data.t_imu <= mid + t_show)
    se = (data.t_enc >= mid) & (data.t_enc <= mid + t_show)
    ax = axs[1]
    ax.plot(data.t_enc[se] - mid, np.linalg.norm(omega_f[se], axis=1), lw=1,
            label="|omega_F| encoders (t_E)")
    ax.plot(data.t_imu[si] - mid, np.linalg.norm(data.gyro[si], axis=1), lw=1, alpha=0.8,
            label="|omega_I| foot IMU (t_I)")
    ax.set_title("before calibration (own stamps, magnitudes)", fontsize=9)
    ax.set_ylabel("rad/s")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)

    ax = axs[2]
    al = sol.aligned if sol is not None else None
    if al is not None and len(al.t):
        s = (al.t_imu >= mid) & (al.t_imu <= mid + t_show)
        for j, name in enumerate("xyz"):
            ax.plot(al.t[s] - mid, al.omega_foot[s, j], lw=1.2, color=f"C{j}",
                    label=f"omega_F {name}")
            ax.plot(al.t[s] - mid, al.omega_imu_in_foot[s, j], lw=0.8, ls="--", color=f"C{j}",
                    label=f"R omega_I {name}")
        ax.legend(loc="upper right", fontsize=7, ncol=3)
    ax.set_title("after calibration (IMU rotated into the foot frame, shifted by t_d)", fontsize=9)
    ax.set_xlabel("s")
    ax.set_ylabel("rad/s")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _warm_figure() -> None:
    t = np.linspace(0.0, 1.0, 50)
    w = np.stack([np.sin(t), np.cos(t), t], axis=1)
    sol = SolverResult(np.eye(3), 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 50, t - 0.5, t,
                       AlignedSignals(t, t, w, w, w), np.zeros(3))
    plot_png(SolveOutcome("FL", solver=sol),
             LegData(t, np.zeros((50, 3)), np.zeros((50, 3)), np.zeros((50, 3)), t, w),
             _ZeroKin())


class _ZeroKin:
    def foot_angular_velocity(self, q, dq, base_omega=None):
        return np.zeros((len(q), 3))


class SolveJob:
    """One queued call (``solve_leg`` unless told); ``done()`` / ``outcome()`` (blocks)."""

    def __init__(self, args: tuple, kwargs: dict, fn=None):
        self.fn = fn or solve_leg
        self.args, self.kwargs = args, kwargs
        self._done = threading.Event()
        self._out: SolveOutcome | None = None

    def _run(self) -> None:
        try:
            self._out = self.fn(*self.args, **self.kwargs)
        except Exception as e:  # the worker must outlive any one job
            log.exception("solve worker: %s failed", getattr(self.fn, "__name__", "job"))
            leg = self.args[1] if len(self.args) > 1 and isinstance(self.args[1], str) else "?"
            self._out = SolveOutcome(leg=leg, error=f"{type(e).__name__}: {e}")
        finally:
            self._done.set()

    def done(self) -> bool:
        return self._done.is_set()

    def outcome(self) -> SolveOutcome:
        self._done.wait()
        return self._out

    def join(self, timeout: float | None = None) -> None:
        self._done.wait(timeout)


class SolveWorker:
    """One long-lived daemon thread that runs SOLVE jobs in order (never the control loop).

    One thread for the whole session, not one per leg: its memory (the C allocator's per-thread
    arena, the solver's buffers) is reused from leg to leg, so a long session does not grow.
    """

    def __init__(self):
        self._q: queue.SimpleQueue[SolveJob | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="a2i-solve", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            job = self._q.get()
            if job is None:
                return
            job._run()

    def warm_up(self, timeout: float = 60.0) -> None:
        """Load and exercise the figure code on the worker now (matplotlib's import and first
        render cost ~1 s and tens of MiB): the loop then never waits for it and the
        process's memory does not step up at the first calibration."""
        job = SolveJob((), {}, fn=_warm_figure)
        self._q.put(job)
        job.join(timeout)

    def submit(self, *args, **kwargs) -> SolveJob:
        """Queue ``solve_leg(*args, **kwargs)``; returns its job."""
        job = SolveJob(args, kwargs)
        self._q.put(job)
        return job

    def close(self, timeout: float = 60.0) -> None:
        self._q.put(None)
        self._thread.join(timeout)
