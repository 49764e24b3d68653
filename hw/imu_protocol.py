"""The A2I foot-IMU frame protocol: encoder and streaming decoder.

Wire format (all multi-byte fields little-endian; full spec with a worked
example in ``docs/imu-protocol.md``)::

    off size field
      0   2  sync          0xA2 0x49
      2   1  length        payload bytes after the type byte (IMU v1: 51)
      3   1  type          (version << 4) | kind; v1 IMU sample = 0x11
      4   1  node_id       u8, radio node on the shared receiver
      5   2  seq           u16, +1 per sample of that node, wraps 65535 -> 0
      7   8  t_device_us   u64, device clock in microseconds (no wrap in practice;
                           a reset to 0 after a reboot is handled by ClockMapper)
     15  12  gyro          3 x f32, rad/s, IMU frame
     27  12  accel         3 x f32, m/s^2, IMU frame (specific force)
     39  16  quat          4 x f32, w x y z, IMU frame -> device world frame
     55   2  crc           CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection,
                           xorout 0) over bytes 2 .. 54 (length, type, payload)

A frame is 57 bytes. The decoder never yields a frame whose CRC fails or whose
floats are not finite, and after a rejected candidate it resumes the search one
byte after the rejected sync, so a real frame that starts inside garbage is kept.
"""

from __future__ import annotations

import binascii
import math
import struct
from dataclasses import dataclass, field
from typing import Protocol

SYNC = b"\xa2\x49"
PROTOCOL_VERSION = 1
KIND_IMU = 1
TYPE_IMU_V1 = (PROTOCOL_VERSION << 4) | KIND_IMU  # 0x11
MAX_PAYLOAD = 200  # longest payload any version may announce; longer = impossible

_HEADER = struct.Struct("<2sBB")  # sync, length, type
_IMU_BODY = struct.Struct("<BHQ10f")  # node, seq, t_us, gyro 3, accel 3, quat 4
IMU_PAYLOAD_LEN = _IMU_BODY.size  # 51
_CRC = struct.Struct("<H")
HEADER_LEN = _HEADER.size  # 4
FRAME_LEN = HEADER_LEN + IMU_PAYLOAD_LEN + _CRC.size  # 57
SEQ_MOD = 1 << 16

# Payload length each known type must have; a candidate disagreeing is rejected
# before its CRC is even computed.
_KNOWN_LENGTHS = {TYPE_IMU_V1: IMU_PAYLOAD_LEN}


def crc16_ccitt_false(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, MSB first, xorout 0).

    ``binascii.crc_hqx`` is the same MSB-first 0x1021 CRC in C; only the initial
    value differs between the CCITT-FALSE (0xFFFF) and XMODEM (0) variants.
    Check value: crc16_ccitt_false(b"123456789") == 0x29B1.
    """
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(slots=True, frozen=True)
class ImuFrame:
    """One decoded IMU sample, SI units, protocol independent.

    node_id: radio node (u8). seq: per-node sequence number (u16, wraps).
    t_device_us: device clock, integer microseconds (may wrap for protocols with
    a narrow counter: see the decoder's ``clock_wrap_us``).
    gyro: rad/s, accel: m/s^2 (specific force), both in the IMU frame.
    quat: (w, x, y, z) orientation of the IMU frame in the device's world frame.
    """

    node_id: int
    seq: int
    t_device_us: int
    gyro: tuple[float, float, float]
    accel: tuple[float, float, float]
    quat: tuple[float, float, float, float]


class FrameDecoderLike(Protocol):
    """What SerialImuReader needs from a decoder (see ``make_decoder``)."""

    clock_wrap_us: int | None
    frames: int
    crc_errors: int
    bytes_discarded: int
    seq_gaps: dict[int, int]

    def feed(self, data: bytes | bytearray | memoryview) -> list[ImuFrame]: ...

    def stats(self) -> dict: ...


def encode_frame(frame: ImuFrame) -> bytes:
    """Serialize one ImuFrame into a 57-byte A2I v1 frame (floats rounded to f32)."""
    if not 0 <= frame.node_id <= 0xFF:
        raise ValueError(f"node_id {frame.node_id} outside u8")
    if not 0 <= frame.seq < SEQ_MOD:
        raise ValueError(f"seq {frame.seq} outside u16")
    if not 0 <= frame.t_device_us < (1 << 64):
        raise ValueError(f"t_device_us {frame.t_device_us} outside u64")
    if len(frame.gyro) != 3 or len(frame.accel) != 3 or len(frame.quat) != 4:
        raise ValueError("gyro and accel need 3 values, quat needs 4")
    body = _IMU_BODY.pack(
        frame.node_id, frame.seq, frame.t_device_us, *frame.gyro, *frame.accel, *frame.quat
    )
    head = _HEADER.pack(SYNC, len(body), TYPE_IMU_V1)
    crc = crc16_ccitt_false(head[2:] + body)
    return head + body + _CRC.pack(crc)


def f32(values) -> tuple[float, ...]:
    """Round floats to what survives an f32 round trip (for building expected frames)."""
    n = len(values)
    return struct.unpack(f"<{n}f", struct.pack(f"<{n}f", *values))


@dataclass(slots=True)
class SeqTracker:
    """Per-node missed-frame counting from a wrapping sequence number.

    A forward step of k (mod ``modulus``) means k - 1 frames were missed. A step
    of 0 (duplicate) or a backward step (more than half the range) counts as a
    restart, never as ~65535 missed frames; so does :meth:`reboot`, which the
    decoders call when a node's device clock goes backwards (a reboot restarts seq
    at 0, which from past half the range reads as a forward step).
    """

    modulus: int = SEQ_MOD
    gaps: dict[int, int] = field(default_factory=dict)
    restarts: int = 0
    _last: dict[int, int] = field(default_factory=dict)

    def reboot(self, node: int) -> None:
        """The node's device clock went backwards: new seq baseline, no gap counted."""
        if self._last.pop(node, None) is not None:
            self.restarts += 1

    def update(self, node: int, seq: int) -> None:
        last = self._last.get(node)
        self._last[node] = seq
        if last is None:
            self.gaps.setdefault(node, 0)
            return
        step = (seq - last) % self.modulus
        if step == 1:
            return
        if step == 0 or step > self.modulus // 2:
            self.restarts += 1
            return
        self.gaps[node] = self.gaps.get(node, 0) + step - 1


