"""A2I frame protocol and HiPNUC decoder: vectors, streaming, resync, fuzzing."""

from __future__ import annotations

import math
import random
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hw.hipnuc import (
    CLOCK_WRAP_US,
    HipnucDecoder,
    crc16_xmodem,
    encode_imu_frame,
    encode_payload,
)
from hw.imu_protocol import (
    FRAME_LEN,
    HEADER_LEN,
    IMU_PAYLOAD_LEN,
    MAX_PAYLOAD,
    SYNC,
    TYPE_IMU_V1,
    FrameDecoder,
    ImuFrame,
    crc16_ccitt_false,
    encode_frame,
    f32,
    make_decoder,
)

FUZZ = settings(max_examples=150, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow])

# The worked example of docs/imu-protocol.md, byte for byte.
DOC_FRAME = ImuFrame(3, 65535, 123456789, f32((0.1, -0.2, 0.3)), f32((0.0, 0.0, 9.81)),
                     (1.0, 0.0, 0.0, 0.0))
DOC_FRAME_HEX = (
    "a2 49 33 11 03 ff ff 15 cd 5b 07 00 00 00 00 cd cc cc 3d cd cc 4c be 9a 99 99 3e "
    "00 00 00 00 00 00 00 00 c3 f5 1c 41 00 00 80 3f 00 00 00 00 00 00 00 00 00 00 00 00 "
    "69 dc"
)

# HiPNUC Hi229 user manual, "Example of data frame structure", 0x91 frame.
HIPNUC_DOC_0X91 = (
    "5A A5 4C 00 6C 51 91 00 A0 3B 01 A8 02 97 BD BB 04 00 9C A0 65 3E A2 26 45 3F 5C E7 "
    "30 3F E2 D4 5A C2 E5 9D A0 C1 EB 23 EE C2 78 77 99 41 AB AA D1 C1 AB 2A 0A C2 8D E1 "
    "42 42 8F 1D A8 C1 1E 0C 36 C2 E6 E5 5A 3F C1 94 9E 3E B8 C0 9E BE BE DF 8D BE"
)
# Same manual, frame configured as 0x90 A0 B0 C0 D0 F0 packets (no 0x91).
HIPNUC_DOC_LEGACY = (
    "5A A5 23 00 FD 61 90 00 A0 55 02 3D 01 E2 02 B0 FE FF 17 00 44 00 C0 80 FF 60 FF 32 "
    "FF D0 64 F2 6C 0E BB 01 F0 00 00 00 00"
)
# HiPNUC SDK fixture (github.com/hipnuc/products python/tests/fixtures), current HI91
# layout: device time 123456 ms, acc (1, -0.5, 0.25) G, gyr (180, -90, 45) deg/s.
HIPNUC_SDK_HI91 = (
    "5aa54c0050959108081980e6c54740e201000000803f000000bf0000803e000034430000b4c2000034420000"
    "20410000a0c10000f041000020410000a0c10000f0410000803f000000000000000000000000"
)


def make_frames(n: int, seed: int = 0, nodes: int = 4) -> list[ImuFrame]:
    rng = random.Random(seed)
    seqs = [rng.randrange(65536) for _ in range(nodes)]
    out = []
    for k in range(n):
        node = k % nodes
        seqs[node] = (seqs[node] + 1) % 65536
        out.append(ImuFrame(
            node, seqs[node], 10_000_000 + 5000 * k,
            f32([rng.uniform(-30, 30) for _ in range(3)]),
            f32([rng.uniform(-150, 150) for _ in range(3)]),
            f32([rng.uniform(-1, 1) for _ in range(4)]),
        ))
    return out


def check_invariant(dec) -> None:
    assert dec.bytes_fed == dec.bytes_consumed + dec.bytes_discarded + dec.buffered


# -- CRC and layout --------------------------------------------------------------


def test_crc_check_values():
    assert crc16_ccitt_false(b"123456789") == 0x29B1
    assert crc16_xmodem(b"123456789") == 0x31C3


def test_layout_sizes():
    assert IMU_PAYLOAD_LEN == 51 and FRAME_LEN == 57 and TYPE_IMU_V1 == 0x11


def test_doc_example_frame_is_exact():
    raw = encode_frame(DOC_FRAME)
    assert raw == bytes.fromhex(DOC_FRAME_HEX)
    assert crc16_ccitt_false(raw[2:-2]) == 0xDC69
    dec = FrameDecoder()
    assert dec.feed(bytes.fromhex(DOC_FRAME_HEX)) == [DOC_FRAME]


def test_round_trip_many():
    frames = make_frames(300)
    dec = FrameDecoder()
    assert dec.feed(b"".join(encode_frame(f) for f in frames)) == frames
    assert dec.frames == 300 and dec.crc_errors == 0 and dec.bytes_discarded == 0
    assert sum(dec.seq_gaps.values()) == 0
    check_invariant(dec)


