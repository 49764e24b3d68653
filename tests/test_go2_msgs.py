"""Go2 wire messages: layouts, CRC, and a byte-for-byte cross-check against pycdr2."""

import re
import struct
import time
from dataclasses import dataclass

import numpy as np
import pytest
from pycdr2 import IdlStruct
from pycdr2 import types as t

from hw import crc as crcmod
from hw import go2_msgs as g


# ----------------------------------------------------------------------------- pycdr2 twins
@dataclass
class MotorCmd_(IdlStruct, typename="unitree_go.msg.dds_.MotorCmd_"):
    mode: t.uint8
    q: t.float32
    dq: t.float32
    tau: t.float32
    kp: t.float32
    kd: t.float32
    reserve: t.array[t.uint32, 3]


@dataclass
class MotorState_(IdlStruct, typename="unitree_go.msg.dds_.MotorState_"):
    mode: t.uint8
    q: t.float32
    dq: t.float32
    ddq: t.float32
    tau_est: t.float32
    q_raw: t.float32
    dq_raw: t.float32
    ddq_raw: t.float32
    temperature: t.uint8
    lost: t.uint32
    reserve: t.array[t.uint32, 2]


@dataclass
class IMUState_(IdlStruct, typename="unitree_go.msg.dds_.IMUState_"):
    quaternion: t.array[t.float32, 4]
    gyroscope: t.array[t.float32, 3]
    accelerometer: t.array[t.float32, 3]
    rpy: t.array[t.float32, 3]
    temperature: t.uint8


@dataclass
class BmsCmd_(IdlStruct, typename="unitree_go.msg.dds_.BmsCmd_"):
    off: t.uint8
    reserve: t.array[t.uint8, 3]


@dataclass
class BmsState_(IdlStruct, typename="unitree_go.msg.dds_.BmsState_"):
    version_high: t.uint8
    version_low: t.uint8
    status: t.uint8
    soc: t.uint8
    current: t.int32
    cycle: t.uint16
    bq_ntc: t.array[t.uint8, 2]
    mcu_ntc: t.array[t.uint8, 2]
    cell_vol: t.array[t.uint16, 15]


@dataclass
class LowCmd_(IdlStruct, typename="unitree_go.msg.dds_.LowCmd_"):
    head: t.array[t.uint8, 2]
    level_flag: t.uint8
    frame_reserve: t.uint8
    sn: t.array[t.uint32, 2]
    version: t.array[t.uint32, 2]
    bandwidth: t.uint16
    motor_cmd: t.array[MotorCmd_, 20]
    bms_cmd: BmsCmd_
    wireless_remote: t.array[t.uint8, 40]
    led: t.array[t.uint8, 12]
    fan: t.array[t.uint8, 2]
    gpio: t.uint8
    reserve: t.uint32
    crc: t.uint32


@dataclass
class LowState_(IdlStruct, typename="unitree_go.msg.dds_.LowState_"):
    head: t.array[t.uint8, 2]
    level_flag: t.uint8
    frame_reserve: t.uint8
    sn: t.array[t.uint32, 2]
    version: t.array[t.uint32, 2]
    bandwidth: t.uint16
    imu_state: IMUState_
    motor_state: t.array[MotorState_, 20]
    bms_state: BmsState_
    foot_force: t.array[t.int16, 4]
    foot_force_est: t.array[t.int16, 4]
    tick: t.uint32
    wireless_remote: t.array[t.uint8, 40]
    bit_flag: t.uint8
    adc_reel: t.float32
    temperature_ntc1: t.uint8
    temperature_ntc2: t.uint8
    power_v: t.float32
    power_a: t.float32
    fan_frequency: t.array[t.uint16, 4]
    reserve: t.uint32
    crc: t.uint32


@dataclass
class WirelessController_(IdlStruct, typename="unitree_go.msg.dds_.WirelessController_"):
    lx: t.float32
    ly: t.float32
    rx: t.float32
    ry: t.float32
    keys: t.uint16


PY_CLASSES = {c.__name__: c for c in (MotorCmd_, MotorState_, IMUState_, BmsCmd_, BmsState_,
                                      LowCmd_, LowState_, WirelessController_)}

