"""Sensor models: encoders, body IMU, foot IMU (noise, clock conventions, losses, bias walk)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sim.go2 import Go2Sim, SimConfig, rotation_about_axis_trajectory, stand_pose
from sim.sensors import (
    PAPER_GYRO_NOISE_DEG,
    BodyImuModel,
    EncoderModel,
    FootImuConfig,
    FootImuModel,
    deg_density_to_rad,
    rad_density_to_deg,
    random_mounting,
    white_noise_std,
)


def _truth(duration=4.0, rate=1000.0):
    """A smooth foot-frame truth: angular velocity (rad/s) and specific force (m/s^2)."""
    t = np.arange(0.0, duration, 1.0 / rate)
    om = np.stack([np.sin(2.1 * t), 0.5 * np.cos(1.3 * t), 0.8 * np.sin(0.7 * t + 1.0)], axis=1)
    sf = np.stack([0.3 * np.cos(t), 0.2 * np.sin(1.7 * t), 9.81 + 0.1 * np.sin(t)], axis=1)
    return t, om, sf


def test_density_conversions():
    assert deg_density_to_rad(0.03) == pytest.approx(0.03 * np.pi / 180)
    assert rad_density_to_deg(deg_density_to_rad(0.06)) == pytest.approx(0.06)
    assert white_noise_std(0.01, 400.0) == pytest.approx(0.2)
    assert PAPER_GYRO_NOISE_DEG == (0.006, 0.03, 0.06)
    with pytest.raises(ValueError):
        white_noise_std(0.01, 0.0)


@pytest.mark.parametrize("rate", [100.0, 400.0])
def test_white_noise_std_matches_density(rate):
    dens_g = deg_density_to_rad(0.06)
    cfg = FootImuConfig(gyro_noise_density=dens_g, accel_noise_density=0.004, rate=rate, seed=3)
    t = np.array([0.0, 100.0])
    batch = FootImuModel(cfg).sample(t, np.zeros((2, 3)), np.zeros((2, 3)))
    assert len(batch.stamps) == int(100.0 * rate) + 1
    std_g = batch.gyro.std(axis=0)
    std_a = batch.accel.std(axis=0)
    np.testing.assert_allclose(std_g, dens_g * np.sqrt(rate), rtol=0.10)
    np.testing.assert_allclose(std_a, 0.004 * np.sqrt(rate), rtol=0.10)
    assert cfg.gyro_noise_std == pytest.approx(dens_g * np.sqrt(rate))


def test_rotation_and_time_offset_convention():
    rot = Rotation.from_euler("xyz", [0.4, -1.1, 2.5]).as_matrix()
    t_d = 0.137
    cfg = FootImuConfig(rotation=rot, time_offset=t_d, rate=200.0, phase=0.0021, seed=1)
    t, om, sf = _truth()
    b = FootImuModel(cfg).sample(t, om, sf)
    np.testing.assert_allclose(b.true_time[1:] - b.true_time[:-1], 1 / 200.0, atol=1e-12)
    assert b.true_time[0] == pytest.approx(0.0021)
    np.testing.assert_allclose(b.stamps, b.true_time + t_d, atol=1e-12)  # t_I = t_E + t_d
    # the IMU measures R^T omega_F at the sample's true time ...
    om_true = np.stack([np.interp(b.true_time, t, om[:, j]) for j in range(3)], axis=1)
    np.testing.assert_allclose(b.gyro, om_true @ rot, atol=1e-12)
    # ... so R @ gyro stamped s is the foot motion the encoders stamped s - t_d
    exact = np.stack([np.sin(2.1 * (b.stamps - t_d)), 0.5 * np.cos(1.3 * (b.stamps - t_d)),
                      0.8 * np.sin(0.7 * (b.stamps - t_d) + 1.0)], axis=1)
    np.testing.assert_allclose(b.gyro @ rot.T, exact, atol=1e-6)
    sf_true = np.stack([np.interp(b.true_time, t, sf[:, j]) for j in range(3)], axis=1)
    np.testing.assert_allclose(b.accel, sf_true @ rot, atol=1e-12)
    np.testing.assert_array_equal(b.seq, np.arange(len(b.seq)))


def test_dropouts_leave_sequence_gaps():
    cfg = FootImuConfig(rate=500.0, dropout_prob=0.1, seed=7)
    t = np.array([0.0, 20.0])
    b = FootImuModel(cfg).sample(t, np.zeros((2, 3)), None)
    total = 20 * 500 + 1
    lost = total - len(b.seq)
    assert lost / total == pytest.approx(0.1, abs=0.015)
    assert np.all(np.diff(b.seq) >= 1)
    assert np.sum(np.diff(b.seq) - 1) == lost - (total - 1 - b.seq[-1]) - b.seq[0]
    assert np.any(np.diff(b.seq) > 1)
    # the samples that remain describe their own instants: lost ones are skipped, not shifted
    np.testing.assert_allclose(b.true_time, b.seq / 500.0, atol=1e-12)


def test_timestamp_jitter_moves_stamps_only():
    cfg = FootImuConfig(rate=200.0, jitter_std=2e-4, time_offset=-0.05, seed=11)
    t, om, sf = _truth(duration=30.0, rate=400.0)
    b = FootImuModel(cfg).sample(t, om, sf)
    err = b.stamps - (b.true_time - 0.05)
    assert err.std() == pytest.approx(2e-4, rel=0.1)
    assert abs(err.mean()) < 2e-5
    om_true = np.stack([np.interp(b.true_time, t, om[:, j]) for j in range(3)], axis=1)
    np.testing.assert_allclose(b.gyro, om_true, atol=1e-12)


def test_bias_random_walk_variance_grows_linearly():
    rw, rate, n_runs = 1e-3, 100.0, 300
    t = np.array([0.0, 40.0])
    zeros = np.zeros((2, 3))
    runs = np.stack([
        FootImuModel(FootImuConfig(rate=rate, gyro_bias_random_walk=rw,
                                   gyro_bias=[0.01, 0.0, -0.02], seed=s)).sample(t, zeros).gyro
        for s in range(n_runs)
    ])  # (runs, K, 3)
    np.testing.assert_allclose(runs[:, 0, :].mean(axis=0), [0.01, 0.0, -0.02], atol=1e-15)
    k1, k2 = int(10 * rate), int(40 * rate)
    v1 = runs[:, k1, :].var(axis=0).mean()  # pooled over the 3 axes: 900 samples
    v2 = runs[:, k2, :].var(axis=0).mean()
    assert v1 == pytest.approx(rw**2 * 10.0, rel=0.15)
    assert v2 == pytest.approx(rw**2 * 40.0, rel=0.15)
    assert v2 / v1 == pytest.approx(4.0, rel=0.25)


def test_streaming_equals_batch():
    cfg = dataclasses.replace(random_mounting(5, rate=250.0), jitter_std=1e-4,
                              dropout_prob=0.05, gyro_bias_random_walk=1e-3,
                              accel_bias_random_walk=1e-2)
    t, om, sf = _truth(duration=2.0, rate=1000.0)
    model = FootImuModel(cfg)
    stream = []
    for i in range(len(t)):
        stream.extend(model.update(t[i], om[i], sf[i]))
    s = FootImuModel.to_batch(stream)
    b = model.sample(t, om, sf)
    np.testing.assert_array_equal(s.seq, b.seq)
    np.testing.assert_allclose(s.stamps, b.stamps, atol=1e-12)
    np.testing.assert_allclose(s.gyro, b.gyro, atol=1e-9)
    np.testing.assert_allclose(s.accel, b.accel, atol=1e-9)
    model.reset()
    again = FootImuModel.to_batch(
        [x for i in range(len(t)) for x in model.update(t[i], om[i], sf[i])])
    np.testing.assert_array_equal(again.gyro, s.gyro)
    with pytest.raises(ValueError):
        model.update(-1.0, om[0], sf[0])


def test_sample_from_truth_function():
    rot = Rotation.from_euler("z", 0.3).as_matrix()
    cfg = FootImuConfig(rotation=rot, rate=100.0)

    def truth(tau):
        om = np.stack([np.sin(tau), np.cos(tau), tau], axis=1)
        return om, np.zeros_like(om)

    b = FootImuModel(cfg).sample((1.0, 2.0), truth)
    assert len(b.stamps) == 101
    np.testing.assert_allclose(b.gyro @ rot.T, truth(b.true_time)[0], atol=1e-12)


def test_random_mounting_and_config_validation():
    a, b = random_mounting(1), random_mounting(1)
    np.testing.assert_array_equal(a.rotation, b.rotation)
    assert a.time_offset == b.time_offset
    c = random_mounting(2)
    assert not np.allclose(a.rotation, c.rotation)
    offsets = [random_mounting(s).time_offset for s in range(50)]
    assert max(np.abs(offsets)) <= 0.2 and np.std(offsets) > 0.05
    assert np.linalg.det(a.rotation) == pytest.approx(1.0)
    assert a.gyro_noise_density == pytest.approx(deg_density_to_rad(0.03))
    assert random_mounting(3, dropout_prob=0.2).dropout_prob == 0.2
    with pytest.raises(ValueError):
        FootImuConfig(rotation=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError):
        FootImuConfig(rate=0.0)
    with pytest.raises(ValueError):
        FootImuConfig(dropout_prob=1.0)
    with pytest.raises(ValueError):
        FootImuConfig(gyro_noise_density=-1.0)
    with pytest.raises(TypeError):
        FootImuModel("not a config")


def test_encoder_quantisation_and_noise():
    res = 2 * np.pi / 2**15
    enc = EncoderModel(seed=0)
    assert enc.resolution == pytest.approx(res)
    q = np.random.default_rng(0).uniform(-2.0, 2.0, (1000, 12))
    qm, dqm = enc.measure(q, np.ones_like(q))
    np.testing.assert_allclose(qm / res, np.round(qm / res), atol=1e-6)
    assert np.abs(qm - q).max() <= res / 2 + 1e-12
    np.testing.assert_array_equal(dqm, 1.0)
    noisy = EncoderModel(resolution=0.0, q_noise_std=0.01, dq_noise_std=0.1, seed=1)
    qm, dqm = noisy.measure(np.zeros(20000), np.zeros(20000))
    assert qm.std() == pytest.approx(0.01, rel=0.05)
    assert dqm.std() == pytest.approx(0.1, rel=0.05)
    with pytest.raises(ValueError):
        EncoderModel(resolution=-1.0)
    with pytest.raises(ValueError):
        enc.measure(np.zeros(3), np.zeros(4))


def test_body_imu_bias_and_noise():
    imu = BodyImuModel(gyro_noise_density=0.001, accel_noise_density=0.01, rate=400.0,
                       gyro_bias=[0.01, 0.0, 0.0], accel_bias=[0.0, 0.0, 0.2], seed=2)
    g, a = imu.measure(np.zeros((20000, 3)), np.tile([0, 0, 9.81], (20000, 1)))
    np.testing.assert_allclose(g.mean(axis=0), [0.01, 0, 0], atol=5e-4)
    np.testing.assert_allclose(a.mean(axis=0), [0, 0, 10.01], atol=5e-3)
    np.testing.assert_allclose(g.std(axis=0), 0.001 * 20, rtol=0.05)
    np.testing.assert_allclose(a.std(axis=0), 0.01 * 20, rtol=0.05)


def test_foot_imu_streams_from_the_simulation():
    """End to end: sim truth -> streaming foot IMU -> the paper's alignment holds."""
    traj = rotation_about_axis_trajectory([1.0, 0.2, 0.0], 0.3, 0.8)
    sim = Go2Sim(SimConfig(base="mocap"))
    sim.set_base_trajectory(traj)
    sim.reset()
    cfg = random_mounting(4, gyro_noise_deg=0.0, rate=200.0, accel_noise_density=0.0)
    imu = FootImuModel(cfg)
    q0 = stand_pose()
    truth_t, truth_w, samples = [], [], []
    for k in range(1500):
        if k % 20 == 0:
            sim.set_command(q0 + 0.4 * np.sin(2 * np.pi * sim.time + np.arange(12)),
                            0.0, 25.0, 0.5, 0.0)
        w = sim.foot_angular_velocity("RL")
        truth_t.append(sim.time)
        truth_w.append(w)
        samples.extend(imu.update(sim.time, w, sim.foot_specific_force("RL")))
        sim.step()
    b = FootImuModel.to_batch(samples)
    assert len(b.seq) == pytest.approx(1.5 * 200, abs=2)
    w_enc = np.stack([np.interp(b.stamps - cfg.time_offset, truth_t, np.array(truth_w)[:, j])
                      for j in range(3)], axis=1)
    np.testing.assert_allclose(b.gyro @ cfg.rotation.T, w_enc, atol=1e-9)
    assert np.abs(w_enc).max() > 0.5
