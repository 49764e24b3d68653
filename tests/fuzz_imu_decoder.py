"""Coverage-guided fuzz target for the foot-IMU decoders (atheris; not part of pytest).

Run:  .venv/bin/python tests/fuzz_imu_decoder.py -max_total_time=60
Needs ``pip install atheris``. Each input is split into a chunk size, a
decoder choice and a byte stream mixing fuzzer bytes with valid frames; the
properties checked are those of tests/test_imu_protocol.py: no exception,
every yielded frame finite and (A2I) present byte for byte in the stream,
byte accounting exact.
"""

from __future__ import annotations

import math
import sys

import atheris

with atheris.instrument_imports():
    from hw.hipnuc import HipnucDecoder, encode_imu_frame
    from hw.imu_protocol import FrameDecoder, ImuFrame, encode_frame

_FRAMES = [
    ImuFrame(k % 4, (65530 + k) % 65536, 1_000_000 + 2500 * k, (0.5 * k, -1.0, 2.0),
             (0.0, 0.1 * k, 9.81), (1.0, 0.0, 0.0, 0.0))
    for k in range(12)
]
_ENCODED = {"a2i": [encode_frame(f) for f in _FRAMES],
            "hipnuc": [encode_imu_frame(f) for f in _FRAMES]}


def test_one_input(data: bytes) -> None:
    fdp = atheris.FuzzedDataProvider(data)
    protocol = "a2i" if fdp.ConsumeBool() else "hipnuc"
    chunk = fdp.ConsumeIntInRange(1, 128)
    stream = bytearray()
    sent = 0
    while fdp.remaining_bytes():
        if fdp.ConsumeBool():
            stream += _ENCODED[protocol][sent % len(_FRAMES)]
            sent += 1
        else:
            stream += fdp.ConsumeBytes(fdp.ConsumeIntInRange(0, 64))
    dec = FrameDecoder() if protocol == "a2i" else HipnucDecoder(node_id_from_packet=True)
    got = []
    for k in range(0, len(stream), chunk):
        got += dec.feed(bytes(stream[k:k + chunk]))
    got += dec.finish()
    for f in got:
        if not math.isfinite(sum(f.gyro + f.accel + f.quat)):
            raise AssertionError(f"non-finite frame yielded: {f}")
        # The fuzzer may well forge CRC-valid frames (it sees the comparison),
        # but the decoder must never invent one: its bytes must be in the stream.
        if protocol == "a2i" and encode_frame(f) not in stream:
            raise AssertionError(f"decoded a frame that is not in the stream: {f}")
    if dec.bytes_fed != dec.bytes_consumed + dec.bytes_discarded + dec.buffered:
        raise AssertionError("byte accounting broken")


def main() -> None:
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
