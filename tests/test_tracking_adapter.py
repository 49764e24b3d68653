"""The lifted leg's tracking adapter: what it identifies on a plant with known unmodelled
torques, how much closer the plant then tracks, its rows, its bounds and its bad inputs."""

from __future__ import annotations

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


def _run(adapter, damping, friction, strength, seconds=12.0):
    """The joints under PD + the model's torque (J ddq_des + G cos q_des) + the adapter's, with viscous
    damping, dry friction and a motor ``strength`` the model lacks. Returns the tracking RMSE
    over the last 4 s, rad."""
    q, dq, _ = _plan(0.0)
    q, dq = q.copy(), dq.copy()
    applied = np.zeros(3)
    err = []
    for k in range(round(seconds / DT)):
        t = k * DT
        q_des, dq_des, ddq_des = _plan(t)
        model = J * ddq_des + G * np.cos(q_des)
        if adapter is not None:
            if k % TICK == 0:
                adapter.observe(t, q_des, dq_des, ddq_des, q, dq, model, applied)
            applied = adapter.torque(t, dq_des, ddq_des, model)[0]
        tau = strength * (KP * (q_des - q) + KD * (dq_des - dq) + model + applied)
        ddq = (tau - G * np.cos(q) - damping * dq - friction * np.tanh(dq / 0.01)) / J
        dq = dq + DT * ddq
        q = q + DT * dq
        if t >= seconds - 4.0:
            err.append(q_des - q)
    return float(np.sqrt(np.mean(np.square(err))))


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
