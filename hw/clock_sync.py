"""Map a device clock onto the host monotonic clock from one-way receive stamps.

Model: ``t_host_rx = t_dev * (1 + drift) + offset + latency`` with latency >= 0
(USB / serial buffering, the reader thread's scheduling, the GIL: mostly about
a millisecond, sometimes tens). Latency is never negative, so the true line is
the *lower envelope* of the points (t_dev, t_host_rx - t_dev). ``ClockMapper``
keeps the minimum-latency point of each time bin over a sliding window and
fits the line as the lower convex hull edge under the points' mean abscissa
(the line below all points that minimises their summed residual: the classic
convex-hull clock-sync estimator). A refit happens only when a bin closes, so
``update`` costs a few microseconds.

What it cannot see: the constant part of the latency (the minimum one-way
delay) is indistinguishable from offset; mapped times are therefore "device
sample time as the host would have stamped it with the fastest observed
delivery". That constant goes into the temporal calibration t_d like any
other fixed delay.

Wrap: with ``wrap_period_ns`` (e.g. HiPNUC's u32 ms counter) forward wraps are
unwrapped. Resets: a backward device step that is not a wrap (reboot), or a
sample that would have arrived before it was taken (residual below
``-reset_tolerance_s``: the device clock jumped forward) restarts the fit.

Order: ``update`` never returns a time before the previous one plus half the
device interval between them. Without that floor, frames delivered in one read
(one host stamp) before the line has a slope all map to that stamp, and a refit
that lowers the line steps later samples back by up to a few ms, so samples
could tie or run backwards at 400 Hz. Under the floor the mapping slews down to
the new line at half the device rate instead of jumping.
"""

from __future__ import annotations

import itertools
from collections import deque
from dataclasses import dataclass


@dataclass(slots=True, frozen=True)
class ClockFit:
    """Line of the host-minus-device offset: offset(t) = a + b * (t - t_ref).

    t_ref_dev_ns / t_ref_host_ns: anchor (unwrapped device ns, host ns);
    a_s: offset at the anchor (s) relative to t_ref_host - t_ref_dev; b: drift
    (dimensionless, 1e-6 = 1 ppm, positive = device clock slow).
    """

    t_ref_dev_ns: int
    t_ref_host_ns: int
    a_s: float
    b: float


