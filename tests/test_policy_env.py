"""policy_train env: shapes, action/joint order, the lifted-leg override, domain randomisation,
terminations, and the signs of the reward terms on hand-made states."""

import mujoco
import numpy as np
import pytest

from calib.excitation import ExcitationConfig
from calib.joints import MODEL_LEGS, model_to_sdk
from deploy.lift_schedule import LiftSchedule, blend_accelerations
from policy_train import rewards as R
from policy_train.config import DR_GROUPS, EnvConfig, RewardConfig, TrainConfig
from policy_train.env import TripodEnv
from policy_train.model import ARMATURE


@pytest.fixture(scope="module")
def env():
    return TripodEnv(EnvConfig(num_envs=6, plans_per_leg=1, seed=1, threads=1))


def test_reset_step_shapes(env):
    obs = env.observations()
    assert obs["policy"].shape == (6, 49) and obs["policy"].dtype == np.float32
    assert obs["critic"].shape[0] == 6 and obs["critic"].shape[1] > 49
    _, r, d, ex = env.step(np.zeros((6, 12)))
    assert r.shape == (6,) and d.shape == (6,) and np.isfinite(r).all()
    assert ex["time_outs"].shape == (6,)
    assert env.max_episode_length == 1000  # 20 s at 50 Hz


def test_action_is_delta_target_in_sdk_order():
    e = TripodEnv(EnvConfig(num_envs=2, plans_per_leg=1, seed=2, threads=1))
    before = e.target.copy()
    a = np.zeros((2, 12))
    a[:, 0] = 1.0  # SDK index 0 = FR_hip = model index 3
    a[:, 3] = 5.0  # FL_hip (model 0), clipped to action_clip
    e.lift_leg[:] = -1  # no override in this step
    e.step(a)
    d = e.target - before
    np.testing.assert_allclose(d[:, 3], e.cfg.action_scale)
    np.testing.assert_allclose(d[:, 0], e.cfg.action_scale * e.cfg.action_clip)
    assert np.allclose(np.delete(d, [0, 3], axis=1), 0.0)
    np.testing.assert_array_equal(e.observations()["critic"][:, 33:45], e.actions)


def test_target_lead_max_holds_each_target_within_it_of_its_joint():
    """``target_lead_max`` (deploy.action, the JSON's action.target_lead_max): pushing every
    joint the same way, no target gets further than the bound from where its joint stood when
    the action came; without it the targets run to the soft limits, as before."""
    lead = np.full(12, 0.15)
    e = TripodEnv(EnvConfig(num_envs=2, plans_per_leg=1, seed=2, threads=1,
                            p_reference_start=0.0, target_lead_max=tuple(lead)))
    free = TripodEnv(EnvConfig(num_envs=2, plans_per_leg=1, seed=2, threads=1,
                               p_reference_start=0.0))
    a = np.ones((2, 12))
    for _ in range(8):
        for x in (e, free):
            x.lift_leg[:] = -1  # no override in these steps
        q = e.qpos[:, 7:19].copy()
        e.step(a)
        free.step(a)
        assert np.all(e.target - q <= lead + 1e-12)
    assert (free.target - free.qpos[:, 7:19]).max() > 0.3  # wound up past it
    with pytest.raises(ValueError, match="target_lead_max"):
        TripodEnv(EnvConfig(num_envs=1, plans_per_leg=1, threads=1, target_lead_max=(0.1,) * 11))


def test_calf_upper_margin_moves_only_the_calves_extension_clamp():
    from calib.joints import MODEL_LEGS, SDK_LEGS, position_limits

    lo0, hi0 = EnvConfig().soft_limits(SDK_LEGS)
    np.testing.assert_allclose(hi0[2], position_limits("FR")[1][2] - 0.05)
    lo, hi = EnvConfig(calf_upper_margin=-0.02).soft_limits(SDK_LEGS)
    calves = [2, 5, 8, 11]
    np.testing.assert_allclose(hi[calves], hi0[calves] + 0.07)  # 0.02 beyond the limit
    np.testing.assert_array_equal(np.delete(hi, calves), np.delete(hi0, calves))
    np.testing.assert_array_equal(lo, lo0)
    cfg = TrainConfig()
    cfg.env.calf_upper_margin = 0.01
    assert TrainConfig.from_dict(cfg.to_dict()).env.calf_upper_margin == 0.01
    # the env clamps the targets there: a policy pushing every calf up ends on the clamp
    e = TripodEnv(EnvConfig(num_envs=1, plans_per_leg=1, seed=2, threads=1, calf_upper_margin=0.01,
                            p_reference_start=0.0))
    e.lift_leg[:] = -1  # no override in this step
    a = np.zeros((1, 12))
    a[:, calves] = 1.0  # 0.1 rad per step, from the start's -1.3 to -1.6 rad
    for _ in range(10):
        e.step(a)
        e.lift_leg[:] = -1
    np.testing.assert_allclose(e.target[0, [2, 5, 8, 11]],
                               EnvConfig(calf_upper_margin=0.01).soft_limits(MODEL_LEGS)[1][calves])


