"""The lifted leg's tracking adapter: what it identifies on a plant with known unmodelled
torques, how much closer the plant then tracks, its rows, its bounds and its bad inputs."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from deploy.tracking_adapter import FEATURES, AdapterConfig, TrackingAdapter, features

KP, KD = 80.0, 2.0
J = np.array([0.03, 0.05, 0.02])  # kg m^2, each joint's inertia (the model knows it)
G = np.array([1.5, 2.5, 1.0])  # N m, each joint's gravity torque at cos(q) = 1 (known too)
DT, TICK = 0.001, 20  # 1 kHz plant, a 50 Hz control tick


def _plan(t):
    """Three joints' plan: two sines each, so velocity and acceleration are not collinear."""
    w = np.array([1.6, 2.3, 3.1])
    q = 0.4 * np.sin(w * t) + 0.15 * np.sin(3.7 * w * t + 0.5)
    dq = 0.4 * w * np.cos(w * t) + 0.15 * 3.7 * w * np.cos(3.7 * w * t + 0.5)
    ddq = -0.4 * w**2 * np.sin(w * t) - 0.15 * (3.7 * w) ** 2 * np.sin(3.7 * w * t + 0.5)
    return q, dq, ddq


def _run(adapter, damping, friction, strength, seconds=12.0, delay_ms=0, report=True,
         shape=False):
    """The joints under PD + the model's torque (J ddq_des + G cos q_des) + the adapter's, with viscous
    damping, dry friction and a motor ``strength`` the model lacks, each command reaching the
    motors ``delay_ms`` late; with ``report`` the adapter is given the torque the motors
    applied (LowState's tau_est), and the plan is commanded at its lead. Returns the tracking
    RMSE against the plan of each instant over the last 4 s, rad (with
    ``shape``, also the RMSE against the plan moved by the lag that fits it best: what is left
    once the delay is taken out, the error a calibration's condition number sees)."""
    q, dq, _ = _plan(0.0)
    q, dq = q.copy(), dq.copy()
    applied = np.zeros(3)
    tau = np.full(3, np.nan)
    sent = deque()
    err, moved, planned = [], [], []
    for k in range(round(seconds / DT)):
        t = k * DT
        # the plan commanded as far ahead as the delay the adapter found (its lead)
        lead = adapter.lead(t)[0] if adapter is not None else 0.0
        q_des, dq_des, ddq_des = _plan(t + lead)
        model = J * ddq_des + G * np.cos(q_des)
        if adapter is not None:
            if k % TICK == 0:
                adapter.observe(t, q_des, dq_des, ddq_des, q, dq, model, applied,
                                tau_motor=tau if report else None)
            applied = adapter.torque(t, dq_des, ddq_des, model)[0]
        sent.append((q_des, dq_des, model + applied))
        c_q, c_dq, c_ff = sent.popleft() if len(sent) > delay_ms else sent[0]
        tau = strength * (KP * (c_q - q) + KD * (c_dq - dq) + c_ff)
        ddq = (tau - G * np.cos(q) - damping * dq - friction * np.tanh(dq / 0.01)) / J
        dq = dq + DT * ddq
        q = q + DT * dq
        if t >= seconds - 4.0:
            err.append(_plan(t)[0] - q)
            moved.append(q.copy())
            planned.append(_plan(t)[0])
    rmse = float(np.sqrt(np.mean(np.square(err))))
    if not shape:
        return rmse
    moved, planned = np.array(moved), np.array(planned)
    n = len(planned)
    left = min(np.sqrt(np.mean((moved[max(lag, 0):n + min(lag, 0)]
                                - planned[max(-lag, 0):n - max(lag, 0)]) ** 2))
               for lag in range(-50, 100))
    return rmse, float(left)


def test_it_identifies_damping_friction_and_a_weak_motor_and_the_leg_tracks_closer():
    damping, friction, strength = 2.0, 0.2, 0.8
    plain = _run(None, damping, friction, strength)
    ad = TrackingAdapter(KP, KD)
    adapted = _run(ad, damping, friction, strength)
    b, f, i, a = ad.coef[0].T
    # u = (damping dq + friction sign(dq)) / strength + (1 / strength - 1) model
    np.testing.assert_allclose(b, damping / strength, rtol=0.1)
    np.testing.assert_allclose(f, friction / strength, rtol=0.2)
    np.testing.assert_allclose(a, 1 / strength - 1, atol=0.05)
    # the inertia was the model's; what is left comes of the samples taken while the leg still
    # lagged (the fit regresses on the plan's features, not the motion's)
    assert np.all(np.abs(i) < 0.3 * J.max())
    assert plain > 0.02 and adapted < plain / 4, (plain, adapted)


