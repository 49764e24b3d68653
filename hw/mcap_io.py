"""MCAP export and import of a :class:`hw.recorder.RecordingSnapshot` (spec: ``docs/recording.md``).

Channels (all CDR, XCDR1 little-endian with the 4-byte encapsulation header, OMG IDL schemas, so
Foxglove decodes every one of them):

* ``rt/lowstate``, ``rt/lowcmd``, ``rt/wirelesscontroller``: the Go2 messages, byte for byte as
  received/sent, schemas ``unitree_go::msg::dds_::LowState_`` / ``LowCmd_`` /
  ``WirelessController_`` whose text is ``hw/idl/unitree_go.idl``.
* ``imu/<LEG>``: foot-IMU samples, schema ``a2i::FootImuSample`` (:data:`A2I_IDL`).
* ``a2i/events``: state-machine events, schema ``a2i::Event``.

Message log time = host receive time (ns, host monotonic clock). Publish time = the foot IMU's
stamp mapped into the host clock when known, else the log time.

Metadata records: ``a2i/session`` (the caller's dict: config, leg, mounting truth when simulated,
...) and ``a2i/recording`` (format version, software version, counters, slot sizes, window).

Reading back: the decoded LowState/LowCmd fields are not stored twice; :func:`read_mcap` decodes
them from the CDR bytes with ``hw.go2_msgs`` (the same decoder the control loop uses).
"""

from __future__ import annotations

import json
import os
import struct
import warnings
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from calib.atomic import atomic_output
from hw.recorder import (
    EVENT_DTYPE,
    EVENT_TEXT_BYTES,
    LEGS,
    LOWCMD_BYTES,
    LOWSTATE_BYTES,
    WIRELESS_BYTES,
    RecordingSnapshot,
    imu_dtype,
    lowcmd_dtype,
    lowstate_dtype,
    stream_names,
    wireless_dtype,
)

__all__ = [
    "A2I_IDL",
    "FORMAT_VERSION",
    "IDL_FILE",
    "decode_event",
    "decode_imu_samples",
    "encode_event",
    "encode_imu_samples",
    "read_mcap",
    "read_mcap_metadata",
    "write_mcap",
]

FORMAT_VERSION = "1"
PROFILE = ""  # no ROS profile: plain CDR + OMG IDL
CDR_HEADER = b"\x00\x01\x00\x00"  # XCDR1 (plain CDR), little-endian
IDL_FILE = Path(__file__).resolve().parent / "idl" / "unitree_go.idl"

TOPIC_LOWSTATE = "rt/lowstate"
TOPIC_LOWCMD = "rt/lowcmd"
TOPIC_WIRELESS = "rt/wirelesscontroller"
TOPIC_EVENTS = "a2i/events"
SCHEMA_LOWSTATE = "unitree_go::msg::dds_::LowState_"
SCHEMA_LOWCMD = "unitree_go::msg::dds_::LowCmd_"
SCHEMA_WIRELESS = "unitree_go::msg::dds_::WirelessController_"
SCHEMA_IMU = "a2i::FootImuSample"
SCHEMA_EVENT = "a2i::Event"

A2I_IDL = """\
// A2I recorder messages (docs/recording.md). Times: int64 ns of the host monotonic clock;
// a negative time means unknown. Vectors: float32, SI units.
module a2i {
  // One foot-IMU sample. gyro rad/s and accel m/s^2 (specific force) in the IMU frame I;
  // quat_wxyz: orientation IMU frame -> device world frame as the device reports it (w, x, y, z).
  struct FootImuSample {
    int64 t_host_ns;    // host receive time
    int64 t_device_ns;  // the device's own stamp, device clock
    int64 t_mapped_ns;  // device stamp mapped into the host clock
    uint16 seq;         // device frame counter, wraps 65535 -> 0
    uint8 node;         // radio node id
    float gyro[3];
    float accel[3];
    float quat_wxyz[4];
  };
  // A state-machine transition or other notable event.
  struct Event {
    int64 t_host_ns;
    int32 code;
    string text;        // UTF-8, at most 64 bytes
  };
};
"""

