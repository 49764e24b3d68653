"""Absolute-deadline ticking and per-tick timing statistics of the control loop.

``DeadlineTicker``: tick k is due at ``t0 + k * period`` on the monotonic clock, whatever the
previous ticks cost, so compute time never accumulates into drift. A tick that starts more than
one period late skips the deadlines it missed (counted), instead of bursting to catch up: a
burst would send several commands computed from the same state.

``TickStats``: preallocated arrays (fixed memory, pages touched at construction) of period error
(start - deadline) and compute time per tick, summarised as p50 / p99 / max.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["DeadlineTicker", "TickStats", "TimingSummary"]


class DeadlineTicker:
    """Sleeps until the next absolute deadline. Times in integer ns of ``clock``.

    period_s: tick period (s). ``wait()`` returns (k, deadline_ns, start_ns): the tick index
    (deadline index, so k * period is the tick's nominal time), its deadline, and when it began.
    """

    def __init__(self, period_s: float, clock: Callable[[], int] = time.monotonic_ns,
                 sleep: Callable[[float], None] = time.sleep):
        if not (np.isfinite(period_s) and period_s > 0):
            raise ValueError(f"period_s must be > 0, got {period_s}")
        self.period_ns = round(period_s * 1e9)
        self._clock = clock
        self._sleep = sleep
        self.t0_ns: int | None = None
        self.k = -1
        self.missed = 0

    def wait(self) -> tuple[int, int, int]:
        now = self._clock()
        if self.t0_ns is None:
            self.t0_ns = now
            self.k = 0
            return 0, now, now
        k = self.k + 1
        deadline = self.t0_ns + k * self.period_ns
        if now - deadline > self.period_ns:
            # Late by more than a period: skip to the latest deadline already passed.
            skip = (now - deadline) // self.period_ns
            self.missed += int(skip)
            k += int(skip)
            deadline = self.t0_ns + k * self.period_ns
        while now < deadline:
            self._sleep((deadline - now) * 1e-9)
            now = self._clock()
        self.k = k
        return k, deadline, now


@dataclass
class TimingSummary:
    """Figures of a run: ticks, missed deadlines, period error and compute time (s);
    frames_skipped: a tick's later LowCmd_ frames not sent because the next one was due."""

    ticks: int
    missed: int
    late: int
    period_error_p50: float
    period_error_p99: float
    period_error_max: float
    compute_p50: float
    compute_p99: float
    compute_max: float
    frames_skipped: int = 0

    def lines(self) -> list[str]:
        return [
            (f"ticks {self.ticks}, missed deadlines {self.missed}, ticks started late "
            f"(> 1 ms) {self.late}, frames skipped {self.frames_skipped}"),
            (f"period error  p50 {self.period_error_p50 * 1e3:7.3f} ms   "
            f"p99 {self.period_error_p99 * 1e3:7.3f} ms   max {self.period_error_max * 1e3:7.3f} ms"),
            (f"compute time  p50 {self.compute_p50 * 1e3:7.3f} ms   "
            f"p99 {self.compute_p99 * 1e3:7.3f} ms   max {self.compute_max * 1e3:7.3f} ms"),
        ]


class TickStats:
    """Per-tick period error and compute time (s) in preallocated rings of ``capacity`` ticks
    (the most recent ones are summarised; the maxima and counts cover the whole run)."""

    LATE_S = 1e-3

    def __init__(self, capacity: int = 180_000):
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self.capacity = int(capacity)
        self._err = np.ones(self.capacity)  # ones, not zeros: touch the pages now (fixed RSS)
        self._cpu = np.ones(self.capacity)
        self.n = 0
        self.late = 0
        self.missed = 0
        self.frames_skipped = 0
        self.max_err = 0.0
        self.max_cpu = 0.0

    def add(self, period_error_s: float, compute_s: float) -> None:
        i = self.n % self.capacity
        self._err[i] = period_error_s
        self._cpu[i] = compute_s
        self.n += 1
        if period_error_s > self.LATE_S:
            self.late += 1
        self.max_err = max(self.max_err, period_error_s)
        self.max_cpu = max(self.max_cpu, compute_s)

    def summary(self) -> TimingSummary:
        m = min(self.n, self.capacity)
        if m == 0:
            nan = float("nan")
            return TimingSummary(0, self.missed, 0, nan, nan, nan, nan, nan, nan,
                                 self.frames_skipped)
        e, c = self._err[:m], self._cpu[:m]
        pe = np.percentile(e, [50, 99])
        pc = np.percentile(c, [50, 99])
        return TimingSummary(self.n, self.missed, self.late, float(pe[0]), float(pe[1]),
                             self.max_err, float(pc[0]), float(pc[1]), self.max_cpu,
                             self.frames_skipped)
