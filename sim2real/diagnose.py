"""Diagnose the sim-to-real gap of one recording: where, which effect, how far it shrinks.

Pipeline (``docs/sim2real.md``):

1. **Replay** the recording in ``sim`` by multiple shooting (:mod:`sim2real.replay`, 0.5 s
   windows). Windows ``k % 3 == 2`` are the **held-out split**; the others train.
2. **Where**: noise-corrected normalised gaps per channel, joint, leg, phase and band
   (:mod:`sim2real.metrics`); the unmodelled torque is localised by the equivalent torque
   residual ``M(q) (ddq_rec - ddq_sim)``.
3. **Screening** (cheap signatures): a dynamic gap (joints) is attributed to one joint when one
   joint carries most of the torque residual, else to ``all``; the matching dynamic candidates
   are fitted. An IMU gap (body IMU channels) brings in the IMU candidates. A per-packet test
   (replay each command interval with and without that packet) looks for dropped packets.
4. **Fit** each shortlisted candidate on the training windows with the largest gaps: a
   coarse grid then a bounded scalar search (scipy), a grid at the physics step for latency,
   closed forms for IMU effects, CMA-ES (``cma``) for the joint refit of combinations.
   Confidence intervals (95 %) come from the Jacobian of the normalised residuals at the
   optimum, inflated for the residuals' autocorrelation (:data:`AUTOCORR` samples).
5. **Rank** on the held-out split by a BIC, ``n_eff ln(SSE / n) + k ln(n_eff)`` with
   ``n_eff = n / AUTOCORR``; packet loss counts one parameter per detected drop. Scored per
   window: a held-out window whose nominal residual is an outlier against the recording's own
   spread of window residuals (median + 3 MAD sigmas) and that no candidate reduces by
   :data:`MIN_REDUCTION` is left out of every score (a residual the library cannot explain,
   e.g. a foot leaving the floor mid-window); on the ground, outlier windows are also kept out
   of localisation, fit-window choice and the IMU fits.
6. **Decide**: the gap is significant when the held-out gap exceeds :data:`MIN_GAP` and some
   effect removes at least :data:`MIN_REDUCTION` of it with a lower BIC than the nominal
   simulator; the answer is the best-BIC effect among those. Greedy combination: the next
   candidate of a different kind is added while it removes a further :data:`MIN_EXTRA` of the
   original gap.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np
from scipy.optimize import minimize_scalar

from calib.joints import SDK_JOINT_NAMES, sdk_to_model
from sim.effects import PacketLoss
from sim.go2 import SimConfig, build_model_for
from sim2real import metrics as mt
from sim2real.candidates import Candidate, dynamic_candidates, imu_candidates
from sim2real.recording import Recording
from sim2real.replay import Prediction, Replayer, make_windows

__all__ = ["AUTOCORR", "DiagnoseConfig", "Diagnosis", "EffectFit", "diagnose"]

AUTOCORR = 10.0  # residual samples per independent sample (500 Hz residuals, ~50 Hz content)
MIN_GAP = 0.01  # held-out noise-corrected normalised gap below which nothing is significant
MIN_REDUCTION = 0.3  # fraction of the held-out gap the best effect must remove
MIN_EXTRA = 0.15  # further fraction of the original gap an added effect must remove
TORQUE_SHARE_LOCAL = 0.45
# Joint-channel gap below which no dynamic effect is fitted (screening), per mount: on the ground
# the re-synchronisation (base state settled by the burn-in, sim2real.replay) alone leaves
# about 0.03 on null recordings (docs/sim2real.md)
DYN_SCREEN = {"suspended": 0.005, "ground": 0.045}


@dataclass
class DiagnoseConfig:
    """window s; fit_windows: training windows used in the fits (largest gaps first);
    progress: called with one line of text per step (None: silent)."""

    window: float = 0.5
    fit_windows: int = 3
    progress: Callable[[str], None] | None = None


@dataclass
class EffectFit:
    """One fitted candidate. parameters / ci: {name: value} / {name: [lo, hi]} (95 %),
    units per :data:`sim2real.candidates.UNITS`; gap_after_heldout: held-out gap with this
    effect (alone, or with the effects chosen before it when ``chosen``); bic on held-out."""

    name: str
    location: list[str]
    parameters: dict[str, float]
    ci: dict[str, list[float]]
    gap_after_heldout: float
    bic: float
    k: int
    evaluations: int = 0
    chosen: bool = False
    candidate: Candidate | None = field(default=None, repr=False)
    x: np.ndarray | None = field(default=None, repr=False)
    drop_times: np.ndarray | None = field(default=None, repr=False)
    partner_x: np.ndarray | None = field(default=None, repr=False)
    partner_ci: list[float] | None = field(default=None, repr=False)
    win_ss: np.ndarray | None = field(default=None, repr=False)  # (W, C) held-out windows
    win_n: np.ndarray | None = field(default=None, repr=False)  # (W,) samples per window
    k_bic: int | None = field(default=None, repr=False)  # parameters in the BIC, when not k

    def effects(self) -> list:
        if self.name == "packet_loss":
            return [PacketLoss(drop_times=self.drop_times)]
        return self.candidate.build(self.x)

    def to_json(self) -> dict:
        return {"name": self.name, "location": list(self.location),
                "parameters": {k: float(v) for k, v in self.parameters.items()},
                "ci": {k: [float(a), float(b)] for k, (a, b) in self.ci.items()},
                "gap_after_heldout": float(self.gap_after_heldout), "bic": float(self.bic),
                "n_parameters": int(self.k), "chosen": bool(self.chosen)}


@dataclass
class Diagnosis:
    """The answer. effects: most likely first (the chosen combination leads).
    where: {"channels"|"joints"|"legs"|"phases"|"bands": {name: gap}} before, over every
    window; ``where_heldout`` the same over the held-out windows and ``where_after`` there
    with the chosen effects (the two to compare; empty without a significant gap)."""

    significant_gap: bool
    gap_before: float
    gap_after: float
    gap_before_train: float
    effects: list[EffectFit]
    where: dict[str, dict[str, float]]
    where_after: dict[str, dict[str, float]]
    screening: dict
    recording: Recording = field(repr=False)
    nominal: Prediction = field(repr=False)
    after: Prediction | None = field(repr=False, default=None)
    heldout_mask: np.ndarray | None = field(repr=False, default=None)
    seconds: float = 0.0
    where_heldout: dict[str, dict[str, float]] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "significant_gap": bool(self.significant_gap),
            "gap_before": float(self.gap_before),
            "gap_after": float(self.gap_after),
            "effects": [e.to_json() for e in self.effects] if self.significant_gap else [],
            "candidates": [e.to_json() for e in self.effects],
            "where": self.where,
            "where_heldout": self.where_heldout,
            "where_after": self.where_after,
            "screening": self.screening,
            "mount": self.recording.mount,
            "duration_s": self.recording.duration,
            "seconds": self.seconds,
        }


# ---------------------------------------------------------------------------- helpers
class _Problem:
    """The recording, its channels, windows and split, and cost functions."""

    def __init__(self, rec: Recording, cfg: DiagnoseConfig):
        self.rec, self.cfg = rec, cfg
        self.cs = mt.channel_set(rec)
        self.rp = Replayer(rec)
        self.windows = make_windows(rec, cfg.window)
        if len(self.windows) < 3:
            raise ValueError(f"recording of {rec.duration:.2f} s is too short: at least "
                             f"{3 * cfg.window:.1f} s are needed (3 windows)")
        self.train = [w for k, w in enumerate(self.windows) if k % 3 != 2]
        self.held = [w for k, w in enumerate(self.windows) if k % 3 == 2]
        self.held_mask = self._mask(self.held)
        self.train_mask = self._mask(self.train)
        self.keep = np.ones(len(self.held), bool)  # held-out windows that are scored
        self.imu_mask = self.train_mask  # training samples of the IMU fits (set by diagnose)
        self.evals = 0

    def _mask(self, windows) -> np.ndarray:
        m = np.zeros(self.rec.n, bool)
        for a, b in windows:
            m[a + 1:b] = True
        return m

    def run(self, effects, windows, key=None) -> Prediction:
        self.evals += 1
        return self.rp.run(effects, windows, key=key)

    def residual(self, pred: Prediction, mask: np.ndarray) -> np.ndarray:
        return mt.normalised_residual(self.cs, mt.pred_matrix(pred), mask & pred.mask)

    def sse(self, pred: Prediction, mask: np.ndarray) -> tuple[float, int]:
        r = self.residual(pred, mask)
        return float(np.sum(r**2)), int(r.size)

    def bic(self, sse: float, n: int, k: int) -> float:
        n_eff = max(n / AUTOCORR, 1.0)
        return float(n_eff * np.log(max(sse, 1e-300) / n) + k * np.log(n_eff))

    def gap(self, pred: Prediction, mask: np.ndarray, channels=None) -> float:
        return mt.gap(self.residual(pred, mask), self.cs.noise, channels)

    def window_stats(self, pred: Prediction, windows) -> tuple[np.ndarray, np.ndarray]:
        """(W, C) sums of squared normalised residuals and (W,) sample counts per window."""
        ss = np.zeros((len(windows), len(self.cs.names)))
        n = np.zeros(len(windows))
        for i, (a, b) in enumerate(windows):
            mk = np.zeros(self.rec.n, bool)
            mk[a + 1:b] = True
            r = self.residual(pred, mk)
            ss[i], n[i] = np.sum(r**2, axis=0), r.shape[0]
        return ss, n

    def stats_gap(self, ss: np.ndarray, n: np.ndarray, sel: np.ndarray) -> float:
        """The gap (:func:`sim2real.metrics.gap`) of the windows ``sel`` from window stats."""
        nt = float(n[sel].sum())
        if nt <= 0:
            return 0.0
        ms = ss[sel].sum(axis=0) / nt - mt._noise_allowance(self.cs.noise, int(nt))
        return float(np.sqrt(np.mean(np.maximum(ms, 0.0))))

    def window_ms(self, ss: np.ndarray, n: np.ndarray) -> np.ndarray:
        """(W,) noise-corrected mean square normalised residual of each window."""
        ms = ss / np.maximum(n, 1)[:, None] - np.stack(
            [mt._noise_allowance(self.cs.noise, int(k)) for k in n])
        return np.mean(np.maximum(ms, 0.0), axis=1)

    def score(self, fit: EffectFit, held: Prediction | None = None) -> EffectFit:
        """Set ``fit``'s held-out gap and BIC on the scored windows (``keep``); ``held``: its
        held-out prediction (stats kept for rescoring)."""
        if held is not None:
            fit.win_ss, fit.win_n = self.window_stats(held, self.held)
        fit.gap_after_heldout = self.stats_gap(fit.win_ss, fit.win_n, self.keep)
        nt = float(fit.win_n[self.keep].sum()) * fit.win_ss.shape[1]
        k = fit.k if fit.k_bic is None else fit.k_bic
        fit.bic = self.bic(float(fit.win_ss[self.keep].sum()), int(nt), k)
        return fit


def _progress(cfg: DiagnoseConfig, msg: str) -> None:
    if cfg.progress is not None:
        cfg.progress(msg)


def _mass_fn(rec: Recording):
    base = "fixed" if rec.mount == "suspended" else "free"
    m = build_model_for(SimConfig(base=base))
    d = mujoco.MjData(m)
    off = 0 if base == "fixed" else 7
    voff = 0 if base == "fixed" else 6
    if base == "free":
        d.qpos[3] = 1.0
    full = np.zeros((m.nv, m.nv))

    def mass(q_sdk):
        d.qpos[off:off + 12] = sdk_to_model(q_sdk)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_crb(m, d)
        mujoco.mj_fullM(m, d, full)
        mm = full[voff:voff + 12, voff:voff + 12]
        return mm[np.ix_(sdk_to_model(np.arange(12)), sdk_to_model(np.arange(12)))]

    return mass


def _peak_torque(rec: Recording) -> np.ndarray:
    """(12,) SDK order, N m: the largest torque each motor is seen to need, from the PD law on
    the recorded state and commands, and from the estimated torques when recorded (a motor
    that saturates shows its plateau there, the PD law the demand)."""
    c = rec.cmd
    pd = c["kp"] * (c["q"] - rec.q) + c["kd"] * (c["dq"] - rec.dq) + c["tau"]
    peak = np.percentile(np.abs(pd), 99.5, axis=0)
    if rec.tau is not None:
        peak = np.maximum(peak, np.percentile(np.abs(rec.tau), 99.5, axis=0))
    return peak


def _fit_scalar(f: Callable[[float], float], lo: float, hi: float, grid: float | None,
                nominal: float, log: bool = False, hints=()) -> float:
    """Coarse grid (with the nominal value and ``hints``; 7 log-spaced points when ``log``,
    steps of 5 ``grid`` when given) then a bounded Brent search / fine grid."""
    if grid is not None:  # a grid-resolved parameter: coarse steps of 5 grid steps (a
        # 15 ms coarse step let ground latency settle in a neighbouring basin)
        coarse = np.arange(lo, hi + grid / 2, 5 * grid)
    elif log and lo > 0:
        coarse = np.geomspace(lo, hi, 7)
    else:
        coarse = np.linspace(lo, hi, 5)
    xs = np.unique(np.concatenate([coarse, [nominal], np.asarray(hints, float)]))
    vals = np.array([f(x) for x in xs])
    b = int(np.argmin(vals))
    a_, c_ = xs[max(b - 1, 0)], xs[min(b + 1, xs.size - 1)]
    if grid is not None:
        fine = np.arange(a_, c_ + grid / 2, grid)
        fv = np.array([f(x) for x in fine])
        k = int(np.argmin(fv))
        if 0 < k < fine.size - 1:  # parabola through the best three grid points
            y0, y1, y2 = fv[k - 1], fv[k], fv[k + 1]
            den = y0 - 2 * y1 + y2
            off = 0.5 * (y0 - y2) / den if den > 0 else 0.0
            return float(fine[k] + np.clip(off, -0.5, 0.5) * grid)
        return float(fine[k])
    if a_ == c_:
        return float(xs[b])
    r = minimize_scalar(f, bounds=(a_, c_), method="bounded",
                        options={"xatol": (hi - lo) * 2e-3, "maxiter": 7})
    return float(r.x) if r.fun <= vals[b] else float(xs[b])


def _ci_from_jacobian(res_fn, x: np.ndarray, lo, hi, steps) -> np.ndarray:
    """(k, 2) 95 % intervals from the finite-difference Jacobian of ``res_fn`` at ``x``."""
    r0 = res_fn(x)
    cols = []
    for i, h in enumerate(steps):
        xp, xm = x.copy(), x.copy()
        xp[i] = min(x[i] + h, hi[i])
        xm[i] = max(x[i] - h, lo[i])
        if xp[i] - xm[i] <= 0:
            cols.append(np.zeros_like(r0))
            continue
        cols.append((res_fn(xp) - res_fn(xm)) / (xp[i] - xm[i]))
    jac = np.stack(cols, axis=1)
    dof = max(r0.size - x.size, 1)
    s2 = float(r0 @ r0) / dof * AUTOCORR
    jtj = jac.T @ jac
    try:
        cov = s2 * np.linalg.pinv(jtj)
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        sd = np.full(x.size, np.inf)
    return np.stack([x - 1.96 * sd, x + 1.96 * sd], axis=1)


# ---------------------------------------------------------------------------- fitting
def _fit_dynamic(pb: _Problem, cand: Candidate, fit_w, fit_mask) -> EffectFit:
    e0 = pb.evals
    key = None if cand.spec else cand.key

    def pred_at(x):
        return pb.run(cand.build(np.atleast_1d(x)), fit_w, key=key)

    def cost(x):
        return pb.sse(pred_at(x), fit_mask)[0]

    x = np.array([_fit_scalar(lambda v: cost(np.array([v])), cand.lo[0], cand.hi[0],
                              cand.grid, cand.nominal[0], cand.log, cand.hints)])
    step = cand.grid if cand.grid else (cand.hi[0] - cand.lo[0]) * 0.01

    def res_fn(xx):
        return pb.residual(pred_at(xx), fit_mask).ravel()

    ci = _ci_from_jacobian(res_fn, x, cand.lo, cand.hi, [step])
    held = pb.run(cand.build(x), pb.held, key=key)
    fit = EffectFit(cand.name, [cand.location], dict(zip(cand.params, x.tolist(), strict=True)),
                    {p: ci[i].tolist() for i, p in enumerate(cand.params)},
                    0.0, 0.0, 1, pb.evals - e0, candidate=cand, x=x)
    return pb.score(fit, held)


def _imu_transform(cand: Candidate, x: np.ndarray, pred: Prediction, t) -> Prediction:
    from sim.effects import apply_imu_effects
    g, a, _ = apply_imu_effects(cand.build(x), t, np.nan_to_num(pred.gyro),
                                np.nan_to_num(pred.acc), np.tile([1.0, 0, 0, 0], (t.size, 1)))
    return Prediction(pred.q, pred.dq, g, a, pred.contact, pred.mask, pred.failed)


def _fit_imu(pb: _Problem, cand: Candidate, base_train: Prediction, base_held: Prediction,
             base_k: int = 0) -> EffectFit:
    rec, cs = pb.rec, pb.cs
    imu_ch = np.concatenate([cs.index("gyro"), cs.index("acc")])
    m = pb.imu_mask & base_train.mask
    pg, pa = np.nan_to_num(base_train.gyro[m]), np.nan_to_num(base_train.acc[m])
    rg, ra = rec.base_gyro[m], rec.base_acc[m]
    if cand.name == "imu_bias":
        x = (rg - pg).mean(axis=0)
    elif cand.name == "imu_misalignment":
        g = 9.81
        p = np.vstack([pg, pa / g])
        r = np.vstack([rg, ra / g])
        u, _, vt = np.linalg.svd(p.T @ r)
        dfix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
        rot = u @ dfix @ vt  # r ~ p @ rot
        from scipy.spatial.transform import Rotation
        rv = Rotation.from_matrix(rot).as_rotvec()
        pr = pg @ rot
        den = float(np.sum(pr * pr))
        s = float(np.sum(rg * pr) / den) if den > 1e-9 else 1.0
        x = np.concatenate([rv, [np.clip(s, 0.5, 2.0)]])
    else:  # time offset: grid at 0.5 ms then parabola
        def cst(v):
            tr = _imu_transform(cand, np.array([v]), base_train, rec.t)
            return float(np.sum(pb.residual(tr, pb.imu_mask)[:, imu_ch] ** 2))
        x = np.array([_fit_scalar(cst, -0.05, 0.05, 0.0005, 0.0)])

    def res_fn(xx):
        tr = _imu_transform(cand, xx, base_train, rec.t)
        return pb.residual(tr, pb.imu_mask)[:, imu_ch].ravel()

    steps = [1e-3] * len(x) if cand.name != "imu_time_offset" else [5e-4]
    ci = _ci_from_jacobian(res_fn, x, cand.lo, cand.hi, steps)
    held = _imu_transform(cand, x, base_held, rec.t)
    fit = EffectFit(cand.name, [cand.location], dict(zip(cand.params, x.tolist(), strict=True)),
                    {p: ci[i].tolist() for i, p in enumerate(cand.params)},
                    0.0, 0.0, len(x), 0, candidate=cand, x=x, k_bic=len(x) + base_k)
    return pb.score(fit, held)


def _detect_drops(pb: _Problem, windows) -> tuple[np.ndarray, int]:
    """Times of the commands whose replay fits better without them (dropped packets), and
    the number of commands tested, within ``windows``."""
    rec = pb.rec
    ct = rec.cmd_t
    idx = np.searchsorted(rec.t, ct - 1e-9)
    inside = np.zeros(ct.size, bool)
    for a, b in windows:
        inside |= (idx > a) & (idx < b - 3)
    cands = np.nonzero(inside & (idx < rec.n))[0]
    if cands.size == 0:
        return np.zeros(0), 0
    nxt = np.append(idx[1:], rec.n)
    wins = [(int(idx[c]), int(min(nxt[c] + 1, rec.n))) for c in cands]
    keep = pb.run([], wins, key="nominal")
    dq_ch = np.concatenate([pb.cs.index("q"), pb.cs.index("dq")])
    sse_keep = np.zeros(cands.size)
    sse_drop = np.zeros(cands.size)
    for parity in (0, 1):
        sel = [k for k in range(cands.size) if k % 2 == parity]
        if not sel:
            continue
        drops = ct[cands[sel]]
        pd_ = pb.run([PacketLoss(drop_times=drops)], [wins[k] for k in sel], key="nominal")
        for k in sel:
            a, b = wins[k]
            mk = np.zeros(rec.n, bool)
            mk[a + 1:b] = True
            sse_keep[k] = np.sum(pb.residual(keep, mk)[:, dq_ch] ** 2)
            sse_drop[k] = np.sum(pb.residual(pd_, mk)[:, dq_ch] ** 2)
    n_samp = np.array([b - a - 1 for a, b in wins])
    floor = n_samp * float(np.sum(pb.cs.noise[dq_ch])) * 3.0
    dropped = (sse_drop < 0.5 * sse_keep) & (sse_keep - sse_drop > floor)
    return ct[cands[dropped]], int(cands.size)


def _fit_packet_loss(pb: _Problem) -> EffectFit | None:
    e0 = pb.evals
    d_train, n_train = _detect_drops(pb, pb.train)
    if n_train == 0 or d_train.size == 0:
        return None
    d_held, _ = _detect_drops(pb, pb.held)
    p = d_train.size / n_train
    # Wilson score interval
    z = 1.96
    den = 1 + z**2 / n_train
    c = (p + z**2 / (2 * n_train)) / den
    h = z * np.sqrt(p * (1 - p) / n_train + z**2 / (4 * n_train**2)) / den
    drops = np.sort(np.concatenate([d_train, d_held]))
    held = pb.run([PacketLoss(drop_times=drops)], pb.held, key="nominal")
    # which packets were lost cannot be predicted, only found: the held-out windows are scored
    # with the drops found on them, so those drops are what the held-out BIC must pay for (one
    # parameter each; the training drops do not touch a held-out window)
    fit = EffectFit("packet_loss", ["all"], {"probability": p},
                    {"probability": [max(c - h, 0.0), min(c + h, 1.0)]},
                    0.0, 0.0, int(d_train.size), pb.evals - e0, drop_times=drops,
                    k_bic=int(d_held.size))
    return pb.score(fit, held)


def _refit_pair(pb: _Problem, a: EffectFit, b: EffectFit, fit_w, fit_mask) -> EffectFit | None:
    """Joint CMA-ES refit of two scalar dynamic effects; returns b's fit within the pair
    (gap/bic of the pair) with a's parameter updated in place, or None."""
    import cma

    ca, cb = a.candidate, b.candidate
    if ca is None or cb is None or len(a.x) != 1 or len(b.x) != 1:
        return None
    lo = np.array([ca.lo[0], cb.lo[0]])
    hi = np.array([ca.hi[0], cb.hi[0]])
    span = hi - lo

    def build(z):
        x = lo + np.clip(z, 0, 1) * span
        return ca.build(x[:1]) + cb.build(x[1:])

    def cost(z):
        return pb.sse(pb.run(build(z), fit_w), fit_mask)[0]

    z0 = (np.array([a.x[0], b.x[0]]) - lo) / span
    es = cma.CMAEvolutionStrategy(np.clip(z0, 0, 1), 0.05,
                                  {"bounds": [0, 1], "maxfevals": 24, "popsize": 6,
                                   "verbose": -9, "seed": 1})
    es.optimize(cost)
    z = es.result.xbest if es.result.xbest is not None else z0
    x = lo + np.clip(z, 0, 1) * span
    held = pb.run(build(z), pb.held)

    def res_fn(xx):
        return pb.residual(pb.run(ca.build(xx[:1]) + cb.build(xx[1:]), fit_w), fit_mask).ravel()

    # the pair's own intervals, at its optimum (each effect's alone no longer hold there: they
    # missed both the parameters and the truth)
    steps = [c.grid if c.grid else (c.hi[0] - c.lo[0]) * 0.01 for c in (ca, cb)]
    ci = _ci_from_jacobian(res_fn, x, lo, hi, steps)
    fit = pb.score(EffectFit(cb.name, [cb.location], {cb.params[0]: float(x[1])},
                             {cb.params[0]: ci[1].tolist()}, 0.0, 0.0, 2, b.evaluations,
                             candidate=cb, x=x[1:]), held)
    fit.partner_x = x[:1]  # a's parameter within the pair, applied if the pair is chosen
    fit.partner_ci = ci[0].tolist()
    return fit