# XCDR1 body layout of a2i::FootImuSample: int64 aligned to 8, float to 4 (relative to the body).
_IMU_WIRE = np.dtype({
    "names": ["t_host_ns", "t_device_ns", "t_mapped_ns", "seq", "node", "gyro", "accel",
              "quat_wxyz"],
    "formats": ["<i8", "<i8", "<i8", "<u2", "u1", ("<f4", (3,)), ("<f4", (3,)), ("<f4", (4,))],
    "offsets": [0, 8, 16, 24, 26, 28, 40, 52],
    "itemsize": 68,
})
_EVENT_HEAD = struct.Struct("<qiI")  # t_host_ns, code, string length incl. the terminating NUL


def _idl_text() -> str | None:
    """The Go2 IDL text, read when exporting (owned by ``hw/go2_msgs.py``)."""
    try:
        return IDL_FILE.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None


def encode_imu_samples(rows: np.ndarray) -> list[bytes]:
    """CDR messages (header included) of ``a2i::FootImuSample`` for rows of ``imu_dtype()``."""
    wire = np.zeros(rows.shape[0], _IMU_WIRE)
    for name in _IMU_WIRE.names:
        wire[name] = rows[name]
    body = wire.tobytes()
    n = _IMU_WIRE.itemsize
    return [CDR_HEADER + body[k:k + n] for k in range(0, len(body), n)]


def decode_imu_samples(messages: list[bytes]) -> np.ndarray:
    """Rows of ``imu_dtype()`` from ``a2i::FootImuSample`` CDR messages."""
    out = np.zeros(len(messages), imu_dtype())
    if not messages:
        return out
    n = _IMU_WIRE.itemsize
    for m in messages:
        if len(m) < 4 + n or m[:2] != CDR_HEADER[:2]:
            raise ValueError(f"not a little-endian XCDR1 a2i::FootImuSample ({len(m)} bytes)")
    wire = np.frombuffer(b"".join(m[4:4 + n] for m in messages), _IMU_WIRE)
    for name in _IMU_WIRE.names:
        out[name] = wire[name]
    return out


def encode_event(t_host_ns: int, code: int, text: bytes) -> bytes:
    """CDR message of ``a2i::Event`` (``text`` already UTF-8, without NUL)."""
    return CDR_HEADER + _EVENT_HEAD.pack(int(t_host_ns), int(code), len(text) + 1) + text + b"\0"


def decode_event(message: bytes) -> tuple[int, int, bytes]:
    """``(t_host_ns, code, text_utf8)`` from an ``a2i::Event`` CDR message."""
    if len(message) < 4 + _EVENT_HEAD.size or message[:2] != CDR_HEADER[:2]:
        raise ValueError("not a little-endian XCDR1 a2i::Event")
    t, code, n = _EVENT_HEAD.unpack_from(message, 4)
    start = 4 + _EVENT_HEAD.size
    if n < 1 or start + n > len(message):
        raise ValueError("a2i::Event string runs past the message")
    return t, code, bytes(message[start:start + n - 1])


def _meta_value(value) -> tuple[str, bool]:
    if isinstance(value, str):
        return value, False
    try:
        return json.dumps(value, default=_json_default, sort_keys=True), True
    except (TypeError, ValueError) as exc:
        raise ValueError(f"metadata value cannot be stored: {exc}") from None


def _json_default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if hasattr(obj, "__dataclass_fields__"):
        from dataclasses import asdict
        return asdict(obj)
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"metadata value of type {type(obj).__name__} is not JSON-serialisable")


def _software_version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("a2i-calib")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown"


def _raw_messages(rows: np.ndarray, stream: str) -> list[bytes]:
    lengths = rows["raw_len"]
    if rows.shape[0] and int(lengths.min()) == 0:
        raise ValueError(f"{stream} row without CDR bytes: the recorder must be given the raw "
                         "message to export it")
    raw = rows["raw"]
    return [raw[k, :lengths[k]].tobytes() for k in range(rows.shape[0])]


