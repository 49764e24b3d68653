"""The recorder: fixed-memory ring buffers for the Go2 messages, the foot IMUs and events.

Writers are the 50 Hz control loop (``record_lowstate``, ``record_lowcmd``,
``record_wireless``), one reader thread per foot IMU (``record_imu``) and the state machine
(``record_event``). Each stream is its own :class:`hw.ringbuffer.RingBuffer`, so every stream has
its own single writer; the writers never wait on readers. The calibrator (or an MCAP export)
calls :meth:`Recorder.snapshot` from any thread and gets copies.

All memory is allocated in the constructor: :meth:`Recorder.memory_bytes` is fixed by the config.

Units and frames of every stream (the same ones the MCAP file documents, ``docs/recording.md``):

* times are ``int64`` nanoseconds of the host's monotonic clock (``t_host_ns``: receive time);
  ``t_device_ns`` is the IMU's own stamp in its own clock, ``t_mapped_ns`` that stamp mapped into
  the host clock by the driver; a negative value means unknown.
* joint arrays are in SDK order (FR, FL, RR, RL) x (hip, thigh, calf): rad, rad/s, N m.
* Go2 body IMU (LowState ``imu_state``): quaternion (w, x, y, z), gyro rad/s, accel m/s^2, in the
  Go2 IMU frame as the robot reports them.
* foot IMUs: gyro rad/s and accel m/s^2 in the foot IMU's own sensor frame I, quaternion
  (w, x, y, z) as the device reports it (all zero when the device gives none).
* sample values are ``float32``: what the Go2 puts on the wire, and more than any MEMS IMU resolves.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import numpy as np

from hw.ringbuffer import RingBuffer, blob_fields

__all__ = [
    "EVENT_DTYPE",
    "EVENT_TEXT_BYTES",
    "LEGS",
    "LOWCMD_BYTES",
    "LOWSTATE_BYTES",
    "Recorder",
    "RecorderConfig",
    "RecordingSnapshot",
    "imu_dtype",
    "lowcmd_dtype",
    "lowstate_dtype",
    "stream_names",
    "wireless_dtype",
]

LEGS = ("FL", "FR", "RL", "RR")
LOWSTATE_BYTES = 1180  # CDR incl. the 4-byte encapsulation header (docs/FACTS)
LOWCMD_BYTES = 812
WIRELESS_BYTES = 24  # 4 header + 18 body + 2 padding as Cyclone DDS writes it (22 unpadded)
EVENT_TEXT_BYTES = 64
TIME_UNKNOWN = -1


def lowstate_dtype(raw_bytes: int = LOWSTATE_BYTES) -> np.dtype:
    """Row of the ``lowstate`` stream: receive time, the exact CDR bytes, and decoded fields."""
    return np.dtype([("t_host_ns", "i8"), *blob_fields("raw", raw_bytes),
                     ("q", "f4", (12,)), ("dq", "f4", (12,)), ("tau_est", "f4", (12,)),
                     ("imu_quat_wxyz", "f4", (4,)), ("imu_gyro", "f4", (3,)),
                     ("imu_accel", "f4", (3,)), ("tick", "u4")])


def lowcmd_dtype(raw_bytes: int = LOWCMD_BYTES) -> np.dtype:
    """Row of the ``lowcmd`` stream: send time, the exact CDR bytes, and the 12 commanded motors."""
    return np.dtype([("t_host_ns", "i8"), *blob_fields("raw", raw_bytes),
                     ("q_des", "f4", (12,)), ("dq_des", "f4", (12,)), ("kp", "f4", (12,)),
                     ("kd", "f4", (12,)), ("tau_ff", "f4", (12,))])


def wireless_dtype(raw_bytes: int = WIRELESS_BYTES) -> np.dtype:
    """Row of the ``wireless`` stream: receive time and the WirelessController_ CDR bytes."""
    return np.dtype([("t_host_ns", "i8"), *blob_fields("raw", raw_bytes)])


def imu_dtype() -> np.dtype:
    """Row of an ``imu/<LEG>`` stream (one foot IMU)."""
    return np.dtype([("t_host_ns", "i8"), ("t_device_ns", "i8"), ("t_mapped_ns", "i8"),
                     ("seq", "u2"), ("node", "u1"), ("gyro", "f4", (3,)),
                     ("accel", "f4", (3,)), ("quat_wxyz", "f4", (4,))])


EVENT_DTYPE = np.dtype([("t_host_ns", "i8"), ("code", "i4"), ("text", f"S{EVENT_TEXT_BYTES}")])


def stream_names(legs=LEGS) -> tuple[str, ...]:
    """Names of the streams of a recorder with these foot IMUs, in a fixed order."""
    return ("lowstate", "lowcmd", "wireless", *(f"imu/{leg}" for leg in legs), "events")


@dataclass(frozen=True)
class RecorderConfig:
    """Sizes of the recorder's ring buffers: ``seconds`` of history at each stream's rate.

    Rates are in Hz; ``headroom`` multiplies every derived capacity (clock jitter, bursts).
    ``capacity_overrides`` maps a stream name (``"lowstate"``, ``"imu/FL"``, ...) to an exact
    row count. ``*_raw_bytes`` are the slot sizes of the raw CDR messages (header included).
    """

    seconds: float = 120.0
    lowstate_hz: float = 500.0
    lowcmd_hz: float = 50.0
    wireless_hz: float = 50.0
    imu_hz: float = 1000.0
    legs: tuple[str, ...] = LEGS
    event_capacity: int = 4096
    headroom: float = 1.1
    lowstate_raw_bytes: int = LOWSTATE_BYTES
    lowcmd_raw_bytes: int = LOWCMD_BYTES
    wireless_raw_bytes: int = WIRELESS_BYTES
    capacity_overrides: dict[str, int] = field(default_factory=dict)

    def __post_init__(self):
        if not (self.seconds > 0 and math.isfinite(self.seconds)):
            raise ValueError(f"seconds must be positive and finite, got {self.seconds}")
        if self.headroom < 1.0:
            raise ValueError(f"headroom must be >= 1, got {self.headroom}")
        for name in ("lowstate_hz", "lowcmd_hz", "wireless_hz", "imu_hz"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        object.__setattr__(self, "legs", tuple(self.legs))
        for leg in self.legs:
            if leg not in LEGS:
                raise ValueError(f"unknown leg {leg!r}; legs are {LEGS}")
        if len(set(self.legs)) != len(self.legs):
            raise ValueError(f"duplicate legs in {self.legs}")
        # One canonical order (FL, FR, RL, RR) so snapshots and files list streams alike.
        object.__setattr__(self, "legs", tuple(leg for leg in LEGS if leg in self.legs))
        known = set(stream_names(self.legs))
        for name, cap in self.capacity_overrides.items():
            if name not in known:
                raise ValueError(f"capacity override for unknown stream {name!r}")
            if int(cap) != cap or cap <= 0:
                raise ValueError(f"capacity of {name} must be a positive integer, got {cap}")

    def capacity(self, stream: str) -> int:
        """Row count of one stream's ring buffer."""
        if stream in self.capacity_overrides:
            return int(self.capacity_overrides[stream])
        if stream == "events":
            return int(self.event_capacity)
        rate = {"lowstate": self.lowstate_hz, "lowcmd": self.lowcmd_hz,
                "wireless": self.wireless_hz}.get(stream)
        if rate is None:
            if stream.startswith("imu/") and stream[4:] in self.legs:
                rate = self.imu_hz
            else:
                raise ValueError(f"unknown stream {stream!r}")
        return max(1, math.ceil(self.seconds * rate * self.headroom))