# ---------------------------------------------------------------------------- main
def diagnose(rec: Recording, config: DiagnoseConfig | None = None) -> Diagnosis:
    """Diagnose ``rec`` (see the module docstring). Raises ValueError on unusable input."""
    cfg = config or DiagnoseConfig()
    t_start = time.perf_counter()
    pb = _Problem(rec, cfg)
    cs = pb.cs
    _progress(cfg, f"replaying {rec.duration:.1f} s ({rec.mount}) in {len(pb.windows)} windows "
                   f"of {cfg.window} s (held out: {len(pb.held)})")
    nominal = pb.run([], pb.windows, key="nominal")
    res_nom = pb.residual(nominal, pb.train_mask)
    gap_train = mt.gap(res_nom, cs.noise)
    gap_held = pb.gap(nominal, pb.held_mask)
    dyn_ch = np.concatenate([cs.index("q"), cs.index("dq")])
    imu_ch = np.concatenate([cs.index("gyro"), cs.index("acc")])
    gap_dyn = mt.gap(res_nom, cs.noise, dyn_ch)
    gap_imu = mt.gap(res_nom, cs.noise, imu_ch)
    _progress(cfg, f"gap before: train {gap_train:.4f}, held-out {gap_held:.4f} "
                   f"(joints {gap_dyn:.4f}, body IMU {gap_imu:.4f})")

    # -- screening
    # windows the replay cannot re-synchronise (e.g. a foot leaving the floor mid-window)
    # stand out against the recording's own spread of per-window residuals
    ss_all, n_all = pb.window_stats(nominal, pb.windows)
    outlier = _outlier_windows(pb.window_ms(ss_all, n_all))
    good_train = [w for k, w in enumerate(pb.windows) if k % 3 != 2 and not outlier[k]]
    edge = np.zeros(rec.n, bool)
    for a, b in pb.windows:
        edge[a + 8:b - 8] = True
    # on the ground the torque residual is located on the windows the replay follows (an
    # outlier window's residual is a contact event the replay missed, not a joint's torque)
    loc_mask = pb._mask(good_train) if rec.mount == "ground" and len(good_train) >= 2 \
        else pb.train_mask
    share = mt.torque_residual_share(rec, nominal, _mass_fn(rec), loc_mask & edge)
    top = int(np.argmax(share))
    location = SDK_JOINT_NAMES[top] if share[top] >= TORQUE_SHARE_LOCAL else "all"
    screening = {"gap_joints": gap_dyn, "gap_imu": gap_imu,
                 "torque_share": {n: float(s) for n, s in zip(SDK_JOINT_NAMES, share, strict=True)},
                 "location": location}
    screening["outlier_windows"] = [_span(rec, w) for w, o in zip(pb.windows, outlier,
                                                                   strict=True) if o]
    cands: list[Candidate] = []
    if gap_dyn > DYN_SCREEN[rec.mount]:
        peak = plateau = None
        if location != "all":
            j = SDK_JOINT_NAMES.index(location)
            peak = float(_peak_torque(rec)[j])
            if rec.tau is not None:
                plateau = float(np.percentile(np.abs(rec.tau[:, j]), 99.5))
        cands += dynamic_candidates(location, rec.mount, peak, plateau)
    imu_ok = gap_imu > MIN_GAP / 2
    _progress(cfg, f"screening: joint gap -> {'location ' + location if cands else 'none'}; "
                   f"body-IMU gap -> {'IMU candidates' if imu_ok else 'none'}")

    # -- fit windows: the training windows with the largest nominal cost
    # (on the ground, not the outlier windows: there a contact event the replay cannot
    # re-synchronise dominates the cost, and a fit there chases it)
    train_idx = [k for k in range(len(pb.windows)) if k % 3 != 2]
    w_cost = np.array([float(np.sum(ss_all[k, dyn_ch])) for k in train_idx])
    if rec.mount == "ground" and np.sum(~outlier[train_idx]) >= cfg.fit_windows:
        w_cost[outlier[train_idx]] = -np.inf
    order = np.argsort(w_cost)[::-1]
    fit_w = sorted(pb.train[k] for k in order[: cfg.fit_windows])
    fit_mask = pb._mask(fit_w)
    # IMU effects are fitted in closed form on the training windows the replay follows (an
    # outlier window's base motion is the replay's failure, not the IMU's)
    if len(good_train) >= 2:
        pb.imu_mask = pb._mask(good_train)

    fits: list[EffectFit] = []
    for cand in cands:
        f = _fit_dynamic(pb, cand, fit_w, fit_mask)
        fits.append(f)
        _progress(cfg, f"  {cand.key:<28} {_fmt_params(f)}  held-out gap {f.gap_after_heldout:.4f}"
                       f"  ({f.evaluations} replays)")
    if location == "all" and cands:
        f = _fit_packet_loss(pb)
        if f is not None:
            fits.append(f)
            _progress(cfg, f"  packet_loss@all               p={f.parameters['probability']:.3f}"
                           f"  held-out gap {f.gap_after_heldout:.4f}")
    imu_fits: list[EffectFit] = []
    if imu_ok:
        held_nom = nominal
        for cand in imu_candidates():
            if rec.mount == "suspended" and cand.name != "imu_bias":
                continue  # a hung base does not move: only a bias is observable
            f = _fit_imu(pb, cand, nominal, held_nom)
            imu_fits.append(f)
            _progress(cfg, f"  {cand.key:<28} {_fmt_params(f)}  held-out gap "
                           f"{f.gap_after_heldout:.4f}")
    fits += imu_fits
    # score on the held-out windows except the outliers that no candidate explains
    held_idx = [k for k in range(len(pb.windows)) if k % 3 == 2]
    ss0, n0 = ss_all[held_idx], n_all[held_idx]
    pb.keep = _scored_windows(pb, ss0, n0, outlier[held_idx], fits)
    gap_all_held = gap_held
    gap_held = pb.stats_gap(ss0, n0, pb.keep)
    for f in fits:
        pb.score(f)
    bic0 = pb.bic(float(ss0[pb.keep].sum()), int(n0[pb.keep].sum()) * ss0.shape[1], 0)
    screening["gap_heldout_all_windows"] = gap_all_held
    screening["unexplained_windows"] = [_span(rec, pb.held[i])
                                        for i in np.nonzero(~pb.keep)[0]]
    if not pb.keep.all():
        _progress(cfg, f"left out {int(np.sum(~pb.keep))} held-out window(s) that no candidate "
                       f"explains: held-out gap {gap_all_held:.4f} -> {gap_held:.4f}")
    fits.sort(key=lambda f: f.bic)

    # -- decision and greedy combination
    chosen: list[EffectFit] = []
    gap_after = gap_held
    after_pred = nominal
    significant = False
    # the best-BIC effect among those that remove the required fraction of the gap (a
    # better-BIC one that does not is a runner-up, not the answer)
    eligible = [f for f in fits if f.bic < bic0
                and 1 - f.gap_after_heldout / max(gap_held, 1e-12) >= MIN_REDUCTION]
    if eligible and gap_held > MIN_GAP:
        best = eligible[0]
        fits = [best] + [f for f in fits if f is not best]
        significant = True
        best.chosen = True
        chosen.append(best)
        gap_after = best.gap_after_heldout
        after_pred = _held_pred(pb, chosen, nominal)
        # greedy: add the best remaining effect of another kind (IMU <-> dynamic), or a
        # second dynamic one, while each removes a further MIN_EXTRA of the gap
        tried = 0
        for other in list(fits[1:]):
            if len(chosen) >= 3 or tried >= 3 or gap_after < max(MIN_GAP, 0.3 * gap_held):
                break
            if any(o.name == other.name for o in chosen):
                continue
            tried += 1
            trial = _combine(pb, chosen, other, fit_w, fit_mask, nominal)
            if trial is None:
                continue
            if gap_after - trial.gap_after_heldout >= MIN_EXTRA * gap_held and \
                    trial.bic < chosen[-1].bic:
                if trial.partner_x is not None:
                    prev = chosen[-1]
                    prev.x = trial.partner_x
                    prev.parameters = {prev.candidate.params[0]: float(trial.partner_x[0])}
                    prev.ci = {prev.candidate.params[0]: trial.partner_ci}
                trial.chosen = True
                chosen.append(trial)
                gap_after = trial.gap_after_heldout
                after_pred = _held_pred(pb, chosen, nominal)
                fits = [f for f in fits if f is not other]
    ranked = chosen + [f for f in fits if not f.chosen]
    where = _where(pb, nominal, pb.train_mask | pb.held_mask)
    where_after = _where(pb, after_pred, pb.held_mask) if significant else {}
    where_heldout = _where(pb, nominal, pb.held_mask) if significant else {}
    secs = time.perf_counter() - t_start
    verdict = ("significant gap: " + " + ".join(f"{e.name}@{','.join(e.location)}" for e in chosen)
               if significant else "no significant gap")
    _progress(cfg, f"{verdict}; held-out gap {gap_held:.4f} -> {gap_after:.4f} "
                   f"({pb.evals} replays, {secs:.1f} s)")
    return Diagnosis(significant, gap_held, gap_after, gap_train, ranked, where, where_after,
                     screening, rec, nominal, after_pred, pb.held_mask, secs,
                     where_heldout=where_heldout)


