"""The mock's foot IMUs on the wire: sensor model -> A2I v1 frames -> pty serial ports.

A :class:`FootImuChannel` turns the simulated foot motion into samples
(:class:`sim.sensors.FootImuModel`: mounting rotation, noise, bias, dropouts, the time offset
in the stamps) and each sample into one 57-byte frame (:func:`hw.imu_protocol.encode_frame`).
A :class:`PortWriter` owns one pty (:class:`hw.pty_link.PtyPair`) and writes whole frames.
In realtime it never blocks: a real UART keeps transmitting whether anyone listens or not, so
when the pty buffer is full (no reader, or a reader that stalls) the frame is lost and
counted, and the simulation never waits for a reader. In lockstep (``wait_s`` > 0) a full port
holds the simulation back until it takes the frame: there the simulation runs as fast as its
controller asks, with no baud rate to pace the frames, and how many a pty can hold then
depends on the host's load, not on the robot (two mock calibrations sharing two cores lost a
third of their frames so, the writes refused while the reader found nothing waiting, and
the lifted legs' IMUs fell silent for over a second). A port that stays
full for ``wait_s`` (nobody reads it) drops that frame and the ones after it without waiting,
until a write gets through again.
"""

from __future__ import annotations

import math
import os
import select
import threading
import time

import numpy as np

from hw.imu_protocol import SEQ_MOD, ImuFrame, encode_frame
from hw.mock.config import ResolvedImu
from hw.pty_link import PtyPair
from sim.sensors import FootImuModel, ImuSample

__all__ = ["FootImuChannel", "PortWriter", "garbage_bytes", "rotation_to_quat_wxyz"]

_SYNC0 = 0xA2


def garbage_bytes(rng: np.random.Generator, n: int) -> bytes:
    """``n`` random bytes without 0xA2 (the first sync byte), so they can never start a frame
    candidate: a decoder discards exactly these bytes and no real frame is lost to them."""
    b = rng.integers(0, 255, int(n), dtype=np.uint16)
    b[b >= _SYNC0] += 1  # 0..254 -> 0..255 minus 0xA2
    return b.astype(np.uint8).tobytes()