def write_mcap(path: str | os.PathLike, snapshot: RecordingSnapshot,
               metadata: dict | None = None, *, compression: str = "zstd") -> Path:
    """Write ``snapshot`` to an MCAP file at ``path`` atomically (temp file, fsync, rename).

    ``metadata``: the session description (config, leg, mounting truth when simulated, ...);
    strings are stored as is, anything else as JSON. ``compression``: ``"zstd"``, ``"lz4"`` or
    ``"none"``. Returns the path written.
    """
    metadata = dict(metadata or {})
    comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE}.get(compression)
    if comp is None:
        raise ValueError(f"compression must be zstd, lz4 or none, got {compression!r}")
    for leg in snapshot.imu:
        if leg not in LEGS:
            raise ValueError(f"unknown leg {leg!r} in snapshot.imu")

    # Everything to write: (log_time, publish_time, sequence, stream key, payload)
    streams: list[tuple[str, np.ndarray, np.ndarray, list[bytes]]] = []
    go2 = ((TOPIC_LOWSTATE, snapshot.lowstate, "lowstate"),
           (TOPIC_LOWCMD, snapshot.lowcmd, "lowcmd"),
           (TOPIC_WIRELESS, snapshot.wireless, "wireless"))
    for topic, rows, name in go2:
        t = rows["t_host_ns"].astype(np.int64)
        streams.append((topic, t, t, _raw_messages(rows, name)))
    for leg, rows in snapshot.imu.items():
        t = rows["t_host_ns"].astype(np.int64)
        pub = np.where(rows["t_mapped_ns"] >= 0, rows["t_mapped_ns"], t).astype(np.int64)
        streams.append((f"imu/{leg}", t, pub, encode_imu_samples(rows)))
    ev = snapshot.events
    streams.append((TOPIC_EVENTS, ev["t_host_ns"].astype(np.int64), ev["t_host_ns"].astype(np.int64),
                    [encode_event(t, c, bytes(s)) for t, c, s in
                     zip(ev["t_host_ns"], ev["code"], ev["text"])]))
    for topic, t, pub, _ in streams:
        if t.size and (int(t.min()) < 0 or int(pub.min()) < 0):
            raise ValueError(f"{topic}: negative timestamp cannot be an MCAP time")

    idl = _idl_text()
    if idl is None:
        warnings.warn(f"{IDL_FILE} not found: Go2 channels are written without a schema "
                      "(Foxglove will not decode them)", RuntimeWarning, stacklevel=2)

    recording = {
        "format_version": FORMAT_VERSION,
        "software_version": _software_version(),
        "streams": json.dumps(list(snapshot.stream_names)),
        "total_written": json.dumps(snapshot.total_written, sort_keys=True),
        "overwritten": json.dumps(snapshot.overwritten, sort_keys=True),
        "raw_bytes": json.dumps({"lowstate": snapshot.lowstate.dtype["raw"].shape[0],
                                 "lowcmd": snapshot.lowcmd.dtype["raw"].shape[0],
                                 "wireless": snapshot.wireless.dtype["raw"].shape[0]}),
        "window_ns": json.dumps([snapshot.t0_ns, snapshot.t1_ns]),
        "time_base": "host monotonic clock, int64 ns",
        "joint_order": "SDK: FR, FL, RR, RL x (hip, thigh, calf)",
    }
    session, json_keys = {}, []
    for key, value in metadata.items():
        if not isinstance(key, str):
            raise TypeError(f"metadata keys must be strings, got {key!r}")
        session[key], is_json = _meta_value(value)
        if is_json:
            json_keys.append(key)
    session["_json_keys"] = json.dumps(sorted(json_keys))

    path = Path(path)
    with atomic_output(path) as f:
        writer = Writer(f, compression=comp)
        writer.start(profile=PROFILE, library="a2i-calib hw.mcap_io")
        channel_ids = _register(writer, streams, idl)
        _write_messages(writer, streams, channel_ids)
        writer.add_metadata("a2i/session", session)
        writer.add_metadata("a2i/recording", recording)
        writer.finish()
    return path


