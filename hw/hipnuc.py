"""HiPNUC serial protocol (0x5A 0xA5 frames, 0x91 IMU packet): decoder and encoder.

Public references:
- HiPNUC Hi229 User Manual, section "Serial communication protocol" / "0x91
  IMUSOL" / "Example of data frame structure"
  (https://www.hipnuc.com/doc_gen/hi229/hi229um_cn.pdf; markdown mirror in
  github.com/SlimeVRX/SlimeVRX, hipnuc/datasheet/). The literal example frame
  of that section is a test vector in tests/test_imu_protocol.py.
- HiPNUC's own SDK, github.com/hipnuc/products: python/src/hipnuc/decoder.py
  (current HI91 field names, acceleration unit 1 G = 9.8 m/s^2) and
  examples/lib/ch_serial.h.

Frame::

    off size field
      0   1  0x5A
      1   1  0xA5
      2   2  payload length, u16 LE (1..512)
      4   2  CRC, u16 LE: CRC-16/XMODEM (poly 0x1021, init 0, MSB first, no
             reflection) over bytes 0..3 followed by the payload (bytes 6..)
      6   n  payload: one or more packets, each starting with its tag byte

0x91 packet (76 bytes), offsets within the packet::

      0  u8      tag 0x91
      1  u8/u16  legacy Hi229 firmware: user ID (u8) + 6 reserved bytes;
                 current firmware: main_status u16, temperature i8, pressure f32
      8  u32     device time, ms since boot (wraps after 2^32 ms, ~49.7 days)
     12  3 f32   acceleration, G (the firmware divides by 9.8)
     24  3 f32   angular velocity, deg/s
     36  3 f32   magnetic field, uT            (not carried into ImuFrame)
     48  3 f32   roll, pitch, yaw, deg         (not carried into ImuFrame)
     60  4 f32   quaternion w x y z

Bytes 8.. are identical in both firmware generations, which is all the
ImuFrame needs. The protocol has no sequence number and, on current firmware,
no node id: ``node_id`` comes from the constructor (one IMU per port), or from
byte 1 with ``node_id_from_packet=True`` (legacy firmware, ``AT+ID``). The
frame's ``seq`` is reconstructed from the device time when ``rate_hz`` is
given (missed frames then show up in ``seq_gaps``), otherwise it is a
receive counter and ``seq_gaps`` stays empty.
"""

from __future__ import annotations

import binascii
import math
import struct

from hw.imu_protocol import SEQ_MOD, ImuFrame, StreamDecoder

SYNC = b"\x5a\xa5"
TAG_IMU = 0x91
IMU_PACKET_LEN = 76
MAX_PAYLOAD = 512  # the manual's LEN range
HEADER_LEN = 6
GRAVITY_ENCODING = 9.8  # m/s^2 per G used by the firmware, not local gravity
DEG = math.pi / 180.0
CLOCK_WRAP_US = (1 << 32) * 1000

# Packet sizes from the Hi229 manual (tag byte included).
PACKET_SIZES = {0x90: 2, 0xA0: 7, 0xB0: 7, 0xC0: 7, 0xD0: 7, 0xD1: 17, 0xF0: 5, 0x91: 76}
_HEADER = struct.Struct("<2sHH")
_IMU = struct.Struct("<BB6xI3f3f3f3f4f")
_IMU_PARTS = struct.Struct("<I3f3f12x12x4f")  # from byte 8: ts, acc, gyr, (mag, eul), quat