def test_actuation_latency_holds_the_targets_that_many_physics_steps():
    """A target reaches the motors ``latency`` physics steps after the policy step that issued
    it, also past one policy step (4 physics steps); the older targets fill the gap."""
    cfg = EnvConfig(num_envs=3, plans_per_leg=1, seed=2, threads=1)
    cfg.dr.latency_steps = (0, 6)
    e = TripodEnv(cfg)
    e.latency[:] = [0, 3, 6]
    e.lift_leg[:] = -1
    seen = []
    step = e.batch.step
    e.batch.step = lambda **kw: (seen.append(e.ctrl[:, 3].copy()), step(**kw))
    old = e.target[:, 3].copy()
    a = np.zeros((3, 12))
    a[:, 0] = 1.0  # FR_hip (model index 3)
    e.step(a)
    new = e.target[:, 3].copy()
    e.step(np.zeros((3, 12)))
    seen = np.array(seen)  # (8 physics steps, 3 envs)
    assert seen.shape == (8, 3) and np.all(new - old > 0.05)
    for i, lat in enumerate([0, 3, 6]):
        np.testing.assert_array_equal(seen[:lat, i], old[i])
        np.testing.assert_array_equal(seen[lat:, i], new[i])


def test_actuation_frames_are_the_state_where_the_action_reaches_the_motors():
    """``actuation_frames``: the clean frame when the step's action takes effect. With no
    latency it is the frame the action was chosen on; with one policy step of latency it is the
    next frame (the previous action still the last issued); in between it is a state the action
    itself cannot have moved, so two different actions meet the same frame."""
    def run(latency, action):
        cfg = EnvConfig(num_envs=3, plans_per_leg=1, seed=5, threads=1)
        cfg.dr.latency_steps = (0, 4)
        e = TripodEnv(cfg)
        e.latency[:] = latency
        e.actuation_frames = np.zeros((3, 49), dtype=np.float32)
        e.step(np.full((3, 12), 0.3))  # a previous action unlike the next
        before = e.observations()["critic"][:, :49]
        after = e.step(np.full((3, 12), action))[0]["critic"][:, :49]
        return e.actuation_frames.copy(), before, after

    pa = slice(33, 45)  # previous actions
    frames, before, _ = run(0, 1.0)
    np.testing.assert_allclose(frames, before, atol=1e-6)
    frames, before, after = run(4, 1.0)
    np.testing.assert_allclose(np.delete(frames, pa, 1), np.delete(after, pa, 1), atol=1e-6)
    np.testing.assert_allclose(frames[:, pa], before[:, pa], atol=1e-6)
    frames, before, after = run(2, 1.0)
    other, _, after_other = run(2, -1.0)
    np.testing.assert_allclose(frames, other, atol=1e-6)
    assert not np.allclose(after, after_other, atol=1e-3)
    assert not np.allclose(np.delete(frames, pa, 1), np.delete(before, pa, 1), atol=1e-4)
    assert not np.allclose(np.delete(frames, pa, 1), np.delete(after, pa, 1), atol=1e-4)


def test_lifted_leg_follows_schedule():
    # zero actions let the body sag onto a thigh: keep that episode running here
    e = TripodEnv(EnvConfig(num_envs=2, plans_per_leg=1, seed=4, threads=1,
                            terminate_on_contact=False, p_reference_start=0.0))
    e.p_excite = 1.0
    e._sample_commands(np.arange(2), legs=np.array([0, 3]))
    n = int((e.cfg.shift_s + e.cfg.lift_s + e.cfg.hold_s) / e.dt) + 10
    for _ in range(n):
        e.step(np.zeros((2, 12)))
    assert (e.phase == 3).all()
    assert np.all(np.abs(e.lift_err) < 0.3)  # zero actions: the body sags, the leg still tracks
    # the error is against the excitation plan at the instant the state is read, the step's
    # end (against the last substep's start it was mostly dq_des x 5 ms: a timing artefact)
    te = e.lift_t - e.lift_dur[:, :3].sum(1)
    q_plan, _ = e.pool.sample(e.lift_plan, te)
    np.testing.assert_allclose(e.lift_q_des, q_plan, atol=1e-9)
    j = np.array([[0, 1, 2], [9, 10, 11]])
    np.testing.assert_allclose(e.q[np.arange(2)[:, None], j] - e.lift_q_des, e.lift_err, atol=1e-9)
    obs = e.observations()["policy"]
    np.testing.assert_allclose(obs[:, 48], 0.25 * np.array([1, 4]))


