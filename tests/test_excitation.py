"""Anti-noise excitation: closed form, Theorem 1, exact gradient, plan quality and safety."""

from __future__ import annotations

import csv

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calib.excitation import (
    FOOT_RADIUS,
    HIP_OFFSET_X,
    HIP_OFFSET_Y,
    TRUNK_BOTTOM_Z,
    TRUNK_HALF_WIDTH,
    ExcitationConfig,
    ExcitationProblem,
    contact_bounds,
    foot_clearance_excess,
    foot_kappa,
    foot_omega,
    foot_position_mirrored,
    initial_guess,
    plan_excitation,
    stance_foot_z,
)
from calib.joints import LEGS, VELOCITY_LIMIT, is_front, is_left, position_limits
from calib.metrics import condition_number
from calib.robot import go2_urdf_path

LEG_Q = {leg: slice(3 * i, 3 * i + 3) for i, leg in enumerate(LEGS)}  # pinocchio = model order


@pytest.fixture(scope="module")
def model():
    m = pin.buildModelFromUrdf(str(go2_urdf_path()))
    return m, m.createData()


@pytest.fixture(scope="module")
def plans():
    return {leg: plan_excitation(ExcitationConfig(leg=leg)) for leg in LEGS}


def _pin_feet(model, leg, q_leg, dq_leg=None):
    """Foot position (base frame) and LOCAL angular velocity of ``leg`` from pinocchio."""
    m, d = model
    fid = m.getFrameId(f"{leg}_foot")
    pos, omg = [], []
    for i in range(len(q_leg)):
        q = np.zeros(m.nq)
        v = np.zeros(m.nv)
        q[LEG_Q[leg]] = q_leg[i]
        if dq_leg is not None:
            v[LEG_Q[leg]] = dq_leg[i]
        pin.forwardKinematics(m, d, q, v)
        pin.updateFramePlacements(m, d)
        pos.append(d.oMf[fid].translation.copy())
        omg.append(pin.getFrameVelocity(m, d, fid, pin.LOCAL).angular.copy())
    return np.array(pos), np.array(omg)


# ---------------------------------------------------------------- closed forms vs pinocchio


@pytest.mark.parametrize("leg", LEGS)
def test_closed_form_matches_pinocchio(model, leg):
    rng = np.random.default_rng(1)
    lo, hi = position_limits(leg)
    q = rng.uniform(lo, hi, size=(20, 3))
    dq = rng.normal(scale=3.0, size=(20, 3))
    _, w_pin = _pin_feet(model, leg, q, dq)
    np.testing.assert_allclose(foot_omega(q, dq), w_pin, atol=1e-12)


@pytest.mark.parametrize("leg", LEGS)
def test_clearance_model_matches_pinocchio(model, leg):
    rng = np.random.default_rng(2)
    lo, hi = position_limits(leg)
    q = rng.uniform(lo, hi, size=(20, 3))
    pos, _ = _pin_feet(model, leg, q)
    hip = np.array([HIP_OFFSET_X * (1 if is_front(leg) else -1),
                    HIP_OFFSET_Y * (1 if is_left(leg) else -1), 0.0])
    mirror = np.array([1.0, 1.0 if is_left(leg) else -1.0, 1.0])
    qm = q * np.array([1.0 if is_left(leg) else -1.0, 1.0, 1.0])
    np.testing.assert_allclose((pos - hip) * mirror, foot_position_mirrored(qm), atol=1e-12)