@dataclass
class RecordingSnapshot:
    """Copies of every stream over a time window: what the calibrator and the MCAP writer read.

    Arrays are numpy structured arrays (dtypes in this module), oldest row first; ``imu`` maps
    leg name to that foot IMU's rows. ``total_written[name]`` and ``overwritten[name]`` are the
    stream's counters when the copy was taken (stream names from :func:`stream_names`):
    ``overwritten > 0`` means the ring wrapped and the oldest rows are gone.
    ``t0_ns``/``t1_ns``: the requested window (``None`` = open), half-open ``[t0, t1)``.
    """

    lowstate: np.ndarray
    lowcmd: np.ndarray
    wireless: np.ndarray
    imu: dict[str, np.ndarray]
    events: np.ndarray
    total_written: dict[str, int]
    overwritten: dict[str, int]
    t0_ns: int | None = None
    t1_ns: int | None = None

    def stream(self, name: str) -> np.ndarray:
        """Rows of a stream by its name (``"lowstate"``, ``"imu/FL"``, ...)."""
        if name.startswith("imu/"):
            leg = name[4:]
            if leg not in self.imu:
                raise ValueError(f"no foot IMU {leg!r} in this snapshot (have {sorted(self.imu)})")
            return self.imu[leg]
        if name not in ("lowstate", "lowcmd", "wireless", "events"):
            raise ValueError(f"unknown stream {name!r}")
        return getattr(self, name)

    @property
    def stream_names(self) -> tuple[str, ...]:
        return stream_names(tuple(self.imu))

    def events_text(self) -> list[tuple[int, int, str]]:
        """Events as ``(t_host_ns, code, text)`` with the text decoded from UTF-8."""
        return [(int(t), int(c), bytes(s).decode("utf-8", "replace"))
                for t, c, s in zip(self.events["t_host_ns"], self.events["code"],
                                   self.events["text"])]