class ClockMapper:
    """Online device-to-host clock mapping with a lower-envelope line fit.

    update(t_device_ns, t_host_ns) -> mapped host ns of that sample.
    map(t_device_unwrapped_ns) -> host ns under the current fit.
    """

    def __init__(
        self,
        wrap_period_ns: int | None = None,
        bin_s: float = 0.25,
        window_s: float = 20.0,
        reset_tolerance_s: float = 0.005,
        max_drift: float = 5e-3,
        max_slew: float = 0.5,
    ) -> None:
        if wrap_period_ns is not None and wrap_period_ns <= 0:
            raise ValueError(f"wrap_period_ns must be positive, got {wrap_period_ns}")
        if not 0 < bin_s < window_s:
            raise ValueError(f"need 0 < bin_s < window_s, got {bin_s}, {window_s}")
        if reset_tolerance_s <= 0 or max_drift <= 0:
            raise ValueError("reset_tolerance_s and max_drift must be positive")
        if not 0 < max_slew < 1:
            raise ValueError(f"need 0 < max_slew < 1, got {max_slew}")
        self.wrap_period_ns = wrap_period_ns
        self.bin_s = bin_s
        self.window_s = window_s
        self.reset_tolerance_s = reset_tolerance_s
        self.max_drift = max_drift
        self.max_slew = max_slew
        self.resets = 0
        self.wraps = 0
        self.samples = 0
        self._last_raw: int | None = None
        self._epoch = 0
        self._last_unwrapped: int | None = None
        self._clear_fit()

    def _clear_fit(self) -> None:
        self._d0: int | None = None  # anchor, unwrapped device ns
        self._h0 = 0  # anchor, host ns
        self._bins: deque[tuple[float, float]] = deque()  # closed bins: (x, y_min)
        self._bin_idx = -1
        self._bin_x = 0.0
        self._bin_y = float("inf")
        self._a = 0.0
        self._b = 0.0
        self._fitted = False
        self._last_mapped: int | None = None  # update's previous answer, this fit
        self._last_device = 0  # and its unwrapped device ns

    # -- public ------------------------------------------------------------------

    @property
    def ready(self) -> bool:
        """True once at least two bins have closed (drift is being estimated)."""
        return len(self._bins) >= 2

    @property
    def unwrapped_last(self) -> int | None:
        """Unwrapped device ns of the latest ``update``."""
        return self._last_unwrapped

    @property
    def drift_ppm(self) -> float:
        return self._b * 1e6

    @property
    def fit(self) -> ClockFit | None:
        if self._d0 is None:
            return None
        return ClockFit(self._d0, self._h0, self._a, self._b)

    def unwrap(self, t_device_ns: int) -> int:
        """Unwrapped device time of a raw stamp (stateful: call in arrival order)."""
        raw = int(t_device_ns)
        if self.wrap_period_ns is not None:
            if not 0 <= raw < self.wrap_period_ns:
                raise ValueError(f"device stamp {raw} outside [0, wrap_period_ns)")
            if self._last_raw is not None and raw < self._last_raw - self.wrap_period_ns // 2:
                self._epoch += self.wrap_period_ns
                self.wraps += 1
        self._last_raw = raw
        return raw + self._epoch

    def map(self, t_device_unwrapped_ns: int) -> int:
        """Host monotonic ns at which the device took a sample stamped ``t``."""
        if self._d0 is None:
            raise ValueError("ClockMapper.map called before any update")
        dd = t_device_unwrapped_ns - self._d0
        x = dd * 1e-9
        return self._h0 + dd + round((self._a + self._b * x) * 1e9)

    def update(self, t_device_ns: int, t_host_ns: int) -> int:
        """Add one (device stamp, host receive stamp) pair; return its mapped host ns.

        Strictly increasing for increasing device stamps (see the module's "Order"):
        the answer is ``map`` of the stamp, or the previous answer plus
        ``1 - max_slew`` of the device interval where that is later. A reset starts over.
        """
        d = self.unwrap(t_device_ns)
        h = int(t_host_ns)
        self.samples += 1
        if self._d0 is None:
            self._anchor(d, h)
        elif d < self._last_unwrapped:
            self._restart(d, h)  # device rebooted: its clock went backwards
        x = (d - self._d0) * 1e-9
        y = ((h - self._h0) - (d - self._d0)) * 1e-9
        if self._fitted and y - (self._a + self._b * x) < -self.reset_tolerance_s:
            # The sample would have arrived before it was taken: clock jumped.
            self._restart(d, h)
            x, y = 0.0, 0.0
        self._last_unwrapped = d
        idx = int(x // self.bin_s)
        if idx != self._bin_idx:
            if self._bin_idx >= 0:
                self._close_bin(x)
            self._bin_idx = idx
            self._bin_x, self._bin_y = x, y
        elif y < self._bin_y:
            self._bin_x, self._bin_y = x, y
        if len(self._bins) < 2:
            # Not enough history for a slope: offset only, lowest point so far.
            lowest = min([self._bin_y] + [p[1] for p in self._bins])
            self._a, self._b = lowest, 0.0
            self._fitted = True
        mapped = self.map(d)
        if self._last_mapped is not None:
            step = d - self._last_device
            mapped = max(mapped, self._last_mapped + max(1, round(step * (1.0 - self.max_slew))))
        self._last_mapped, self._last_device = mapped, d
        return mapped

    # -- internals ---------------------------------------------------------------

    def _anchor(self, d: int, h: int) -> None:
        self._d0, self._h0 = d, h

    def _restart(self, d: int, h: int) -> None:
        self.resets += 1
        self._clear_fit()
        self._anchor(d, h)

    def _close_bin(self, x_now: float) -> None:
        self._bins.append((self._bin_x, self._bin_y))
        while self._bins and self._bins[0][0] < x_now - self.window_s:
            self._bins.popleft()
        if len(self._bins) >= 2:
            self._refit()

    def _refit(self) -> None:
        pts = list(self._bins)
        hull: list[tuple[float, float]] = []
        for p in pts:  # monotone chain, lower hull; bins are already x-sorted
            while len(hull) >= 2:
                (x1, y1), (x2, y2) = hull[-2], hull[-1]
                if (x2 - x1) * (p[1] - y1) - (y2 - y1) * (p[0] - x1) <= 0:
                    hull.pop()
                else:
                    break
            hull.append(p)
        xm = sum(p[0] for p in pts) / len(pts)
        a, b = hull[0][1], 0.0
        for (x1, y1), (x2, y2) in itertools.pairwise(hull):
            if x1 <= xm <= x2 and x2 > x1:
                b = (y2 - y1) / (x2 - x1)
                a = y1 - b * x1
                break
        if abs(b) > self.max_drift:
            # Implausible slope (too little history, a stall): keep offset only.
            b = 0.0
            a = min(p[1] for p in pts)
        self._a, self._b = a, b
