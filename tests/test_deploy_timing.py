"""Absolute-deadline ticking: compute time never drifts the schedule; missed deadlines skip."""

import numpy as np
import pytest

from deploy.timing import DeadlineTicker, TickStats

PERIOD_NS = 20_000_000


class FakeClock:
    """Monotonic ns clock; ``sleep`` advances it (with an overshoot, like a real sleep)."""

    def __init__(self, overshoot_ns: int = 150_000):
        self.t = 1_000_000_000
        self.overshoot = overshoot_ns

    def now(self) -> int:
        return self.t

    def sleep(self, s: float) -> None:
        self.t += round(s * 1e9) + self.overshoot


def test_deadlines_are_absolute_despite_compute_and_sleep_overshoot():
    clk = FakeClock()
    tk = DeadlineTicker(0.02, clock=clk.now, sleep=clk.sleep)
    rng = np.random.default_rng(0)
    k0, d0, s0 = tk.wait()
    assert (k0, d0, s0) == (0, clk.t, clk.t)
    for i in range(1, 500):
        clk.t += int(rng.integers(1_000_000, 15_000_000))  # compute: 1..15 ms
        k, deadline, start = tk.wait()
        assert k == i
        assert deadline == d0 + i * PERIOD_NS  # no accumulation of compute or overshoot
        assert 0 <= start - deadline <= clk.overshoot
    assert tk.missed == 0


def test_overrun_skips_missed_deadlines_without_burst():
    clk = FakeClock(overshoot_ns=0)
    tk = DeadlineTicker(0.02, clock=clk.now, sleep=clk.sleep)
    _, d0, _ = tk.wait()
    clk.t += 75_000_000  # a 75 ms stall: deadlines 1, 2, 3 pass
    k, deadline, start = tk.wait()
    assert tk.missed == 2  # 1 and 2 skipped; 3 runs late
    assert k == 3 and deadline == d0 + 3 * PERIOD_NS and start - deadline == 15_000_000
    k, deadline, _ = tk.wait()
    assert k == 4 and deadline == d0 + 4 * PERIOD_NS


def test_tick_stats_summary():
    st = TickStats(capacity=1000)
    for i in range(1000):
        st.add(i * 1e-6, 2e-3)
    st.add(5e-3, 1e-2)  # wraps the ring; maxima cover the whole run
    s = st.summary()
    assert s.ticks == 1001 and s.late == 1
    assert s.period_error_max == pytest.approx(5e-3)
    assert s.compute_max == pytest.approx(1e-2)
    assert s.period_error_p50 == pytest.approx(500.5e-6, rel=0.01)
    assert len(s.lines()) == 3


def test_empty_stats_and_bad_period():
    assert TickStats(10).summary().ticks == 0
    with pytest.raises(ValueError):
        DeadlineTicker(0.0)


def _frames(n):
    from deploy.session import Command

    z = np.zeros(12)
    return [Command(np.full(12, float(i)), z, z, z, z, f"frame {i}") for i in range(n)]


def _frame_stub(clk, sent):
    """What DeployRunner._publish_rest uses of the runner, on a fake clock."""
    from types import SimpleNamespace

    return SimpleNamespace(n_cmd=5, dt=0.02, stats=TickStats(), _clock=clk.now,
                           _sleep=clk.sleep, _publish=lambda c: sent.append((clk.now(), c)))


def test_a_ticks_later_frames_go_out_on_their_sub_deadlines():
    """The realtime loop sends a tick's substep frames dt / n apart, on absolute sub-deadlines
    (never early), in order; a tick with no substeps repeats its frame."""
    from deploy.runtime import DeployRunner

    clk, sent = FakeClock(), []
    stub = _frame_stub(clk, sent)
    first, *rest = _frames(5)
    first.substeps = tuple(rest)
    t0 = clk.now()
    clk.t += 2_500_000  # the tick's compute
    DeployRunner._publish_rest(stub, first, t0, lockstep=False)
    assert [c for _, c in sent] == rest
    for i, (t, _) in enumerate(sent, start=1):
        assert t0 + i * 4_000_000 <= t <= t0 + i * 4_000_000 + clk.overshoot
    assert stub.stats.frames_skipped == 0

    sent.clear()
    t1 = clk.now()
    DeployRunner._publish_rest(stub, _frames(1)[0], t1, lockstep=True)
    assert [c.source for _, c in sent] == ["frame 0"] * 4  # repeats, at once
    assert clk.now() == t1


def test_a_late_tick_skips_the_frames_already_overtaken():
    from deploy.runtime import DeployRunner

    clk, sent = FakeClock(), []
    stub = _frame_stub(clk, sent)
    first, *rest = _frames(5)
    first.substeps = tuple(rest)
    # the tick's compute ran 10 ms: frame 1 (due +4 ms) is overtaken by frame 2 (due +8 ms),
    # which goes out at once; the last frame is never skipped
    t0 = clk.now()
    clk.t += 10_000_000
    DeployRunner._publish_rest(stub, first, t0, lockstep=False)
    assert [c.source for _, c in sent] == ["frame 2", "frame 3", "frame 4"]
    assert sent[0][0] == t0 + 10_000_000
    assert stub.stats.frames_skipped == 1
    assert "frames skipped 1" in stub.stats.summary().lines()[0]

    sent.clear()
    t0 = clk.now()
    clk.t += 30_000_000  # a whole tick late: frames 1-3 overtaken, frame 4 still sent
    DeployRunner._publish_rest(stub, first, t0, lockstep=False)
    assert [c.source for _, c in sent] == ["frame 4"] and stub.stats.frames_skipped == 4