class Recorder:
    """Ring buffers for ``lowstate``, ``lowcmd``, ``wireless``, ``imu/<LEG>`` and ``events``.

    One writer thread per stream (the control loop for the Go2 streams, one reader thread per
    foot IMU); ``record_event`` alone takes a small lock so that several threads may log events.
    """

    def __init__(self, config: RecorderConfig | None = None):
        self.config = config = config if config is not None else RecorderConfig()
        self._rings: dict[str, RingBuffer] = {
            "lowstate": RingBuffer(lowstate_dtype(config.lowstate_raw_bytes),
                                   config.capacity("lowstate")),
            "lowcmd": RingBuffer(lowcmd_dtype(config.lowcmd_raw_bytes), config.capacity("lowcmd")),
            "wireless": RingBuffer(wireless_dtype(config.wireless_raw_bytes),
                                   config.capacity("wireless")),
        }
        self._imu: dict[str, RingBuffer] = {}
        for leg in config.legs:
            ring = RingBuffer(imu_dtype(), config.capacity(f"imu/{leg}"))
            self._rings[f"imu/{leg}"] = ring
            self._imu[leg] = ring
        self._rings["events"] = RingBuffer(EVENT_DTYPE, config.capacity("events"))
        self._event_lock = threading.Lock()
        self._memory = sum(r.nbytes for r in self._rings.values())

    # ---------------------------------------------------------------- writers

    def record_lowstate(self, t_ns: int, raw, q, dq, tau, quat, gyro, accel, tick: int) -> None:
        """One LowState_: host receive time (ns), its CDR bytes, decoded fields (SDK order).

        ``q`` rad, ``dq`` rad/s, ``tau`` (tau_est) N m, each 12; body IMU ``quat`` (w, x, y, z),
        ``gyro`` rad/s, ``accel`` m/s^2; ``tick`` the robot's u32 tick.
        """
        self._rings["lowstate"].append_row(t_ns, raw, q, dq, tau, quat, gyro, accel, tick)

    def record_lowcmd(self, t_ns: int, raw, q_des, dq_des, kp, kd, tau_ff) -> None:
        """One LowCmd_ as sent: host send time (ns), its CDR bytes, and motors 0-11 (SDK order).

        ``q_des`` rad, ``dq_des`` rad/s, ``kp`` N m/rad, ``kd`` N m s/rad, ``tau_ff`` N m.
        """
        self._rings["lowcmd"].append_row(t_ns, raw, q_des, dq_des, kp, kd, tau_ff)

    def record_wireless(self, t_ns: int, raw) -> None:
        """One WirelessController_: host receive time (ns) and its CDR bytes."""
        self._rings["wireless"].append_row(t_ns, raw)

    def record_imu(self, leg: str, t_host_ns: int, t_device_ns: int, t_mapped_ns: int,
                   seq: int, node: int, gyro, accel, quat_wxyz) -> None:
        """One foot-IMU sample of ``leg``: host receive time, device stamp, mapped stamp (ns;
        negative = unknown), frame sequence number (u16), node id (u8), gyro rad/s, accel
        m/s^2 (IMU frame), quaternion (w, x, y, z)."""
        ring = self._imu.get(leg)
        if ring is None:
            raise ValueError(f"no foot IMU stream for leg {leg!r} (configured: {self.config.legs})")
        ring.append_row(t_host_ns, t_device_ns, t_mapped_ns, seq, node, gyro, accel, quat_wxyz)

    def record_event(self, t_ns: int, text: str, code: int = 0) -> None:
        """A state-machine event: host time (ns), UTF-8 text (cut to 64 bytes), integer code."""
        data = text.encode("utf-8")
        if len(data) > EVENT_TEXT_BYTES:
            data = data[:EVENT_TEXT_BYTES].decode("utf-8", "ignore").encode("utf-8")
        with self._event_lock:  # events come from several threads; they are rare
            self._rings["events"].append_row(t_ns, code, data)

    # ---------------------------------------------------------------- readers

    def ring(self, stream: str) -> RingBuffer:
        """The ring buffer of one stream (for readers and counters)."""
        try:
            return self._rings[stream]
        except KeyError:
            raise ValueError(f"unknown stream {stream!r}; have {tuple(self._rings)}") from None

    @property
    def stream_names(self) -> tuple[str, ...]:
        return tuple(self._rings)

    def snapshot(self, t0_ns: int | None = None, t1_ns: int | None = None) -> RecordingSnapshot:
        """Copies of every stream with ``t0_ns <= t_host_ns < t1_ns`` (``None`` = open end).

        Never blocks the writers. Each stream's copy is internally consistent; streams are
        copied one after another, so their newest rows may differ by the time the copy took.
        """
        reads = {name: ring.read(t0_ns, t1_ns) for name, ring in self._rings.items()}
        return RecordingSnapshot(
            lowstate=reads["lowstate"].rows,
            lowcmd=reads["lowcmd"].rows,
            wireless=reads["wireless"].rows,
            imu={leg: reads[f"imu/{leg}"].rows for leg in self.config.legs},
            events=reads["events"].rows,
            total_written={n: r.total_written for n, r in reads.items()},
            overwritten={n: r.overwritten for n, r in reads.items()},
            t0_ns=t0_ns,
            t1_ns=t1_ns,
        )

    def counters(self) -> dict[str, tuple[int, int]]:
        """``{stream: (total_written, overwritten)}`` right now."""
        return {n: (r.total_written, r.overwritten) for n, r in self._rings.items()}

    def memory_bytes(self) -> int:
        """Bytes of ring storage: fixed by the config at construction, never grows."""
        return self._memory
