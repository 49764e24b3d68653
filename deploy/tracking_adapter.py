"""The lifted leg's unmodelled joint torque, identified while it plays the excitation.

The lifted leg follows its plan under a soft PD law plus the planned motion's inverse-dynamics
torque (:mod:`deploy.leg_dynamics`). What that model leaves out, the PD law supplies from a
tracking error: ``kp e + kd de`` with ``e = q_des - q``. On a joint with viscous damping ``b``
the error is ``b dq / kp``, a lag in phase with the velocity: MuJoCo Menagerie's Go2 has
b = 2 N m s/rad, which at kp 80 leaves the lifted leg 0.023 rad RMS off its plan and raises the
executed excitation's condition number from ~1.07 to ~1.13. A real motor adds dry friction, a
torque constant off its nominal one, rotor inertia and a command latency, none of which is
known before the leg moves.

Per joint, the torque the PD law had to supply beyond the feed-forward it was given,
``u = kp (q_des - q) + kd (dq_des - dq) + c_applied``, is regressed on four features of the
plan, by ridge least squares over the excitation so far, older samples fading (they were taken
while the leg lagged more, further from the plan whose features they are regressed on)::

    u ~ b dq_des  +  f tanh(dq_des / V_SIGN)  +  i ddq_des  +  a tau_model

b: viscous damping; f: dry friction, smoothed; i: inertia the model lacks; a: a torque constant
off by ``1 / (1 + a)``. From ``start_s`` into the excitation on, the fitted torque of the plan is
added to the feed-forward, faded in over ``fade_s`` and refitted every ``refit_s``. It is a
feed-forward of the plan, not a feedback: the loop's stability stays the PD law's whatever the
fit says, and each coefficient is clipped to a physically plausible bound. The calibration does
not depend on it (the solver reads the executed motion), but the executed motion comes closer to
the plan, whose condition number is 1.

**Latency.** A command that reaches the motors ``d`` s late makes the leg play the plan ``d``
late: measured against the plan of the same instant, that lag reads as ``kp d`` of damping
(plus a second-order term as inertia). Fed forward, such a "damping" drives the leg ahead of
the late plan by a velocity lead, which is exact for a sine of one frequency only: it raises
the plan's higher harmonics by ``sqrt(1 + (w d)^2)``, unevenly between the joints, and under
20-40 ms it took the executed excitation's condition number from 1.03 to 1.19-1.22 where the
adapter off leaves it at 1.03. A pure delay needs no torque: the leg then plays the plan
exactly, late, and a late excitation is as well conditioned (the calibration solves the time
offset between the foot IMU and the encoders, not the command's). The delay is identified from
the torque the motors report with each measurement (LowState's ``tau_est``): for each candidate
delay ``d_k`` of ``0..max_delay_s``, the commands of ``t - d_k`` (interpolated between the
ticks' samples) under the PD law with the joints as measured give a torque; the candidate that
matches the reported one best (up to a scale, the motors' strength) is the delay, whatever the
leg's dynamics, and the regression above is then read at that delay: the joints at ``t``
against the commands of ``t - d``. The delay is the one found by the first fit (``start_s``
in) and kept for the rest of the excitation: a command path's latency does not change within
one, and a fitted row then costs one delay's interpolation a tick instead of every
candidate's. Without a reported torque the delay stays 0, as before.
Once the delay is known, the plan is commanded that far ahead (:meth:`lead`), so that the leg
plays it on time as well as undistorted: the plan is known in advance, and a time shift bends
nothing.

Batched: row ``r`` is one lifted leg (an environment of the training's vectorised simulator;
deploy and the free-base runs use one row). Pure numpy. Units: rad, rad/s, rad/s^2, N m, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FEATURES", "AdapterConfig", "TrackingAdapter", "features"]

FEATURES = ("damping", "friction", "inertia", "scale")
"""The fitted coefficients per joint: N m s/rad, N m, kg m^2, and a fraction of the model's
torque."""

V_SIGN = 0.1
"""rad/s over which the dry-friction feature turns from -1 to +1 (tanh)."""


@dataclass(frozen=True)
class AdapterConfig:
    """start_s: s into the excitation before the first fit (a period of the plan at t_r 0.5 s
    is 4 s; 2 s already span its velocities). refit_s: s between fits. fade_s: s over which
    the first fit's torque is faded in. memory_s: time constant, s, over which a sample's weight
    in the fit falls by e. ridge: regularisation, a fraction of each feature's sum
    of squares. bounds: the largest |coefficient| kept, per :data:`FEATURES` (a damping of
    5 N m s/rad is 2.5 times Menagerie's, a friction of 1.5 N m 7 times, an inertia of
    0.05 kg m^2 5 times the rotor's; a torque constant off by up to a half either way).
    max_delay_s, delay_step_s: the candidate delays, s, from 0 to ``max_delay_s`` in steps of
    ``delay_step_s`` (0-80 ms: the trained 0-20 ms of actuation latency, twice that, and the
    state's own way back). max_gap_s: a sample whose candidates fall in a gap between the
    kept samples longer than this (lost frames) is not used. history: samples kept for that
    interpolation; they must span ``max_delay_s`` at the caller's tick (8 at 50 Hz: 140 ms).
    min_explained: the share of the reported torque's sum of squares the delay's PD law must
    explain for the delay to be taken (0.996-0.9997 in the simulators); below it the report is
    not the PD law's torque (a firmware reporting something else, a broken sensor) and the
    delay stays 0."""

    start_s: float = 2.0
    refit_s: float = 1.0
    fade_s: float = 0.5
    memory_s: float = 4.0
    ridge: float = 1e-3
    bounds: tuple[float, float, float, float] = (5.0, 1.5, 0.05, 0.5)
    max_delay_s: float = 0.08
    delay_step_s: float = 0.005
    max_gap_s: float = 0.045
    history: int = 8
    min_explained: float = 0.8

    def __post_init__(self) -> None:
        for k in ("start_s", "refit_s", "fade_s", "memory_s", "ridge", "delay_step_s",
                  "max_gap_s"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{k} must be > 0, got {v}")
        if not (np.isfinite(self.min_explained) and 0 <= self.min_explained <= 1):
            raise ValueError(f"min_explained must be in [0, 1], got {self.min_explained}")
        if not (np.isfinite(self.max_delay_s) and self.max_delay_s >= 0):
            raise ValueError(f"max_delay_s must be >= 0, got {self.max_delay_s}")
        if isinstance(self.history, bool) or not isinstance(self.history, int) \
                or self.history < 2:
            raise ValueError(f"history must be an integer >= 2, got {self.history!r}")
        if len(self.bounds) != len(FEATURES) or not all(
                np.isfinite(b) and b >= 0 for b in self.bounds):
            raise ValueError(f"bounds must be {len(FEATURES)} values >= 0, got {self.bounds}")

    @property
    def delays(self) -> np.ndarray:
        """The candidate delays, s (0 first)."""
        n = int(np.floor(self.max_delay_s / self.delay_step_s + 1e-9))
        return self.delay_step_s * np.arange(n + 1)


def features(dq_des, ddq_des, tau_model) -> np.ndarray:
    """(..., 3 joints, 4): dq_des, tanh(dq_des / V_SIGN), ddq_des, tau_model (the plan's
    velocity rad/s, acceleration rad/s^2 and model torque N m, (..., 3) each)."""
    dq_des, ddq_des, tau_model = np.broadcast_arrays(
        *(np.asarray(v, dtype=float) for v in (dq_des, ddq_des, tau_model)))
    return np.stack([dq_des, np.tanh(dq_des / V_SIGN), ddq_des, tau_model], axis=-1)


def _hermite(y0, y1, m0, m1, s, h):
    """Cubic Hermite between (y0, slope m0) and (y1, m1) at ``s`` in [0, 1] of a step ``h`` s
    long: the plan's position from its velocity (its velocity from its acceleration) is
    within 1e-4 of itself at 50 Hz on the excitation's harmonics, where a straight line is not."""
    s2, s3 = s * s, s * s * s
    return ((2 * s3 - 3 * s2 + 1) * y0 + (s3 - 2 * s2 + s) * h * m0
            + (-2 * s3 + 3 * s2) * y1 + (s3 - s2) * h * m1)


class TrackingAdapter:
    """Identify the lifted legs' unmodelled torque and their command delay from their tracking,
    and feed the torque forward.

    kp N m/rad, kd N m s/rad: the gains the lifted legs are commanded with (the schedule's).
    rows: how many lifted legs (batch rows). Each row starts empty; :meth:`reset` empties rows
    for a new excitation. :meth:`observe` once per control tick during the excitation (the
    measured joints against the plan at that instant, and the correction the motors were
    given); :meth:`torque` for each command frame; :meth:`lead`: how far ahead to command
    the plan. :attr:`delay`: each row's delay, s, found by its first fit; :attr:`delay_found`:
    whether that fit read it from the motors' reported torque (False: none reported, or no
    candidate explained it, and the delay is taken as 0).
    """

    _FIELDS = 5  # q_des, dq_des, ddq_des, tau_model, applied: what a sample keeps per joint

    def __init__(self, kp: float, kd: float, rows: int = 1,
                 config: AdapterConfig | None = None) -> None:
        if not (np.isfinite(kp) and kp > 0 and np.isfinite(kd) and kd >= 0):
            raise ValueError(f"kp must be > 0 and kd >= 0, got {kp}, {kd}")
        if isinstance(rows, bool) or not isinstance(rows, int) or rows < 1:
            raise ValueError(f"rows must be a positive integer, got {rows!r}")
        self.kp, self.kd = float(kp), float(kd)
        self.cfg = config or AdapterConfig()
        self._delays = self.cfg.delays
        nf, nd, h = len(FEATURES), len(self._delays), self.cfg.history
        # per row and joint: the fit's sums (x x^T, x u, x^2 for the ridge)
        self._xtx = np.zeros((rows, 3, nf, nf))
        self._xty = np.zeros((rows, 3, nf))
        self._sq = np.zeros((rows, 3, nf))
        # per row and candidate delay: the reported motor torque against the command's, summed
        # over the joints (sum tau_motor pd, pd^2, tau_motor^2)
        self._tp, self._pp, self._tt = (np.zeros((rows, nd)) for _ in range(3))
        self.coef = np.zeros((rows, 3, nf))
        self.delay = np.zeros(rows)  # s, each row's delay, found by its first fit
        self.delay_found = np.zeros(rows, dtype=bool)  # ... from the reported torque
        # the lead (:meth:`lead`) moves from _lead_from to the delay over fade_s from _lead_t
        self._lead_from = np.zeros(rows)
        self._lead_t = np.full(rows, np.nan)
        # the last ``history`` samples of each row, oldest first (time NaN: none yet)
        self._hist_t = np.full((rows, h), np.nan)
        self._hist = np.zeros((rows, h, self._FIELDS, 3))
        self._t_fit = np.full(rows, np.nan)  # s into the excitation of the first fit
        self._t_last = np.full(rows, -np.inf)
        self._t_sample = np.full(rows, np.nan)  # s into the excitation of the last sample used

    @property
    def fitted(self) -> np.ndarray:
        """(rows,) bool: rows with a fit (their torque is on)."""
        return np.isfinite(self._t_fit)

    def reset(self, rows=None) -> None:
        """Forget what ``rows`` (None: all) learnt: a new excitation starts there."""
        r = slice(None) if rows is None else rows
        for a in (self._xtx, self._xty, self._sq, self._tp, self._pp, self._tt,
                  self.coef, self.delay, self._hist, self._lead_from):
            a[r] = 0.0
        self.delay_found[r] = False
        self._lead_t[r] = np.nan
        self._hist_t[r] = np.nan
        self._t_fit[r] = np.nan
        self._t_last[r] = -np.inf
        self._t_sample[r] = np.nan

    def observe(self, t, q_des, dq_des, ddq_des, q, dq, tau_model, applied, rows=None,
                tau_motor=None) -> None:
        """One sample per row of ``rows`` (None: all), ``t`` s into its excitation ((n,) or a
        scalar): the plan's targets and model torque at that instant, the measured joints, and
        the adapter's correction the motors were given with them, (n, 3) each. tau_motor: the
        torque the motors report with the measurement (LowState's ``tau_est``), N m, (n, 3);
        what the delay is identified from (None, or a row not finite: the delay stays 0 s).
        A row with a non-finite value elsewhere skips this sample (a lost frame). A sample
        enters the fit once the row's samples reach back ``max_delay_s`` before it. Refits the
        rows that are due."""
        idx = np.arange(len(self.coef)) if rows is None else np.asarray(rows).reshape(-1)
        n = len(idx)
        t = np.broadcast_to(np.asarray(t, dtype=float), (n,))
        v = [np.asarray(a, dtype=float).reshape(n, 3)
             for a in (q_des, dq_des, ddq_des, q, dq, tau_model, applied)]
        ok = np.all([np.isfinite(a).all(axis=1) for a in v], axis=0) & np.isfinite(t)
        if not ok.any():
            return
        q_des, dq_des, ddq_des, q, dq, tau_model, applied = (a[ok] for a in v)
        idx, t = idx[ok], t[ok]
        tau_motor = np.full((n, 3), np.nan) if tau_motor is None else \
            np.asarray(tau_motor, dtype=float).reshape(n, 3)
        tau_motor = tau_motor[ok]
        # the commands of this instant join the row's history, the oldest leaves
        self._hist_t[idx, :-1] = self._hist_t[idx, 1:]
        self._hist[idx, :-1] = self._hist[idx, 1:]
        self._hist_t[idx, -1] = t
        self._hist[idx, -1] = np.stack([q_des, dq_des, ddq_des, tau_model, applied], axis=1)
        nd = len(self._delays)
        got = []
        # a row still finding its delay weighs every candidate; a fitted row keeps the delay of
        # its first fit (the command path's latency does not change within an excitation),
        # and costs one candidate's interpolation a tick instead of all of them
        searching = ~self.fitted[idx]
        for part in (np.flatnonzero(searching), np.flatnonzero(~searching)):
            if len(part) == 0:
                continue
            ip = idx[part]
            delays = np.broadcast_to(self._delays, (len(part), nd)) if searching[part[0]] \
                else self.delay[ip][:, None]
            c, use = self._commands_back(ip, t[part], delays)
            part, ip, c = part[use], ip[use], c[use]
            if len(part) == 0:
                continue
            tp = t[part]
            # older samples fade: they were taken further from the plan (before the fit closed
            # the lag, the measured motion was not the plan whose features they are regressed on)
            age = np.nan_to_num(tp - self._t_sample[ip], nan=0.0)
            keep = np.exp(-np.maximum(age, 0.0) / self.cfg.memory_s)
            choice = np.zeros(len(part), dtype=int)
            if searching[part[0]]:
                self._score(ip, keep, c, q[part], dq[part], tau_motor[part])
                choice = self._best(ip)[0]
            self._regress(ip, keep, c[np.arange(len(part)), choice], q[part], dq[part])
            self._t_sample[ip] = tp
            got.append(part)
        if not got:
            return
        part = np.concatenate(got)
        idx, t = idx[part], t[part]
        due = (t >= self.cfg.start_s) & (t - self._t_last[idx] >= self.cfg.refit_s)
        if due.any():
            self._fit(idx[due], t[due])

    def _score(self, idx, keep, c, q, dq, tau_motor) -> None:
        """Add a sample to the delay's sums of the rows ``idx``: which candidate's commands
        ``c`` (n, delays, fields, 3), under the PD law with the joints as measured, give the
        torque the motors report (up to a scale, the motors' strength). Whatever the leg's
        dynamics, only the true delay does. A row without a finite report adds nothing."""
        qd, dqd, tau, app = c[:, :, 0], c[:, :, 1], c[:, :, 3], c[:, :, 4]
        # (n, delays, 3) N m: the whole command's torque, as the motors would play it
        pd = self.kp * (qd - q[:, None]) + self.kd * (dqd - dq[:, None]) + tau + app
        m = np.isfinite(tau_motor).all(axis=1)
        tm = np.where(m[:, None], tau_motor, 0.0)
        k = keep[:, None]
        self._tp[idx] = k * self._tp[idx] + np.einsum("nj,ndj->nd", tm, pd)
        self._pp[idx] = k * self._pp[idx] + np.where(m[:, None], (pd**2).sum(-1), 0.0)
        self._tt[idx] = k * self._tt[idx] + (tm**2).sum(-1)[:, None]

    def _regress(self, idx, keep, c, q, dq) -> None:
        """Add a sample to the regression's sums of the rows ``idx``: the commands ``c`` (n,
        fields, 3) that reached the motors when the joints were ``q``, ``dq`` (n, 3)."""
        qd, dqd, ddqd, tau, app = (c[:, f] for f in range(self._FIELDS))
        u = self.kp * (qd - q) + self.kd * (dqd - dq) + app
        x = features(dqd, ddqd, tau)  # (n, 3, nf)
        k = keep[:, None, None]
        self._xtx[idx] = k[..., None] * self._xtx[idx] + x[..., :, None] * x[..., None, :]
        self._xty[idx] = k * self._xty[idx] + x * u[..., None]
        self._sq[idx] = k * self._sq[idx] + x**2

    def _commands_back(self, idx: np.ndarray, t: np.ndarray, delays: np.ndarray):
        """The commands of rows ``idx`` at ``t - d`` for each of their ``delays`` d (n, k),
        interpolated between their kept samples: (n, k, fields, 3), and (n,) bool: the
        rows whose kept samples span every one without a gap over ``max_gap_s``."""
        ht, hv = self._hist_t[idx], self._hist[idx]  # (n, h), (n, h, fields, 3)
        tau = t[:, None] - delays  # (n, k)
        # the kept sample at or before each instant, and the one after it
        # (the empty slots, NaN, are the oldest and compare False)
        j = ht.shape[1] - 1 - np.sum(ht[:, None, :] > tau[..., None] + 1e-9, axis=2)
        j0 = np.clip(j, 0, ht.shape[1] - 2)
        rows = np.arange(len(idx))[:, None]
        t0, t1 = ht[rows, j0], ht[rows, j0 + 1]
        span = t1 - t0
        with np.errstate(invalid="ignore"):
            ok = (t0 <= tau + 1e-9) & (span <= self.cfg.max_gap_s)  # False where NaN
        now = delays == 0
        ok |= now & np.isfinite(ht[:, -1])[:, None]  # no delay: the sample itself
        use = ok.all(axis=1)
        h = np.where(ok & (span > 0), span, 1.0)
        s = np.clip((tau - t0) / h, 0.0, 1.0)[..., None]  # (n, nd, 1)
        a, b = hv[rows, j0], hv[rows, j0 + 1]  # (n, nd, fields, 3)
        out = s[..., None] * b + (1.0 - s[..., None]) * a  # straight lines: ddq, tau, applied
        out[:, :, 0] = _hermite(a[:, :, 0], b[:, :, 0], a[:, :, 1], b[:, :, 1], s, h[..., None])
        out[:, :, 1] = _hermite(a[:, :, 1], b[:, :, 1], a[:, :, 2], b[:, :, 2], s, h[..., None])
        out[now] = np.broadcast_to(hv[:, None, -1], out.shape)[now]  # no delay: exact
        return out, use

    def _best(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n,) the index of the candidate delay that explains the torque reported so far by
        the rows ``idx``, and (n,) whether it does: 0 and False for a row with none reported,
        or whose report the best candidate does not explain (``min_explained``)."""
        pp, tt = self._pp[idx], self._tt[idx]
        rss = tt - np.where(pp > 0, self._tp[idx] ** 2 / np.maximum(pp, 1e-12), 0.0)
        best = np.argmin(rss, axis=1)
        explained = 1.0 - rss[np.arange(len(idx)), best] / np.maximum(tt[:, 0], 1e-12)
        found = (pp[:, 0] > 0) & (tt[:, 0] > 0) & (explained >= self.cfg.min_explained)
        return np.where(found, best, 0), found

    def _fit(self, idx: np.ndarray, t: np.ndarray) -> None:
        nf = len(FEATURES)
        lam = self.cfg.ridge * np.maximum(self._sq[idx], 1e-9)
        a = self._xtx[idx] + lam[..., None] * np.eye(nf)
        coef = np.linalg.solve(a, self._xty[idx][..., None])[..., 0]  # (n, 3, nf)
        bound = np.asarray(self.cfg.bounds)
        self.coef[idx] = np.clip(coef, -bound, bound)
        first = ~self.fitted[idx]  # the delay is the first fit's, kept from then on
        best, found = self._best(idx)
        self.delay[idx] = np.where(first, self._delays[best], self.delay[idx])
        self.delay_found[idx] = np.where(first, found, self.delay_found[idx])
        self._lead_from[idx] = np.where(first, 0.0, self._lead_from[idx])
        self._lead_t[idx] = np.where(first, t, self._lead_t[idx])
        self._t_fit[idx] = np.where(np.isfinite(self._t_fit[idx]), self._t_fit[idx], t)
        self._t_last[idx] = t

    def lead(self, t, rows=None) -> np.ndarray:
        """(n,) s: how far ahead of ``t`` (s into the excitation) the plan of each row of
        ``rows`` (None: all) is to be commanded, so that the motors, ``delay`` late, play it on
        time. 0 before the first fit; from it on it moves to the delay found over ``fade_s``
        (30 ms plays the plan 6 % faster for 0.5 s), so the commands never jump. Whoever commands the plan evaluates it at ``t + lead`` and gives
        :meth:`observe` and :meth:`torque` what it commanded, at ``t``."""
        idx = np.arange(len(self.coef)) if rows is None else np.asarray(rows).reshape(-1)
        t = np.broadcast_to(np.asarray(t, dtype=float), (len(idx),))
        w = np.clip((t - self._lead_t[idx]) / self.cfg.fade_s, 0.0, 1.0)
        w = np.where(np.isfinite(w), w, 0.0)
        return self._lead_from[idx] + w * (self.delay[idx] - self._lead_from[idx])

    def torque(self, t, dq_des, ddq_des, tau_model, rows=None) -> np.ndarray:
        """(n, 3) N m to add to the feed-forward of each row of ``rows`` (None: all), ``t`` s
        into its excitation: zero before the row's first fit, faded in over ``fade_s`` after
        it. dq_des, ddq_des, tau_model: the plan's at ``t``, (n, 3): the command of now, which
        the motors play ``delay`` s later, as the fit saw them play the ones before."""
        idx = np.arange(len(self.coef)) if rows is None else np.asarray(rows).reshape(-1)
        t = np.broadcast_to(np.asarray(t, dtype=float), (len(idx),))
        w = np.clip((t - self._t_fit[idx]) / self.cfg.fade_s, 0.0, 1.0)
        w = np.where(np.isfinite(w), w, 0.0)
        x = features(np.asarray(dq_des, dtype=float).reshape(-1, 3),
                     np.asarray(ddq_des, dtype=float).reshape(-1, 3),
                     np.asarray(tau_model, dtype=float).reshape(-1, 3))
        return w[:, None] * np.einsum("njf,njf->nj", x, self.coef[idx])