def _outlier_windows(ms: np.ndarray, k: float = 3.0) -> np.ndarray:
    """(W,) bool: windows whose noise-corrected mean square residual ``ms`` is an outlier
    above the recording's own spread (median + k robust sigmas, MAD) and above the
    significance floor."""
    med = float(np.median(ms))
    mad = 1.4826 * float(np.median(np.abs(ms - med)))
    return (ms > med + k * max(mad, 1e-3 * med)) & (ms > MIN_GAP**2)


def _scored_windows(pb: _Problem, ss0, n0, outlier: np.ndarray,
                    fits: list[EffectFit]) -> np.ndarray:
    """(W_held,) bool: the held-out windows that are scored: all but the outliers that no
    fitted candidate reduces by :data:`MIN_REDUCTION` (a residual no effect of the library
    explains, e.g. a contact event the replay cannot re-synchronise). At least half the
    held-out windows are kept (those of lowest nominal residual first)."""
    ms0 = pb.window_ms(ss0, n0)
    keep = np.ones(ms0.size, bool)
    for w in np.nonzero(outlier)[0]:
        best = min((pb.window_ms(f.win_ss, f.win_n)[w] for f in fits if f.win_ss is not None),
                   default=ms0[w])
        keep[w] = best <= (1 - MIN_REDUCTION) * ms0[w]
    need = int(np.ceil(ms0.size / 2))
    if keep.sum() < need:
        for w in np.argsort(ms0):
            if keep.sum() >= need:
                break
            keep[w] = True
    return keep


