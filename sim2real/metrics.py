"""Gap metrics: where recording and replay differ (channels, joints, legs, phases, bands).

Channels: ``q_<joint>``, ``dq_<joint>`` (SDK order), ``gyro_x|y|z``, ``acc_x|y|z`` (body IMU, base
frame). Each residual is divided by the channel's scale, ``max(std of the recorded signal,
floor)`` (floors 0.02 rad, 0.2 rad/s, 0.05 rad/s, 0.5 m/s^2), so channels of different units
are comparable: a normalised residual of 0.1 is 10 % of the motion.

The **gap** of a set of samples is the noise-corrected normalised RMS residual
``sqrt(mean_c max(ms_c - a_c, 0))``, ``ms_c`` the mean square normalised residual of channel
c and ``a_c`` the normalised variance that sensor noise alone gives (plus three standard errors
of its mean square over the samples), estimated from the
recording itself (second differences of each channel: white noise of std s gives second
differences of std s * sqrt(6)). A perfect simulator scores 0 whatever the sensors' noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, savgol_filter, sosfiltfilt

from calib.joints import JOINTS, SDK_JOINT_NAMES, SDK_LEGS
from sim2real.recording import Recording

__all__ = ["BANDS", "ChannelSet", "channel_set", "gap", "phase_labels", "pred_matrix"]

BANDS: tuple[tuple[float, float], ...] = ((0.0, 1.0), (1.0, 3.0), (3.0, 10.0), (10.0, 30.0),
                                          (30.0, 100.0))
_FLOORS = {"q": 0.02, "dq": 0.2, "gyro": 0.05, "acc": 0.5}


@dataclass
class ChannelSet:
    """names (C,), group of each channel ("q", "dq", "gyro", "acc"), rec (N, C) recorded values,
    scale (C,), noise (C,) normalised noise variance."""

    names: list[str]
    groups: list[str]
    rec: np.ndarray
    scale: np.ndarray
    noise: np.ndarray

    def index(self, group: str) -> np.ndarray:
        return np.array([i for i, g in enumerate(self.groups) if g == group])


def _noise_var(x: np.ndarray, robust: np.ndarray) -> np.ndarray:
    """Per-column white-noise variance from second differences: median absolute deviation
    where ``robust`` (joint channels, whose motion curves sharply), plain variance elsewhere
    (half the estimator's variance on smooth IMU channels)."""
    d2 = x[2:] - 2 * x[1:-1] + x[:-2]
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) * 1.4826
    sd = np.where(robust, mad, d2.std(axis=0))
    return (sd / np.sqrt(6.0)) ** 2


def channel_set(rec: Recording) -> ChannelSet:
    names, groups, cols = [], [], []
    for g, arr, labels in (("q", rec.q, SDK_JOINT_NAMES), ("dq", rec.dq, SDK_JOINT_NAMES),
                           ("gyro", rec.base_gyro, "xyz"), ("acc", rec.base_acc, "xyz")):
        for k, lab in enumerate(labels):
            names.append(f"{g}_{lab}")
            groups.append(g)
            cols.append(arr[:, k])
    x = np.stack(cols, axis=1)
    floors = np.array([_FLOORS[g] for g in groups])
    scale = np.maximum(x.std(axis=0), floors)
    noise = _noise_var(x, np.array([g in ('q', 'dq') for g in groups])) / scale**2
    return ChannelSet(names, groups, x, scale, noise)


def pred_matrix(pred) -> np.ndarray:
    """(N, C) of a :class:`sim2real.replay.Prediction` in :func:`channel_set` order."""
    return np.concatenate([pred.q, pred.dq, pred.gyro, pred.acc], axis=1)