# The C image as the Unitree Python SDK packs it for its CRC (explicit padding 'x').
SDK_LOWCMD_FMT = "<4B4IH2x" + "B3x5f3I" * 20 + "4B" + "55Bx2I"
LOWSTATE_C_FMT = ("<4B4IH2x" + "13fB3x" + "B3x7fB3xI2I" * 20 + "4BiH2B2B15H" + "8h" + "I" + "40B"
                  + "B3xf2B2x2f4H2I")


# ----------------------------------------------------------------------------- random messages
def _rand_prim(prim: str, rng: np.random.Generator):
    dt = np.dtype(prim)
    if dt.kind == "f":
        return float(np.float32(rng.standard_normal() * 10.0 ** rng.integers(-3, 4)))
    info = np.iinfo(dt)
    return int(rng.integers(info.min, int(info.max) + 1))


def _rand_struct(st: g.Struct, rng) -> dict:
    out = {}
    for name, typ, count in st.fields:
        if isinstance(typ, g.Struct):
            out[name] = ([_rand_struct(typ, rng) for _ in range(count)] if count
                         else _rand_struct(typ, rng))
        else:
            out[name] = [_rand_prim(typ, rng) for _ in range(count)] if count else \
                _rand_prim(typ, rng)
    return out


def _to_py(st: g.Struct, vals: dict):
    kw = {}
    for name, typ, count in st.fields:
        v = vals[name]
        if isinstance(typ, g.Struct):
            v = [_to_py(typ, e) for e in v] if count else _to_py(typ, v)
        kw[name] = v
    return PY_CLASSES[st.name](**kw)


def _from_py(obj):
    """pycdr2 object -> plain values (uint8 arrays come back as bytes)."""
    if isinstance(obj, IdlStruct):
        return {k: _from_py(v) for k, v in vars(obj).items()}
    if isinstance(obj, (bytes, bytearray)):
        return list(obj)
    if isinstance(obj, list):
        return [_from_py(v) for v in obj]
    return obj


def _flat(st: g.Struct, vals: dict) -> list:
    """Leaf values in declaration order (for struct.pack of the C image)."""
    out = []
    for name, typ, count in st.fields:
        v = vals[name]
        if isinstance(typ, g.Struct):
            for e in (v if count else [v]):
                out += _flat(typ, e)
        else:
            out += v if count else [v]
    return out


def _fill(rec, st: g.Struct, vals: dict) -> None:
    """Write every field through the public set_field names."""
    for name, typ, count in st.fields:
        if not isinstance(typ, g.Struct):
            g.set_field(rec, name, vals[name])
            continue
        for sub, _styp, _scount in typ.fields:
            v = [e[sub] for e in vals[name]] if count else vals[name][sub]
            g.set_field(rec, f"{name}.{sub}", v)


def _check_decoded(rec, st: g.Struct, vals: dict) -> None:
    for name, typ, count in st.fields:
        if not isinstance(typ, g.Struct):
            np.testing.assert_array_equal(g.get_field(rec, name), vals[name], err_msg=name)
            continue
        for sub, _styp, _scount in typ.fields:
            want = [e[sub] for e in vals[name]] if count else vals[name][sub]
            np.testing.assert_array_equal(g.get_field(rec, f"{name}.{sub}"), want,
                                          err_msg=f"{name}.{sub}")


# ----------------------------------------------------------------------------- layouts
def test_totals():
    assert g.LOWCMD_SIZE == 812 and g.LOWSTATE_SIZE == 1180
    assert g.LOWCMD_C.itemsize == 812 and g.LOWCMD_C.itemsize // 4 == 203
    assert g.LOWSTATE_C.itemsize == 1180
    assert g.WIRELESS_CDR.itemsize == 18 and g.WIRELESS_SIZE == 24
    assert struct.calcsize(SDK_LOWCMD_FMT) == 812
    assert struct.calcsize(LOWSTATE_C_FMT) == 1180