def test_a_command_delay_is_found_from_the_motor_torque_and_not_fed_forward():
    """30 ms of latency and nothing else: from the torque the motors report the adapter finds
    the delay and learns nothing to feed forward, so the leg plays the plan exactly, late. Not
    told the torque, it reads the lag as damping (kp d = 2.4 N m s/rad) and drives the leg ahead
    by a velocity lead, which bends the plan's faster harmonics."""
    ad = TrackingAdapter(KP, KD)
    rmse, left = _run(ad, 0.0, 0.0, 1.0, delay_ms=30, shape=True)
    assert ad.delay[0] == pytest.approx(0.030) and ad.delay_found[0]
    assert np.abs(ad.coef[0]).max() < 0.05 * KP * 0.030
    # commanded 30 ms ahead (its lead), the late leg plays the plan on time
    assert ad.lead(11.0)[0] == pytest.approx(0.030)
    late = _run(None, 0.0, 0.0, 1.0, delay_ms=30)
    assert rmse < late / 10, (rmse, late)
    blind = TrackingAdapter(KP, KD)
    _, left_blind = _run(blind, 0.0, 0.0, 1.0, delay_ms=30, report=False, shape=True)
    assert blind.delay[0] == 0.0 and not blind.delay_found[0]
    np.testing.assert_allclose(blind.coef[0, :, 0], KP * 0.030, rtol=0.25)
    assert left < 3e-4 and left_blind > 5 * left, (left, left_blind)


def test_damping_and_delay_together_are_told_apart():
    """A damping and a weak motor behind 20 ms of latency: the delay from the motors' torque,
    the damping as without latency, and once the delay is taken out the leg plays the plan
    ten times closer than under PD alone."""
    damping, friction, strength = 2.0, 0.2, 0.8
    ad = TrackingAdapter(KP, KD)
    _, left = _run(ad, damping, friction, strength, delay_ms=20, shape=True)
    assert ad.delay[0] == pytest.approx(0.020) and ad.delay_found[0]
    np.testing.assert_allclose(ad.coef[0, :, 0], damping / strength, rtol=0.1)
    _, left_plain = _run(None, damping, friction, strength, delay_ms=20, shape=True)
    assert left < left_plain / 5, (left, left_plain)


def test_no_reported_torque_keeps_the_delay_at_zero():
    ad = TrackingAdapter(KP, KD, rows=2)
    ones = np.ones((2, 3))
    tau = np.array([[np.nan, 1.0, 1.0], [1.0, 1.0, 1.0]])  # row 0 lost its torque
    for t in np.arange(0.0, 2.2, 0.02):
        dq = np.sin(3 * t) * ones
        ad.observe(t, 0.01 * dq, dq, 0 * ones, 0 * ones, dq, 0 * ones, 0 * ones,
                   tau_motor=tau * 0.8 * dq)
    assert ad.fitted.all()
    assert ad.delay[0] == 0.0
    # row 1's torque is the PD law's with no delay: found, 0; row 0's is not read
    assert ad.delay[1] == 0.0 and ad.delay_found[1] and not ad.delay_found[0]
    ad.reset([1])  # a new excitation: found again or not at all
    assert not ad.delay_found.any()


def test_a_reported_torque_that_is_not_the_pd_laws_keeps_the_delay_at_zero():
    """Noise for a torque report (a firmware that reports something else, a broken sensor):
    whichever delay fits it least badly explains little of it, and none is taken."""
    rng = np.random.default_rng(3)
    ad = TrackingAdapter(KP, KD)
    ones = np.ones(3)
    for t in np.arange(0.0, 2.2, 0.02):
        q, dq, ddq = _plan(t)
        ad.observe(t, q, dq, ddq, q - 0.01 * dq, dq, 0 * ones, 0 * ones,
                   tau_motor=rng.normal(0.0, 2.0, 3))
    assert ad.fitted[0] and ad.delay[0] == 0.0 and not ad.delay_found[0]


def test_nothing_to_learn_leaves_the_plant_as_it_was():
    """The model is the plant: the fit stays near zero and the tracking as good."""
    plain = _run(None, 0.0, 0.0, 1.0)
    ad = TrackingAdapter(KP, KD)
    adapted = _run(ad, 0.0, 0.0, 1.0)
    assert np.abs(ad.coef).max() < 0.01
    assert adapted < 1.1 * plain + 1e-5