# ---------------------------------------------------------------- Theorem 1 and kappa


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(-2.5, 0.5))
def test_theorem1_parity_offdiagonals_vanish(seed, s0):
    """Over a whole period, in the foot frame rotated by s0 about y, Sigma_xy = Sigma_xz = 0
    for any coefficients (the y-z term is not forced to zero: the optimiser removes it)."""
    rng = np.random.default_rng(seed)
    f, n = np.pi / 2, 6
    tau = 4.0 * np.arange(4000) / 4000
    k = np.arange(1, n + 1)
    A, B = rng.normal(size=n), rng.normal(size=n)
    ph = np.outer(tau, k * f)
    dh = np.sin(ph) @ A
    s = s0 + np.sin(ph) @ (B / (k * f))
    ds = np.cos(ph) @ B
    q = np.stack([np.zeros_like(s), s, np.zeros_like(s)], -1)
    dq = np.stack([dh, ds, np.zeros_like(s)], -1)
    w = foot_omega(q, dq)
    c, sn = np.cos(s0), np.sin(s0)
    rot = np.array([[c, 0, sn], [0, 1, 0], [-sn, 0, c]])  # R_y(s0)^T applied to row vectors
    sig = np.cov(w @ rot.T, rowvar=False)
    scale = np.trace(sig)
    assert abs(sig[0, 1]) < 1e-9 * scale and abs(sig[0, 2]) < 1e-9 * scale
    # kappa is invariant to that constant rotation
    assert condition_number(w) == pytest.approx(condition_number(w @ rot.T), rel=1e-9)


def test_foot_kappa_basic():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(5000, 3))
    dq = rng.normal(size=(5000, 3))
    dq[:, 0] = 0.0  # hip still: the foot turns about y only
    assert foot_kappa(q, dq) == float("inf")
    w = rng.normal(size=(200_000, 3))
    assert condition_number(w) < 1.05
    with pytest.raises(ValueError):
        foot_kappa(np.zeros((5, 3)), np.zeros((5, 2)))


# ---------------------------------------------------------------- exact gradient


@pytest.mark.parametrize("leg,scale", [("FL", 1.0), ("RR", 2.5)])
def test_gradient_matches_finite_differences(leg, scale):
    """scale 2.5 drives the motion through the position, velocity and clearance penalties."""
    cfg = ExcitationConfig(leg=leg, n_basis=6, grid_rate=100.0,
                           velocity_fraction=0.5 if scale == 1 else 0.05)
    q0m = cfg.q0() * np.array([1.0 if is_left(leg) else -1.0, 1.0, 1.0])
    prob = ExcitationProblem(cfg, q0m)
    th = initial_guess(cfg, q0m, np.random.default_rng(7))
    th[: 3 * cfg.n_basis] *= scale
    if scale > 1:
        v = prob.violations(th)
        assert v["position"] > 0 and v["velocity"] > 0 and v["trunk"] > 0 and v["reach"] > 0
    _, g = prob.value_grad(th)
    h = 1e-6
    g_fd = np.array([(prob.value_grad(th + h * e)[0] - prob.value_grad(th - h * e)[0]) / (2 * h)
                     for e in np.eye(len(th))])
    assert np.linalg.norm(g - g_fd) / np.linalg.norm(g) < 1e-5


# ---------------------------------------------------------------- plans


@pytest.mark.parametrize("leg", LEGS)
def test_plan_reaches_kappa_fast(plans, leg):
    p = plans[leg]
    assert p.kappa <= 1.02
    assert p.process_time < 2.0
    for rate in (100.0, 173.0, 250.0, 1000.0):
        assert p.steady_kappa(rate) <= 1.02
    # the foot turns at a useful rate, not a vanishing one
    t, q, dq = p.sample(200.0)
    steady = (t >= p.steady_window[0]) & (t < p.steady_window[1])
    assert np.all(foot_omega(q[steady], dq[steady]).std(0) > 0.5)


@pytest.mark.parametrize("leg", LEGS)
def test_plan_limits_and_smoothness(plans, leg):
    p = plans[leg]
    cfg = p.config
    t, q, dq = p.sample(1000.0)
    lo, hi = position_limits(leg)
    assert np.all(q >= lo + cfg.position_margin - 1e-9)
    assert np.all(q <= hi - cfg.position_margin + 1e-9)
    assert np.all(np.abs(dq) <= VELOCITY_LIMIT * cfg.velocity_fraction)
    # starts and ends at q0 at rest
    assert p.duration == pytest.approx(2 * cfg.ramp + cfg.periods * cfg.period)
    np.testing.assert_allclose(q[0], p.q0, atol=1e-12)
    np.testing.assert_allclose(q[-1], p.q0, atol=1e-12)
    np.testing.assert_allclose(dq[[0, -1]], 0.0, atol=1e-12)
    np.testing.assert_allclose(p.accelerations(np.array([0.0, p.duration])), 0.0, atol=1e-9)
    # velocities and accelerations are the derivatives (C2: accelerations continuous)
    np.testing.assert_allclose(np.gradient(q, t, axis=0)[1:-1], dq[1:-1], atol=2e-4)
    acc = p.accelerations(t)
    # (atol: the jerk jumps where a ramp meets the steady part, C2 is not C3)
    np.testing.assert_allclose(np.gradient(dq, t, axis=0)[1:-1], acc[1:-1], atol=2e-2)
    assert np.max(np.abs(np.diff(acc, axis=0))) < 0.2  # 1 ms steps
    t0, t1 = p.steady_window
    for tj in (t0, t1):
        a = p.accelerations(np.array([tj - 1e-7, tj + 1e-7]))
        np.testing.assert_allclose(a[0], a[1], atol=1e-4)
    # the steady part is exactly the periodic motion
    ts = np.linspace(t0, t1 - p.period, 50)
    np.testing.assert_allclose(p.positions(ts), p.positions(ts + p.period), atol=1e-12)