def test_every_substeps_lift_command_is_the_schedule_at_that_substep():
    """Each physics step of a policy step gets the lifted leg's plan and feed-forward of its
    own instant, a leg whose shift ends part-way through a step is latched at that substep,
    and one whose schedule ends there goes back to the policy's target from where it stands
    then, the other joints staying on the policy's targets throughout."""
    cfg = EnvConfig(num_envs=2, plans_per_leg=1, seed=4, threads=1, terminate_on_contact=False,
                    p_reference_start=0.0, shift_s=1.01,  # the shift ends at a step's substep 2
                    p_excite=0.0, hold_range=(2.0, 2.0), lower_s=0.615)  # ends part-way too
    cfg.dr.enabled = False  # nominal gains and no latency: the motors get the command as sent
    e = TripodEnv(cfg)
    e._sample_commands(np.arange(2), legs=np.array([1, 2]))
    sent, launch = [], e._launch

    def record(ids):
        sent.append((e.ctrl.copy(), e.qpos.copy(), e.lift_latched.copy(),
                     e.gainprm[:, :, 0].copy(), -e.biasprm[:, :, 2]))
        return launch(ids)

    e._launch = record
    dt, ids = cfg.physics_dt, np.arange(2)
    legs = e.lift_leg.copy()
    joints = 3 * legs[:, None] + np.arange(3)
    checked, latched_at, ended_at = 0, set(), set()
    while (e.lift_leg >= 0).any():
        t0, g = e.lift_t.copy(), e.gravity_b.copy()
        lifted, target = e.lift_leg >= 0, e.target.copy()  # zero actions keep the target
        sent.clear()
        e.step(np.zeros((2, 12)))
        stand = {}
        for s, (ctrl, qpos, latched, kp, kd) in enumerate(sent):
            latched_at |= {s for i in ids if latched[i] and not (sent[s - 1][2][i] if s else True)}
            t = t0 + s * dt
            qd, dqd, ph = e._plan(ids, t)
            k = e.lift_plan
            ddq_plan = e.pool.sample_acceleration(k, t - e.lift_dur[:, :3].sum(1))
            ddq = blend_accelerations(t, e.lift_dur, e.lift_q_start, e.pool.q0[k],
                                      np.where(e.lift_excite[:, None], ddq_plan, 0.0))
            policy = np.ones((2, 12), dtype=bool)  # joints on the policy's target
            policy[ids[lifted & (ph >= 1)][:, None], joints[lifted & (ph >= 1)]] = False
            np.testing.assert_array_equal(ctrl[policy], target[policy])
            # the actuators' gains: the schedule's on the lifted leg from its lift to its end
            # (written only where they change), the policy's everywhere else
            sched = ~policy & (ph[:, None] <= 4)
            np.testing.assert_array_equal(kp[sched], cfg.lift_kp)
            np.testing.assert_array_equal(kd[sched], cfg.lift_kd)
            np.testing.assert_array_equal(kp[~sched], np.broadcast_to(e._kp, (2, 12))[~sched])
            np.testing.assert_array_equal(kd[~sched], np.broadcast_to(e._kd, (2, 12))[~sched])
            for i in np.flatnonzero(lifted & (ph >= 1) & (ph <= 4)):
                tau = LiftSchedule.feedforward_torque(MODEL_LEGS[legs[i]], qd[i], dqd[i],
                                                      ddq[i], g[i])[0]
                want = qd[i] + cfg.lift_kd / cfg.lift_kp * dqd[i] + tau / cfg.lift_kp
                np.testing.assert_allclose(ctrl[i, joints[i]], want, atol=1e-12)
                checked += 1
            for i in np.flatnonzero(lifted & (ph == 5)):
                if i not in stand:  # the policy's target from where the leg stands now
                    stand[i] = qpos[i, 7 + joints[i]]
                    ended_at.add(s)
                np.testing.assert_array_equal(ctrl[i, joints[i]], stand[i])
    # both part-way through a step (where a step's first substep would not tell)
    assert latched_at == {2} and ended_at and 0 not in ended_at and checked > 400


def test_blocks_step_every_env_as_one_block_does():
    """``EnvConfig.blocks``: the envs stepped in blocks, one block's commands computed while
    another's physics runs on a second thread, take the same steps as in one block."""
    def run(blocks):
        e = TripodEnv(EnvConfig(num_envs=7, plans_per_leg=1, seed=3, threads=1, blocks=blocks,
                                p_reference_start=0.6, lift_adapt=True))
        e.actuation_frames = np.zeros((7, 49), dtype=np.float32)
        rng = np.random.default_rng(0)
        out = []
        for _ in range(60):
            obs, rew, done, _ = e.step(rng.normal(0, 0.3, (7, 12)))
            out.append(np.concatenate([obs["critic"].ravel(), rew, done, e.qpos.ravel(),
                                       e.actuation_frames.ravel()]))
        assert (e._physics is None) == (blocks == 1)
        return np.array(out)

    np.testing.assert_array_equal(run(1), run(3))
    with pytest.raises(ValueError, match="blocks"):
        TripodEnv(EnvConfig(num_envs=2, plans_per_leg=1, threads=1, blocks=-1))
    # a training run's blocks on an evaluation of fewer envs: one env a block
    assert len(TripodEnv(EnvConfig(num_envs=2, plans_per_leg=1, threads=1, blocks=4))._blocks) == 2


def test_feedforward_torque_cuts_the_lifted_legs_lag():
    def tracking_rms(feedforward):
        # balanced tripods in hold, then the excitation; zero actions keep the stance
        e = TripodEnv(EnvConfig(num_envs=4, plans_per_leg=1, seed=5, threads=1,
                                p_reference_start=1.0, p_reference_shift=0.0,
                                lift_feedforward=feedforward))
        err = []
        for _ in range(40):
            e.step(np.zeros((4, 12)))
            ok = np.isin(e.phase, (2, 3))
            err.append(e.lift_err[ok])
        assert not e.other_touch.any()
        return np.sqrt(np.mean(np.square(np.concatenate(err))))

    plain, ff = tracking_rms(False), tracking_rms(True)
    assert ff < 0.5 * plain, (ff, plain)


def test_tracking_adapter_cuts_the_lag_of_joint_friction_the_model_lacks():
    """``lift_adapt`` (the evaluation plays the JSON's ``adapt``): on joints with 0.5 N m of
    dry friction, once fitted (2 s into the excitation, faded in by 2.5 s) the lifted leg tracks
    its plan closer; the adapter's torque is off outside the excitation's envs. No latency: a
    delay the adapter finds is not fed forward (the next test), and would stay in the error."""
    from policy_train.config import DRConfig

    def tracking_rms(adapt):
        # 8 robots: each starts in a hold of its own length, and only some of them are 2.6 s
        # into their excitation within these 6 s (4 gave 46 samples once inertias were drawn)
        e = TripodEnv(EnvConfig(num_envs=8, plans_per_leg=1, seed=5, threads=1,
                                p_reference_start=1.0, p_reference_shift=0.0, lift_adapt=adapt,
                                dr=DRConfig(latency_steps=(0, 0))))
        e._joint_fric[:, 6:] = 0.5
        err = []
        for _ in range(300):
            e.step(np.zeros((8, 12)))
            te = e.lift_t - e.lift_dur[:, :3].sum(1)
            fitted = (e.phase == 3) & (te > 2.6)
            err.append(e.lift_err[fitted])
            if adapt:
                assert not e.lift_applied[(e.phase < 3) | (e.phase > 4)].any()
        assert len(np.concatenate(err)) > 50 and not e.other_touch.any()
        return np.sqrt(np.mean(np.square(np.concatenate(err))))

    plain, adapted = tracking_rms(False), tracking_rms(True)
    assert adapted < 0.6 * plain, (adapted, plain)


