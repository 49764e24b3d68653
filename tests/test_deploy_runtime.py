"""deploy.runtime without a robot: what a run refuses before it starts, and how long a lockstep
SOLVE waits for a solver that does not finish."""

import threading
import time

import pytest

from deploy.lift_schedule import LiftSchedule
from deploy.policy import PolicyMeta
from deploy.runtime import DeployConfig, DeployError, DeployRunner, ImuPort
from deploy.session import SessionConfig, State

pytest.importorskip("onnx")


@pytest.fixture(scope="module")
def meta(tmp_path_factory):
    from deploy.hold_policy import write_hold_policy

    sched = LiftSchedule(shift=0.2, lift=0.2, hold=0.2, lower=0.2, periods=1)
    return PolicyMeta.load(write_hold_policy(tmp_path_factory.mktemp("pol"), "hold",
                                             schedule=sched))


@pytest.mark.parametrize("imus, why", [
    ([ImuPort("FL", "/dev/ttyUSB0"), ImuPort("FL", "/dev/ttyUSB1")],
     "--imu gives FL more than one port"),
    # two IMUs on one port told apart by nothing: one leg's ring would get both
    ([ImuPort("FL", "/dev/ttyUSB0"), ImuPort("FR", "/dev/ttyUSB0")],
     "port /dev/ttyUSB0 is shared by 2 IMUs: give every one its own node id"),
    ([ImuPort("FL", "/dev/ttyUSB0", 1), ImuPort("FR", "/dev/ttyUSB0")], "its own node id"),
    ([ImuPort("FL", "/dev/ttyUSB0", 1), ImuPort("FR", "/dev/ttyUSB0", 1)], "its own node id"),
])
def test_foot_imu_ports_that_would_mix_two_imus_are_refused(meta, imus, why):
    with pytest.raises(DeployError, match=why):
        DeployRunner(DeployConfig(legs=["FL"], imus=imus), meta)


def test_joystick_mode_needs_a_foot_imu(meta):
    # without one every combo would lift a leg whose samples go nowhere
    with pytest.raises(DeployError, match="no foot IMU"):
        DeployRunner(DeployConfig(joystick=True), meta)


def test_lockstep_solve_waits_its_timeout_once_not_at_every_tick(meta, tmp_path):
    class Hung:  # a solver that never finishes
        def __init__(self):
            self.e = threading.Event()

        def done(self):
            return False

        def join(self, timeout=None):
            self.e.wait(timeout)

    timeout = 0.3
    r = DeployRunner(DeployConfig(legs=["FL"], imus=[ImuPort("FL", "/dev/null")],
                                  clock="lockstep", out_dir=tmp_path,
                                  session=SessionConfig(solve_timeout_s=timeout)), meta)
    r.session.state = State.SOLVE
    r._jobs.append(Hung())
    t0 = time.monotonic()
    for _ in range(20):  # 20 ticks of SOLVE: the wall-clock wait is spent on the first
        r._wait_solver()
    assert timeout - 0.05 < time.monotonic() - t0 < timeout + 0.5
    # a stop that arrives during a wait ends it within a poll (20 ms), not at the timeout
    r._jobs.append(Hung())
    threading.Timer(0.05, r.request_stop).start()
    t0 = time.monotonic()
    r._wait_solver()
    assert time.monotonic() - t0 > 0.04 and time.monotonic() < r._wait_deadline
    r._jobs.append(Hung())  # and one set before the wait ends it at once
    t0 = time.monotonic()
    r._wait_solver()
    assert time.monotonic() - t0 < 0.1


def test_a_record_history_shorter_than_a_lift_is_refused(meta):
    # SOLVE reads the excitation back from the rings after the lowering and the stand
    with pytest.raises(DeployError, match="--record-seconds 5 cannot hold FL's"):
        DeployRunner(DeployConfig(legs=["FL"], imus=[ImuPort("FL", "/dev/null")],
                                  record_seconds=5.0), meta)


class _TakeJobs:
    """A SOLVE worker that only keeps what it is given (the real one starts with the loop)."""

    def __init__(self):
        self.kwargs = []

    def submit(self, *args, **kwargs):
        self.kwargs.append(kwargs)


@pytest.mark.parametrize("t_r", [0.3, 0.8])
def test_the_solve_searches_the_offsets_the_leg_s_plan_was_designed_for(tmp_path, t_r):
    # the paper's t_r is the sensor offset range the excitation is planned for: a policy whose
    # schedule plans for +-0.3 s must not be searched over the solver's default +-0.5 s, nor one
    # planned for +-0.8 s over less (offsets up to t_r would be refused at the edge)
    from deploy.hold_policy import write_hold_policy

    sched = LiftSchedule(shift=0.2, lift=0.2, hold=0.2, lower=0.2, periods=1, t_r=t_r)
    m = PolicyMeta.load(write_hold_policy(tmp_path, "hold", schedule=sched))
    r = DeployRunner(DeployConfig(legs=["FL"], imus=[ImuPort("FL", "/dev/null")],
                                  out_dir=tmp_path), m)
    r._worker = worker = _TakeJobs()
    r._start_solve("FL", (None, None))
    (kw,) = worker.kwargs
    assert kw["config"].max_offset == t_r
    assert kw["config"].min_correlation == r.cfg.solver.min_correlation  # the gates kept
    assert kw["pad_s"] == pytest.approx(t_r + 0.1)