def test_known_offsets():
    cdr = g.LOWCMD_CDR.fields
    assert cdr["motor_cmd.mode[0]"][1] == 22
    assert cdr["motor_cmd"][1] == 24  # motor_cmd[0].q
    assert cdr["motor_cmd.mode[1:]"][1] == 56
    assert cdr["motor_cmd"][0].subdtype[0].itemsize == 36
    assert cdr["bms_cmd"][1] == 740 and cdr["wireless_remote"][1] == 744
    assert cdr["crc"][1] == 804
    c = g.LOWCMD_C
    assert c.fields["motor_cmd"][1] == 24 and c.fields["crc"][1] == 808
    assert c.fields["motor_cmd"][0].subdtype[0].fields["q"][1] == 4
    s = g.LOWSTATE_CDR.fields
    assert s["imu_state"][1] == 24 and s["motor_state.mode[0]"][1] == 77
    assert s["motor_state"][1] == 80 and s["motor_state.mode[1:]"][1] == 124
    assert s["bms_state"][1] == 1036 and s["tick"][1] == 1096
    assert s["wireless_remote"][1] == 1100 and s["crc"][1] == 1172
    sc = g.LOWSTATE_C.fields
    assert sc["motor_state"][1] == 80 and sc["bms_state"][1] == 1040 and sc["tick"][1] == 1100


@pytest.mark.parametrize("st", [g.LOW_CMD, g.LOW_STATE, g.WIRELESS_CONTROLLER])
def test_padding_is_only_alignment(st):
    """Every byte is one leaf's or a pad; each gap is the alignment pad before the next leaf."""
    leaves, end = g._cdr_leaves(st, 0, ())
    owner = np.full(end, -1)
    pos = 0
    for k, (path, prim, count, off) in enumerate(leaves):
        size = np.dtype(prim).itemsize
        assert off % size == 0, path
        assert 0 <= off - pos < size, f"gap before {path}"
        assert np.all(owner[off:off + size * max(count, 1)] == -1), f"overlap at {path}"
        owner[off:off + size * max(count, 1)] = k
        pos = off + size * max(count, 1)
    assert pos == end
    # the dtype's leaf fields read exactly those bytes, each once
    hits = np.zeros(end, int)
    _mark(g.cdr_dtype(st), 0, hits)
    np.testing.assert_array_equal(hits, (owner >= 0).astype(int))


def _mark(dt: np.dtype, base: int, hits: np.ndarray) -> None:
    for name in dt.names:
        fdt, off = dt.fields[name][:2]
        elem, shape = fdt.subdtype if fdt.subdtype else (fdt, ())
        n = shape[0] if shape else 1
        for k in range(n):
            at = base + off + k * elem.itemsize
            if elem.names is not None:
                _mark(elem, at, hits)
            else:
                hits[at:at + elem.itemsize] += 1


def test_c_image_equals_field_copy_and_sdk_packing():
    rng = np.random.default_rng(1)
    vals = _rand_struct(g.LOW_CMD, rng)
    frame = _to_py(g.LOW_CMD, vals).serialize()
    img = g.lowcmd_c_image(frame)
    # 1) field-by-field copy through the LOWCMD_C dtype
    crec = np.zeros((), g.LOWCMD_C)
    view = g.decode_lowcmd(frame).rec
    for name in g.LOWCMD_C.names:
        if name == "motor_cmd":
            for sub in g.LOWCMD_C["motor_cmd"].base.names:
                crec["motor_cmd"][sub] = g.get_field(view, f"motor_cmd.{sub}")
        else:
            crec[name] = view[name]
    assert img == crec.tobytes()
    # 2) the SDK's struct format
    assert img == struct.pack(SDK_LOWCMD_FMT, *_flat(g.LOW_CMD, vals))
    svals = _rand_struct(g.LOW_STATE, rng)
    sframe = _to_py(g.LOW_STATE, svals).serialize()
    assert g.lowstate_c_image(sframe) == struct.pack(LOWSTATE_C_FMT, *_flat(g.LOW_STATE, svals))


# ----------------------------------------------------------------------------- CRC
def _vector2_frame() -> bytes:
    b = g.LowCmdBuffer()
    b.rec["motor_cmd"]["q"] = 0
    b.rec["motor_cmd"]["dq"] = 0
    return bytes(b.buf)


