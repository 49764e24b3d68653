"""Which clock stamps the encoders (t_E) and the foot IMU (t_I) for the calibration.

The solver estimates ``t_d = t_I - t_E``; what that number means depends on the clocks the two
streams are put on, so the choice is made in one place:

* ``RealtimeTimeBase`` (the robot, and the mock's ``realtime`` clock): t_E is the host receive
  time of each LowState_ and t_I that of each foot-IMU sample, both de-jittered through the
  sender's own clock (the robot's ``tick``, the IMU's device stamp) mapped onto the host clock
  by the lower envelope of the delivery delay. t_d is then the physical delay between the two
  paths (IMU latency and filters against LowState's, each with its fastest delivery), which is
  what a user needs to align the two streams on this host.
* ``LockstepTimeBase`` (the mock's ``lockstep`` clock): the simulation runs as fast as the CPU
  allows, so host stamps mean nothing; the mock's IMU device clock *is* the simulation clock
  (plus the same epoch as the LowState tick), so t_E is the LowState ``tick`` (ms) and t_I the
  device stamp ``t_device_ns``. t_d is then exactly the mock's configured offset.

Both return float seconds on an arbitrary common origin (the solver only uses differences).
"""

from __future__ import annotations

import numpy as np

__all__ = ["TIME_BASES", "LockstepTimeBase", "RealtimeTimeBase", "TimeBase", "make_time_base",
           "map_lower_envelope"]

TIME_BASES = ("realtime", "lockstep")