def _span(rec: Recording, w) -> list[float]:
    a, b = w
    return [float(rec.t[a] - rec.t[0]), float(rec.t[b - 1] - rec.t[0])]


def _combine(pb: _Problem, chosen: list[EffectFit], other: EffectFit, fit_w, fit_mask,
             nominal: Prediction) -> EffectFit | None:
    """``other`` added on top of ``chosen`` (refitted on top of them), or None."""
    dyn = [c for c in chosen if c.candidate is None or not c.candidate.imu]
    imu = [c for c in chosen if c.candidate is not None and c.candidate.imu]
    if other.candidate is not None and other.candidate.imu:
        if imu:
            return None
        effects = [e for c in dyn for e in c.effects()]
        base_train = pb.run(effects, pb.train) if effects else nominal
        base_held = pb.run(effects, pb.held) if effects else nominal
        k = sum(c.k for c in dyn)
        return _fit_imu(pb, other.candidate, base_train, base_held, base_k=k)
    if other.name == "packet_loss" or len(dyn) != 1 or dyn[0].name == "packet_loss":
        return None
    if imu:
        return None
    return _refit_pair(pb, dyn[0], other, fit_w, fit_mask)


def _held_pred(pb: _Problem, chosen: list[EffectFit], nominal: Prediction) -> Prediction:
    dyn = [e for c in chosen if c.candidate is None or not c.candidate.imu for e in c.effects()]
    imu = [c for c in chosen if c.candidate is not None and c.candidate.imu]
    pred = pb.run(dyn, pb.held) if dyn else nominal
    for c in imu:
        pred = _imu_transform(c.candidate, c.x, pred, pb.rec.t)
    return pred


