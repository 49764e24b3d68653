"""Foot-IMU serial reader: a thread per port that decodes, stamps and maps IMU frames.

One ``SerialImuReader`` owns one port. Several IMUs may share that port (one
radio receiver, frames told apart by node id) or each IMU has its own port and
reader. Every frame is stamped with the host ``time.monotonic_ns()`` taken
right after the read that completed it, and its device time is mapped onto the
host clock by a per-node ``ClockMapper``.

Failure is loud: a port that errors or disappears (``SerialException`` /
``OSError``, e.g. the USB adapter was unplugged) or an exception raised by the
``on_sample`` callback puts the reader in the ``"error"`` state, stores the
exception in ``reader.error``, calls ``on_error(exc)`` and ends the thread;
``get()`` then raises ``ImuReaderError`` once the queue is drained.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Self

import numpy as np
import serial

from hw.clock_sync import ClockMapper
from hw.imu_protocol import ImuFrame, make_decoder

log = logging.getLogger(__name__)


class ImuReaderError(RuntimeError):
    """The reader stopped because of an error (see ``__cause__``)."""


@dataclass(slots=True)
class ImuSample:
    """One foot-IMU sample delivered to consumers.

    t_device_ns: the device's own stamp (unwrapped, integer ns).
    t_host_ns: host ``time.monotonic_ns()`` at the read that delivered it.
    t_mapped_ns: device stamp mapped onto the host monotonic clock (ClockMapper).
    gyro (3,) rad/s and accel (3,) m/s^2 in the IMU frame; quat (4,) w, x, y, z.
    name: label from ``node_map`` (e.g. the leg "FL"), None without a map.
    """

    node_id: int
    seq: int
    t_device_ns: int
    t_host_ns: int
    t_mapped_ns: int
    gyro: np.ndarray
    accel: np.ndarray
    quat: np.ndarray
    name: str | None = None


class SerialImuReader:
    """Thread reading one serial port of foot IMUs.

    port: device path (``/dev/ttyUSB0``, a pty's ``port_path``).
    protocol: "a2i" or "hipnuc" (``hw.imu_protocol.make_decoder``);
    decoder_options go to the decoder (e.g. ``{"node_id": 2, "rate_hz": 400}``).
    node_map: {node_id: name}; when given, frames of other nodes are dropped and
    counted in ``stats()["unknown_node"]``.
    on_sample(sample) runs in the reader thread: keep it short.
    queue_size: bound of the internal queue (``get``); 0 disables the queue.
    A full queue drops the new sample and counts it in ``queue_overflows``.
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 921600,
        protocol: str = "a2i",
        node_map: Mapping[int, str] | None = None,
        on_sample: Callable[[ImuSample], None] | None = None,
        on_error: Callable[[BaseException], None] | None = None,
        queue_size: int = 8192,
        read_timeout_s: float = 0.02,
        decoder_options: Mapping | None = None,
    ) -> None:
        if queue_size < 0:
            raise ValueError(f"queue_size must be >= 0, got {queue_size}")
        if read_timeout_s <= 0:
            raise ValueError(f"read_timeout_s must be positive, got {read_timeout_s}")
        self.port = port
        self.baudrate = baudrate
        self.protocol = protocol
        self.node_map = dict(node_map) if node_map is not None else None
        self.on_sample = on_sample
        self.on_error = on_error
        self.read_timeout_s = read_timeout_s
        self.decoder = make_decoder(protocol, **dict(decoder_options or {}))
        self.queue: queue.Queue[ImuSample] | None = (
            queue.Queue(maxsize=queue_size) if queue_size else None
        )
        self.error: BaseException | None = None
        self.state = "idle"  # idle -> running -> stopped | error
        self._serial: serial.Serial | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._clocks: dict[int, ClockMapper] = {}
        self._bytes_read = 0
        self._reads = 0
        self._samples = 0
        self._queue_overflows = 0
        self._unknown_node = 0

    # -- lifecycle ---------------------------------------------------------------

    def start(self) -> Self:
        """Open the port (errors raise here, synchronously) and start the thread."""
        if self._thread is not None:
            raise RuntimeError("SerialImuReader already started")
        self._serial = serial.Serial(self.port, self.baudrate, timeout=self.read_timeout_s)
        self.state = "running"
        self._thread = threading.Thread(
            target=self._run, name=f"imu-reader:{self.port}", daemon=True
        )
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the thread, join it and close the port (idempotent)."""
        self._stop.set()
        ser = self._serial
        if ser is not None and ser.is_open:
            try:
                ser.cancel_read()
            except (OSError, TypeError, serial.SerialException):  # closed meanwhile
                pass
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                raise RuntimeError(f"IMU reader thread on {self.port} did not stop")
        self._close_port()
        if self.state == "running":
            self.state = "stopped"

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # -- consumer side -----------------------------------------------------------

    def get(self, timeout_s: float | None = None) -> ImuSample | None:
        """Next queued sample; None on timeout; ImuReaderError once failed and drained."""
        if self.queue is None:
            raise RuntimeError("reader was created with queue_size=0")
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            try:
                return self.queue.get(timeout=0.05)
            except queue.Empty:
                if self.error is not None:
                    raise ImuReaderError(f"IMU reader on {self.port} failed") from self.error
                if deadline is not None and time.monotonic() >= deadline:
                    return None

    def drain(self) -> list[ImuSample]:
        """All samples queued right now (non-blocking)."""
        out: list[ImuSample] = []
        if self.queue is None:
            return out
        while True:
            try:
                out.append(self.queue.get_nowait())
            except queue.Empty:
                return out

    def stats(self) -> dict:
        """Counters: decoder ones plus reads, bytes_read, samples, queue_overflows."""
        d = self.decoder.stats()
        with self._lock:
            d.update(
                bytes_read=self._bytes_read,
                reads=self._reads,
                samples=self._samples,
                queue_overflows=self._queue_overflows,
                unknown_node=self._unknown_node,
                clock_resets={n: c.resets for n, c in self._clocks.items()},
                drift_ppm={n: c.drift_ppm for n, c in self._clocks.items()},
                state=self.state,
            )
        d["seq_gaps_total"] = sum(d["seq_gaps"].values())
        return d

    # -- thread ------------------------------------------------------------------

    def _close_port(self) -> None:
        ser = self._serial
        if ser is not None:
            try:
                ser.close()
            except (OSError, serial.SerialException):
                pass

    def _fail(self, exc: BaseException) -> None:
        self.error = exc
        self.state = "error"
        log.error("IMU reader on %s failed: %r", self.port, exc)
        if self.on_error is not None:
            try:
                self.on_error(exc)
            except Exception:  # the error is already recorded; don't mask it
                log.exception("on_error callback raised")

    def _run(self) -> None:
        ser = self._serial
        assert ser is not None
        try:
            while not self._stop.is_set():
                # Block for the first byte (up to the timeout), then take
                # everything already buffered in one go.
                data = ser.read(1)
                if not data:
                    continue
                waiting = ser.in_waiting
                if waiting:
                    data += ser.read(waiting)
                t_host = time.monotonic_ns()
                with self._lock:
                    self._reads += 1
                    self._bytes_read += len(data)
                frames = self.decoder.feed(data)
                if frames:
                    self._deliver(frames, t_host)
        except (serial.SerialException, OSError) as exc:
            if not self._stop.is_set():
                self._fail(exc)
        except Exception as exc:  # noqa: BLE001 - callback/decoder bug: surface it, never die silently
            self._fail(exc)
        finally:
            self._close_port()

    def _deliver(self, frames: list[ImuFrame], t_host: int) -> None:
        wrap = self.decoder.clock_wrap_us
        wrap_ns = None if wrap is None else wrap * 1000
        for fr in frames:
            name = None
            if self.node_map is not None:
                name = self.node_map.get(fr.node_id)
                if name is None:
                    with self._lock:
                        self._unknown_node += 1
                    continue
            clock = self._clocks.get(fr.node_id)
            if clock is None:  # under the lock: stats() walks the dict from another thread
                with self._lock:
                    clock = self._clocks[fr.node_id] = ClockMapper(wrap_period_ns=wrap_ns)
            t_dev = fr.t_device_us * 1000
            t_mapped = clock.update(t_dev, t_host)
            sample = ImuSample(
                node_id=fr.node_id,
                seq=fr.seq,
                t_device_ns=clock.unwrapped_last,
                t_host_ns=t_host,
                t_mapped_ns=t_mapped,
                gyro=np.array(fr.gyro),
                accel=np.array(fr.accel),
                quat=np.array(fr.quat),
                name=name,
            )
            if self.on_sample is not None:
                self.on_sample(sample)
            overflow = False
            if self.queue is not None:
                try:
                    self.queue.put_nowait(sample)
                except queue.Full:
                    overflow = True
            with self._lock:
                self._samples += 1
                self._queue_overflows += overflow