@pytest.mark.parametrize("leg", LEGS)
def test_plan_keeps_the_lifted_foot_clear(model, plans, leg):
    p = plans[leg]
    cfg = p.config
    _, q, _ = p.sample(50.0)
    pos, _ = _pin_feet(model, leg, q)
    hip = np.array([HIP_OFFSET_X * (1 if is_front(leg) else -1),
                    HIP_OFFSET_Y * (1 if is_left(leg) else -1), 0.0])
    rel = (pos - hip) * np.array([1.0, 1.0 if is_left(leg) else -1.0, 1.0])
    # above the stance feet by the clearance (base level, stance legs at the stand pose)
    assert np.all(rel[:, 2] >= stance_foot_z() + cfg.ground_clearance - 1e-9)
    # never inside the band beside the trunk at trunk height
    at_trunk = rel[:, 2] > TRUNK_BOTTOM_Z - FOOT_RADIUS - cfg.body_clearance
    y_min = TRUNK_HALF_WIDTH - HIP_OFFSET_Y + FOOT_RADIUS + cfg.body_clearance
    assert np.all(rel[at_trunk, 1] >= y_min - 1e-9)
    assert np.all(np.abs(rel[:, 0]) <= cfg.reach_x + 1e-9)


def test_plan_is_deterministic_and_mirrored(plans):
    again = plan_excitation(ExcitationConfig(leg="FL"))
    np.testing.assert_array_equal(again.A, plans["FL"].A)
    np.testing.assert_array_equal(again.B, plans["FL"].B)
    other = plan_excitation(ExcitationConfig(leg="FL", seed=3))
    assert not np.array_equal(other.A, plans["FL"].A) and other.kappa <= 1.02
    # a right leg is the mirror image of the left one (hip sign flips)
    np.testing.assert_allclose(plans["FR"].A, -plans["FL"].A, atol=1e-12)
    np.testing.assert_allclose(plans["FR"].B, plans["FL"].B, atol=1e-12)


def test_other_settings_still_reach_the_target():
    for cfg in (ExcitationConfig(leg="RL", t_r=1.0, n_basis=5),
                ExcitationConfig(leg="FR", periods=1, ramp=0.5, velocity_fraction=0.2)):
        p = plan_excitation(cfg)
        assert p.kappa <= 1.02
        assert p.period == pytest.approx(8 * cfg.t_r)
        assert p.f == pytest.approx(np.pi / (4 * cfg.t_r))
        assert p.duration == cfg.duration == 2 * cfg.ramp + cfg.periods * 8 * cfg.t_r
        assert p.steady_window == pytest.approx((cfg.ramp, cfg.duration - cfg.ramp))
        _, _, dq = p.sample(500.0)
        assert np.all(np.abs(dq) <= VELOCITY_LIMIT * cfg.velocity_fraction)


def test_to_csv(tmp_path, plans):
    p = plans["RR"]
    path = p.to_csv(tmp_path / "exc.csv", rate_hz=100.0)
    with open(path) as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["t", "q_RR_hip", "q_RR_thigh", "q_RR_calf",
                       "dq_RR_hip", "dq_RR_thigh", "dq_RR_calf"]
    data = np.array(rows[1:], dtype=float)
    t, q, dq = p.sample(100.0)
    np.testing.assert_allclose(data[:, 0], t, atol=1e-6)
    np.testing.assert_allclose(data[:, 1:4], q, atol=1e-8)
    np.testing.assert_allclose(data[:, 4:7], dq, atol=1e-8)