@pytest.mark.parametrize("bad", [
    {"node_id": 256}, {"seq": 65536}, {"seq": -1}, {"t_device_us": -1},
    {"gyro": (0.0, 0.0)}, {"quat": (1.0, 0.0, 0.0)},
])
def test_encode_rejects_bad_fields(bad):
    fields = {"node_id": 0, "seq": 0, "t_device_us": 0, "gyro": (0.0,) * 3,
              "accel": (0.0,) * 3, "quat": (1.0, 0.0, 0.0, 0.0)}
    fields.update(bad)
    with pytest.raises(ValueError):
        encode_frame(ImuFrame(**fields))


# -- streaming -------------------------------------------------------------------


def test_split_at_every_boundary():
    frames = make_frames(3)
    stream = b"".join(encode_frame(f) for f in frames)
    for k in range(len(stream) + 1):
        dec = FrameDecoder()
        got = dec.feed(stream[:k]) + dec.feed(stream[k:])
        assert got == frames, k
        check_invariant(dec)


def test_two_splits_and_byte_at_a_time():
    frames = make_frames(2)
    stream = b"".join(encode_frame(f) for f in frames)
    for a in range(0, len(stream), 3):
        for b in range(a, len(stream) + 1, 5):
            dec = FrameDecoder()
            assert dec.feed(stream[:a]) + dec.feed(stream[a:b]) + dec.feed(stream[b:]) == frames
    dec = FrameDecoder()
    got = [f for i in range(len(stream)) for f in dec.feed(stream[i:i + 1])]
    assert got == frames


def test_garbage_between_frames_is_discarded_and_counted():
    frames = make_frames(40, seed=3)
    rng = random.Random(7)
    parts, garbage = [], 0
    for f in frames:
        g = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 30)))
        if rng.random() < 0.3:
            g += SYNC + bytes([IMU_PAYLOAD_LEN, TYPE_IMU_V1])  # a fake header, no body
        garbage += len(g)
        parts += [g, encode_frame(f)]
    dec = FrameDecoder()
    got = dec.feed(b"".join(parts))
    assert got == frames
    assert dec.bytes_discarded == garbage
    check_invariant(dec)


def test_real_frame_inside_rejected_candidate_is_kept():
    real = make_frames(1)[0]
    fake = SYNC + bytes([IMU_PAYLOAD_LEN, TYPE_IMU_V1, 0x00])  # promises 57 bytes
    stream = fake + encode_frame(real) + b"\x00" * 10
    dec = FrameDecoder()
    assert dec.feed(stream) == [real]
    assert dec.crc_errors == 1 and dec.bytes_discarded == len(fake) + 10


def test_impossible_length_rejected_without_waiting():
    real = make_frames(1)[0]
    dec = FrameDecoder()
    # A known type with a wrong length, then an unknown type claiming > MAX_PAYLOAD.
    junk = SYNC + bytes([200, TYPE_IMU_V1]) + SYNC + bytes([MAX_PAYLOAD + 1, 0x7F])
    assert dec.feed(junk + encode_frame(real)) == [real]
    assert dec.length_errors == 2


def test_unknown_packet_type_with_valid_crc_is_skipped():
    body = bytes(range(20))
    head = SYNC + bytes([len(body), 0x25])
    pkt = head + body + struct.pack("<H", crc16_ccitt_false(head[2:] + body))
    real = make_frames(1)[0]
    dec = FrameDecoder()
    assert dec.feed(pkt + encode_frame(real)) == [real]
    assert dec.unknown_packets == 1 and dec.bytes_discarded == 0
    check_invariant(dec)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_never_yielded(bad):
    frame = ImuFrame(1, 5, 0, (0.0, bad, 0.0), (0.0, 0.0, 9.8), (1.0, 0.0, 0.0, 0.0))
    good = make_frames(1)[0]
    dec = FrameDecoder()
    assert dec.feed(encode_frame(frame) + encode_frame(good)) == [good]
    assert dec.invalid_frames == 1 and dec.crc_errors == 0


def test_finish_releases_frames_behind_a_pending_candidate():
    real = make_frames(2)
    # An unknown type announcing a long packet: feed() waits for its bytes.
    stream = SYNC + bytes([150, 0x33]) + encode_frame(real[0]) + encode_frame(real[1])
    dec = FrameDecoder()
    assert dec.feed(stream) == []
    assert dec.finish() == real
    assert dec.buffered == 0
    check_invariant(dec)


# -- sequence numbers -------------------------------------------------------------