def _where(pb: _Problem, pred: Prediction, mask: np.ndarray) -> dict[str, dict[str, float]]:
    cs, rec = pb.cs, pb.rec
    m = mask & pred.mask
    res = mt.normalised_residual(cs, mt.pred_matrix(pred), m)
    cg = mt.channel_gaps(res, cs.noise)
    jg = mt.joint_gaps(cg, cs)
    labels = mt.phase_labels(rec, pred.contact if rec.mount == "ground" else None)[m]
    full = np.zeros_like(cs.rec)
    full[m] = res
    dyn_ch = np.concatenate([cs.index("q"), cs.index("dq")])
    out = {
        "channels": {n: float(v) for n, v in zip(cs.names, cg, strict=True)},
        "joints": jg,
        "legs": mt.leg_gaps(jg),
        "sensors": {"encoders": mt.gap(res, cs.noise, dyn_ch),
                    "body_gyro": mt.gap(res, cs.noise, cs.index("gyro")),
                    "body_accel": mt.gap(res, cs.noise, cs.index("acc"))},
        "phases": mt.phase_gaps(res, cs.noise, labels),
        "bands": mt.band_gaps(full, m, 1.0 / rec.sample_period, dyn_ch),
    }
    return out


def _fmt_params(f: EffectFit) -> str:
    return " ".join(f"{k}={v:.4g}" for k, v in f.parameters.items())


def print_progress(msg: str) -> None:
    """Progress printer for the command line (stderr)."""
    print(msg, file=sys.stderr, flush=True)