def test_the_grid_sees_every_harmonic_and_the_audit_checks_between_its_points(plans):
    # 40 terms of a 0.32 s period on 64 points aliased: kappa 1.0 there, 1421 in the motion
    cfg = ExcitationConfig(leg="FL", t_r=0.04, n_basis=40)
    assert ExcitationProblem(cfg, cfg.q0()).N == 8 * 40  # FL: its mirror is the identity
    for plan in plans.values():  # the default plans: the grid told the truth
        a = plan.audit()
        assert a["kappa"] == pytest.approx(plan.kappa, rel=1e-6)
        assert a["position_excess"] == 0 and a["velocity_excess"] == 0
        assert a["floor_excess"] == 0 and a["trunk_excess"] == 0


def test_the_audit_refuses_a_foot_that_goes_into_the_floor_or_the_trunk(plans):
    """The optimiser keeps its clearances on the grid; the audit, which a lift schedule and the
    CLI ask before a plan plays, checked only the joints' limits between the grid's points."""
    import dataclasses

    hard = contact_bounds()
    assert hard["z_min"] == stance_foot_z()
    lifted = np.array([[0.0, 1.1, -2.3]])  # the tripod's lifted pose: clear of both
    assert foot_clearance_excess(lifted, **hard) == (0.0, 0.0)
    folded_in = np.array([[-0.9, 2.5, -2.6]])  # hip inward, the foot up at the trunk's side
    floor, trunk = foot_clearance_excess(folded_in, **hard)
    assert floor == 0 and trunk > 0.02
    # the knee opened 0.8 rad over the whole motion: every joint inside its limits, the foot
    # 17 mm below the stance feet's plane
    plan = plans["FR"]
    sunk = dataclasses.replace(plan, s0=plan.s0 + 0.8, c0=plan.c0 + 0.8)
    a = sunk.audit()
    assert a["position_excess"] == 0 and a["velocity_excess"] == 0
    assert a["floor_excess"] > 0.01 and a["trunk_excess"] == 0
    assert any("into the floor" in why for why in sunk.problems())
    assert plan.problems() == []


def test_a_plan_the_optimiser_could_not_bring_to_kappa_1_is_not_played():
    """The optimiser returns its best feasible start whatever kappa it reached; the CLI refused
    such a plan, a lift schedule played it. Both now ask ExcitationPlan.problems()."""
    from deploy.lift_schedule import LiftSchedule

    poor = plan_excitation(ExcitationConfig(leg="FL", t_r=0.04, n_basis=4))
    assert poor.problems() and "kappa" in poor.problems()[0]
    sched = LiftSchedule.from_metadata({"t_r": 0.04, "n_basis": 4.0, "periods": 1,
                                        "seed": 0.0})
    with pytest.raises(ValueError, match="excitation for FL cannot be played: the optimiser"):
        sched.plan("FL")
    # a JSON's whole-number floats are the integers (numpy refused them at plan time)
    cfg = sched.excitation_config("FL")
    assert (cfg.n_basis, cfg.seed) == (4, 0) and isinstance(cfg.n_basis, int)


def test_bad_inputs():
    with pytest.raises(ValueError, match="seed"):
        ExcitationConfig(leg="FL", seed=-1)
    with pytest.raises(ValueError):
        ExcitationConfig(leg="XX")
    with pytest.raises(ValueError):
        ExcitationConfig(leg="FL", t_r=0.0)
    with pytest.raises(ValueError):
        ExcitationConfig(leg="FL", n_basis=1)
    with pytest.raises(ValueError):
        ExcitationConfig(leg="FL", start_pose=(0.0, 1.0))
    with pytest.raises(ValueError, match="joint limits"):
        plan_excitation(ExcitationConfig(leg="FL", start_pose=(0.0, 1.0, -0.8)))
    with pytest.raises(ValueError, match="clearance"):  # the stand pose: foot on the ground
        plan_excitation(ExcitationConfig(leg="FL", start_pose=(0.0, 0.67, -1.3)))
