"""Correlation solver: foot-IMU time offset and rotation from two angular-velocity streams.

Method (A2I-Calib, section II-B, after Qiu et al. 2021), with the numerics made exact:

1. The IMU samples of a fixed window are compared with the encoder-side (forward-kinematics)
   foot angular velocity interpolated at ``t_imu - t_d`` by a cubic smoothing spline (bandwidth
   about one encoder period, robust to stamp jitter) built on the true encoder stamps, segment
   by segment (no interpolation across gaps). The window keeps the IMU
   samples whose shifted time stays inside the encoder record for every candidate offset, so
   the statistic is comparable across offsets. The IMU is never interpolated: its samples are
   the noisy ones, each used once at its own stamp.
2. Coarse scan of the trace correlation
   ``r = sqrt(tr(S_II^-1 S_IF S_FF^-1 S_FI) / 3)`` over +-``max_offset`` on a ``coarse_step``
   grid, all offsets at once: the sums behind every covariance are cross-correlations of
   binned IMU moments with gridded encoder moments, computed by FFT.
3. Continuous maximisation of the exact ``r`` (bounded Brent) around the coarse peak.
4. Rotation from the covariances at the optimum, projected on SO(3) by SVD with the determinant
   fix. ``rotation_method="procrustes"`` (default) decomposes ``S_FI`` (the maximum-likelihood
   rotation for isotropic gyro noise); ``"paper"`` decomposes ``S_FF^-1 S_FI`` as in the paper.
   Note: with ``omega_F = R_I^F omega_I`` and ``S_FI = E[F I^T]``, ``S_FF^-1 S_FI = R_I^F``
   directly; the paper's extra inverse belongs to its opposite convention.
5. Observability gates; a refusal raises :class:`CalibrationRefused` carrying the diagnostics.
6. Uncertainty from the Fisher information of the residual ``omega_F(t - t_d) - R omega_I - c``
   (parameters: rotation, offset, constant), with the residual covariance, inflated by the
   residual's integrated autocorrelation (coloured noise carries less information).

Conventions: ``omega_F = R_I^F @ omega_I``; ``t_d = t_I - t_E``, so an IMU sample stamped ``s``
describes the motion the encoders stamped ``s - t_d``: ``omega_F(s - t_d) = R_I^F omega_I(s)``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sfft
from scipy.interpolate import CubicSpline, PPoly
from scipy.linalg import solveh_banded
from scipy.optimize import minimize_scalar

from calib.metrics import covariance_condition

_PAIRS6 = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


class CalibrationRefused(Exception):
    """The data do not support a trustworthy calibration.

    ``reasons``: one-line human reasons; ``diagnostics``: the :class:`SolverResult` computed so
    far (CN, CC, curve, ...), for reporting a refused run. Its rotation must not be used.
    """

    def __init__(self, reasons: list[str], diagnostics: SolverResult):
        super().__init__("calibration refused: " + "; ".join(reasons))
        self.reasons = list(reasons)
        self.diagnostics = diagnostics


@dataclass(frozen=True)
class SolverConfig:
    """Solver settings. Times in s, eigenvalues in (rad/s)^2.

    max_offset: search range of ``t_d`` is [-max_offset, +max_offset].

    Gates: a refusal must mean "this result could be wrong", not "this motion is worse than
    A2I's", because ``a2i-calib solve`` takes other people's logs. So the defaults refuse rank
    deficiency (kappa, smallest eigenvalue) and what the data cannot pin down (the estimated
    1-sigma uncertainties), while an ordinary ill-conditioned but well-measured motion
    (kappa ~ 20-200, seen in random multi-joint motions) is accepted with its uncertainty.
    The authors' own gates (kappa < 20, lambda_min > 0.015, r > 0.9) are
    :meth:`paper_gates`, for the robot's own calibration motion (kappa ~ 1 by design).
    min_eigenvalue: gate on the smallest eigenvalue of S_FF, (rad/s)^2.
    max_condition_number: gate on kappa(S_FF).
    min_correlation: gate on r at the optimum.
    max_rotation_std_deg: gate on the rotation's 1-sigma uncertainty (expected geodesic error).
    max_time_offset_std_s: gate on the offset's 1-sigma uncertainty.
    coarse_step: grid of the coarse scan; must be well below 1/(4 f_max) of the motion.
    refine_tol: absolute tolerance of the continuous maximisation.
    gap_factor: an encoder interval longer than gap_factor x the median period is a gap; the
        spline is cut there and IMU samples whose shifted time falls in it are not used.
    enc_smoothing: bandwidth of the encoder-side smoothing spline in median encoder periods
        (0 = interpolating spline). Guards against timestamp jitter; response
        1 / (1 + (2 pi f h)^4), zero-phase: at 100 Hz encoders and 5 Hz motion, 1 %.
    edge_margin: a peak within this many coarse steps of +-max_offset is refused.
    ambiguity_ratio: refuse when another, separate local maximum of r has
        ``1 - r_side < ambiguity_ratio * (1 - r_best)`` (periodic motion: offset ambiguous).
    min_samples, min_overlap_s: least IMU samples / window duration to accept.
    rotation_method: "procrustes" (SVD of S_FI) or "paper" (SVD of S_FF^-1 S_FI).
    """

    max_offset: float = 0.5
    min_eigenvalue: float = 1e-3
    max_condition_number: float = 1000.0
    min_correlation: float = 0.8
    max_rotation_std_deg: float = 1.0
    max_time_offset_std_s: float = 0.005
    coarse_step: float = 0.002
    refine_tol: float = 1e-7
    gap_factor: float = 4.0
    enc_smoothing: float = 1.0
    edge_margin: int = 2
    ambiguity_ratio: float = 2.0
    min_samples: int = 200
    min_overlap_s: float = 2.0
    rotation_method: str = "procrustes"

    @classmethod
    def paper_gates(cls, **overrides) -> SolverConfig:
        """The authors' gates (kappa < 20, lambda_min > 0.015 (rad/s)^2, r > 0.9): for a motion
        designed to excite every axis, where anything worse means the execution went wrong."""
        base = {"min_eigenvalue": 0.015, "max_condition_number": 20.0, "min_correlation": 0.9}
        return cls(**{**base, **overrides})

    def __post_init__(self):
        if not self.max_offset > 0:
            raise ValueError(f"max_offset must be > 0 s, got {self.max_offset}")
        if not 0 < self.coarse_step <= self.max_offset / 4:
            raise ValueError(f"coarse_step must be in (0, max_offset/4], got {self.coarse_step}")
        if not self.refine_tol > 0:
            raise ValueError(f"refine_tol must be > 0, got {self.refine_tol}")
        if not self.gap_factor > 1:
            raise ValueError(f"gap_factor must be > 1, got {self.gap_factor}")
        if self.rotation_method not in ("procrustes", "paper"):
            raise ValueError(
                f"rotation_method must be 'procrustes' or 'paper', got {self.rotation_method!r}"
            )


@dataclass
class AlignedSignals:
    """Data to plot before/after alignment (the samples used at the optimum).

    t_imu: IMU stamps (s, IMU clock); t: the same instants on the encoder clock (t_imu - t_d);
    omega_foot: encoder-side foot angular velocity at t (rad/s, foot frame);
    omega_imu: raw gyro (rad/s, IMU frame); omega_imu_in_foot: R_I^F (omega_imu - gyro_bias).
    """

    t_imu: np.ndarray
    t: np.ndarray
    omega_foot: np.ndarray
    omega_imu: np.ndarray
    omega_imu_in_foot: np.ndarray


@dataclass
class SolverResult:
    """Outcome of :func:`solve` (also the diagnostics of a refusal).

    rotation: R_I^F (3, 3); time_offset: t_d = t_I - t_E (s); correlation: r at the optimum;
    condition_number, min_eigenvalue: of S_FF ((rad/s)^2) at the optimum;
    rotation_std_deg: sqrt(trace) of the rotation-error covariance (expected geodesic error
    magnitude, degrees); rotation_cov: that covariance (rad^2, foot frame, left perturbation
    R_true = exp([d]x) R); time_offset_std_s (s); samples: IMU samples used; offsets (s) and
    correlation_curve: the coarse scan of r; gyro_bias: constant gyro offset (rad/s, IMU frame);
    residual_rms: rms of omega_F - R (omega_I - bias) per axis (rad/s); reasons: refusal reasons
    (empty when accepted).
    """

    rotation: np.ndarray
    time_offset: float
    correlation: float
    condition_number: float
    min_eigenvalue: float
    rotation_std_deg: float
    time_offset_std_s: float
    samples: int
    offsets: np.ndarray
    correlation_curve: np.ndarray
    aligned: AlignedSignals | None
    gyro_bias: np.ndarray
    rotation_cov: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    residual_rms: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    reasons: list[str] = field(default_factory=list)

    @property
    def accepted(self) -> bool:
        return not self.reasons


# ----------------------------------------------------------------------------- input handling


def _clean_stream(t, w, name: str) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t, dtype=float)
    w = np.asarray(w, dtype=float)
    if t.ndim != 1:
        raise ValueError(f"{name}: stamps must be 1-D, got shape {t.shape}")
    if w.shape != (t.size, 3):
        raise ValueError(f"{name}: angular velocity must be ({t.size}, 3), got {w.shape}")
    ok = np.isfinite(t) & np.all(np.isfinite(w), axis=1)
    t, w = t[ok], w[ok]
    if t.size and np.any(np.diff(t) < 0):
        order = np.argsort(t, kind="stable")
        t, w = t[order], w[order]
    return t, w


def _smooth_values(t: np.ndarray, w: np.ndarray, lam: float) -> np.ndarray:
    """Fitted values of the cubic smoothing spline (Reinsch): minimises
    sum |w_i - g(t_i)|^2 + lam * int |g''|^2; the natural cubic spline through them is g."""
    if lam <= 0 or t.size < 4:
        return w
    h = np.diff(t)
    a = 1.0 / h
    n2 = t.size - 2
    ab = np.zeros((3, n2))  # upper banded form of R + lam Q^T Q
    ab[2] = (h[:-1] + h[1:]) / 3.0 + lam * (a[:-1] ** 2 + (a[:-1] + a[1:]) ** 2 + a[1:] ** 2)
    ab[1, 1:] = h[1:-1] / 6.0 - lam * a[1:-1] * (a[:-2] + 2.0 * a[1:-1] + a[2:])
    ab[0, 2:] = lam * a[1:-2] * a[2:-1]
    slopes = np.diff(w, axis=0) * a[:, None]
    gamma = solveh_banded(ab, slopes[1:] - slopes[:-1], check_finite=False)
    q_gamma = np.zeros_like(w)
    q_gamma[:-2] += a[:-1, None] * gamma
    q_gamma[1:-1] -= (a[:-1] + a[1:])[:, None] * gamma
    q_gamma[2:] += a[1:, None] * gamma
    return w - lam * q_gamma


class _Encoder:
    """Cubic (smoothing) spline of the encoder-side angular velocity, cut at gaps (PPoly pieces
    of zeros bridge the gaps and are flagged invalid).

    The smoothing bandwidth is ``smoothing`` x the median period: jittered stamps make an
    interpolating spline ring (two close stamps, different values); a smoothing spline averages
    them. Its response 1 / (1 + (2 pi f h)^4) is zero-phase and the same on every axis, so it
    shifts neither the offset nor the (Procrustes) rotation.
    """

    def __init__(self, t: np.ndarray, w: np.ndarray, gap_factor: float, smoothing: float):
        if t.size < 4:
            raise ValueError("encoder stream: fewer than 4 samples")
        period = float(np.median(np.diff(t)))
        if not period > 0:
            raise ValueError("encoder stream: stamps do not advance")
        # merge (average) samples whose stamps nearly coincide: the spline needs distinct x
        grp = np.concatenate([[0], np.cumsum(np.diff(t) > 1e-3 * period)])
        if grp[-1] + 1 < t.size:
            cnt = np.bincount(grp)
            t = np.bincount(grp, weights=t) / cnt
            w = np.stack([np.bincount(grp, weights=w[:, k]) / cnt for k in range(3)], axis=1)
        if t.size < 4:
            raise ValueError("encoder stream: fewer than 4 distinct samples")
        dt = np.diff(t)
        self.period = period
        lam = (smoothing * period) ** 4 / period
        cut = np.flatnonzero(dt > gap_factor * period)
        bounds = np.concatenate([[0], cut + 1, [t.size]])
        xs, cs, gap = [], [], []
        for a, b in itertools.pairwise(bounds):
            if b - a < 4:  # too short for a cubic: counts as part of the gap
                continue
            ta = t[a:b]
            sp = CubicSpline(ta, _smooth_values(ta, w[a:b], lam), axis=0, bc_type="natural")
            if xs:  # bridge piece from the previous segment's end to this start
                cs.append(np.zeros((4, 1, 3)))
                gap.append(True)
            xs.append(ta)
            cs.append(sp.c)
            gap.extend([False] * (b - a - 1))
        if not xs:
            raise ValueError("encoder stream: no run of 4 samples without a gap")
        self.x = np.concatenate(xs)
        self.pp = PPoly(np.concatenate(cs, axis=1), self.x, extrapolate=False)
        self.dpp = self.pp.derivative()
        self.gap = np.asarray(gap, dtype=bool)
        self.gap_cum = np.concatenate([[0], np.cumsum(self.gap)])
        self.t0, self.t1 = float(self.x[0]), float(self.x[-1])

    def _piece(self, tq: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.x, tq, side="right") - 1, 0, self.gap.size - 1)

    def valid(self, tq: np.ndarray) -> np.ndarray:
        inside = (tq >= self.t0) & (tq <= self.t1)
        return inside & ~self.gap[self._piece(tq)]

    def valid_span(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """True where the whole interval [lo, hi] lies in data (no gap piece touched)."""
        inside = (lo >= self.t0) & (hi <= self.t1)
        a, b = self._piece(lo), self._piece(hi)
        return inside & (self.gap_cum[b + 1] - self.gap_cum[a] == 0)


# ----------------------------------------------------------------------------- statistics


def _sym(v6: np.ndarray) -> np.ndarray:
    """(..., 6) upper-triangle moments -> (..., 3, 3) symmetric."""
    out = np.empty(v6.shape[:-1] + (3, 3))
    for p, (a, b) in enumerate(_PAIRS6):
        out[..., a, b] = v6[..., p]
        out[..., b, a] = v6[..., p]
    return out


def _trace_corr2(s_ii, s_if, s_ff) -> np.ndarray:
    """r^2 = tr(S_II^-1 S_IF S_FF^-1 S_FI) / 3 for batched (..., 3, 3) covariances."""
    a = np.linalg.pinv(s_ii, rcond=1e-12, hermitian=True) @ s_if
    b = np.linalg.pinv(s_ff, rcond=1e-12, hermitian=True) @ np.swapaxes(s_if, -1, -2)
    return np.trace(a @ b, axis1=-2, axis2=-1) / 3.0


def _coarse_scan(enc: _Encoder, s: np.ndarray, w_i: np.ndarray, f_mean: np.ndarray,
                 h: float, k_max: int) -> tuple[np.ndarray, np.ndarray]:
    """r at offsets k*h, k = -k_max..k_max (ascending), via FFT cross-correlation of binned
    IMU moments with gridded encoder moments (per-offset gap masks included)."""
    s0 = s[0]
    j = np.rint((s - s0) / h).astype(np.int64)
    n_bins = int(j[-1]) + 1
    i_c = w_i - w_i.mean(axis=0)
    imu_side = np.empty((10, n_bins))
    imu_side[0] = np.bincount(j, minlength=n_bins)
    for a in range(3):
        imu_side[1 + a] = np.bincount(j, weights=i_c[:, a], minlength=n_bins)
    for p, (a, b) in enumerate(_PAIRS6):
        imu_side[4 + p] = np.bincount(j, weights=i_c[:, a] * i_c[:, b], minlength=n_bins)

    n_grid = n_bins + 2 * k_max
    tg = s0 + (np.arange(n_grid) - k_max) * h
    v = enc.valid(tg)
    g = np.where(v[:, None], np.nan_to_num(enc.pp(tg)) - f_mean, 0.0)
    enc_side = np.empty((10, n_grid))
    enc_side[0] = v
    enc_side[1:4] = g.T
    for p, (a, b) in enumerate(_PAIRS6):
        enc_side[4 + p] = g[:, a] * g[:, b]

    nfft = sfft.next_fast_len(n_grid, real=True)
    fa = np.conj(sfft.rfft(imu_side, nfft, axis=1))
    fb = sfft.rfft(enc_side, nfft, axis=1)
    ia = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 0, 0, 0, 0, 0, 0, 0, 0, 0]
    ib = [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9]
    for a in range(3):
        for b in range(3):
            ia.append(1 + a)
            ib.append(1 + b)
    sums = sfft.irfft(fa[ia] * fb[ib], nfft, axis=1)[:, : 2 * k_max + 1]
    # lag index q <-> offset (k_max - q) * h; reverse to ascending offsets
    sums = sums[:, ::-1].T  # (n_offsets, 28)
    n = np.maximum(np.rint(sums[:, 0]), 1.0)[:, None]
    m_i, m_f = sums[:, 1:4] / n, sums[:, 10:13] / n
    s_ii = _sym(sums[:, 4:10] / n) - m_i[:, :, None] * m_i[:, None, :]
    s_ff = _sym(sums[:, 13:19] / n) - m_f[:, :, None] * m_f[:, None, :]
    s_if = sums[:, 19:28].reshape(-1, 3, 3) / n[:, :, None] - m_i[:, :, None] * m_f[:, None, :]
    r2 = _trace_corr2(s_ii, s_if, s_ff)
    r = np.sqrt(np.clip(r2, 0.0, None))
    r[sums[:, 0] < 10] = np.nan
    offsets = np.arange(-k_max, k_max + 1) * h
    return offsets, r


def _covariances(f: np.ndarray, w_i: np.ndarray):
    fc = f - f.mean(axis=0)
    ic = w_i - w_i.mean(axis=0)
    n1 = max(f.shape[0] - 1, 1)
    return ic.T @ ic / n1, ic.T @ fc / n1, fc.T @ fc / n1


def _project_so3(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    return u @ d @ vt


def _skew(v: np.ndarray) -> np.ndarray:
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _autocorr_factor(e: np.ndarray, max_lag: int = 50) -> float:
    """1 + 2 sum of the residual autocorrelation (summed over axes) up to its first
    non-positive lag: the variance inflation of a mean of correlated samples."""
    e = e - e.mean(axis=0)
    den = float(np.sum(e * e))
    if den <= 0:
        return 1.0
    tot = 0.0
    for k in range(1, min(max_lag, e.shape[0] // 4) + 1):
        rho = float(np.sum(e[k:] * e[:-k])) / den
        if rho <= 0:
            break
        tot += rho
    return 1.0 + 2.0 * tot


def _uncertainty(f, df, resid) -> tuple[np.ndarray, float]:
    """Fisher covariance of (rotation (3), offset) with the constant marginalised."""
    n = f.shape[0]
    jac = np.empty((n, 3, 4))
    jac[:, :, :3] = _skew(f)  # d residual / d rotation (left perturbation), R omega_I ~ omega_F
    jac[:, :, 3] = -df  # d residual / d t_d
    jac -= jac.mean(axis=0)  # marginalises the free constant (bias, means)
    s_e = resid.T @ resid / max(n - 3, 1)
    s_e += np.eye(3) * (1e-12 * np.trace(s_e) / 3 + 1e-300)
    # whiten with S_e^-1 = L^-T L^-1: info = sum_s J_s^T S_e^-1 J_s = (L^-1 J)^T (L^-1 J)
    jw = np.linalg.solve(np.linalg.cholesky(s_e), jac.transpose(1, 0, 2).reshape(3, -1))
    jw = jw.reshape(3, n, 4).transpose(1, 0, 2).reshape(-1, 4)
    info = jw.T @ jw
    try:
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return np.full((3, 3), np.inf), float("inf")
    cov *= _autocorr_factor(resid)
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0):
        return np.full((3, 3), np.inf), float("inf")
    return cov[:3, :3], float(np.sqrt(cov[3, 3]))


def _empty_result(offsets=None, curve=None, samples=0, reasons=None) -> SolverResult:
    return SolverResult(
        rotation=np.full((3, 3), np.nan), time_offset=float("nan"), correlation=float("nan"),
        condition_number=float("nan"), min_eigenvalue=float("nan"),
        rotation_std_deg=float("nan"), time_offset_std_s=float("nan"), samples=samples,
        offsets=np.zeros(0) if offsets is None else offsets,
        correlation_curve=np.zeros(0) if curve is None else curve, aligned=None,
        gyro_bias=np.full(3, np.nan), reasons=list(reasons or []),
    )


def _side_peak(offsets: np.ndarray, r: np.ndarray, k: int) -> tuple[float, float]:
    """Highest interior local maximum of r outside the lobe of the main peak at index k."""
    rr = np.where(np.isfinite(r), r, -np.inf)
    lo = k
    while lo > 0 and rr[lo - 1] <= rr[lo]:
        lo -= 1
    hi = k
    while hi < rr.size - 1 and rr[hi + 1] <= rr[hi]:
        hi += 1
    idx = np.arange(1, rr.size - 1)
    peaks = idx[(rr[idx] > rr[idx - 1]) & (rr[idx] >= rr[idx + 1])]
    peaks = peaks[(peaks < lo) | (peaks > hi)]
    if peaks.size == 0:
        return float("nan"), float("nan")
    best = peaks[np.argmax(rr[peaks])]
    return float(offsets[best]), float(rr[best])


# ----------------------------------------------------------------------------- solver


def solve(t_enc, omega_foot, t_imu, omega_imu, config: SolverConfig | None = None) -> SolverResult:
    """Time offset t_d (s) and rotation R_I^F from encoder-side and gyro angular velocities.

    t_enc (N,) s, omega_foot (N, 3) rad/s in the foot frame (forward kinematics);
    t_imu (M,) s, omega_imu (M, 3) rad/s in the IMU frame. Rates, jitter, drops and a constant
    gyro bias are allowed; non-finite rows are dropped. Raises ValueError on malformed input and
    :class:`CalibrationRefused` when a gate fails.
    """
    cfg = SolverConfig() if config is None else config
    t_e, w_e = _clean_stream(t_enc, omega_foot, "encoder stream")
    t_i, w_i = _clean_stream(t_imu, omega_imu, "IMU stream")
    if t_i.size < 4 or t_e.size < 4:
        raise ValueError(
            f"need at least 4 finite samples per stream, got {t_e.size} encoder, {t_i.size} IMU"
        )
    t_ref = min(t_e[0], t_i[0])  # float precision with epoch stamps
    enc = _Encoder(t_e - t_ref, w_e, cfg.gap_factor, cfg.enc_smoothing)
    s_all = t_i - t_ref

    h, tau_max = cfg.coarse_step, cfg.max_offset
    k_max = int(np.floor(tau_max / h + 1e-9))
    in_win = (s_all >= enc.t0 + tau_max) & (s_all <= enc.t1 - tau_max)
    s, wi = s_all[in_win], w_i[in_win]
    span = float(s[-1] - s[0]) if s.size else 0.0
    overlap_reason = (
        f"too little overlap: {s.size} IMU samples over {span:.2f} s where the encoder record "
        f"covers every offset within +-{tau_max * 1e3:.0f} ms "
        f"(need {cfg.min_samples} samples and {cfg.min_overlap_s:.1f} s)"
    )
    if s.size < 10 or span < 4 * h:
        raise CalibrationRefused([overlap_reason], _empty_result(samples=int(s.size)))
    too_little = s.size < cfg.min_samples or span < cfg.min_overlap_s

    f_mean = np.nanmean(enc.pp(np.clip(s, enc.t0, enc.t1)), axis=0)
    f_mean = np.nan_to_num(f_mean)
    offsets, curve = _coarse_scan(enc, s, wi, f_mean, h, k_max)
    if not np.any(np.isfinite(curve)):
        reasons = ["correlation undefined at every offset (no usable samples)"]
        if too_little:
            reasons.insert(0, overlap_reason)
        raise CalibrationRefused(reasons, _empty_result(offsets, curve, int(s.size)))
    k_best = int(np.nanargmax(curve))

    # Continuous maximisation of the exact r on a fixed sample set within a bracket.
    def neg_r2(tau, ss, ii, s_ii_inv):
        f = enc.pp(ss - tau)
        fc = f - f.mean(axis=0)
        s_if = ii.T @ fc
        s_ff = fc.T @ fc
        return -np.trace(s_ii_inv @ s_if @ np.linalg.solve(s_ff, s_if.T)) / 3.0

    lo, hi = offsets[k_best] - 2 * h, offsets[k_best] + 2 * h
    tau = offsets[k_best]
    for _ in range(6):
        lo, hi = max(lo, -tau_max), min(hi, tau_max)
        m = enc.valid_span(s - hi, s - lo)
        if m.sum() < 10:
            break
        ss, ii = s[m], wi[m] - wi[m].mean(axis=0)
        try:
            s_ii_inv = np.linalg.inv(ii.T @ ii)
            res = minimize_scalar(neg_r2, bounds=(lo, hi), args=(ss, ii, s_ii_inv),
                                  method="bounded", options={"xatol": cfg.refine_tol})
        except np.linalg.LinAlgError:
            break
        tau = float(res.x)
        near = 4 * cfg.refine_tol
        if tau - lo < near and lo > -tau_max:
            lo, hi = lo - 3 * h, lo + h
        elif hi - tau < near and hi < tau_max:
            lo, hi = hi - h, hi + 3 * h
        else:
            break

    # Everything at the optimum, on the samples valid there.
    m = enc.valid(s - tau)
    if m.sum() < 10:
        raise CalibrationRefused([overlap_reason], _empty_result(offsets, curve, int(m.sum())))
    ss, ii_raw = s[m], wi[m]
    f = enc.pp(ss - tau)
    s_ii, s_if, s_ff = _covariances(f, ii_raw)
    r = float(np.sqrt(max(_trace_corr2(s_ii, s_if, s_ff), 0.0)))
    lam_min = float(np.linalg.eigvalsh(s_ff)[0])
    kappa = covariance_condition(s_ff)
    s_fi = s_if.T
    if cfg.rotation_method == "paper":
        rot = _project_so3(np.linalg.pinv(s_ff, rcond=1e-12, hermitian=True) @ s_fi)
    else:
        rot = _project_so3(s_fi)
    bias = ii_raw.mean(axis=0) - rot.T @ f.mean(axis=0)
    w_in_foot = (ii_raw - bias) @ rot.T
    resid = f - w_in_foot
    rot_cov, tau_std = _uncertainty(f, enc.dpp(ss - tau), resid)

    reasons = []
    if too_little:
        reasons.append(overlap_reason)
    if not lam_min >= cfg.min_eigenvalue:
        reasons.append(
            f"smallest eigenvalue of Sigma_FF {lam_min:.3g} (rad/s)^2 < {cfg.min_eigenvalue:g}: "
            "the motion does not excite all three rotation axes"
        )
    if not kappa <= cfg.max_condition_number:
        reasons.append(
            f"condition number of Sigma_FF {kappa:.3g} > {cfg.max_condition_number:g}: "
            "ill-conditioned motion, the rotation would be noise-sensitive"
        )
    if not r >= cfg.min_correlation:
        reasons.append(
            f"correlation {r:.3f} < {cfg.min_correlation:g}: IMU and encoder angular velocities "
            "do not match well (noise, wrong leg/stream, or a clock problem)"
        )
    rot_std_deg = float(np.degrees(np.sqrt(np.trace(rot_cov))))
    if not rot_std_deg <= cfg.max_rotation_std_deg:
        reasons.append(
            f"rotation uncertainty {rot_std_deg:.3g} deg > {cfg.max_rotation_std_deg:g} deg: the "
            "motion does not pin the rotation down against this noise"
        )
    if not tau_std <= cfg.max_time_offset_std_s:
        reasons.append(
            f"time offset uncertainty {tau_std * 1e3:.3g} ms > "
            f"{cfg.max_time_offset_std_s * 1e3:g} ms: the motion is too slow or too noisy"
        )
    edge = cfg.edge_margin
    if k_best < edge or k_best > curve.size - 1 - edge or abs(tau) > tau_max - edge * h:
        reasons.append(
            f"time offset peak at {tau * 1e3:+.1f} ms is at the edge of the "
            f"+-{tau_max * 1e3:.0f} ms search range (not a peak: widen max_offset or check clocks)"
        )
    side_tau, side_r = _side_peak(offsets, curve, k_best)
    if np.isfinite(side_r) and (1.0 - side_r) < cfg.ambiguity_ratio * (1.0 - curve[k_best]):
        reasons.append(
            f"ambiguous time offset: a second peak of r at {side_tau * 1e3:+.1f} ms reaches "
            f"{side_r:.4f} against {curve[k_best]:.4f} (periodic motion?)"
        )

    result = SolverResult(
        rotation=rot, time_offset=tau, correlation=r, condition_number=kappa,
        min_eigenvalue=lam_min,
        rotation_std_deg=rot_std_deg,
        time_offset_std_s=tau_std, samples=int(m.sum()), offsets=offsets,
        correlation_curve=curve,
        aligned=AlignedSignals(ss + t_ref, ss - tau + t_ref, f, ii_raw, w_in_foot),
        gyro_bias=bias, rotation_cov=rot_cov,
        residual_rms=np.sqrt(np.mean(resid**2, axis=0)), reasons=reasons,
    )
    if reasons:
        raise CalibrationRefused(reasons, result)
    return result