def crc16_xmodem(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """CRC-16/XMODEM (poly 0x1021, init 0). Check: crc16_xmodem(b"123456789") == 0x31C3."""
    return binascii.crc_hqx(data, crc)


def encode_imu_frame(
    frame: ImuFrame,
    mag_ut: tuple[float, float, float] = (0.0, 0.0, 0.0),
    euler_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
    legacy_id: bool = True,
) -> bytes:
    """One HiPNUC frame carrying a single 0x91 packet (for tests and the mock robot).

    ``frame.t_device_us`` is truncated to whole ms (mod 2^32); gyro rad/s and
    accel m/s^2 are converted to deg/s and G. With ``legacy_id`` byte 1 holds
    ``frame.node_id`` (Hi229 layout), otherwise bytes 1..7 are zero.
    """
    if not 0 <= frame.node_id <= 0xFF:
        raise ValueError(f"node_id {frame.node_id} outside u8")
    ts_ms = (frame.t_device_us // 1000) % (1 << 32)
    packet = _IMU.pack(
        TAG_IMU,
        frame.node_id if legacy_id else 0,
        ts_ms,
        *(a / GRAVITY_ENCODING for a in frame.accel),
        *(g / DEG for g in frame.gyro),
        *mag_ut,
        *euler_deg,
        *frame.quat,
    )
    return encode_payload(packet)


def encode_payload(payload: bytes) -> bytes:
    """Wrap an arbitrary payload (one or more packets) into a HiPNUC frame."""
    if not 1 <= len(payload) <= MAX_PAYLOAD:
        raise ValueError(f"payload length {len(payload)} outside 1..{MAX_PAYLOAD}")
    head = SYNC + struct.pack("<H", len(payload))
    crc = crc16_xmodem(payload, crc16_xmodem(head))
    return head + struct.pack("<H", crc) + payload


class HipnucDecoder(StreamDecoder):
    """Streaming decoder of HiPNUC frames yielding ``ImuFrame`` (SI units).

    Same interface and counters as ``hw.imu_protocol.FrameDecoder``. Frames
    whose payload holds no 0x91 packet (other packet sets) are CRC-checked,
    counted in ``unknown_packets`` and skipped. Packets are walked by tag with
    the manual's packet sizes; an unknown tag ends the walk (its size is not
    knowable), after any 0x91 already found.
    """

    clock_wrap_us: int | None = CLOCK_WRAP_US
    sync = SYNC
    header_len = HEADER_LEN

    def __init__(
        self,
        node_id: int = 0,
        node_id_from_packet: bool = False,
        rate_hz: float | None = None,
    ) -> None:
        if not 0 <= node_id <= 0xFF:
            raise ValueError(f"node_id {node_id} outside u8")
        if rate_hz is not None and not 0 < rate_hz <= 600:
            raise ValueError(f"rate_hz {rate_hz} outside (0, 600]: 1 ms stamps cannot "
                             "tell one frame period from two above that")
        self.node_id = node_id
        self.node_id_from_packet = node_id_from_packet
        self.rate_hz = rate_hz
        super().__init__()
        self._counter: dict[int, int] = {}
        self._seq_anchor: dict[int, tuple[int, int]] = {}  # node -> (ts_ms, seq)

    def _seq_for(self, node: int, ts_ms: int) -> int:
        if self.rate_hz is None:
            seq = self._counter.get(node, -1) + 1
            self._counter[node] = seq
            return seq % SEQ_MOD
        anchor = self._seq_anchor.get(node)
        if anchor is None:
            self._seq_anchor[node] = (ts_ms, 0)
            return 0
        dt_ms = (ts_ms - anchor[0]) % (1 << 32)
        if dt_ms >= 1 << 31:  # device clock went backwards: the IMU rebooted
            self._seq.reboot(node)
            self._seq_anchor[node] = (ts_ms, anchor[1])
            return anchor[1]
        seq = (anchor[1] + round(dt_ms * self.rate_hz / 1000.0)) % SEQ_MOD
        self._seq_anchor[node] = (ts_ms, seq)
        return seq

    def _imu_packets(self, buf: bytearray, start: int, end: int) -> list[int]:
        """Offsets of the 0x91 packets in payload buf[start:end]."""
        found = []
        k = start
        while k < end:
            size = PACKET_SIZES.get(buf[k])
            if size is None or k + size > end:
                break
            if buf[k] == TAG_IMU:
                found.append(k)
            k += size
        return found

    def _frame_end(self, buf: bytearray, i: int) -> int:
        length = buf[i + 2] | (buf[i + 3] << 8)
        return i + HEADER_LEN + length if 1 <= length <= MAX_PAYLOAD else -1

    def _crc_ok(self, mv: memoryview, i: int, end: int) -> bool:
        crc = binascii.crc_hqx(mv[i : i + 4], 0)
        return binascii.crc_hqx(mv[i + HEADER_LEN : end], crc) == mv[i + 4] | (mv[i + 5] << 8)

    def _unpack(self, buf: bytearray, i: int, end: int, out: list[ImuFrame]) -> None:
        offsets = self._imu_packets(buf, i + HEADER_LEN, end)
        if not offsets:
            self.unknown_packets += 1
            return
        for k in offsets:
            vals = _IMU_PARTS.unpack_from(buf, k + 8)
            if not math.isfinite(sum(vals[1:])):
                self.invalid_frames += 1
                continue
            node = buf[k + 1] if self.node_id_from_packet else self.node_id
            ts_ms = vals[0]
            seq = self._seq_for(node, ts_ms)
            self._seq.update(node, seq)
            accel = tuple(a * GRAVITY_ENCODING for a in vals[1:4])
            gyro = tuple(g * DEG for g in vals[4:7])
            out.append(ImuFrame(node, seq, ts_ms * 1000, gyro, accel, vals[7:11]))