def test_torque_starts_after_the_first_fit_and_fades_in():
    cfg = AdapterConfig(start_s=2.0, refit_s=1.0, fade_s=0.5)
    ad = TrackingAdapter(KP, KD, config=cfg)
    ones = np.ones(3)
    for t in np.arange(0.0, 2.0, 0.02):
        ad.observe(t, 0.01 * ones, ones, 0 * ones, 0 * ones, ones, 0 * ones, 0 * ones)
    assert not ad.fitted[0]
    assert not ad.torque(1.99, ones, 0 * ones, 0 * ones).any()
    ad.observe(2.0, 0.01 * ones, ones, 0 * ones, 0 * ones, ones, 0 * ones, 0 * ones)
    assert ad.fitted[0]
    full = ad.torque(2.5, ones, 0 * ones, 0 * ones)
    np.testing.assert_allclose(ad.torque(2.25, ones, 0 * ones, 0 * ones), 0.5 * full)
    assert np.all(full > 0.5)  # kp * 0.01 rad at 1 rad/s: ~0.8 N m of damping and friction


def test_old_samples_fade_so_the_fit_follows_a_change():
    """A damping of 1 N m s/rad for 10 s, then of 2: at the last fit, 9 s later, the older
    samples weigh exp(-9 s / memory_s) of the new ones (0.11 at 4 s); kept for ever, as much."""
    zeros = np.zeros(3)
    fits = {}
    for memory in (4.0, 1000.0):
        ad = TrackingAdapter(KP, KD, config=AdapterConfig(memory_s=memory))
        for t in np.arange(0.0, 20.0, 0.02):
            dq = np.full(3, np.sin(2.0 * t))
            b = 1.0 if t < 10.0 else 2.0
            ad.observe(t, b * dq / KP, dq, zeros, zeros, dq, zeros, zeros)
        fits[memory] = ad.coef[0, :, 0]
    np.testing.assert_allclose(fits[4.0], (np.exp(-9 / 4) + 2) / (np.exp(-9 / 4) + 1), atol=0.01)
    np.testing.assert_allclose(fits[1000.0], 1.45, atol=0.05)


def test_rows_learn_apart_and_reset_forgets():
    ad = TrackingAdapter(KP, KD, rows=3)
    ones = np.ones((2, 3))
    for t in np.arange(0.0, 2.1, 0.02):
        dq = np.sin(3 * t) * ones
        ad.observe(t, 0.01 * dq, dq, 0 * ones, 0 * ones, dq, 0 * ones, 0 * ones, rows=[0, 2])
    assert ad.fitted.tolist() == [True, False, True]
    assert not ad.coef[1].any() and ad.coef[0].any()
    np.testing.assert_allclose(ad.coef[0], ad.coef[2])
    assert not ad.torque(3.0, ones[:1], 0 * ones[:1], 0 * ones[:1], rows=[1]).any()
    ad.reset([0])
    assert ad.fitted.tolist() == [False, False, True] and not ad.coef[0].any()


def test_coefficients_stay_within_their_bounds_and_lost_samples_are_skipped():
    ad = TrackingAdapter(KP, KD)
    ones = np.ones(3)
    ad.observe(0.0, np.full(3, np.nan), ones, ones, ones, ones, ones, ones)  # a lost frame
    assert not ad._sq.any()
    for t in np.arange(0.0, 2.1, 0.02):
        dq = np.cos(2 * t) * ones
        ad.observe(t, 10.0 * dq, dq, -dq, 0 * ones, dq, 0.1 * ones, 0 * ones)  # absurd lag
    assert np.all(np.abs(ad.coef) <= np.asarray(ad.cfg.bounds) + 1e-12)
    assert np.isclose(np.abs(ad.coef[0, :, 0]), ad.cfg.bounds[0]).all()


def test_features_and_bad_settings():
    x = features(np.array([0.0, 1.0, -1.0]), np.array([1.0, 2.0, 3.0]), 0.5)
    assert x.shape == (3, len(FEATURES))
    np.testing.assert_allclose(x[:, 0], [0, 1, -1])
    np.testing.assert_allclose(x[:, 1], [0, np.tanh(10), -np.tanh(10)])
    np.testing.assert_allclose(x[:, 2:], [[1, 0.5], [2, 0.5], [3, 0.5]])
    with pytest.raises(ValueError, match="kp"):
        TrackingAdapter(0.0, 1.0)
    with pytest.raises(ValueError, match="rows"):
        TrackingAdapter(KP, KD, rows=0)
    with pytest.raises(ValueError, match="start_s"):
        AdapterConfig(start_s=0.0)
    with pytest.raises(ValueError, match="bounds"):
        AdapterConfig(bounds=(1.0, 1.0))
    with pytest.raises(ValueError, match="max_delay_s"):
        AdapterConfig(max_delay_s=-0.01)
    with pytest.raises(ValueError, match="min_explained"):
        AdapterConfig(min_explained=1.5)
    with pytest.raises(ValueError, match="history"):
        AdapterConfig(history=1)
    np.testing.assert_allclose(AdapterConfig(max_delay_s=0.02, delay_step_s=0.005).delays,
                               [0.0, 0.005, 0.01, 0.015, 0.02])