def test_crc_vectors():
    zero = np.zeros(202, np.uint32)
    for fn in (crcmod.crc32_core, crcmod.crc32_words):
        assert fn(zero) == 0x4B5A4880
    assert crcmod.crc32_mpeg2_table(bytes(808)) == 0x4B5A4880
    frame = bytearray(812)
    frame[1] = 1
    assert g.lowcmd_crc(bytes(frame)) == 0x4B5A4880
    assert g.lowcmd_crc(_vector2_frame()) == 0x57ECF19D
    img = g.lowcmd_c_image(_vector2_frame())
    assert crcmod.crc32_core(img[:808]) == 0x57ECF19D


def test_crc_implementations_agree():
    rng = np.random.default_rng(2)
    for n in (1, 3, 202, 294):
        w = rng.integers(0, 2**32, n, dtype=np.uint32)
        ref = crcmod.crc32_core(w)
        assert crcmod.crc32_words(w) == ref
        assert crcmod.crc32_words(w.astype("<u4").tobytes()) == ref
        assert crcmod.crc32_mpeg2_table(w.astype(">u4").tobytes()) == ref


def test_crc_speed():
    w = np.random.default_rng(3).integers(0, 2**32, 202, dtype=np.uint32)
    best = min(_timed(lambda: crcmod.crc32_words(w)) for _ in range(200))
    assert best < 50e-6, f"crc32_words took {best * 1e6:.1f} us for 202 words"
    frame = g.LowCmdBuffer().finalize()
    best = min(_timed(lambda: g.lowcmd_crc(frame)) for _ in range(200))
    assert best < 50e-6, f"lowcmd_crc took {best * 1e6:.1f} us"


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def test_crc_bad_input():
    with pytest.raises(ValueError):
        crcmod.crc32_words(b"\x00\x01\x02")
    with pytest.raises(ValueError):
        crcmod.crc32_words(np.array([-1]))


# ----------------------------------------------------------------------------- pycdr2 cross-check
@pytest.mark.parametrize("seed", range(12))
def test_lowcmd_matches_pycdr2(seed):
    rng = np.random.default_rng(100 + seed)
    vals = _rand_struct(g.LOW_CMD, rng)
    buf = g.LowCmdBuffer()
    _fill(buf.rec, g.LOW_CMD, vals)
    m = vals["motor_cmd"][:12]
    buf.set_motors(*([e[k] for e in m] for k in ("q", "dq", "kp", "kd", "tau")))
    ours = buf.finalize()
    vals["crc"] = crcmod.crc32_core(struct.pack(SDK_LOWCMD_FMT, *_flat(g.LOW_CMD, vals))[:808])
    ref = _to_py(g.LOW_CMD, vals)
    assert ours == ref.serialize()
    assert _from_py(LowCmd_.deserialize(ours)) == vals
    view = g.decode_lowcmd(ours)
    _check_decoded(view.rec, g.LOW_CMD, vals)
    assert view.crc_ok() and g.lowcmd_crc_ok(ours)
    np.testing.assert_array_equal(view.kp, [e["kp"] for e in m])
    np.testing.assert_array_equal(view.mode, [e["mode"] for e in m])


@pytest.mark.parametrize("seed", range(12))
def test_lowstate_matches_pycdr2(seed):
    rng = np.random.default_rng(200 + seed)
    vals = _rand_struct(g.LOW_STATE, rng)
    buf = g.LowStateBuffer()
    _fill(buf.rec, g.LOW_STATE, vals)
    ours = buf.finalize()
    vals["crc"] = crcmod.crc32_core(struct.pack(LOWSTATE_C_FMT, *_flat(g.LOW_STATE, vals))[:1176])
    ref = _to_py(g.LOW_STATE, vals)
    assert ours == ref.serialize()
    assert _from_py(LowState_.deserialize(ours)) == vals
    v = g.decode_lowstate(ours)
    _check_decoded(v.rec, g.LOW_STATE, vals)
    ms = vals["motor_state"][:12]
    for acc in ("q", "dq", "ddq", "tau_est", "temperature", "lost", "mode"):
        np.testing.assert_array_equal(getattr(v, acc), [e[acc] for e in ms], err_msg=acc)
    imu = vals["imu_state"]
    for acc in ("quaternion", "gyroscope", "accelerometer", "rpy"):
        np.testing.assert_array_equal(getattr(v, acc), imu[acc], err_msg=acc)
    assert v.imu_temperature == imu["temperature"]
    np.testing.assert_array_equal(v.foot_force, vals["foot_force"])
    assert v.tick == vals["tick"] and v.wireless_remote.tobytes() == bytes(vals["wireless_remote"])
    assert v.crc_ok()


