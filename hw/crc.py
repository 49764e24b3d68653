"""The CRC-32 of Unitree low-level frames (``LowCmd_.crc``).

Definition (Unitree SDK ``crc32_core``): CRC-32 with polynomial 0x04C11DB7, initial value
0xFFFFFFFF, MSB first, no reflection, no final XOR, fed 32-bit words MSB first. The words are the
little-endian u32 words of the message's *C struct image* (natural C alignment, zero padding), all
but the last word (the crc itself). Feeding a u32 MSB first is feeding its bytes big-endian, so the
result equals CRC-32/MPEG-2 over the word-wise byte-swapped image.

Three implementations that must agree (tests check it):

* :func:`crc32_core` - bit-by-bit transcription of the SDK loop (slow, the reference);
* :func:`crc32_mpeg2_table` - the classic 256-entry table over the big-endian byte stream;
* :func:`crc32_mpeg2` / :func:`crc32_words` - the fast path: zlib's table-driven C CRC-32 is the
  *reflected* twin of MPEG-2 (same polynomial bit-reversed, same all-ones init), so
  ``mpeg2(d) = rev32(~zlib.crc32(rev8(d)))`` where ``rev8`` reverses the bits of every byte
  (``bytes.translate``) and ``rev32`` the bits of the 32-bit result. A few microseconds for a
  LowCmd, with no Python loop over the data.
"""

from __future__ import annotations

import zlib

import numpy as np

POLY = 0x04C11DB7
INIT = 0xFFFFFFFF
_MASK = 0xFFFFFFFF

# REV8[b] = b with its 8 bits reversed; used as a bytes.translate table.
REV8 = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))


def _make_table() -> tuple[int, ...]:
    table = []
    for b in range(256):
        r = b << 24
        for _ in range(8):
            r = ((r << 1) ^ POLY) if r & 0x80000000 else (r << 1)
        table.append(r & _MASK)
    return tuple(table)


MPEG2_TABLE: tuple[int, ...] = _make_table()
"""Non-reflected CRC-32 table for polynomial 0x04C11DB7 (byte index -> register update)."""


def _as_words(words) -> np.ndarray:
    """Little-endian u32 words from bytes-like (length multiple of 4) or an integer array."""
    if isinstance(words, (bytes, bytearray, memoryview)):
        if len(words) % 4:
            raise ValueError(f"CRC input must be whole u32 words, got {len(words)} bytes")
        return np.frombuffer(words, dtype="<u4")
    arr = np.asarray(words)
    if arr.ndim != 1 or arr.dtype.kind not in "ui":
        raise ValueError("CRC input must be a 1-D integer array of u32 words or bytes")
    if arr.size and (arr.min() < 0 or arr.max() > _MASK):
        raise ValueError("CRC words must lie in [0, 2**32)")
    return arr.astype("<u4", copy=False)


def crc32_core(words) -> int:
    """Reference: the SDK's bit loop over u32 ``words`` (ints or LE bytes). Slow; for tests."""
    crc = INIT
    for w in _as_words(words).tolist():
        for bit in range(31, -1, -1):
            top = crc & 0x80000000
            crc = (crc << 1) & _MASK
            if top:
                crc ^= POLY
            if (w >> bit) & 1:
                crc ^= POLY
    return crc


def crc32_mpeg2_table(data: bytes, crc: int = INIT) -> int:
    """CRC-32/MPEG-2 of the byte stream ``data`` with the 256-entry table (pure Python)."""
    t = MPEG2_TABLE
    for b in data:
        crc = ((crc << 8) & _MASK) ^ t[(crc >> 24) ^ b]
    return crc


def _rev32(x: int) -> int:
    return int.from_bytes(x.to_bytes(4, "little").translate(REV8), "big")


def crc32_mpeg2(data: bytes) -> int:
    """CRC-32/MPEG-2 (init 0xFFFFFFFF, no final XOR) of the byte stream ``data``, at C speed."""
    return _rev32(zlib.crc32(bytes(data).translate(REV8)) ^ _MASK)


def crc32_words(words) -> int:
    """The Unitree CRC of u32 ``words`` (array of ints, or little-endian bytes), fast path.

    Pass exactly the words to checksum (for a message: its C image without the last word).
    """
    w = _as_words(words)
    return crc32_mpeg2(w.astype(">u4").tobytes())