class StreamDecoder:
    """What every serial IMU decoder shares: the byte buffer, the counters, feed and finish.

    Counters (all monotonic): ``frames`` accepted, ``crc_errors``, ``length_errors``
    (impossible length for the type, or beyond the protocol's maximum), ``invalid_frames``
    (CRC fine but a non-finite float), ``unknown_packets`` (CRC-valid packet of a type the
    decoder does not know: skipped whole), ``bytes_discarded`` and per-node ``seq_gaps``.
    Invariant: bytes_fed == bytes_consumed + bytes_discarded + buffered. The framing (sync
    search, length, CRC, resynchronisation) is shared; a protocol gives its ``sync`` and
    ``header_len``, and ``_frame_end``, ``_crc_ok`` and ``_unpack``.
    """

    clock_wrap_us: int | None = None
    sync: bytes = b""  # the protocol's sync bytes
    header_len: int = 0  # bytes from the sync to where the frame's length is known

    def __init__(self) -> None:
        self._buf = bytearray()
        self.frames = 0
        self.crc_errors = 0
        self.length_errors = 0
        self.invalid_frames = 0
        self.unknown_packets = 0
        self.bytes_discarded = 0
        self.bytes_fed = 0
        self.bytes_consumed = 0  # bytes of CRC-valid packets, decoded or skipped
        self._seq = SeqTracker()
        self._last_t: dict[int, int] = {}  # node -> its last device time (A2I frames)

    @property
    def seq_gaps(self) -> dict[int, int]:
        return self._seq.gaps

    @property
    def buffered(self) -> int:
        return len(self._buf)

    def stats(self) -> dict:
        return {
            "frames": self.frames,
            "crc_errors": self.crc_errors,
            "length_errors": self.length_errors,
            "invalid_frames": self.invalid_frames,
            "unknown_packets": self.unknown_packets,
            "bytes_discarded": self.bytes_discarded,
            "bytes_fed": self.bytes_fed,
            "bytes_consumed": self.bytes_consumed,
            "seq_gaps": dict(self._seq.gaps),
            "seq_restarts": self._seq.restarts,
        }

    def feed(self, data: bytes | bytearray | memoryview) -> list[ImuFrame]:
        """Append ``data`` and return every complete, valid frame now available."""
        self._buf += data
        self.bytes_fed += len(data)
        return self._decode(final=False)

    def finish(self) -> list[ImuFrame]:
        """End of stream: reject incomplete candidates, return frames they hid.

        A garbage sync announcing a long packet makes ``feed`` wait for its bytes; at the end
        of a finite stream (a log file) call this so real frames behind such a candidate are
        not left in the buffer.
        """
        out = self._decode(final=True)
        self.bytes_discarded += len(self._buf)
        self._buf.clear()
        return out

    def _frame_end(self, buf: bytearray, i: int) -> int:
        """The end (exclusive) of the frame whose header starts at ``buf[i]`` (``header_len``
        bytes there), or -1 where the header announces a length the protocol cannot have."""
        raise NotImplementedError

    def _crc_ok(self, mv: memoryview, i: int, end: int) -> bool:
        """Whether the frame ``mv[i:end]`` carries a valid CRC."""
        raise NotImplementedError

    def _unpack(self, buf: bytearray, i: int, end: int, out: list[ImuFrame]) -> None:
        """Append the IMU samples of the CRC-valid frame ``buf[i:end]`` to ``out``, counting
        ``unknown_packets`` and ``invalid_frames``."""
        raise NotImplementedError

    def _decode(self, final: bool) -> list[ImuFrame]:
        """Consume ``self._buf``: every frame whose header, length and CRC hold, in order. After
        a rejected candidate the search resumes one byte after its sync, so a real frame that
        starts inside garbage is kept; a candidate still incomplete waits for more bytes unless
        ``final``."""
        buf = self._buf
        out: list[ImuFrame] = []
        n = len(buf)
        pos = 0  # start of the bytes not yet consumed or discarded
        search = 0  # where the next sync search starts (> pos after a rejection)
        sync, header_len = self.sync, self.header_len
        frame_end, crc_ok, unpack = self._frame_end, self._crc_ok, self._unpack
        mv = memoryview(buf)
        try:
            while True:
                i = buf.find(sync, search)
                if i < 0:
                    # Keep a trailing first sync byte: its partner may come next.
                    keep = 1 if n > pos and buf[n - 1] == sync[0] else 0
                    self.bytes_discarded += n - keep - pos
                    pos = n - keep
                    break
                end = i + header_len
                if end <= n:
                    end = frame_end(buf, i)
                    if end < 0:
                        self.length_errors += 1
                        search = i + 1
                        continue
                if end > n:
                    if final:
                        search = i + 1
                        continue
                    self.bytes_discarded += i - pos
                    pos = i
                    break
                if not crc_ok(mv, i, end):
                    self.crc_errors += 1
                    search = i + 1
                    continue
                self.bytes_discarded += i - pos
                self.bytes_consumed += end - i
                pos = search = end
                unpack(buf, i, end, out)
        finally:
            mv.release()
        if pos:
            del buf[:pos]
        self.frames += len(out)
        return out


