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

b: viscous damping (a latency ``d`` looks like ``kp d`` more of it); f: dry friction, smoothed;
i: inertia the model lacks (and a latency's second-order term); a: a torque constant off by
``1 / (1 + a)``. From ``start_s`` into the excitation on, the fitted torque of the plan is added
to the feed-forward, faded in over ``fade_s`` and refitted every ``refit_s``. It is a
feed-forward of the plan, not a feedback: the loop's stability stays the PD law's whatever the
fit says, and each coefficient is clipped to a physically plausible bound. The calibration does
not depend on it (the solver reads the executed motion), but the executed motion comes closer to
the plan, whose condition number is 1.

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
    0.05 kg m^2 5 times the rotor's; a torque constant off by up to a half either way)."""

    start_s: float = 2.0
    refit_s: float = 1.0
    fade_s: float = 0.5
    memory_s: float = 4.0
    ridge: float = 1e-3
    bounds: tuple[float, float, float, float] = (5.0, 1.5, 0.05, 0.5)

    def __post_init__(self) -> None:
        for k in ("start_s", "refit_s", "fade_s", "memory_s", "ridge"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{k} must be > 0, got {v}")
        if len(self.bounds) != len(FEATURES) or not all(
                np.isfinite(b) and b >= 0 for b in self.bounds):
            raise ValueError(f"bounds must be {len(FEATURES)} values >= 0, got {self.bounds}")


def features(dq_des, ddq_des, tau_model) -> np.ndarray:
    """(..., 3 joints, 4): dq_des, tanh(dq_des / V_SIGN), ddq_des, tau_model (the plan's
    velocity rad/s, acceleration rad/s^2 and model torque N m, (..., 3) each)."""
    dq_des, ddq_des, tau_model = np.broadcast_arrays(
        *(np.asarray(v, dtype=float) for v in (dq_des, ddq_des, tau_model)))
    return np.stack([dq_des, np.tanh(dq_des / V_SIGN), ddq_des, tau_model], axis=-1)


class TrackingAdapter:
    """Identify the lifted legs' unmodelled torque from their tracking, and feed it forward.

    kp N m/rad, kd N m s/rad: the gains the lifted legs are commanded with (the schedule's).
    rows: how many lifted legs (batch rows). Each row starts empty; :meth:`reset` empties rows
    for a new excitation. :meth:`observe` once per control tick during the excitation (the
    measured joints against the plan at that instant, and the correction the motors held);
    :meth:`torque` for each command frame.
    """

    def __init__(self, kp: float, kd: float, rows: int = 1,
                 config: AdapterConfig | None = None) -> None:
        if not (np.isfinite(kp) and kp > 0 and np.isfinite(kd) and kd >= 0):
            raise ValueError(f"kp must be > 0 and kd >= 0, got {kp}, {kd}")
        if isinstance(rows, bool) or not isinstance(rows, int) or rows < 1:
            raise ValueError(f"rows must be a positive integer, got {rows!r}")
        self.kp, self.kd = float(kp), float(kd)
        self.cfg = config or AdapterConfig()
        nf = len(FEATURES)
        self._xtx = np.zeros((rows, 3, nf, nf))  # per row and joint: sum of x x^T
        self._xty = np.zeros((rows, 3, nf))
        self._sq = np.zeros((rows, 3, nf))  # sum of x^2: the ridge's scale
        self.coef = np.zeros((rows, 3, nf))
        self._t_fit = np.full(rows, np.nan)  # s into the excitation of the first fit
        self._t_last = np.full(rows, -np.inf)
        self._t_sample = np.full(rows, np.nan)  # s into the excitation of the last sample

    @property
    def fitted(self) -> np.ndarray:
        """(rows,) bool: rows with a fit (their torque is on)."""
        return np.isfinite(self._t_fit)

    def reset(self, rows=None) -> None:
        """Forget what ``rows`` (None: all) learnt: a new excitation starts there."""
        r = slice(None) if rows is None else rows
        for a in (self._xtx, self._xty, self._sq, self.coef):
            a[r] = 0.0
        self._t_fit[r] = np.nan
        self._t_last[r] = -np.inf
        self._t_sample[r] = np.nan

    def observe(self, t, q_des, dq_des, ddq_des, q, dq, tau_model, applied, rows=None) -> None:
        """One sample per row of ``rows`` (None: all), ``t`` s into its excitation ((n,) or a
        scalar): the plan's targets and model torque at that instant, the measured joints, and
        the correction the motors held then, (n, 3) each. A row with a non-finite value skips
        this sample (a lost frame). Refits the rows that are due."""
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
        u = self.kp * (q_des - q) + self.kd * (dq_des - dq) + applied
        x = features(dq_des, ddq_des, tau_model)  # (n, 3, nf)
        # older samples fade: they were taken further from the plan (before the fit closed the
        # lag, the measured motion was not the plan whose features they are regressed on)
        age = np.nan_to_num(t - self._t_sample[idx], nan=0.0)
        keep = np.exp(-np.maximum(age, 0.0) / self.cfg.memory_s)
        self._xtx[idx] = keep[:, None, None, None] * self._xtx[idx] + \
            x[..., :, None] * x[..., None, :]
        self._xty[idx] = keep[:, None, None] * self._xty[idx] + x * u[..., None]
        self._sq[idx] = keep[:, None, None] * self._sq[idx] + x**2
        self._t_sample[idx] = t
        due = (t >= self.cfg.start_s) & (t - self._t_last[idx] >= self.cfg.refit_s)
        if due.any():
            self._fit(idx[due], t[due])

    def _fit(self, idx: np.ndarray, t: np.ndarray) -> None:
        lam = self.cfg.ridge * np.maximum(self._sq[idx], 1e-9)
        a = self._xtx[idx] + lam[..., None] * np.eye(len(FEATURES))
        coef = np.linalg.solve(a, self._xty[idx][..., None])[..., 0]
        bound = np.asarray(self.cfg.bounds)
        self.coef[idx] = np.clip(coef, -bound, bound)
        self._t_fit[idx] = np.where(np.isfinite(self._t_fit[idx]), self._t_fit[idx], t)
        self._t_last[idx] = t

    def torque(self, t, dq_des, ddq_des, tau_model, rows=None) -> np.ndarray:
        """(n, 3) N m to add to the feed-forward of each row of ``rows`` (None: all), ``t`` s
        into its excitation: zero before the row's first fit, faded in over ``fade_s`` after
        it. dq_des, ddq_des, tau_model: the plan's at ``t``, (n, 3)."""
        idx = np.arange(len(self.coef)) if rows is None else np.asarray(rows).reshape(-1)
        t = np.broadcast_to(np.asarray(t, dtype=float), (len(idx),))
        w = np.clip((t - self._t_fit[idx]) / self.cfg.fade_s, 0.0, 1.0)
        w = np.where(np.isfinite(w), w, 0.0)
        x = features(np.asarray(dq_des, dtype=float).reshape(-1, 3),
                     np.asarray(ddq_des, dtype=float).reshape(-1, 3),
                     np.asarray(tau_model, dtype=float).reshape(-1, 3))
        return w[:, None] * np.einsum("njf,njf->nj", x, self.coef[idx])