def test_wireless_controller_matches_pycdr2():
    rng = np.random.default_rng(5)
    for _ in range(10):
        vals = _rand_struct(g.WIRELESS_CONTROLLER, rng)
        ref = _to_py(g.WIRELESS_CONTROLLER, vals).serialize()
        ours = g.encode_wireless_controller(pad=False, **vals)
        assert ours == ref
        padded = g.encode_wireless_controller(**vals)
        assert padded == b"\x00\x01\x00\x02" + ref[4:] + b"\x00\x00"
        for frame in (ours, padded):
            _check_decoded(g.decode_wireless_controller(frame), g.WIRELESS_CONTROLLER, vals)
        assert _from_py(WirelessController_.deserialize(ours)) == vals


# ----------------------------------------------------------------------------- buffers and API
def test_new_lowcmd_is_sdk_init():
    v = g.decode_lowcmd(g.new_lowcmd().finalize())
    r = v.rec
    assert list(r["head"]) == [0xFE, 0xEF] and r["level_flag"] == 0xFF
    assert np.all(g.get_field(r, "motor_cmd.mode") == 1)
    np.testing.assert_array_equal(g.get_field(r, "motor_cmd.q"), np.float32(g.POS_STOP_F))
    np.testing.assert_array_equal(g.get_field(r, "motor_cmd.dq"), g.VEL_STOP_F)
    for k in ("kp", "kd", "tau"):
        assert np.all(g.get_field(r, f"motor_cmd.{k}") == 0)
    assert v.crc_ok()


def test_set_motors_sdk_order_and_slots_12_19_untouched():
    b = g.LowCmdBuffer()
    q = np.arange(12) * 0.1
    b.set_motors(q, -q, np.full(12, 20.0), np.full(12, 0.5), q * 2)
    v = g.decode_lowcmd(b.finalize())
    np.testing.assert_allclose(v.q, q, rtol=1e-6)
    np.testing.assert_allclose(v.dq, -q, rtol=1e-6)
    np.testing.assert_allclose(v.tau, 2 * q, rtol=1e-6)
    assert np.all(v.kp == 20) and np.all(v.kd == 0.5)
    assert np.all(v.rec["motor_cmd"]["q"][12:] == np.float32(g.POS_STOP_F))
    with pytest.raises(ValueError):
        b.set_motors(np.zeros(11), *([np.zeros(12)] * 4))


def test_lowstate_buffer_roundtrip_and_crc_detects_corruption():
    b = g.LowStateBuffer()
    q = np.linspace(-1, 1, 12)
    b.set_motors(q, q * 2, q * 3, ddq=q * 4, temperature=np.full(12, 40), lost=np.arange(12))
    b.set_imu([1, 0, 0, 0], [0.1, 0.2, 0.3], [0, 0, 9.81], rpy=[0.01, 0.02, 0.03], temperature=33)
    b.set_foot_force([10, 20, 30, 40.4])
    b.set_tick(2**32 + 7)
    b.set_wireless_remote(bytes(range(40)))
    frame = b.finalize()
    v = g.decode_lowstate(frame)
    np.testing.assert_allclose(v.q, q, rtol=1e-6)
    np.testing.assert_allclose(v.tau_est, 3 * q, rtol=1e-6)
    np.testing.assert_allclose(v.ddq, 4 * q, rtol=1e-6)
    assert np.all(v.temperature == 40) and list(v.lost) == list(range(12))
    np.testing.assert_allclose(v.accelerometer, [0, 0, 9.81], rtol=1e-6)
    assert v.imu_temperature == 33 and list(v.foot_force) == [10, 20, 30, 40]
    assert v.tick == 7 and v.wireless_remote.tobytes() == bytes(range(40))
    assert v.crc_ok()
    bad = bytearray(frame)
    bad[200] ^= 0x10
    assert not g.decode_lowstate(bytes(bad)).crc_ok()
    bad = bytearray(b.finalize())
    assert g.decode_lowstate(bytes(bad)).crc_ok()
    with pytest.raises(ValueError):
        b.set_imu([1, 0, 0], [0, 0, 0], [0, 0, 0])