class FrameDecoder(StreamDecoder):
    """Streaming decoder of A2I frames; feed arbitrary chunks, get whole frames (counters:
    :class:`StreamDecoder`)."""

    clock_wrap_us: int | None = None  # u64 microseconds: never wraps in practice
    sync = SYNC
    header_len = HEADER_LEN

    def _frame_end(self, buf: bytearray, i: int) -> int:
        length = buf[i + 2]
        expected = _KNOWN_LENGTHS.get(buf[i + 3])
        if (expected is not None and length != expected) or length > MAX_PAYLOAD:
            return -1
        return i + HEADER_LEN + length + 2

    def _crc_ok(self, mv: memoryview, i: int, end: int) -> bool:
        return binascii.crc_hqx(mv[i + 2 : end - 2], 0xFFFF) == mv[end - 2] | (mv[end - 1] << 8)

    def _unpack(self, buf: bytearray, i: int, end: int, out: list[ImuFrame]) -> None:
        if buf[i + 3] not in _KNOWN_LENGTHS:
            self.unknown_packets += 1
            return
        vals = _IMU_BODY.unpack_from(buf, i + HEADER_LEN)
        # Each f32 is exactly representable in f64 and 10 of them cannot
        # overflow a double, so the sum is finite iff every value is.
        if not math.isfinite(sum(vals[3:])):
            self.invalid_frames += 1
            return
        node, seq = vals[0], vals[1]
        last_t = self._last_t.get(node)
        self._last_t[node] = vals[2]
        if last_t is not None and vals[2] < last_t:
            self._seq.reboot(node)
        self._seq.update(node, seq)
        out.append(ImuFrame(node, seq, vals[2], vals[3:6], vals[6:9], vals[9:13]))


def make_decoder(protocol: str, **kwargs) -> FrameDecoderLike:
    """Decoder by protocol name: "a2i" (this module) or "hipnuc" (HiPNUC 0x91)."""
    name = protocol.lower()
    if name == "a2i":
        if kwargs:
            raise ValueError(f"a2i decoder takes no options, got {sorted(kwargs)}")
        return FrameDecoder()
    if name == "hipnuc":
        from hw.hipnuc import HipnucDecoder

        return HipnucDecoder(**kwargs)
    raise ValueError(f"unknown IMU protocol {protocol!r}; known: 'a2i', 'hipnuc'")


PROTOCOLS = ("a2i", "hipnuc")