def _register(writer: Writer, streams, idl: str | None) -> dict[str, int]:
    a2i_idl = A2I_IDL.encode("utf-8")
    schema_ids = {}
    for name in (SCHEMA_LOWSTATE, SCHEMA_LOWCMD, SCHEMA_WIRELESS):
        schema_ids[name] = (writer.register_schema(name, "omgidl", idl.encode("utf-8"))
                            if idl is not None else 0)
    schema_ids[SCHEMA_IMU] = writer.register_schema(SCHEMA_IMU, "omgidl", a2i_idl)
    schema_ids[SCHEMA_EVENT] = writer.register_schema(SCHEMA_EVENT, "omgidl", a2i_idl)
    schema_of = {TOPIC_LOWSTATE: SCHEMA_LOWSTATE, TOPIC_LOWCMD: SCHEMA_LOWCMD,
                 TOPIC_WIRELESS: SCHEMA_WIRELESS, TOPIC_EVENTS: SCHEMA_EVENT}
    ids = {}
    for topic, *_ in streams:
        schema = schema_of.get(topic, SCHEMA_IMU)
        ids[topic] = writer.register_channel(topic, "cdr", schema_ids[schema])
    return ids


def _write_messages(writer: Writer, streams, channel_ids) -> None:
    # Interleave all channels in log-time order (stable: ties keep stream, then row order) so
    # that players streaming the file see time advance monotonically.
    times = np.concatenate([t for _, t, _, _ in streams]) if streams else np.zeros(0, np.int64)
    which = np.concatenate([np.full(t.shape[0], k, np.int64) for k, (_, t, _, _) in
                            enumerate(streams)])
    index = np.concatenate([np.arange(t.shape[0]) for _, t, _, _ in streams])
    order = np.argsort(times, kind="stable")
    cids = [channel_ids[topic] for topic, *_ in streams]
    pubs = [p.tolist() for _, _, p, _ in streams]
    logs = [t.tolist() for _, t, _, _ in streams]
    datas = [d for *_, d in streams]
    for k, i in zip(which[order].tolist(), index[order].tolist()):
        writer.add_message(cids[k], log_time=logs[k][i], data=datas[k][i],
                           publish_time=pubs[k][i], sequence=i)


def _go2_decoders():
    try:
        from hw import go2_msgs
    except ImportError as exc:
        raise ImportError("read_mcap decodes LowState/LowCmd with hw.go2_msgs, which failed to "
                          f"import: {exc}") from exc
    return go2_msgs


def read_mcap_metadata(path: str | os.PathLike) -> dict[str, dict]:
    """``{"a2i/session": {...}, "a2i/recording": {...}}`` with JSON values decoded."""
    out = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        for record in reader.iter_metadata():
            data = dict(record.metadata)
            if record.name == "a2i/session":
                json_keys = json.loads(data.pop("_json_keys", "[]"))
                for key in json_keys:
                    data[key] = json.loads(data[key])
            elif record.name == "a2i/recording":
                for key in ("streams", "total_written", "overwritten", "raw_bytes", "window_ns"):
                    if key in data:
                        data[key] = json.loads(data[key])
            out[record.name] = data
    return out