def test_lowcmd_crc_detects_corruption_in_every_field():
    frame = g.LowCmdBuffer().finalize()
    leaves, _ = g._cdr_leaves(g.LOW_CMD, 0, ())
    for path, prim, count, off in leaves:
        if path == ("crc",):
            continue
        bad = bytearray(frame)
        bad[4 + off] ^= 0x01
        assert not g.lowcmd_crc_ok(bytes(bad)), path


def test_decode_errors():
    frame = g.LowCmdBuffer().finalize()
    with pytest.raises(ValueError, match="812"):
        g.decode_lowcmd(frame[:-1])
    with pytest.raises(ValueError, match="encapsulation"):
        g.decode_lowcmd(b"\x00\x00" + frame[2:])
    with pytest.raises(ValueError, match="1180"):
        g.decode_lowstate(frame)
    with pytest.raises(ValueError):
        g.decode_wireless_controller(b"\x00\x01\x00\x00" + bytes(10))
    with pytest.raises(ValueError):
        g.encode_wireless_controller(keys=70000)
    with pytest.raises(ValueError):
        g.get_field(g.decode_lowcmd(frame).rec, "motor_cmd.nope")


def test_batch_records():
    frames = []
    for k in range(5):
        b = g.LowStateBuffer()
        b.set_motors(np.full(12, k * 0.5), np.zeros(12), np.zeros(12))
        b.set_tick(k)
        frames.append(np.frombuffer(b.finalize(), np.uint8))
    r = g.lowstate_records(np.stack(frames))
    assert list(r["tick"]) == list(range(5))
    np.testing.assert_allclose(r["motor_state"]["q"][:, :12], np.repeat(np.arange(5) * 0.5, 12)
                               .reshape(5, 12))
    assert g.get_field(r, "motor_state.mode").shape == (5, 20)
    with pytest.raises(ValueError):
        g.lowstate_records(np.zeros((2, 1180), np.uint8))


# ----------------------------------------------------------------------------- IDL
_IDL_TYPES = {"uint8": "u1", "int16": "<i2", "uint16": "<u2", "int32": "<i4", "uint32": "<u4",
              "float": "<f4"}


def _parse_idl(text: str) -> tuple[list[str], dict[str, list[tuple[str, str, int]]]]:
    text = re.sub(r"//[^\n]*", "", text)
    modules = re.findall(r"module\s+(\w+)\s*{", text)
    structs = {}
    for name, body in re.findall(r"struct\s+(\w+)\s*{(.*?)}\s*;", text, flags=re.DOTALL):
        fields = []
        for decl in filter(None, (d.strip() for d in body.split(";"))):
            m = re.fullmatch(r"(\w+)\s+(\w+)(?:\[(\d+)\])?", decl)
            assert m, f"cannot parse {decl!r} in {name}"
            fields.append((m[1], m[2], int(m[3] or 0)))
        structs[name] = fields
    return modules, structs


def _dtype_fields(dt: np.dtype) -> list[tuple[np.dtype, str, int]]:
    out = []
    for name in dt.names:
        fdt = dt.fields[name][0]
        base, shape = fdt.subdtype if fdt.subdtype else (fdt, ())
        out.append((base, name, shape[0] if shape else 0))
    return out


def test_idl_matches_dtypes():
    text = g.idl_schema_text()
    assert text == g.IDL_PATH.read_text()
    modules, structs = _parse_idl(text)
    assert modules == ["unitree_go", "msg", "dds_"]
    assert list(structs) == [s.name for s in g.STRUCTS]

    def check(sname: str, dt: np.dtype):
        idl = structs[sname]
        ours = _dtype_fields(dt)
        assert [f[1] for f in idl] == [f[1] for f in ours], sname
        for (ityp, name, icount), (base, _, count) in zip(idl, ours, strict=True):
            assert icount == count, f"{sname}.{name}"
            if base.names is not None:
                check(ityp, base)
            else:
                assert np.dtype(_IDL_TYPES[ityp]) == base, f"{sname}.{name}"

    check("LowCmd_", g.LOWCMD_C)
    check("LowState_", g.LOWSTATE_C)
    check("WirelessController_", g.WIRELESS_C)
    for name in g.TYPE_NAMES.values():
        assert name.split("::")[-1] in structs