def _seq_stream(node_seqs):
    return b"".join(
        encode_frame(ImuFrame(n, s, 0, (0.0,) * 3, (0.0,) * 3, (1.0, 0.0, 0.0, 0.0)))
        for n, s in node_seqs
    )


def test_seq_wrap_is_not_a_gap():
    dec = FrameDecoder()
    dec.feed(_seq_stream([(0, 65534), (1, 7), (0, 65535), (1, 8), (0, 0), (0, 1)]))
    assert dec.seq_gaps == {0: 0, 1: 0}


def test_seq_gaps_counted_per_node_across_wrap():
    dec = FrameDecoder()
    dec.feed(_seq_stream([(0, 65534), (0, 2), (1, 10), (1, 12), (1, 13)]))
    assert dec.seq_gaps == {0: 3, 1: 1}  # 65535, 0, 1 missed; 11 missed


def test_seq_backwards_is_a_restart_not_a_gap():
    dec = FrameDecoder()
    dec.feed(_seq_stream([(2, 1000), (2, 1001), (2, 3), (2, 4)]))
    assert dec.seq_gaps == {2: 0} and dec.stats()["seq_restarts"] == 1


# -- fuzzing -----------------------------------------------------------------------


@FUZZ
@given(st.binary(max_size=600), st.integers(1, 64))
def test_fuzz_random_bytes(data, chunk):
    for dec in (FrameDecoder(), HipnucDecoder()):
        got = []
        for k in range(0, len(data), chunk):
            got += dec.feed(data[k:k + chunk])
        got += dec.finish()
        for f in got:  # a CRC-valid frame in random bytes is astronomically rare
            assert math.isfinite(sum(f.gyro + f.accel + f.quat))
        assert dec.frames == len(got)
        check_invariant(dec)


@st.composite
def corrupted_stream(draw):
    n = draw(st.integers(1, 12))
    frames = make_frames(n, seed=draw(st.integers(0, 10_000)))
    encoded = [bytearray(encode_frame(f)) for f in frames]
    touched = set()
    for _ in range(draw(st.integers(0, 6))):
        k = draw(st.integers(0, n - 1))
        kind = draw(st.sampled_from(["flip", "truncate", "insert"]))
        if kind == "flip" and encoded[k]:
            pos = draw(st.integers(0, len(encoded[k]) - 1))
            encoded[k][pos] ^= 1 << draw(st.integers(0, 7))
            touched.add(k)
        elif kind == "truncate":
            cut = draw(st.integers(0, len(encoded[k])))
            del encoded[k][cut:]
            touched.add(k)
        elif kind == "insert":
            blob = draw(st.binary(min_size=1, max_size=40))
            encoded[k][0:0] = blob  # garbage before frame k leaves frame k intact
    return frames, [bytes(e) for e in encoded], touched


@FUZZ
@given(corrupted_stream(), st.integers(1, 80))
def test_fuzz_corrupted_valid_stream(case, chunk):
    frames, encoded, touched = case
    stream = b"".join(encoded)
    dec = FrameDecoder()
    got = []
    for k in range(0, len(stream), chunk):
        got += dec.feed(stream[k:k + chunk])
    got += dec.finish()
    sent = set(frames)
    assert all(f in sent for f in got), "decoder produced a frame that was never sent"
    intact = [f for k, f in enumerate(frames) if k not in touched]
    assert [f for f in got if f in set(intact)] == intact, "an intact frame was lost"
    assert dec.frames == len(got) <= len(frames)
    check_invariant(dec)


# -- HiPNUC --------------------------------------------------------------------------


def test_hipnuc_manual_0x91_example():
    dec = make_decoder("hipnuc", node_id_from_packet=True)
    (fr,) = dec.feed(bytes.fromhex(HIPNUC_DOC_0X91))
    # The manual's decoded values: timestamp 310205 ms, acc 0.224 0.770 0.691 G,
    # gyr -54.708 -20.077 -119.070 deg/s, quat 0.855 0.310 -0.310 -0.277.
    assert fr.node_id == 0 and fr.t_device_us == 310_205_000
    acc_g = [a / 9.8 for a in fr.accel]
    gyr_dps = [math.degrees(g) for g in fr.gyro]
    assert acc_g == pytest.approx([0.224, 0.770, 0.691], abs=5e-4)
    assert gyr_dps == pytest.approx([-54.708, -20.077, -119.070], abs=5e-4)
    assert fr.quat == pytest.approx([0.855, 0.310, -0.310, -0.277], abs=5e-4)
    assert dec.crc_errors == 0 and dec.frames == 1


def test_hipnuc_manual_legacy_packets_pass_crc_and_are_skipped():
    dec = HipnucDecoder()
    assert dec.feed(bytes.fromhex(HIPNUC_DOC_LEGACY)) == []
    assert dec.crc_errors == 0 and dec.unknown_packets == 1