def rotation_to_quat_wxyz(r: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method, w >= 0)."""
    m = r
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    if q[0] < 0:
        q = tuple(-v for v in q)
    return tuple(float(v) for v in q)


class PortWriter:
    """One pty serial port; writes whole frames. wait_s: how long a full port may hold a
    write back (0: never, a full port drops the frame; see the module docstring)."""

    def __init__(self, wait_s: float = 0.0) -> None:
        if not (math.isfinite(wait_s) and wait_s >= 0):
            raise ValueError(f"wait_s must be >= 0 s, got {wait_s!r}")
        self.pty = PtyPair()
        self.port_path = self.pty.port_path
        self.wait_s = wait_s
        self._lock = threading.Lock()
        self._stalled = False  # the last write timed out waiting: nobody reads this port
        self.bytes_written = 0
        self.writes_dropped_full = 0  # buffer full: nobody reading
        self.writes_dropped_closed = 0  # after hang_up
        self.writes_truncated = 0
        self.writes_waited = 0  # held back by a full port, then written
        self.wait_max_s = 0.0  # the longest such wait

    @property
    def closed(self) -> bool:
        return self.pty.closed

    def write(self, data: bytes) -> bool:
        """Write ``data`` whole (True) or not at all; with ``wait_s``, waiting up to that long
        for a full port to take it."""
        with self._lock:
            if self.pty.closed:
                self.writes_dropped_closed += 1
                return False
            fd, view, t0 = self.pty.master_fd, memoryview(data), None
            while True:
                try:
                    n = os.write(fd, view)
                except BlockingIOError:
                    n = 0
                except OSError:
                    self.writes_dropped_closed += 1
                    return False
                self.bytes_written += n
                view = view[n:]
                if not view:
                    break
                now = time.monotonic()
                t0 = now if t0 is None else t0
                if self._stalled or now - t0 >= self.wait_s:
                    self._stalled = self.wait_s > 0
                    if len(view) == len(data):
                        self.writes_dropped_full += 1
                    else:
                        # The rest is lost as on an overrun UART; the reader's decoder
                        # rejects the truncated frame by its CRC.
                        self.writes_truncated += 1
                    return False
                select.select([], [fd], [], self.wait_s - (now - t0))
            self._stalled = False
            if t0 is not None:
                self.writes_waited += 1
                self.wait_max_s = max(self.wait_max_s, time.monotonic() - t0)
            return True

    def hang_up(self) -> None:
        """Close the master: a reader on ``port_path`` gets EIO (the adapter was unplugged)."""
        with self._lock:
            self.pty.hang_up()

    def close(self) -> None:
        with self._lock:
            self.pty.close()


class FootImuChannel:
    """One foot IMU: the sensor model plus its frames' encoding and its port.

    ``writer`` may be shared by several channels (all IMUs on one receiver, told apart by
    ``node_id``). Counters: ``samples`` (produced by the model), ``frames_written``,
    ``frames_dropped`` (port full or closed), ``garbage_bytes`` written.
    """

    def __init__(self, imu: ResolvedImu, writer: PortWriter) -> None:
        self.imu = imu
        self.leg = imu.leg
        self.node_id = imu.node_id
        self.model = FootImuModel(imu.sensor)
        self.rotation = imu.sensor.rotation  # R_I^F
        self.writer = writer
        # Garbage draws come from their own stream so that enabling them does not change the
        # samples (the model has its own generator).
        self._rng = np.random.default_rng([imu.seed, 0x6A5B])
        self._drift = 1.0 + imu.clock_drift_ppm * 1e-6
        self._rate = imu.sensor.rate
        self._t0: float | None = None  # the model's sampling grid origin, sim s
        self.samples = 0
        self.frames_written = 0
        self.frames_dropped = 0
        self.garbage_bytes = 0

    def wants(self, t: float, dt: float) -> bool:
        """Whether the truth at physics step time ``t`` (step ``dt``) is needed: the model
        interpolates linearly between consecutive truths, so only the two steps around each
        sample instant matter; feeding just those gives the same samples as feeding every step
        (at 400 Hz on a 1 kHz physics ~80 % of the steps, at 200 Hz ~40 %)."""
        if self._t0 is None:
            return True
        rate = self._rate
        n = math.floor((t - dt - self._t0) * rate + 1e-9) + 1  # first instant after t - dt
        return self._t0 + n / rate <= t + dt + 1e-9

    def update(self, t: float, omega_foot: np.ndarray, specific_force_foot: np.ndarray
               ) -> list[ImuSample]:
        """Feed the truth at sim time ``t`` (foot frame, rad/s and m/s^2); the samples due."""
        if self._t0 is None:
            self._t0 = t + self.imu.sensor.phase
        out = self.model.update(t, omega_foot, specific_force_foot)
        self.samples += len(out)
        return out

    def device_us_lockstep(self, stamp_s: float, epoch_s: float) -> int:
        """Lockstep device clock = the simulation clock + epoch: ``stamp_s`` (sim time of the
        described motion + t_d + jitter, s) -> integer microseconds."""
        return round((stamp_s + epoch_s) * 1e6)

    def device_us_realtime(self, host_rel_s: float) -> int:
        """Realtime device clock (its own offset and drift) at ``host_rel_s`` s of the host's
        monotonic wall clock after the mock's start (the instant the frame is written; never
        sim time, so the stamps do not jump when the simulation falls behind) -> integer
        microseconds."""
        return round((self.imu.clock_offset_s + host_rel_s * self._drift) * 1e6)

    def frame(self, sample: ImuSample, t_device_us: int, quat_wxyz) -> bytes:
        """The wire bytes of ``sample`` (with random garbage ahead of it, per ``garbage_prob``)."""
        data = encode_frame(ImuFrame(
            node_id=self.node_id,
            seq=sample.seq % SEQ_MOD,
            t_device_us=max(0, int(t_device_us)),
            gyro=tuple(float(v) for v in sample.gyro),
            accel=tuple(float(v) for v in sample.accel),
            quat=tuple(quat_wxyz),
        ))
        p = self.imu.garbage_prob
        if p > 0 and self._rng.random() < p:
            junk = garbage_bytes(self._rng, self._rng.integers(1, self.imu.garbage_max_bytes + 1))
            self.garbage_bytes += len(junk)
            data = junk + data
        return data

    def send(self, data: bytes) -> bool:
        ok = self.writer.write(data)
        if ok:
            self.frames_written += 1
        else:
            self.frames_dropped += 1
        return ok

    def inject_garbage(self, nbytes: int) -> int:
        """Write ``nbytes`` of garbage (no 0xA2) to the port now; bytes written (0 if closed)."""
        junk = garbage_bytes(self._rng, nbytes)
        if self.writer.write(junk):
            self.garbage_bytes += len(junk)
            return len(junk)
        return 0