class TimeBase:
    """Maps recorder rows to the times the solver compares (float s, common origin)."""

    name = ""

    def encoder_times(self, lowstate_rows: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def imu_times(self, imu_rows: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def imu_valid(self, imu_rows: np.ndarray) -> np.ndarray:
        """Rows whose stamp in this time base is known."""
        return np.ones(len(imu_rows), bool)

    def check(self, lowstate_rows: np.ndarray, imu_rows: np.ndarray) -> list[str]:
        """Reasons not to trust the two clocks over these rows (empty: fine)."""
        return []


def _unwrap_tick_ms(tick) -> np.ndarray:
    """LowState ``tick`` (u32 ms, wraps after 49.7 days of uptime) unwrapped, int64 ms."""
    tick = np.asarray(tick).astype(np.int64)
    steps = np.diff(tick, prepend=tick[:1])
    return tick + np.cumsum(np.where(steps < -(1 << 31), 1 << 32, 0))


def map_lower_envelope(t_dev_ns, t_host_ns, bin_s: float = 0.25, min_bins: int = 4,
                       spread: list | None = None):
    """Device stamps mapped onto the host clock (ns) by the lower envelope of the receive
    latency: the minimum of ``host - device`` in each ``bin_s`` bin, a line fitted through
    those minima (drift), the upper outliers (late bins) trimmed once. The constant minimum
    delivery delay stays in the result, as in :class:`hw.clock_sync.ClockMapper`.
    None when the span has fewer than ``min_bins`` bins. ``spread`` (a list) receives the
    5-95 % range (s) of the bin minima around the line: near zero for two steady clocks,
    large when one of them jumped or paused."""
    d = np.asarray(t_dev_ns, dtype=np.int64)
    h = np.asarray(t_host_ns, dtype=np.int64)
    if d.size < 2:
        return None
    x = (d - d[0]) * 1e-9
    y = (h - d - (h[0] - d[0])) * 1e-9  # latency + offset, relative to the first sample
    b = np.floor(x / bin_s).astype(np.int64)
    order = np.lexsort((y, b))
    first = np.ones(order.size, bool)
    first[1:] = b[order][1:] != b[order][:-1]
    idx = order[first]  # the minimum-latency sample of each bin
    if idx.size < min_bins:
        return None
    xb, yb = x[idx], y[idx]
    coef = np.polyfit(xb, yb, 1)
    r = yb - np.polyval(coef, xb)
    mad = np.median(np.abs(r - np.median(r))) + 1e-6
    keep = r < np.median(r) + 3 * mad
    if keep.sum() >= min_bins:
        coef = np.polyfit(xb[keep], yb[keep], 1)
        # the envelope lies below the points: shift the line to the lowest kept minimum
        coef[1] += min(0.0, float(np.min(yb[keep] - np.polyval(coef, xb[keep]))))
    if spread is not None:
        p5, p95 = np.percentile(yb - np.polyval(coef, xb), [5, 95])
        spread.append(float(p95 - p5))
    return d + (h[0] - d[0]) + np.round(np.polyval(coef, x) * 1e9).astype(np.int64)


class RealtimeTimeBase(TimeBase):
    """Both streams on the host clock, de-jittered: t_E = the robot's LowState ``tick`` and t_I =
    the foot IMU's device stamp, each mapped onto the host clock by the lower envelope of its
    delivery delay over the rows given (:func:`map_lower_envelope`: a fit over the whole
    window, past and future, rather than the driver's online ``t_mapped_ns``, which lags
    behind a clock step for its 20 s window). Too short a span falls back to the host receive
    stamps (encoders) and the driver's mapping (IMU)."""

    name = "realtime"

    # A clock pair that does not keep to a straight line over the window (a device reset, a
    # robot whose tick skipped, a simulator that fell behind real time) gives a wrong t_d that
    # the correlation cannot see: refuse it.
    MAX_SPREAD_S = 0.002  # fastest deliveries around the fitted line, 5-95 %
    EARLY_NS = 1_000_000  # a sample "received" this long before its mapped time ...
    EARLY_FRACTION = 0.005  # ... for more than this fraction of the samples

    def __init__(self, origin_ns: int = 0, map_tick: bool = True):
        self.origin_ns = int(origin_ns)
        self.map_tick = map_tick

    def _encoder_map(self, rows, spread=None):
        host = rows["t_host_ns"].astype(np.int64)
        if not (self.map_tick and host.size):
            return host, False
        mapped = map_lower_envelope(_unwrap_tick_ms(rows["tick"]) * 1_000_000, host,
                                    spread=spread)
        return (host, False) if mapped is None else (mapped, True)

    def _imu_map(self, rows, spread=None):
        mapped = map_lower_envelope(rows["t_device_ns"], rows["t_host_ns"], spread=spread)
        if mapped is None:
            return rows["t_mapped_ns"].astype(np.int64), False
        return mapped, True

    def encoder_times(self, lowstate_rows):
        return (self._encoder_map(lowstate_rows)[0] - self.origin_ns) * 1e-9

    def imu_times(self, imu_rows):
        return (self._imu_map(imu_rows)[0] - self.origin_ns) * 1e-9

    def imu_valid(self, imu_rows):
        return (imu_rows["t_device_ns"] >= 0) & (imu_rows["t_mapped_ns"] >= 0)

    def check(self, lowstate_rows, imu_rows):
        reasons = []
        for what, rows, fn in (("the robot's LowState tick", lowstate_rows, self._encoder_map),
                               ("the foot IMU's clock", imu_rows, self._imu_map)):
            if not len(rows):
                continue
            spread: list[float] = []
            mapped, fitted = fn(rows, spread)
            early = float(np.mean(rows["t_host_ns"].astype(np.int64) - mapped < -self.EARLY_NS))
            sp = spread[0] if spread else 0.0
            if (fitted and sp > self.MAX_SPREAD_S) or early > self.EARLY_FRACTION:
                reasons.append(
                    f"{what} does not follow the host clock on one line over the window "
                    f"(fastest deliveries spread {sp * 1e3:.1f} ms, {100 * early:.1f} % of "
                    "samples early): it jumped or paused, the time offset would be wrong")
        return reasons


class LockstepTimeBase(TimeBase):
    """t_E = LowState ``tick`` (ms, u32, unwrapped); t_I = IMU device stamp (ns)."""

    name = "lockstep"

    def encoder_times(self, lowstate_rows):
        return _unwrap_tick_ms(lowstate_rows["tick"]) * 1e-3

    def imu_times(self, imu_rows):
        return imu_rows["t_device_ns"].astype(np.int64) * 1e-9

    def imu_valid(self, imu_rows):
        return imu_rows["t_device_ns"] >= 0


def make_time_base(name: str) -> TimeBase:
    if name == "realtime":
        return RealtimeTimeBase()
    if name == "lockstep":
        return LockstepTimeBase()
    raise ValueError(f"time base must be one of {TIME_BASES}, got {name!r}")