def test_tracking_adapter_finds_the_actuation_latency_from_the_motor_torque():
    """30 ms of actuation latency (6 physics steps): from the actuators' force the adapter finds
    it within a physics step, and learns no damping from the lag it makes. (The robots stand
    on zero actions, and tip within a few seconds of excitation under such a delay: the fit
    starts 0.5 s in.)"""
    from deploy.tracking_adapter import AdapterConfig, TrackingAdapter
    from policy_train.config import DRConfig
    cfg = EnvConfig(num_envs=8, plans_per_leg=1, seed=5, threads=1, p_reference_start=1.0,
                    p_reference_shift=0.0, lift_adapt=True, dr=DRConfig(latency_steps=(6, 6)))
    e = TripodEnv(cfg)
    e.adapter = TrackingAdapter(cfg.lift_kp, cfg.lift_kd, 8, AdapterConfig(start_s=0.5))
    fitted = np.zeros(8, dtype=bool)
    for _ in range(100):
        e.step(np.zeros((8, 12)))
        fitted |= e.adapter.fitted
        if fitted.sum() >= 3:
            break
    fitted = e.adapter.fitted
    assert fitted.sum() >= 3
    assert np.all(np.abs(e.adapter.delay[fitted] - 0.030) <= 0.005), e.adapter.delay[fitted]
    # a lag read as damping would be kp d = 2.4 N m s/rad
    assert np.abs(e.adapter.coef[fitted][..., 0]).max() < 0.5


def test_reference_start_is_a_level_tripod_in_hold():
    e = TripodEnv(EnvConfig(num_envs=8, plans_per_leg=1, seed=5, threads=1,
                            p_reference_start=1.0, p_reference_shift=0.0))
    assert (e.phase == 2).all() and (e.lift_leg >= 0).all() and e.lift_latched.all()
    tilt = np.arccos(np.clip(-e.gravity_b[:, 2], -1, 1))
    assert np.all(tilt < 1e-6)
    np.testing.assert_allclose(e.base_pos[:, 2], e.cfg.rewards.base_height_target + 0.003)
    for _ in range(5):  # 0.1 s of zero actions: balanced, so still nearly level
        e.step(np.zeros((8, 12)))
    tilt = np.arccos(np.clip(-e.gravity_b[:, 2], -1, 1))
    assert np.all(np.degrees(tilt) < 2.0)
    assert not e.lift_touch.any() and not e.other_touch.any()
    # the leg goes back to the four-leg stance it was reset to (q_start is the reset pose)
    np.testing.assert_allclose(e.lift_q_start[:, 1], np.take_along_axis(
        e.default_pose.reshape(4, 3)[:, 1][None].repeat(8, 0), e.lift_leg[:, None], 1)[:, 0],
        atol=e.cfg.dr.init_joint_noise + 1e-9)


def test_reference_start_in_the_shift_phase_has_four_feet_down():
    e = TripodEnv(EnvConfig(num_envs=8, plans_per_leg=1, seed=8, threads=1,
                            p_reference_start=1.0, p_reference_shift=1.0))
    assert (e.phase == 0).all() and not e.lift_latched.any()
    assert np.all((e.lift_t >= 0) & (e.lift_t <= e.cfg.shift_s))
    z = e.sensordata[:, e.tm.foot_pos + 2]  # foot sites: on the floor or a few mm above
    assert np.all((z > 0.022 - 0.006) & (z < 0.022 + 0.012))
    for _ in range(4):  # 80 ms: the feet have settled on the floor, nothing else touches
        e.step(np.zeros((8, 12)))
    assert e.foot_touch.all() and not e.other_touch.any()


def test_lift_leg_weights_pick_the_lifted_leg():
    e = TripodEnv(EnvConfig(num_envs=16, plans_per_leg=1, seed=7, threads=1, p_no_lift=0.0,
                            lift_leg_weights=(0.0, 1.0, 0.0, 0.0)))
    assert (e.lift_leg == 1).all()  # FR (model index 1), reference starts included
    with pytest.raises(ValueError, match="lift_leg_weights"):
        TripodEnv(EnvConfig(num_envs=2, plans_per_leg=1, threads=1, lift_leg_weights=(0, 0, 0, 0)))


def test_contact_other_than_feet_ends_the_episode():
    from types import SimpleNamespace
    e = TripodEnv(EnvConfig(num_envs=2, plans_per_leg=1, seed=6, threads=1,
                            p_reference_start=0.0))
    e.step(np.zeros((2, 12)))
    assert e.geom_touch.shape == (2, len(e.tm.collision_geoms))
    assert np.array_equal(e.other_touch, e.geom_touch.any(1))
    e.other_touch[:] = [True, False]
    _, _, term = R.compute_rewards(e)
    assert term[0] and not term[1]
    e.cfg = SimpleNamespace(**{**vars(e.cfg), "terminate_on_contact": False})
    _, _, term = R.compute_rewards(e)
    assert not term[0]