def test_hipnuc_sdk_fixture_current_layout():
    dec = HipnucDecoder(node_id=5)
    (fr,) = dec.feed(bytes.fromhex(HIPNUC_SDK_HI91))
    assert fr.node_id == 5 and fr.t_device_us == 123_456_000
    assert fr.accel == pytest.approx([9.8, -4.9, 2.45])
    assert fr.gyro == pytest.approx([math.pi, -math.pi / 2, math.pi / 4])
    assert fr.quat == (1.0, 0.0, 0.0, 0.0)


def test_hipnuc_round_trip_split_everywhere_and_garbage():
    frames = [ImuFrame(2, 0, 1000 * (5000 + 5 * k), (0.1 * k, -0.2, 0.3), (0.0, 1.0, 9.7),
                       (1.0, 0.0, 0.0, 0.0)) for k in range(3)]
    stream = b"".join(encode_imu_frame(f) for f in frames)
    for k in range(len(stream) + 1):
        dec = HipnucDecoder(node_id_from_packet=True)
        got = dec.feed(b"\x5a\x5a\xa5" + stream[:k]) + dec.feed(stream[k:])
        assert len(got) == 3, k
        for g, f in zip(got, frames):
            assert g.node_id == 2 and g.t_device_us == f.t_device_us
            assert g.gyro == pytest.approx(f.gyro, abs=1e-6)
            assert g.accel == pytest.approx(f.accel, abs=1e-5)
        check_invariant(dec)


def test_hipnuc_seq_from_rate_counts_missed_frames():
    frames = [ImuFrame(0, 0, (CLOCK_WRAP_US - 5000) + 2500 * k, (0.0,) * 3, (0.0,) * 3,
                       (1.0, 0.0, 0.0, 0.0)) for k in range(8)]
    kept = [f for k, f in enumerate(frames) if k != 4]  # one frame lost, across the wrap
    dec = HipnucDecoder(rate_hz=400)
    got = dec.feed(b"".join(encode_imu_frame(f) for f in kept))
    assert len(got) == 7 and dec.seq_gaps == {0: 1}
    assert got[2].t_device_us == 0  # the u32 ms counter wrapped


def _still(node, seq, t_us):
    return ImuFrame(node, seq, t_us, (0.0,) * 3, (0.0, 0.0, 9.8), (1.0, 0.0, 0.0, 0.0))


@pytest.mark.parametrize("last_seq", [20000, 40000, 60000])
def test_a_reboot_is_a_restart_not_missed_frames(last_seq):
    # A rebooted node restarts seq and its clock at 0; from past half the seq range the jump
    # back to 0 reads as a forward step: the clock going back says which it is.
    before = [_still(1, last_seq - 4 + k, 100_000_000 + 2500 * k) for k in range(5)]
    after = [_still(1, k, 1000 + 2500 * k) for k in range(5)]
    dec = FrameDecoder()
    assert len(dec.feed(b"".join(encode_frame(f) for f in before + after))) == 10
    assert dec.seq_gaps == {1: 0} and dec.stats()["seq_restarts"] == 1


def test_hipnuc_reboot_is_a_restart_and_fast_rates_are_refused():
    before = [_still(0, 0, 600_000_000 + 2500 * k) for k in range(5)]
    after = [_still(0, 0, 2000 + 2500 * k) for k in range(5)]
    dec = HipnucDecoder(rate_hz=400)
    assert len(dec.feed(b"".join(encode_imu_frame(f) for f in before + after))) == 10
    assert dec.seq_gaps == {0: 0} and dec.stats()["seq_restarts"] == 1
    # 1 ms stamps cannot tell one frame period from two above 600 Hz (800 Hz: a gap at
    # every other frame, none lost)
    with pytest.raises(ValueError, match="600"):
        HipnucDecoder(rate_hz=800)


def test_hipnuc_rejects_bad_crc_and_length():
    good = bytearray(encode_imu_frame(make_frames(1)[0]))
    bad = bytearray(good)
    bad[30] ^= 0x10
    dec = HipnucDecoder()
    zero_len = b"\x5a\xa5\x00\x00\x00\x00"
    assert len(dec.feed(bytes(bad) + zero_len + bytes(good))) == 1
    assert dec.crc_errors == 1 and dec.length_errors == 1
    with pytest.raises(ValueError):
        encode_payload(b"")


def test_make_decoder_by_name():
    assert isinstance(make_decoder("a2i"), FrameDecoder)
    assert isinstance(make_decoder("HiPNUC", node_id=3), HipnucDecoder)
    with pytest.raises(ValueError):
        make_decoder("witmotion")
    with pytest.raises(ValueError):
        make_decoder("a2i", node_id=1)


def test_header_constant():
    assert HEADER_LEN == 4