def normalised_residual(cs: ChannelSet, pred_mat: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """(n, C) normalised residuals at the samples ``sel`` (bool or index)."""
    return (cs.rec[sel] - pred_mat[sel]) / cs.scale


def gap(res: np.ndarray, noise: np.ndarray, channels: np.ndarray | None = None) -> float:
    """Noise-corrected normalised RMS residual (module docstring) over ``channels``."""
    if res.shape[0] == 0:
        return 0.0
    ms = np.mean(res**2, axis=0) - _noise_allowance(noise, res.shape[0])
    if channels is not None:
        ms = ms[channels]
    return float(np.sqrt(np.mean(np.maximum(ms, 0.0))))


def channel_gaps(res: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Per-channel noise-corrected normalised RMS residual, (C,)."""
    if res.shape[0] == 0:
        return np.zeros(res.shape[1])
    return np.sqrt(np.maximum(np.mean(res**2, axis=0) - _noise_allowance(noise, res.shape[0]),
                              0.0))


def _noise_allowance(noise: np.ndarray, n: int) -> np.ndarray:
    """Noise variance plus three standard errors of a mean square of ``n`` noise samples, so
    that pure noise scores 0 (the noise estimate itself is a few per cent off)."""
    return noise * (1.0 + 3.0 * np.sqrt(2.0 / max(n, 1)))


def joint_gaps(cg: np.ndarray, cs: ChannelSet) -> dict[str, float]:
    """Per joint (SDK names): RMS of its q and dq channel gaps."""
    iq, idq = cs.index("q"), cs.index("dq")
    return {n: float(np.sqrt((cg[iq[k]] ** 2 + cg[idq[k]] ** 2) / 2))
            for k, n in enumerate(SDK_JOINT_NAMES)}


def leg_gaps(jg: dict[str, float]) -> dict[str, float]:
    return {leg: float(np.sqrt(np.mean([jg[f"{leg}_{j}"] ** 2 for j in JOINTS])))
            for leg in SDK_LEGS}


def phase_labels(rec: Recording, contact: np.ndarray | None = None) -> np.ndarray:
    """A phase name per sample: suspended ``"hold"`` / ``"excitation"`` (commanded joint
    speed above 0.05 rad/s); ground ``"stance"`` (4 feet loaded), ``"tripod"`` (3),
    ``"swing"`` (fewer). Feet loaded: ``foot_force`` > 10 when recorded, else the replay's
    contacts."""
    if rec.mount == "suspended":
        moving = np.linalg.norm(rec.cmd["dq"], axis=1) > 0.05
        return np.where(moving, "excitation", "hold")
    if rec.foot_force is not None:
        n_feet = (rec.foot_force > 10.0).sum(axis=1)
    elif contact is not None:
        n_feet = contact.sum(axis=1)
    else:
        n_feet = np.full(rec.n, 4)
    return np.where(n_feet >= 4, "stance", np.where(n_feet == 3, "tripod", "swing"))


def phase_gaps(res: np.ndarray, noise: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    return {str(p): gap(res[labels == p], noise) for p in np.unique(labels)}


def band_gaps(res_full: np.ndarray, mask: np.ndarray, rate: float,
              channels: np.ndarray) -> dict[str, float]:
    """RMS of the normalised residual of ``channels`` in each band of :data:`BANDS` (Hz).

    ``res_full`` (N, C) residuals with zeros outside ``mask`` (window starts are jumps:
    zeroed too)."""
    out = {}
    x = np.where(mask[:, None], res_full[:, channels], 0.0)
    nyq = rate / 2.0
    for lo, hi in BANDS:
        if lo >= nyq:
            continue
        hi_c = min(hi, 0.95 * nyq)
        if lo <= 0:
            sos = butter(2, hi_c / nyq, "low", output="sos")
        else:
            sos = butter(2, [lo / nyq, hi_c / nyq], "band", output="sos")
        y = sosfiltfilt(sos, x, axis=0)[mask]
        out[f"{lo:g}-{hi:g} Hz"] = float(np.sqrt(np.mean(y**2))) if y.size else 0.0
    return out


def torque_residual_share(rec: Recording, pred, model_mass, sel: np.ndarray) -> np.ndarray:
    """Share of the unexplained torque per joint, (12,) SDK order, summing to 1: where an
    unmodelled torque acts.

    The replay and the recording differ in acceleration by ``M^-1 (tau_e + d_tau_pd)``: the
    unmodelled torque ``tau_e`` plus the PD law's response to the state difference. So
    ``tau_e ~ M(q) (ddq_rec - ddq_sim) - (tau_pd(rec) - tau_pd(sim))``; the mass matrix undoes
    the coupling that spreads one joint's torque over its leg. model_mass(q_sdk) -> (12, 12)
    joint-space mass matrix, SDK order.
    """
    dt = rec.sample_period
    win = 11
    a_rec = savgol_filter(rec.dq, win, 2, deriv=1, delta=dt, axis=0)
    dq_p = np.nan_to_num(pred.dq)
    q_p = np.nan_to_num(pred.q)
    a_sim = savgol_filter(dq_p, win, 2, deriv=1, delta=dt, axis=0)
    c = rec.cmd
    d_pd = c["kp"] * (q_p - rec.q) + c["kd"] * (dq_p - rec.dq)  # tau_pd(rec) - tau_pd(sim)
    # only where the replay predicted, the filter's half-width clear of where it did not: a
    # ground window's unpredicted burn-in read as q_sim = 0, ~80 N m on every calf, and hid a
    # local effect under a fixed share
    pm = np.asarray(pred.mask, bool)
    near_gap = np.convolve(~pm, np.ones(win), mode="same") > 0
    idx = np.nonzero(sel & pm & ~near_gap)[0][::5]
    tau = np.zeros(12)
    for i in idx:
        m = model_mass(rec.q[i])
        tau += (m @ (a_rec[i] - a_sim[i]) - d_pd[i]) ** 2
    s = tau.sum()
    return tau / s if s > 0 else np.full(12, 1 / 12)