def test_a_contact_counts_by_its_whole_force():
    """More than 1 N of net contact force with the floor, whatever its direction: a push along
    world y counts as one along z does (the sensor's netforce is in the world frame)."""
    e = TripodEnv(EnvConfig(num_envs=2, plans_per_leg=1, seed=6, threads=1,
                            p_reference_start=0.0))
    e.step(np.zeros((2, 12)))
    a = int(e.tm.other_contact[0])
    e.geom_touch[:] = False
    e.sensordata = e.sensordata.copy()    # the batch's own rows are read-only
    e.sensordata[:, a:a + 4] = 0.0
    e.sensordata[0, a + 2] = 1.5          # 1.5 N along y alone
    e.sensordata[1, a + 1:a + 4] = 0.5    # 0.87 N in all
    e._contacts(slice(None))
    assert e.geom_touch[0, 0] and not e.geom_touch[1, 0]


def test_domain_randomisation_applied(env):
    assert np.ptp(env.kp_s) > 0 and np.ptp(env.friction) > 0 and np.ptp(env.strength) > 0
    lo, hi = env.cfg.dr.friction
    assert np.all((env.friction >= lo) & (env.friction <= hi))
    fr = env.batch.expanded("geom_friction")[:, env._feet_geoms[0], 0]
    np.testing.assert_allclose(fr, env.friction)
    mass = env.batch.expanded("body_mass")[:, env.tm.base_body]
    assert np.ptp(mass) > 0.1
    # every body keeps its density: inertia scaled as its mass (the base's 2 kg is not a point)
    masses, inertia = env.batch.expanded("body_mass"), env.batch.expanded("body_inertia")
    ratio = masses[:, 1:] / env._masses_nominal[1:]
    assert np.ptp(ratio) > 0.05
    np.testing.assert_allclose(inertia[:, 1:], env._inertia_nominal[1:] * ratio[:, :, None])
    # joint armature per robot (all 12 joints alike), inside the range; the free base has none
    arm = env.batch.expanded("dof_armature")
    lo, hi = env.cfg.dr.armature
    assert np.all(arm[:, :6] == 0) and np.all(arm[:, 6:] == arm[:, 6:7])
    assert np.all((arm[:, 6] >= lo) & (arm[:, 6] <= hi)) and np.ptp(arm[:, 6]) > 0.002
    assert set(np.unique(env.latency)) <= set(range(5))
    gain = env.batch.expanded("actuator_gainprm")[:, 0, 0]
    assert np.ptp(gain) > 0
    off = TripodEnv(EnvConfig(num_envs=3, plans_per_leg=1, seed=1, threads=1,
                              dr=EnvConfig().dr.__class__(enabled=False)))
    assert np.all(off.kp_s == 1.0) and np.all(off.latency == 0)
    s1, s2 = off.signals(noise=True), off.signals(noise=False)
    np.testing.assert_array_equal(s1["joint_pos"], s2["joint_pos"])
    assert not np.array_equal(env.signals(True)["joint_pos"], env.signals(False)["joint_pos"])
    np.testing.assert_array_equal(env.signals(False)["joint_pos"], model_to_sdk(env.q))


def test_joint_friction_is_drawn_per_joint_only_when_on(env):
    # off by default (v7's configuration): no friction, and the draws of older configs stand
    assert np.all(env.batch.expanded("dof_frictionloss") == 0)
    cfg = EnvConfig(num_envs=4, plans_per_leg=1, seed=1, threads=1)
    cfg.dr.joint_friction = (0.1, 0.4)
    on = TripodEnv(cfg)
    fl = on.batch.expanded("dof_frictionloss").copy()
    assert np.all(fl[:, :6] == 0)  # the free base has none
    assert np.all((fl[:, 6:] >= 0.1) & (fl[:, 6:] <= 0.4)) and np.ptp(fl[0, 6:]) > 0.05
    on.reset_idx(np.array([0]))
    assert not np.array_equal(on.batch.expanded("dof_frictionloss")[0], fl[0])
    np.testing.assert_array_equal(on.batch.expanded("dof_frictionloss")[1:], fl[1:])


def test_floor_that_gives_sinks_the_feet_and_is_drawn_only_when_on(env):
    """DRConfig.floor_timeconst: the floor's solref time constant drawn per env within its
    range, its solmix governing its contacts, the other geoms untouched; the feet sink deeper
    than on the model's own floor; off by default with the model's contact shared; a time
    constant under two physics steps refused."""
    assert env.batch.expanded("geom_solref") is None
    assert env.batch.expanded("geom_solmix") is None

    def standing(timeconst):
        cfg = EnvConfig(num_envs=3, plans_per_leg=1, seed=7, threads=1)
        cfg.dr = cfg.dr.without(*DR_GROUPS).with_settings(
            {"init_joint_noise": 0.0, "floor_timeconst": timeconst})
        e = TripodEnv(cfg)
        for _ in range(25):  # 0.5 s: settled; some envs may have begun a lift
            e.step(np.zeros((3, 12)))
        return e, e.sensordata[:, e.tm.foot_pos + 2]

    hard, z_hard = standing((0.0, 0.0))
    assert hard.batch.expanded("geom_solref") is None
    soft, z_soft = standing((0.045, 0.045))
    floor = soft._floor_geom
    solref, solmix = soft.batch.expanded("geom_solref"), soft.batch.expanded("geom_solmix")
    np.testing.assert_array_equal(solref[:, floor], [[0.045, 1.0]] * 3)
    np.testing.assert_array_equal(solmix[:, floor], 1e6)
    others = np.arange(soft.tm.model.ngeom) != floor
    np.testing.assert_array_equal(solref[:, others], np.broadcast_to(
        soft.tm.model.geom_solref[others], solref[:, others].shape))
    # the three lowest foot centres of each env (a lift may have begun), m: the sphere's
    # radius, 22 mm, over the floor when it just touches
    low_hard, low_soft = np.sort(z_hard, 1)[:, :3], np.sort(z_soft, 1)[:, :3]
    assert np.all(low_hard > 0.0175), z_hard
    assert np.all(low_soft.mean(1) < 0.017), z_soft
    drawn, _ = standing((0.03, 0.045))
    tc = drawn.batch.expanded("geom_solref")[:, floor, 0]
    assert np.all((tc >= 0.03) & (tc <= 0.045)) and np.ptp(tc) > 0
    with pytest.raises(ValueError, match="two physics steps"):
        standing((0.005, 0.03))