def read_mcap(path: str | os.PathLike) -> RecordingSnapshot:
    """Read a recording written by :func:`write_mcap` back into a :class:`RecordingSnapshot`.

    The Go2 messages keep their exact CDR bytes; their decoded fields (q, dq, tau_est, body
    IMU, tick; LowCmd motor targets) are decoded from those bytes with ``hw.go2_msgs``.
    Counters come from the ``a2i/recording`` metadata when present.
    """
    meta = read_mcap_metadata(path)
    rec = meta.get("a2i/recording", {})
    if rec.get("format_version", FORMAT_VERSION) != FORMAT_VERSION:
        raise ValueError(f"unsupported a2i recording format {rec.get('format_version')!r}")
    payloads: dict[str, list[tuple[int, bytes]]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        if summary is not None:
            for ch in summary.channels.values():
                payloads.setdefault(ch.topic, [])
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            payloads.setdefault(channel.topic, []).append((message.log_time, message.data))

    sizes = {"lowstate": LOWSTATE_BYTES, "lowcmd": LOWCMD_BYTES, "wireless": WIRELESS_BYTES}
    sizes.update(rec.get("raw_bytes", {}))
    lowstate = _raw_rows(payloads.get(TOPIC_LOWSTATE, []), lowstate_dtype, sizes["lowstate"])
    lowcmd = _raw_rows(payloads.get(TOPIC_LOWCMD, []), lowcmd_dtype, sizes["lowcmd"])
    wireless = _raw_rows(payloads.get(TOPIC_WIRELESS, []), wireless_dtype, sizes["wireless"])
    if lowstate.shape[0] or lowcmd.shape[0]:
        _decode_go2(lowstate, lowcmd)

    imu = {}
    for leg in LEGS:
        topic = f"imu/{leg}"
        if topic in payloads:
            imu[leg] = decode_imu_samples([d for _, d in payloads[topic]])
    events = np.zeros(len(payloads.get(TOPIC_EVENTS, [])), EVENT_DTYPE)
    for k, (_, data) in enumerate(payloads.get(TOPIC_EVENTS, [])):
        t, code, text = decode_event(data)
        events[k] = (t, code, text[:EVENT_TEXT_BYTES])

    names = stream_names(tuple(imu))
    counts = {"lowstate": lowstate.shape[0], "lowcmd": lowcmd.shape[0],
              "wireless": wireless.shape[0], "events": events.shape[0],
              **{f"imu/{leg}": rows.shape[0] for leg, rows in imu.items()}}
    total = {n: int(rec.get("total_written", {}).get(n, counts[n])) for n in names}
    over = {n: int(rec.get("overwritten", {}).get(n, 0)) for n in names}
    t0, t1 = rec.get("window_ns", [None, None])
    return RecordingSnapshot(lowstate=lowstate, lowcmd=lowcmd, wireless=wireless, imu=imu,
                             events=events, total_written=total, overwritten=over,
                             t0_ns=t0, t1_ns=t1)


def _raw_rows(messages: list[tuple[int, bytes]], make_dtype, size: int) -> np.ndarray:
    size = max([size, *(len(d) for _, d in messages)])
    rows = np.zeros(len(messages), make_dtype(size))
    for k, (t, data) in enumerate(messages):
        rows["t_host_ns"][k] = t
        rows["raw"][k, :len(data)] = np.frombuffer(data, np.uint8)
        rows["raw_len"][k] = len(data)
    return rows


def _decode_go2(lowstate: np.ndarray, lowcmd: np.ndarray) -> None:
    """Fill the decoded fields of ``lowstate``/``lowcmd`` rows in place from their CDR bytes."""
    go2 = _go2_decoders()
    if lowstate.shape[0]:
        _check_lengths(lowstate, go2.LOWSTATE_SIZE, "LowState_")
        rec = go2.lowstate_records(lowstate["raw"])
        motors = go2.get_field(rec, "motor_state")
        imu = rec["imu_state"]
        lowstate["q"] = motors["q"][:, :12]
        lowstate["dq"] = motors["dq"][:, :12]
        lowstate["tau_est"] = motors["tau_est"][:, :12]
        lowstate["imu_quat_wxyz"] = imu["quaternion"]
        lowstate["imu_gyro"] = imu["gyroscope"]
        lowstate["imu_accel"] = imu["accelerometer"]
        lowstate["tick"] = rec["tick"]
    if lowcmd.shape[0]:
        _check_lengths(lowcmd, go2.LOWCMD_SIZE, "LowCmd_")
        motors = go2.get_field(go2.lowcmd_records(lowcmd["raw"]), "motor_cmd")
        for field, wire in (("q_des", "q"), ("dq_des", "dq"), ("kp", "kp"), ("kd", "kd"),
                            ("tau_ff", "tau")):
            lowcmd[field] = motors[wire][:, :12]


def _check_lengths(rows: np.ndarray, size: int, what: str) -> None:
    bad = np.flatnonzero(rows["raw_len"] != size)
    if bad.size:
        raise ValueError(f"{what} message {int(bad[0])} has {int(rows['raw_len'][bad[0]])} "
                         f"bytes, expected {size}")
