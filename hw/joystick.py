"""The Unitree remote: keys and sticks, edge detection and combos.

Two sources carry the same remote: ``WirelessController_`` (lx, ly, rx, ry, keys) and the 40-byte
``LowState_.wireless_remote`` image (bytes 2-3 keys u16 LE; f32 lx at byte 4, rx 8, ry 12, L2 16,
ly 20). Both use one key bit map, bits 0-15:
R1, L1, Start, Select, R2, L2, F1, F2, A, B, X, Y, Up, Right, Down, Left.

Combos fire once, on the update where all their keys are held and at least one of them was just
pressed (so holding L2 and then pressing A fires L2+A once; releasing A and pressing it again fires
again). Extra keys held do not block a combo: L2+B (damp) must work whatever else is held.

Per-leg calibration combos: a shoulder button picks the side, the D-pad the end of the body,
as the legs sit seen from above with the robot facing away from the operator:

    L1 + Up   -> FL        R1 + Up   -> FR
    L1 + Down -> RL        R1 + Down -> RR

Sticks are in [-1, 1] (x right, y up, as the remote reports them); ``l2`` is the analog trigger in
[0, 1] (only in the LowState image; 0 from WirelessController_).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from hw.go2_msgs import decode_wireless_controller, encode_wireless_controller

KEY_NAMES: tuple[str, ...] = (
    "R1", "L1", "Start", "Select", "R2", "L2", "F1", "F2",
    "A", "B", "X", "Y", "Up", "Right", "Down", "Left",
)
"""Key name of bit i of the u16 key mask."""
KEY_BITS: dict[str, int] = {name: 1 << i for i, name in enumerate(KEY_NAMES)}

REMOTE_LEN = 40
__all__ = [
    "COMBO_CALIB",
    "COMBO_DAMP",
    "COMBO_STAND",
    "DEFAULT_COMBOS",
    "KEY_BITS",
    "KEY_NAMES",
    "Combo",
    "Joystick",
    "JoystickEvents",
    "JoystickState",
    "decode_wireless_controller",
    "encode_wireless_controller",
    "encode_wireless_remote",
    "key_mask",
    "key_names",
]

_REMOTE = struct.Struct("<2sHfffff16s")  # head, keys, lx, rx, ry, L2, ly, idle


def key_mask(*names: str) -> int:
    """Bitmask of the named keys; ValueError on an unknown name."""
    mask = 0
    for n in names:
        if n not in KEY_BITS:
            raise ValueError(f"unknown key {n!r}: expected one of {', '.join(KEY_NAMES)}")
        mask |= KEY_BITS[n]
    return mask


def key_names(mask: int) -> frozenset[str]:
    """Names of the keys set in ``mask``."""
    return frozenset(n for i, n in enumerate(KEY_NAMES) if mask >> i & 1)


@dataclass(frozen=True)
class Combo:
    """A key chord with a name; ``mask`` is the bitmask of its keys."""

    name: str
    keys: tuple[str, ...]

    @property
    def mask(self) -> int:
        return key_mask(*self.keys)


COMBO_STAND = Combo("stand", ("L2", "A"))
COMBO_DAMP = Combo("damp", ("L2", "B"))
COMBO_CALIB = {
    "FL": Combo("calibrate_FL", ("L1", "Up")),
    "FR": Combo("calibrate_FR", ("R1", "Up")),
    "RL": Combo("calibrate_RL", ("L1", "Down")),
    "RR": Combo("calibrate_RR", ("R1", "Down")),
}
"""Per-leg calibration triggers, keyed by leg name."""
DEFAULT_COMBOS: tuple[Combo, ...] = (COMBO_DAMP, COMBO_STAND, *COMBO_CALIB.values())
"""Checked in this order; damp first so that it leads the events of an update."""


@dataclass(frozen=True)
class JoystickState:
    """One reading of the remote: ``keys`` u16 bitmask, sticks in [-1, 1], ``l2`` in [0, 1]."""

    keys: int = 0
    lx: float = 0.0
    ly: float = 0.0
    rx: float = 0.0
    ry: float = 0.0
    l2: float = 0.0

    @property
    def names(self) -> frozenset[str]:
        return key_names(self.keys)

    def held(self, *names: str) -> bool:
        """True when all the named keys are down."""
        m = key_mask(*names)
        return self.keys & m == m

    @classmethod
    def from_wireless_remote(cls, data) -> JoystickState:
        """From the 40-byte ``LowState_.wireless_remote`` image (bytes or a uint8 array)."""
        raw = data.tobytes() if isinstance(data, np.ndarray) else bytes(data)
        if len(raw) != REMOTE_LEN:
            raise ValueError(f"wireless_remote must be {REMOTE_LEN} bytes, got {len(raw)}")
        _, keys, lx, rx, ry, l2, ly, _ = _REMOTE.unpack(raw)
        return cls(keys, lx, ly, rx, ry, l2)

    @classmethod
    def from_wireless_controller(cls, msg) -> JoystickState:
        """From a WirelessController_ frame (bytes) or its decoded record."""
        if isinstance(msg, (bytes, bytearray, memoryview)):
            msg = decode_wireless_controller(msg)
        return cls(int(msg["keys"]), float(msg["lx"]), float(msg["ly"]),
                   float(msg["rx"]), float(msg["ry"]))


@dataclass(frozen=True)
class JoystickEvents:
    """What changed between two readings: key names pressed / released, combos fired (in order)."""

    pressed: frozenset[str]
    released: frozenset[str]
    combos: tuple[Combo, ...]

    def __bool__(self) -> bool:
        return bool(self.pressed or self.released or self.combos)

    def fired(self, combo: Combo) -> bool:
        return combo in self.combos


class Joystick:
    """Tracks the remote across updates: edge detection and combos.

    The first update compares against "nothing held", so keys already down when tracking starts
    count as pressed; construct with ``initial`` to suppress that.
    """

    def __init__(self, combos: tuple[Combo, ...] = DEFAULT_COMBOS,
                 initial: JoystickState | None = None):
        self.combos = tuple(combos)
        self._masks = [c.mask for c in self.combos]
        self.state = initial or JoystickState()

    def update(self, state: JoystickState) -> JoystickEvents:
        prev = self.state.keys
        now = int(state.keys)
        down = now & ~prev
        up = prev & ~now
        self.state = state
        fired = tuple(c for c, m in zip(self.combos, self._masks)
                      if now & m == m and down & m)
        return JoystickEvents(key_names(down), key_names(up), fired)


def encode_wireless_remote(keys: int = 0, lx: float = 0.0, ly: float = 0.0, rx: float = 0.0,
                           ry: float = 0.0, l2: float = 0.0, head: bytes = b"\x00\x00") -> bytes:
    """The 40-byte ``wireless_remote`` image (for the mock robot's LowState_)."""
    if not 0 <= int(keys) <= 0xFFFF:
        raise ValueError(f"keys must be a u16 bitmask, got {keys}")
    return _REMOTE.pack(bytes(head), int(keys), lx, rx, ry, l2, ly, bytes(16))