def test_mujocos_default_cone_is_drawn_per_episode_only_when_on(env):
    """DRConfig.default_cone: that fraction of the episodes runs on MuJoCo's default friction
    cone (pyramidal, impratio 1) instead of the model's (elliptic, impratio 100); off by
    default with the model's option shared; a fraction over 1 refused."""
    assert env.batch.expanded("opt.cone") is None
    own = (int(env.tm.model.opt.cone), float(env.tm.model.opt.impratio))
    assert own == (int(mujoco.mjtCone.mjCONE_ELLIPTIC), 100.0)

    def drawn(fraction, n=8):
        cfg = EnvConfig(num_envs=n, plans_per_leg=1, seed=3, threads=1)
        cfg.dr.default_cone = fraction
        e = TripodEnv(cfg)
        return e, e.batch.expanded("opt.cone").copy(), e.batch.expanded("opt.impratio").copy()

    _, cone, imp = drawn(1.0)
    assert np.all(cone == int(mujoco.mjtCone.mjCONE_PYRAMIDAL)) and np.all(imp == 1.0)
    half, cone, imp = drawn(0.5, 16)
    pyr = cone == int(mujoco.mjtCone.mjCONE_PYRAMIDAL)
    assert 0 < pyr.sum() < 16
    np.testing.assert_array_equal(imp, np.where(pyr, 1.0, 100.0))
    half.reset_idx(np.arange(16))  # drawn afresh per episode
    assert not np.array_equal(half.batch.expanded("opt.cone"), cone)
    with pytest.raises(ValueError, match="default_cone"):
        drawn(1.5)


def test_floor_tilt_turns_gravity_and_is_drawn_only_when_on(env):
    """DRConfig.floor_tilt_deg: gravity turned from the floor's normal by the drawn angle, in
    the physics (the centre of mass falls along it), in the projected gravity the policy
    observes and in the tilt; off by default, with the model's gravity untouched."""
    assert np.all(env.down == [0.0, 0.0, -1.0])
    assert env.batch.expanded("opt.gravity") is None  # the model's own gravity, shared
    # and deploy's projected gravity to the last digit: committed evaluations keep their figures
    from deploy.observation import projected_gravity
    np.testing.assert_array_equal(env.gravity_b, projected_gravity(env.quat))
    cfg = EnvConfig(num_envs=3, plans_per_leg=1, seed=7, threads=1)
    cfg.dr.floor_tilt_deg = (10.0, 10.0)
    e = TripodEnv(cfg)
    np.testing.assert_allclose(np.degrees(np.arccos(-e.down[:, 2])), 10.0)
    assert np.ptp(np.arctan2(e.down[:, 1], e.down[:, 0])) > 0.1  # downhill any way
    np.testing.assert_allclose(e.batch.expanded("opt.gravity"), 9.81 * e.down)
    tilt = np.degrees(e.tilt)
    assert np.all(np.abs(tilt - 10.0) < 3.0), tilt  # a body level on the floor leans with it
    expect = np.array([_rot(q).T @ d for q, d in zip(e.qpos[:, 3:7], e.down)])
    np.testing.assert_allclose(e.gravity_b, expect, atol=1e-9)
    # the centre of mass over the floor (the support reward's, refine's capture point) is
    # where gravity carries it: downhill by its height times tan 10 deg
    com = e.subtree_com[:, e.tm.base_body]
    shift = e.com_over_floor()[:, :2] - com[:, :2]
    np.testing.assert_allclose(shift, com[:, 2:3] * np.tan(np.radians(10.0)) * e.down[:, :2]
                               / np.linalg.norm(e.down[:, :2], axis=1, keepdims=True))
    np.testing.assert_array_equal(e.com_xy, e.com_over_floor()[:, :2])
    np.testing.assert_array_equal(env.com_over_floor(), env.subtree_com[:, env.tm.base_body])
    # in the air the centre of mass falls along the drawn gravity, whatever the legs do
    e.qpos[:, 2] += 1.0
    e.qvel[:] = 0.0
    e.batch.forward()
    base = e.tm.base_body
    com = [e.subtree_com[:, base].copy()]
    for _ in range(2):
        e.step(np.zeros((3, 12)))
        com.append(e.subtree_com[:, base].copy())
    accel = (com[2] - 2 * com[1] + com[0]) / e.dt**2
    np.testing.assert_allclose(accel, 9.81 * e.down, atol=0.05)


