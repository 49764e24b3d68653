"""Go2 low-level wire messages (``unitree_go::msg::dds_``) as XCDR1 bytes, decoded through numpy.

On the wire (DDS, forwarded unchanged by ``zenoh-bridge-dds``) every message is a 4-byte
encapsulation header ``00 01 00 0p`` (CDR little-endian, ``p`` = padding bytes appended to reach a
multiple of 4, per XTypes 7.6.3.1.2) and the body in plain CDR: each primitive aligned to its own
size relative to the start of the body (the byte after the header). LowCmd_ is 812 bytes on the
wire, LowState_ 1180, WirelessController_ 24 (18-byte body + 2 padding, header ``00 01 00 02``,
as Cyclone DDS writes it).

Fast path: a numpy structured dtype per message with the CDR offsets, so decoding is
``np.frombuffer(buf, DTYPE, count=1, offset=4)``, a zero-copy record view (kept 0-d), and
encoding fills a preallocated record in a bytearray. CDR aligns relative to the stream, so element 0 of a struct
array is packed differently from the others (``motor_cmd[0].mode`` at body 22, its ``q`` at 24,
``motor_cmd[1].mode`` at 56, its ``q`` at 60): every field of ``MotorCmd_``/``MotorState_`` but
the leading ``mode`` has a uniform stride (36 resp. 48 bytes) and lives in the nested subarray
``motor_cmd`` / ``motor_state``; the modes are the fields ``motor_cmd.mode[0]`` and
``motor_cmd.mode[1:]``. :func:`get_field` / :func:`set_field` hide that (``"motor_cmd.mode"``).

The CRC (see :mod:`hw.crc`) runs over the *C struct image* (natural C alignment, zero padding),
which differs from the CDR body; the image is gathered from the CDR bytes with one precomputed
index (a vectorised field-by-field copy; the tests check it against a copy through ``LOWCMD_C``).

Joint arrays at this interface are in SDK order (FR, FL, RR, RL x hip, thigh, calf), units SI:
q rad, dq rad/s, tau N m, kp N m/rad, kd N m s/rad, IMU gyroscope rad/s (body frame),
accelerometer m/s^2 (body frame), quaternion (w, x, y, z) body -> world, rpy rad.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hw.crc import crc32_mpeg2

HEADER_LEN = 4
CDR_LE = b"\x00\x01"
"""Encapsulation identifier of plain CDR, little-endian (XCDR1)."""

POS_STOP_F = 2.146e9
"""SDK sentinel for "no position target" (``PosStopF``)."""
VEL_STOP_F = 16000.0
"""SDK sentinel for "no velocity target" (``VelStopF``)."""
HEAD = (0xFE, 0xEF)
LEVEL_LOW = 0xFF
NUM_LEG_MOTORS = 12
NUM_MOTOR_SLOTS = 20

IDL_PATH = Path(__file__).resolve().parent / "idl" / "unitree_go.idl"
"""OMG IDL of the messages (for MCAP ``omgidl`` schemas)."""

TYPE_NAMES = {
    "LowCmd_": "unitree_go::msg::dds_::LowCmd_",
    "LowState_": "unitree_go::msg::dds_::LowState_",
    "WirelessController_": "unitree_go::msg::dds_::WirelessController_",
}
"""Fully qualified type names (DDS type name, MCAP schema name)."""


def idl_schema_text() -> str:
    """The IDL text of all ``unitree_go::msg::dds_`` structs used here."""
    return IDL_PATH.read_text(encoding="utf-8")


# ----------------------------------------------------------------------------- schema
@dataclass(frozen=True)
class Struct:
    """An IDL struct: ``fields`` are (name, numpy primitive code or Struct, count; 0 = scalar)."""

    name: str
    fields: tuple[tuple[str, object, int], ...]


MOTOR_CMD = Struct("MotorCmd_", (
    ("mode", "u1", 0), ("q", "<f4", 0), ("dq", "<f4", 0), ("tau", "<f4", 0),
    ("kp", "<f4", 0), ("kd", "<f4", 0), ("reserve", "<u4", 3),
))
MOTOR_STATE = Struct("MotorState_", (
    ("mode", "u1", 0), ("q", "<f4", 0), ("dq", "<f4", 0), ("ddq", "<f4", 0),
    ("tau_est", "<f4", 0), ("q_raw", "<f4", 0), ("dq_raw", "<f4", 0), ("ddq_raw", "<f4", 0),
    ("temperature", "u1", 0), ("lost", "<u4", 0), ("reserve", "<u4", 2),
))
IMU_STATE = Struct("IMUState_", (
    ("quaternion", "<f4", 4), ("gyroscope", "<f4", 3), ("accelerometer", "<f4", 3),
    ("rpy", "<f4", 3), ("temperature", "u1", 0),
))
BMS_CMD = Struct("BmsCmd_", (("off", "u1", 0), ("reserve", "u1", 3)))
BMS_STATE = Struct("BmsState_", (
    ("version_high", "u1", 0), ("version_low", "u1", 0), ("status", "u1", 0), ("soc", "u1", 0),
    ("current", "<i4", 0), ("cycle", "<u2", 0), ("bq_ntc", "u1", 2), ("mcu_ntc", "u1", 2),
    ("cell_vol", "<u2", 15),
))
LOW_CMD = Struct("LowCmd_", (
    ("head", "u1", 2), ("level_flag", "u1", 0), ("frame_reserve", "u1", 0), ("sn", "<u4", 2),
    ("version", "<u4", 2), ("bandwidth", "<u2", 0), ("motor_cmd", MOTOR_CMD, 20),
    ("bms_cmd", BMS_CMD, 0), ("wireless_remote", "u1", 40), ("led", "u1", 12), ("fan", "u1", 2),
    ("gpio", "u1", 0), ("reserve", "<u4", 0), ("crc", "<u4", 0),
))
LOW_STATE = Struct("LowState_", (
    ("head", "u1", 2), ("level_flag", "u1", 0), ("frame_reserve", "u1", 0), ("sn", "<u4", 2),
    ("version", "<u4", 2), ("bandwidth", "<u2", 0), ("imu_state", IMU_STATE, 0),
    ("motor_state", MOTOR_STATE, 20), ("bms_state", BMS_STATE, 0), ("foot_force", "<i2", 4),
    ("foot_force_est", "<i2", 4), ("tick", "<u4", 0), ("wireless_remote", "u1", 40),
    ("bit_flag", "u1", 0), ("adc_reel", "<f4", 0), ("temperature_ntc1", "u1", 0),
    ("temperature_ntc2", "u1", 0), ("power_v", "<f4", 0), ("power_a", "<f4", 0),
    ("fan_frequency", "<u2", 4), ("reserve", "<u4", 0), ("crc", "<u4", 0),
))
WIRELESS_CONTROLLER = Struct("WirelessController_", (
    ("lx", "<f4", 0), ("ly", "<f4", 0), ("rx", "<f4", 0), ("ry", "<f4", 0), ("keys", "<u2", 0),
))
STRUCTS: tuple[Struct, ...] = (
    IMU_STATE, MOTOR_CMD, MOTOR_STATE, BMS_CMD, BMS_STATE, LOW_CMD, LOW_STATE, WIRELESS_CONTROLLER,
)
"""Every struct, dependencies first (the order of the IDL file)."""


def _fmt(prim: str, count: int):
    return (prim, (count,)) if count else prim


def c_dtype(struct: Struct) -> np.dtype:
    """Natural C struct layout (numpy ``align=True`` = the C compiler's rule for these types)."""
    fields = []
    for name, typ, count in struct.fields:
        base = c_dtype(typ) if isinstance(typ, Struct) else np.dtype(typ)
        fields.append((name, (base, (count,)) if count else base))
    return np.dtype(fields, align=True)


def _cdr_leaves(struct: Struct, pos: int, path: tuple) -> tuple[list, int]:
    """CDR leaves (path, primitive, count, body offset) of ``struct`` starting at body ``pos``."""
    leaves = []
    for name, typ, count in struct.fields:
        if isinstance(typ, Struct):
            for k in range(max(count, 1)):
                sub, pos = _cdr_leaves(typ, pos, path + ((name, k) if count else (name,)))
                leaves += sub
        else:
            size = np.dtype(typ).itemsize
            pos = -(-pos // size) * size
            leaves.append((path + (name,), typ, count, pos))
            pos += size * max(count, 1)
    return leaves, pos


def _struct_array_fields(name: str, elem: Struct, offs: np.ndarray) -> list:
    """dtype fields for ``name[n]`` of ``elem`` given per-element leaf offsets (n, nleaves)."""
    n = offs.shape[0]
    steps = np.diff(offs, axis=0)
    uniform = np.all(steps == steps[:1], axis=0)
    stride = int(steps[0, uniform][0])
    if not np.all(steps[1:] == stride):
        raise ValueError(f"{name}: CDR layout is not periodic after element 0")
    fields = []
    anchor = int(offs[0, uniform].min())
    sub = [(lname, _fmt(p, c), int(offs[0, j]) - anchor)
           for j, (lname, p, c) in enumerate(elem.fields) if uniform[j]]
    sub_dt = np.dtype({"names": [s[0] for s in sub], "formats": [s[1] for s in sub],
                       "offsets": [s[2] for s in sub], "itemsize": stride})
    fields.append((name, (sub_dt, (n,)), anchor))
    for j, (lname, p, c) in enumerate(elem.fields):
        if uniform[j]:
            continue
        rest = np.dtype({"names": [lname], "formats": [_fmt(p, c)], "offsets": [0],
                         "itemsize": stride})
        fields.append((f"{name}.{lname}[0]", _fmt(p, c), int(offs[0, j])))
        fields.append((f"{name}.{lname}[1:]", (rest, (n - 1,)), int(offs[1, j])))
    return fields


def cdr_dtype(struct: Struct) -> np.dtype:
    """Structured dtype of the CDR body of ``struct`` (offsets relative to the body start)."""
    leaves, end = _cdr_leaves(struct, 0, ())
    fields = []
    for name, typ, count in struct.fields:
        mine = [lf for lf in leaves if lf[0][0] == name]
        if not isinstance(typ, Struct):
            (_, p, c, off), = mine
            fields.append((name, _fmt(p, c), off))
        elif count == 0:
            if any(isinstance(t, Struct) for _, t, _ in typ.fields):
                raise ValueError(f"{name}: nested structs two levels deep are not supported")
            anchor = mine[0][3]
            sub_dt = np.dtype({"names": [lf[0][-1] for lf in mine],
                               "formats": [_fmt(lf[1], lf[2]) for lf in mine],
                               "offsets": [lf[3] - anchor for lf in mine],
                               "itemsize": mine[-1][3] + np.dtype(_fmt(mine[-1][1], mine[-1][2])
                                                                   ).itemsize - anchor})
            fields.append((name, sub_dt, anchor))
        else:
            offs = np.array([lf[3] for lf in mine]).reshape(count, len(typ.fields))
            fields += _struct_array_fields(name, typ, offs)
    return np.dtype({"names": [f[0] for f in fields], "formats": [f[1] for f in fields],
                     "offsets": [f[2] for f in fields], "itemsize": end})


def _c_leaves(dt: np.dtype, base: int, path: tuple) -> list:
    """(path, primitive, count, C offset) of every leaf of a C dtype, struct arrays expanded."""
    out = []
    for name in dt.names:
        fdt, off = dt.fields[name][:2]
        if fdt.subdtype is not None and fdt.subdtype[0].names is not None:
            elem, (n,) = fdt.subdtype
            for k in range(n):
                out += _c_leaves(elem, base + off + k * elem.itemsize, path + (name, k))
        elif fdt.names is not None:
            out += _c_leaves(fdt, base + off, path + (name,))
        elif fdt.subdtype is not None:
            out.append((path + (name,), fdt.subdtype[0].str, fdt.subdtype[1][0], base + off))
        else:
            out.append((path + (name,), fdt.str, 0, base + off))
    return out


class _CImage:
    """Gather of the C struct image from the CDR body, and the CRC over it."""

    def __init__(self, struct: Struct):
        c_dt = c_dtype(struct)
        cdr = {lf[0]: lf for lf in _cdr_leaves(struct, 0, ())[0]}
        src, dst = [], []
        for path, prim, count, c_off in _c_leaves(c_dt, 0, ()):
            _, p2, c2, cdr_off = cdr[path]
            nbytes = np.dtype(prim).itemsize * max(count, 1)
            if np.dtype(p2) != np.dtype(prim) or c2 != count:
                raise ValueError(f"layout mismatch at {path}")
            src.append(np.arange(cdr_off, cdr_off + nbytes))
            dst.append(np.arange(c_off, c_off + nbytes))
        self.size = c_dt.itemsize
        self.src = np.concatenate(src)
        self.dst = np.concatenate(dst)
        if self.size % 4:
            raise ValueError(f"{struct.name}: C image of {self.size} bytes is not whole words")
        # The CRC stream is the image minus its last word, each word fed MSB first: byte j of the
        # image goes to stream position 4*(j//4) + 3 - j%4.
        keep = self.dst < self.size - 4
        self.crc_src = self.src[keep]
        d = self.dst[keep]
        self.crc_dst = 4 * (d // 4) + 3 - d % 4

    def image(self, body: np.ndarray) -> np.ndarray:
        """C image (u8, zero padding) of a CDR body given as a u8 array."""
        img = np.zeros(self.size, np.uint8)
        img[self.dst] = body[self.src]
        return img

    def crc(self, body: np.ndarray) -> int:
        stream = np.zeros(self.size - 4, np.uint8)
        stream[self.crc_dst] = body[self.crc_src]
        return crc32_mpeg2(stream.tobytes())


LOWCMD_CDR: np.dtype = cdr_dtype(LOW_CMD)
"""CDR body of LowCmd_ (808 bytes; offsets from the byte after the header)."""
LOWSTATE_CDR: np.dtype = cdr_dtype(LOW_STATE)
"""CDR body of LowState_ (1176 bytes)."""
WIRELESS_CDR: np.dtype = cdr_dtype(WIRELESS_CONTROLLER)
"""CDR body of WirelessController_ (18 bytes)."""
LOWCMD_C: np.dtype = c_dtype(LOW_CMD)
"""C struct image of LowCmd_ (812 bytes, 203 u32 words; the CRC covers the first 202)."""
LOWSTATE_C: np.dtype = c_dtype(LOW_STATE)
"""C struct image of LowState_ (1180 bytes, 295 words)."""
WIRELESS_C: np.dtype = c_dtype(WIRELESS_CONTROLLER)

LOWCMD_SIZE = HEADER_LEN + LOWCMD_CDR.itemsize
LOWSTATE_SIZE = HEADER_LEN + LOWSTATE_CDR.itemsize
WIRELESS_PAD = -WIRELESS_CDR.itemsize % 4
WIRELESS_SIZE = HEADER_LEN + WIRELESS_CDR.itemsize + WIRELESS_PAD

_LOWCMD_IMG = _CImage(LOW_CMD)
_LOWSTATE_IMG = _CImage(LOW_STATE)


# ----------------------------------------------------------------------------- generic access
def get_field(rec, name: str) -> np.ndarray:
    """Field ``name`` of a record (or an array of records): ``"tick"``, ``"imu_state.rpy"``,
    ``"motor_state.q"`` (20,), ``"motor_cmd.mode"`` (20,; gathered from its two CDR pieces, so a
    copy where the others are views)."""
    names = rec.dtype.names
    if name in names:
        return rec[name]
    outer, _, inner = name.partition(".")
    if outer in names and rec[outer].dtype.names and inner in rec[outer].dtype.names:
        return rec[outer][inner]
    first, rest = f"{name}[0]", f"{name}[1:]"
    if first in names:
        return np.concatenate((np.asarray(rec[first])[..., None], rec[rest][inner]), axis=-1)
    raise ValueError(f"no field {name!r} in {rec.dtype}")


def set_field(rec, name: str, value) -> None:
    """Write ``value`` into field ``name`` of a writable record (names as in :func:`get_field`)."""
    names = rec.dtype.names
    if name in names:
        rec[name] = value
        return
    outer, _, inner = name.partition(".")
    if outer in names and rec[outer].dtype.names and inner in rec[outer].dtype.names:
        rec[outer][inner] = value
        return
    first, rest = f"{name}[0]", f"{name}[1:]"
    if first in names:
        n = rec[rest][inner].shape[-1] + 1
        v = np.broadcast_to(np.asarray(value), np.shape(rec[first]) + (n,))
        rec[first] = v[..., 0]
        rec[rest][inner] = v[..., 1:]
        return
    raise ValueError(f"no field {name!r} in {rec.dtype}")


def _check(buf, size: int, what: str) -> None:
    if len(buf) != size:
        raise ValueError(f"{what}: expected {size} bytes, got {len(buf)}")
    if bytes(buf[:2]) != CDR_LE:
        raise ValueError(f"{what}: encapsulation {bytes(buf[:2]).hex()} is not CDR_LE (0001)")


def _record(buf, dtype: np.dtype) -> np.ndarray:
    # A 0-d array rather than np.void: field access on it is about twice as fast.
    return np.frombuffer(buf, dtype, count=1, offset=HEADER_LEN).reshape(())


def _sdk12(x: np.ndarray, what: str, dtype=np.float32) -> np.ndarray:
    a = np.asarray(x, dtype=dtype)
    if a.shape != (NUM_LEG_MOTORS,):
        raise ValueError(f"{what} must have shape (12,) in SDK order, got {a.shape}")
    return a


# ----------------------------------------------------------------------------- LowCmd_
class LowCmdView:
    """Decoded LowCmd_: ``rec`` is a zero-copy 0-d record (LOWCMD_CDR) over the received bytes.

    Motor accessors return (12,) SDK-order float32 views (mode: uint8 copy).
    """

    __slots__ = ("_m", "raw", "rec")

    def __init__(self, raw, rec):
        self.raw = raw
        self.rec = rec
        self._m = rec["motor_cmd"][:NUM_LEG_MOTORS]

    q = property(lambda s: s._m["q"])
    dq = property(lambda s: s._m["dq"])
    tau = property(lambda s: s._m["tau"])
    kp = property(lambda s: s._m["kp"])
    kd = property(lambda s: s._m["kd"])
    mode = property(lambda s: get_field(s.rec, "motor_cmd.mode")[:NUM_LEG_MOTORS])
    level_flag = property(lambda s: int(s.rec["level_flag"]))
    crc = property(lambda s: int(s.rec["crc"]))

    def crc_ok(self) -> bool:
        return lowcmd_crc(self.raw) == self.crc


def decode_lowcmd(buf) -> LowCmdView:
    """Zero-copy view of an 812-byte LowCmd_ frame; ValueError on wrong size or header."""
    _check(buf, LOWCMD_SIZE, "LowCmd_")
    return LowCmdView(buf, _record(buf, LOWCMD_CDR))


def lowcmd_crc(buf) -> int:
    """The CRC a LowCmd_ frame should carry (computed over its C image)."""
    _check(buf, LOWCMD_SIZE, "LowCmd_")
    return _LOWCMD_IMG.crc(np.frombuffer(buf, np.uint8, offset=HEADER_LEN))


def lowcmd_crc_ok(buf) -> bool:
    """True when the frame's ``crc`` field matches its content."""
    _check(buf, LOWCMD_SIZE, "LowCmd_")
    return lowcmd_crc(buf) == int(np.frombuffer(buf, "<u4", count=1, offset=LOWCMD_SIZE - 4)[0])


def lowcmd_c_image(buf) -> bytes:
    """C struct image (812 bytes) of a LowCmd_ frame: what the CRC is computed over."""
    _check(buf, LOWCMD_SIZE, "LowCmd_")
    return _LOWCMD_IMG.image(np.frombuffer(buf, np.uint8, offset=HEADER_LEN)).tobytes()


class LowCmdBuffer:
    """A preallocated LowCmd_ frame (header + body) filled in place; ``finalize()`` -> bytes.

    Initialised as the SDK's ``InitLowCmd``: head FE EF, level_flag 0xFF, every motor mode 0x01,
    q = PosStopF, dq = VelStopF, kp = kd = tau = 0.
    """

    def __init__(self):
        self.buf = bytearray(LOWCMD_SIZE)
        self.buf[:HEADER_LEN] = CDR_LE + b"\x00\x00"
        self._body = np.frombuffer(self.buf, np.uint8, offset=HEADER_LEN)
        self.rec = _record(self.buf, LOWCMD_CDR)
        self.rec["head"] = HEAD
        self.rec["level_flag"] = LEVEL_LOW
        set_field(self.rec, "motor_cmd.mode", 1)
        m = self.rec["motor_cmd"]
        m["q"] = POS_STOP_F
        m["dq"] = VEL_STOP_F
        self._m = m[:NUM_LEG_MOTORS]

    def set_motors(self, q, dq, kp, kd, tau) -> None:
        """Targets of the 12 leg motors, each a (12,) SDK-order array (rad, rad/s, N m/rad,
        N m s/rad, N m); the motor PD law is tau + kp (q - q_m) + kd (dq - dq_m)."""
        m = self._m
        m["q"] = _sdk12(q, "q")
        m["dq"] = _sdk12(dq, "dq")
        m["kp"] = _sdk12(kp, "kp")
        m["kd"] = _sdk12(kd, "kd")
        m["tau"] = _sdk12(tau, "tau")

    def set_modes(self, mode) -> None:
        """Motor modes (20,) or a scalar (0x01 = servo/FOC enabled, 0x00 = off)."""
        set_field(self.rec, "motor_cmd.mode", np.asarray(mode, np.uint8))

    def finalize(self) -> bytes:
        """Compute and store the CRC; return the 812-byte frame."""
        self.rec["crc"] = _LOWCMD_IMG.crc(self._body)
        return bytes(self.buf)


def new_lowcmd() -> LowCmdBuffer:
    """A LowCmd_ initialised as the SDK does (see :class:`LowCmdBuffer`)."""
    return LowCmdBuffer()


# ----------------------------------------------------------------------------- LowState_
class LowStateView:
    """Decoded LowState_: ``rec`` is a zero-copy 0-d record (LOWSTATE_CDR) over the bytes.

    Motor accessors are (12,) SDK-order views (float32; temperature uint8 in deg C; lost uint32);
    IMU in the body frame: quaternion (4,) w, x, y, z; gyroscope rad/s; accelerometer m/s^2;
    rpy rad. foot_force (4,) int16 raw sensor units, in SDK leg order FR, FL, RR, RL.
    """

    __slots__ = ("_imu", "_m", "raw", "rec")

    def __init__(self, raw, rec):
        self.raw = raw
        self.rec = rec
        self._m = rec["motor_state"][:NUM_LEG_MOTORS]
        self._imu = rec["imu_state"]

    q = property(lambda s: s._m["q"])
    dq = property(lambda s: s._m["dq"])
    ddq = property(lambda s: s._m["ddq"])
    tau_est = property(lambda s: s._m["tau_est"])
    temperature = property(lambda s: s._m["temperature"])
    lost = property(lambda s: s._m["lost"])
    mode = property(lambda s: get_field(s.rec, "motor_state.mode")[:NUM_LEG_MOTORS])
    quaternion = property(lambda s: s._imu["quaternion"])
    gyroscope = property(lambda s: s._imu["gyroscope"])
    accelerometer = property(lambda s: s._imu["accelerometer"])
    rpy = property(lambda s: s._imu["rpy"])
    imu_temperature = property(lambda s: int(s._imu["temperature"]))
    foot_force = property(lambda s: s.rec["foot_force"])
    foot_force_est = property(lambda s: s.rec["foot_force_est"])
    tick = property(lambda s: int(s.rec["tick"]))
    wireless_remote = property(lambda s: s.rec["wireless_remote"])
    crc = property(lambda s: int(s.rec["crc"]))

    def crc_ok(self) -> bool:
        return lowstate_crc(self.raw) == self.crc


def decode_lowstate(buf) -> LowStateView:
    """Zero-copy view of a 1180-byte LowState_ frame; ValueError on wrong size or header."""
    _check(buf, LOWSTATE_SIZE, "LowState_")
    return LowStateView(buf, _record(buf, LOWSTATE_CDR))


def lowstate_crc(buf) -> int:
    """CRC of a LowState_ frame over its C image, as for LowCmd_.

    Assumption: the SDK checks only LowCmd_'s CRC; we give LowState_ the same rule (over its
    1180-byte C image, first 294 words) so the mock robot's frames carry a checkable CRC.
    """
    _check(buf, LOWSTATE_SIZE, "LowState_")
    return _LOWSTATE_IMG.crc(np.frombuffer(buf, np.uint8, offset=HEADER_LEN))


def lowstate_c_image(buf) -> bytes:
    """C struct image (1180 bytes) of a LowState_ frame."""
    _check(buf, LOWSTATE_SIZE, "LowState_")
    return _LOWSTATE_IMG.image(np.frombuffer(buf, np.uint8, offset=HEADER_LEN)).tobytes()


class LowStateBuffer:
    """A preallocated LowState_ frame for the mock robot: set fields, then ``finalize()``.

    Starts with head FE EF and everything else zero. Units and frames as :class:`LowStateView`.
    """

    def __init__(self):
        self.buf = bytearray(LOWSTATE_SIZE)
        self.buf[:HEADER_LEN] = CDR_LE + b"\x00\x00"
        self._body = np.frombuffer(self.buf, np.uint8, offset=HEADER_LEN)
        self.rec = _record(self.buf, LOWSTATE_CDR)
        self.rec["head"] = HEAD
        self._m = self.rec["motor_state"][:NUM_LEG_MOTORS]
        self._imu = self.rec["imu_state"]

    def set_motors(self, q, dq, tau_est, ddq=None, temperature=None, lost=None) -> None:
        """(12,) SDK-order arrays: rad, rad/s, N m, rad/s^2, deg C (uint8), lost-frame count."""
        m = self._m
        m["q"] = _sdk12(q, "q")
        m["dq"] = _sdk12(dq, "dq")
        m["tau_est"] = _sdk12(tau_est, "tau_est")
        if ddq is not None:
            m["ddq"] = _sdk12(ddq, "ddq")
        if temperature is not None:
            m["temperature"] = _sdk12(temperature, "temperature", np.uint8)
        if lost is not None:
            m["lost"] = _sdk12(lost, "lost", np.uint32)

    def set_modes(self, mode) -> None:
        set_field(self.rec, "motor_state.mode", np.asarray(mode, np.uint8))

    def set_imu(self, quaternion_wxyz, gyroscope, accelerometer, rpy=None,
                temperature=None) -> None:
        """Body IMU: quaternion (w, x, y, z), gyro rad/s, accel m/s^2 (body frame), rpy rad."""
        imu = self._imu
        for key, val, n in (("quaternion", quaternion_wxyz, 4), ("gyroscope", gyroscope, 3),
                            ("accelerometer", accelerometer, 3), ("rpy", rpy, 3)):
            if val is None:
                continue
            a = np.asarray(val, np.float32)
            if a.shape != (n,):
                raise ValueError(f"{key} must have shape ({n},), got {a.shape}")
            imu[key] = a
        if temperature is not None:
            imu["temperature"] = temperature

    def set_foot_force(self, force, est=None) -> None:
        """Foot contact sensors (4,) int16 raw units, SDK leg order FR, FL, RR, RL."""
        self.rec["foot_force"] = np.clip(np.round(np.asarray(force, float)), -32768, 32767)
        if est is not None:
            self.rec["foot_force_est"] = np.clip(np.round(np.asarray(est, float)), -32768, 32767)

    def set_wireless_remote(self, data: bytes) -> None:
        """The 40-byte remote image (see :func:`hw.joystick.encode_wireless_remote`)."""
        if len(data) != 40:
            raise ValueError(f"wireless_remote must be 40 bytes, got {len(data)}")
        self.rec["wireless_remote"] = np.frombuffer(bytes(data), np.uint8)

    def set_tick(self, tick_ms: int) -> None:
        """The robot's millisecond tick counter (u32, wraps)."""
        self.rec["tick"] = int(tick_ms) & 0xFFFFFFFF

    def finalize(self) -> bytes:
        """Compute and store the CRC; return the 1180-byte frame."""
        self.rec["crc"] = _LOWSTATE_IMG.crc(self._body)
        return bytes(self.buf)


def encode_lowstate(q, dq, tau_est, quaternion_wxyz, gyroscope, accelerometer, *, rpy=None,
                    tick: int = 0, foot_force=None, wireless_remote: bytes | None = None) -> bytes:
    """One-shot LowState_ frame (allocates; the mock loop should reuse a LowStateBuffer)."""
    b = LowStateBuffer()
    b.set_motors(q, dq, tau_est)
    b.set_imu(quaternion_wxyz, gyroscope, accelerometer, rpy)
    b.set_tick(tick)
    if foot_force is not None:
        b.set_foot_force(foot_force)
    if wireless_remote is not None:
        b.set_wireless_remote(wireless_remote)
    return b.finalize()


# ----------------------------------------------------------------------------- WirelessController_
def encode_wireless_controller(*, keys: int = 0, lx: float = 0.0, ly: float = 0.0,
                               rx: float = 0.0, ry: float = 0.0, pad: bool = True) -> bytes:
    """WirelessController_ frame. Sticks in [-1, 1]; ``keys`` the u16 bitmask (hw.joystick).

    ``pad=True`` gives what Cyclone DDS writes: the 18-byte body padded to 20 with header
    ``00 01 00 02`` (24 bytes); ``pad=False`` the unpadded 22-byte form (as pycdr2 writes it).
    """
    if not 0 <= int(keys) <= 0xFFFF:
        raise ValueError(f"keys must be a u16 bitmask, got {keys}")
    rec = np.zeros((), WIRELESS_CDR)
    rec["lx"], rec["ly"], rec["rx"], rec["ry"], rec["keys"] = lx, ly, rx, ry, keys
    if pad:
        return CDR_LE + bytes((0, WIRELESS_PAD)) + rec.tobytes() + bytes(WIRELESS_PAD)
    return CDR_LE + b"\x00\x00" + rec.tobytes()


def decode_wireless_controller(buf):
    """0-d record (lx, ly, rx, ry float32; keys uint16) of a WirelessController_ frame.

    Accepts the padded (24-byte) and unpadded (22-byte) forms; ValueError otherwise.
    """
    n = len(buf)
    if n < HEADER_LEN or bytes(buf[:2]) != CDR_LE:
        raise ValueError("WirelessController_: encapsulation is not CDR_LE (0001)")
    pad = buf[3] & 0x3
    if n - HEADER_LEN - pad != WIRELESS_CDR.itemsize:
        raise ValueError(f"WirelessController_: body of {n - HEADER_LEN} bytes with {pad} "
                         f"padding, expected {WIRELESS_CDR.itemsize}")
    return _record(buf, WIRELESS_CDR)


# ----------------------------------------------------------------------------- batches (logs)
def _batch(raw, size: int, dtype: np.dtype, what: str) -> np.ndarray:
    a = np.asarray(raw, np.uint8)
    if a.ndim != 2 or a.shape[1] < size:
        raise ValueError(f"{what} batch must be (N, >={size}) uint8, got {a.shape}")
    if a.shape[0] and not (np.all(a[:, 0] == 0) and np.all(a[:, 1] == 1)):
        raise ValueError(f"{what} batch: some rows are not CDR_LE (0001)")
    return np.ascontiguousarray(a[:, HEADER_LEN:size]).view(dtype)[:, 0]


def lowstate_records(raw) -> np.ndarray:
    """(N,) LOWSTATE_CDR records (a copy) from an (N, >=1180) uint8 array of frames; use
    :func:`get_field` on the result, e.g. ``get_field(r, "motor_state")["q"][:, :12]``."""
    return _batch(raw, LOWSTATE_SIZE, LOWSTATE_CDR, "LowState_")


def lowcmd_records(raw) -> np.ndarray:
    """(N,) LOWCMD_CDR records (a copy) from an (N, >=812) uint8 array of frames."""
    return _batch(raw, LOWCMD_SIZE, LOWCMD_CDR, "LowCmd_")