def _rot(q: np.ndarray) -> np.ndarray:
    """3x3 rotation (body to world) of the unit quaternion q, wxyz."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_fall_terminates():
    e = TripodEnv(EnvConfig(num_envs=2, plans_per_leg=1, seed=5, threads=1))
    e.qpos[0, 2] = 0.08  # base dropped to the floor
    e.qpos[0, 3:7] = [np.cos(0.9), np.sin(0.9), 0, 0]  # rolled ~100 deg
    e.batch.forward()
    _, r, d, ex = e.step(np.zeros((2, 12)))
    assert d[0] and ex["terminated"][0]
    assert r[0] < r[1]


def test_reward_term_signs():
    assert list(R.lift_indicator(np.array([True, True, False]), np.array([False, True, False]))) == [1, -1, 0]
    w0 = np.zeros((2, 3))
    tr = R.track_ang_vel(w0, np.array([[0, 0, 0], [0, 0, 1.0]]), 0.25)
    assert tr[0] == 1.0 and 0 < tr[1] < tr[0]
    v = np.zeros((1, 4, 2))
    v[0, 1] = [0.3, 0.4]
    assert R.slip(v, np.array([[True, True, True, False]])) == pytest.approx(0.5)
    assert R.slip(v, np.array([[True, False, True, True]])) == 0.0
    assert R.collision(np.array([[0.5, 2.0, 3.0]])) == 2.0
    assert R.base_height(np.array([0.33, 0.25]), 0.33)[1] > 0 == R.base_height(np.array([0.33]), 0.33)[0]
    assert R.orientation(np.array([[0, 0, -1.0], [0.2, 0, -0.98]]))[1] > 0
    assert R.lin_vel(np.array([[0.1, 0, 0]])) > 0
    assert R.joint_acc(np.ones((1, 12)), np.zeros((1, 12)), 0.02) > 0
    assert R.torques(np.ones((1, 12))) == 12
    assert R.action_rate(np.ones((1, 12)), np.zeros((1, 12))) == 12
    w = EnvConfig().rewards
    # task terms reward, regularisers penalise
    assert w.lift > 0 and w.track_ang_vel > 0
    for k in ("slip", "termination", "collision", "base_height", "orientation", "lin_vel",
              "joint_acc", "torques", "action_rate"):
        assert getattr(w, k) < 0, k


def test_v2_shaping_terms():
    g = np.array([[0, 0, -1.0], [np.sin(0.1), 0, -np.cos(0.1)]])
    up = R.upright(g, 0.005)
    assert up[0] == 1.0 and 0 < up[1] < 0.2  # 5.7 deg tilt: |g_xy|^2 = 0.00997
    assert list(R.ang_vel_xy(np.array([[0.3, 0.4, 2.0]]))) == [pytest.approx(0.25)]  # yaw free
    z = np.array([R.FOOT_RADIUS, R.FOOT_RADIUS + 0.02, R.FOOT_RADIUS + 0.1, R.FOOT_RADIUS])
    act = np.array([True, True, True, False])
    np.testing.assert_allclose(R.lift_clearance(z, act, 0.04), [1.0, 0.5, 0.0, 0.0])
    feet = np.array([[[0.2, 0.1], [0.2, -0.1], [-0.2, 0.0]]] * 3)  # either winding works
    feet[1] = feet[1, ::-1]
    com = np.array([[0.05, 0.0], [0.05, 0.0], [0.5, 0.0]])
    sm = R.support_margin(com, feet, np.ones(3, bool), 0.03)
    # centroid-ish point: 0.09 m from the rear edges, 0.15 m from the front edge
    assert sm[0] == 0.0 and sm[1] == 0.0
    assert sm[2] == pytest.approx(0.3 + 0.03)  # 0.3 m outside the front edge x = 0.2
    assert R.support_margin(com, feet, np.zeros(3, bool), 0.03).sum() == 0.0
    w = RewardConfig()
    assert w.upright > 0
    for k in ("ang_vel_xy", "lift_clearance", "support"):
        assert getattr(w, k) < 0, k
    paper = RewardConfig.paper()
    assert paper.orientation == -1.0 and paper.collision == -1.0 and paper.support == 0.0


def test_old_configs_load_without_v2_terms():
    d = TrainConfig().to_dict()
    for k in ("upright", "ang_vel_xy", "lift_clearance", "support"):
        del d["env"]["rewards"][k]
    rw = TrainConfig.from_dict(d).env.rewards
    assert rw.upright == rw.ang_vel_xy == rw.lift_clearance == rw.support == 0.0
    assert TrainConfig.from_dict(TrainConfig().to_dict()).env.rewards == RewardConfig()
    d = TrainConfig().to_dict()
    d["ppo"]["smoothness_coef"] = 0.1  # the dropped experiment after v7 (runs/v15)
    assert TrainConfig.from_dict(d).ppo == TrainConfig().ppo


def test_old_configs_keep_their_plan_clearance_and_armature():
    d = TrainConfig().to_dict()
    del d["env"]["ground_clearance"]
    del d["env"]["dr"]["armature"]
    del d["env"]["dr"]["joint_friction"]
    old = TrainConfig.from_dict(d).env
    assert old.ground_clearance == ExcitationConfig.ground_clearance
    assert old.dr.armature == (ARMATURE, ARMATURE) and old.dr.joint_friction == (0.0, 0.0)
    assert TrainConfig.from_dict(TrainConfig().to_dict()).env.ground_clearance == 0.12


def test_com_and_v2_terms_in_env(env):
    assert env.com_xy.shape == (6, 2)
    # the whole robot's centre of mass lies near the base origin at the start pose
    assert np.all(np.linalg.norm(env.com_xy - env.base_pos[:, :2], axis=1) < 0.1)
    _, terms, _ = R.compute_rewards(env)
    assert {"upright", "ang_vel_xy", "lift_clearance", "support"} <= set(terms)


def test_calf_low_point_is_the_lowest_vertex_of_the_calf_geoms(env):
    import mujoco

    from calib.joints import MODEL_LEGS
    from deploy.observation import projected_gravity

    m = env.tm.model
    d = mujoco.MjData(m)
    rng = np.random.default_rng(3)
    for _ in range(20):
        quat = rng.normal(size=4) + [3.0, 0, 0, 0]
        d.qpos[:3] = [0.1, -0.2, 0.3]
        d.qpos[3:7] = quat / np.linalg.norm(quat)
        d.qpos[7:19] = np.tile([0.0, 0.8, -1.6], 4) + rng.uniform(-0.8, 0.8, 12)
        mujoco.mj_kinematics(m, d)
        foot_z = np.array([[d.site_xpos[m.site(f"{leg}_foot").id][2] for leg in MODEL_LEGS]])
        got = env.tm.calf_low_z(projected_gravity(d.qpos[None, 3:7].copy()),
                                d.qpos[None, 7:19].copy(), foot_z)
        want = []
        for leg in MODEL_LEGS:  # brute force: every mesh vertex of the calf in the world frame
            z = []
            for g in np.flatnonzero(m.geom_bodyid == m.body(f"{leg}_calf").id):
                if m.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH:
                    continue
                a, n = m.mesh_vertadr[m.geom_dataid[g]], m.mesh_vertnum[m.geom_dataid[g]]
                z.append(d.geom_xpos[g][2] + m.mesh_vert[a:a + n] @ d.geom_xmat[g].reshape(3, 3)[2])
            want.append(np.concatenate(z).min())
        np.testing.assert_allclose(got[0], want, atol=1e-9)


def test_noise_amplitude_is_the_envs_observation_noise():
    """``observation_noise_amplitude`` (the noise diagnosis's draws) against the noise the
    observations actually carry: policy (noisy) minus the critic's clean copy."""
    env = TripodEnv(EnvConfig(num_envs=64, plans_per_leg=1, seed=2, threads=1))
    amp = env.observation_noise_amplitude()
    assert amp.shape == (49,)
    draws = [env.observations() for _ in range(20)]  # 1 280 noisy and clean observations
    diff = np.concatenate([o["policy"] - o["critic"][:, :49] for o in draws])
    reach = np.abs(diff).max(0)
    assert np.all(reach <= amp + 1e-6)
    noisy = amp > 0
    assert noisy.sum() == 3 + 3 + 12 + 12  # gyro, gravity, joint positions and velocities
    assert np.all(reach[noisy] > 0.95 * amp[noisy])  # uniform over the whole half-width
    np.testing.assert_allclose(amp[3:6], 0.2 * 0.25)  # gyro +-0.2 rad/s at scale 0.25
    np.testing.assert_allclose(amp[21:33], 1.5 * 0.05)  # joint velocities +-1.5 rad/s
    env.cfg.dr.enabled = False
    assert not env.observation_noise_amplitude().any()


def test_noise_scale_quiets_the_sensors_per_episode_and_is_drawn_only_when_set():
    """DRConfig.noise_scale multiplies every observation noise by a factor drawn per episode;
    at (0, 0) the policy sees the clean frame, and left at (1, 1) nothing extra is drawn (the
    committed evaluations keep their draws)."""
    quiet = EnvConfig(num_envs=3, plans_per_leg=1, seed=6, threads=1)
    quiet.dr.noise_scale = (0.0, 0.0)
    env = TripodEnv(quiet)
    ob = env.observations()
    np.testing.assert_array_equal(ob["policy"], ob["critic"][:, :49])
    plain, spread = (EnvConfig(num_envs=3, plans_per_leg=1, seed=6, threads=1) for _ in range(2))
    spread.dr.noise_scale = (0.2, 0.9)
    a, b = TripodEnv(plain), TripodEnv(spread)
    assert np.all(a.noise_scale == 1.0)
    assert np.all((b.noise_scale >= 0.2) & (b.noise_scale <= 0.9))


def test_motor_strength_scales_the_torque_peak_as_on_the_mocks_simulator():
    """A weak motor delivers s times the clamped PD torque, its peak included (as
    sim.effects.MotorStrength after sim.go2's clamp); a strong one stays at the effort limit."""
    from calib.joints import EFFORT_LIMIT
    from policy_train.config import DRConfig

    dr = DRConfig(motor_strength=(0.6, 0.6), kp_scale=(1.0, 1.0), kd_scale=(1.0, 1.0),
                  latency_steps=(0, 0), push_vel=0.0)
    e = TripodEnv(EnvConfig(num_envs=2, plans_per_leg=1, seed=3, threads=1, kp=60.0,
                            decimation=1, dr=dr))
    lim = np.tile(EFFORT_LIMIT, 4)
    np.testing.assert_allclose(e.forcerange[:, :, 1], 0.6 * np.broadcast_to(lim, (2, 12)))
    np.testing.assert_allclose(e.forcerange[:, :, 0], -e.forcerange[:, :, 1])
    np.testing.assert_allclose(e.torque_peak(np.array([0.5, 1.3])), [0.5 * lim, lim])
    # the physics: every target 1.5 rad off (to the soft limits: 0.6-1.2 rad) asks
    # kp x strength x error of 22-43 N m of every motor in the (one, 5 ms) physics step, over
    # 0.6 x the effort limit
    e.lift_leg[:] = -1
    e.target[:] = e.q + np.tile([1.5, 1.5, -1.5], 4)
    e.step(np.zeros((2, 12)))
    np.testing.assert_allclose(np.abs(e.act_force), 0.6 * np.broadcast_to(lim, (2, 12)),
                               rtol=1e-9)
