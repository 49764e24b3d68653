"""MCAP export/import of recordings: round trip, channels and schemas, CDR of our own types, atomicity."""

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from pycdr2 import IdlStruct
from pycdr2.types import array, float32, int32, int64, uint8, uint16

from hw import go2_msgs, mcap_io
from hw.mcap_io import (
    A2I_IDL,
    decode_event,
    decode_imu_samples,
    encode_event,
    encode_imu_samples,
    read_mcap,
    read_mcap_metadata,
    write_mcap,
)
from hw.recorder import LEGS, LOWCMD_BYTES, LOWSTATE_BYTES, WIRELESS_BYTES, Recorder, RecorderConfig


# An independent CDR implementation (pycdr2) of our two IDL structs, to check our bytes against.
@dataclass
class RefFootImuSample(IdlStruct, typename="a2i::FootImuSample"):
    t_host_ns: int64
    t_device_ns: int64
    t_mapped_ns: int64
    seq: uint16
    node: uint8
    gyro: array[float32, 3]
    accel: array[float32, 3]
    quat_wxyz: array[float32, 4]


@dataclass
class RefEvent(IdlStruct, typename="a2i::Event"):
    t_host_ns: int64
    code: int32
    text: str


DOC = Path(__file__).resolve().parents[1] / "docs" / "recording.md"


def _record_session(rec: Recorder, n_ls: int = 60, seed: int = 7) -> dict:
    """Fill a recorder with real Go2 CDR frames and foot-IMU samples; return what was sent."""
    rng = np.random.default_rng(seed)
    sent = {"lowstate": [], "lowcmd": [], "wireless": []}
    for k in range(n_ls):
        t = 10_000_000 + 2_000_000 * k
        q, dq, tau = rng.normal(size=(3, 12)).astype(np.float32)
        quat = rng.normal(size=4).astype(np.float32)
        gyro, acc = rng.normal(size=(2, 3)).astype(np.float32)
        raw = go2_msgs.encode_lowstate(q, dq, tau, quat, gyro, acc, tick=5 * k)
        rec.record_lowstate(t, raw, q, dq, tau, quat, gyro, acc, 5 * k)
        sent["lowstate"].append(raw)
        if k % 10 == 0:
            kp, kd = np.full(12, 20.0, np.float32), np.full(12, 0.5, np.float32)
            cmd = go2_msgs.new_lowcmd()
            cmd.set_motors(q, dq, kp, kd, tau)
            raw = cmd.finalize()
            rec.record_lowcmd(t + 300_000, raw, q, dq, kp, kd, tau)
            sent["lowcmd"].append(raw)
            raw = go2_msgs.encode_wireless_controller(keys=k, lx=0.25, ry=-0.5)
            rec.record_wireless(t + 400_000, raw)
            sent["wireless"].append(raw)
        for node, leg in enumerate(("FL", "RR")):
            for j in range(2):  # foot IMUs at twice the LowState rate
                ti = t + 1_000_000 * j + 17 * node
                mapped = ti - 250_000 if k % 3 else -1  # sometimes no mapped device time
                rec.record_imu(leg, ti, 123_000 * (2 * k + j), mapped, (2 * k + j) % 65536, node,
                               rng.normal(size=3), rng.normal(size=3), rng.normal(size=4))
    rec.record_event(10_000_000, "PASSIVE -> STAND", 1)
    rec.record_event(50_000_000, "TRIPOD(FL) ✓ calibration", 3)
    return sent


def _assert_same(a, b):
    assert a.stream_names == b.stream_names
    for name in a.stream_names:
        x, y = a.stream(name), b.stream(name)
        assert x.dtype == y.dtype, name
        assert x.shape == y.shape, name
        for field in x.dtype.names:
            assert np.array_equal(x[field], y[field]), (name, field)
    assert a.total_written == b.total_written
    assert a.overwritten == b.overwritten
    assert (a.t0_ns, a.t1_ns) == (b.t0_ns, b.t1_ns)


def test_sizes_agree_with_go2_msgs():
    assert (LOWSTATE_BYTES, LOWCMD_BYTES, WIRELESS_BYTES) == (
        go2_msgs.LOWSTATE_SIZE, go2_msgs.LOWCMD_SIZE, go2_msgs.WIRELESS_SIZE)
    assert go2_msgs.TYPE_NAMES["LowState_"] == mcap_io.SCHEMA_LOWSTATE
    assert go2_msgs.TYPE_NAMES["LowCmd_"] == mcap_io.SCHEMA_LOWCMD
    assert go2_msgs.TYPE_NAMES["WirelessController_"] == mcap_io.SCHEMA_WIRELESS


def test_round_trip_snapshot_mcap_snapshot(tmp_path):
    rec = Recorder(RecorderConfig(seconds=1, legs=("FL", "RR"),
                                  capacity_overrides={"lowstate": 50, "imu/RR": 64}))
    _record_session(rec)
    snap = rec.snapshot()
    assert snap.overwritten["lowstate"] == 10 and snap.overwritten["imu/RR"] == 120 - 64
    meta = {"leg": "FL", "config": {"seconds": 1.0, "legs": ["FL", "RR"]},
            "mounting_truth_R": np.eye(3), "mounting_truth_td_s": 0.0125}
    path = write_mcap(tmp_path / "rec.mcap", snap, meta)
    back = read_mcap(path)
    _assert_same(snap, back)
    got = read_mcap_metadata(path)
    assert got["a2i/session"] == {"leg": "FL", "config": {"seconds": 1.0, "legs": ["FL", "RR"]},
                                  "mounting_truth_R": np.eye(3).tolist(),
                                  "mounting_truth_td_s": 0.0125}
    assert got["a2i/recording"]["overwritten"]["lowstate"] == 10
    assert got["a2i/recording"]["format_version"] == mcap_io.FORMAT_VERSION

    win = rec.snapshot(30_000_000, 60_000_000)
    back = read_mcap(write_mcap(tmp_path / "win.mcap", win, {}))
    _assert_same(win, back)
    assert back.lowstate.shape == (15,) and back.events.shape == (1,)


def test_channels_schemas_and_times(tmp_path):
    rec = Recorder(RecorderConfig(seconds=1))
    sent = _record_session(rec, n_ls=20)
    snap = rec.snapshot()
    path = write_mcap(tmp_path / "rec.mcap", snap, {"leg": "FL"}, compression="lz4")
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {ch.topic: ch for ch in summary.channels.values()}
        assert set(topics) == {"rt/lowstate", "rt/lowcmd", "rt/wirelesscontroller", "a2i/events",
                               *(f"imu/{leg}" for leg in LEGS)}
        expected_schema = {"rt/lowstate": "unitree_go::msg::dds_::LowState_",
                           "rt/lowcmd": "unitree_go::msg::dds_::LowCmd_",
                           "rt/wirelesscontroller": "unitree_go::msg::dds_::WirelessController_",
                           "a2i/events": "a2i::Event", "imu/FL": "a2i::FootImuSample"}
        for topic, name in expected_schema.items():
            ch = topics[topic]
            assert ch.message_encoding == "cdr"
            schema = summary.schemas[ch.schema_id]
            assert (schema.name, schema.encoding) == (name, "omgidl")
            struct = name.split("::")[-1]
            assert re.search(rf"struct\s+{re.escape(struct)}\s*{{", schema.data.decode())
        counts = summary.statistics.channel_message_counts
        assert counts[topics["rt/lowstate"].id] == 20 and counts[topics["imu/RR"].id] == 40
        assert topics["imu/FR"].id not in counts or counts[topics["imu/FR"].id] == 0

        got = {"rt/lowstate": [], "rt/lowcmd": [], "rt/wirelesscontroller": []}
        imu_times, last_log = [], -1
        for _schema, ch, msg in reader.iter_messages(log_time_order=False):
            assert msg.log_time >= last_log  # written interleaved in log-time order
            last_log = msg.log_time
            if ch.topic in got:
                got[ch.topic].append(msg.data)
            if ch.topic == "imu/FL":
                imu_times.append((msg.log_time, msg.publish_time, msg.sequence))
    assert got["rt/lowstate"] == sent["lowstate"]  # byte for byte
    assert got["rt/lowcmd"] == sent["lowcmd"]
    assert got["rt/wirelesscontroller"] == sent["wireless"]
    fl = snap.imu["FL"]
    pub = np.where(fl["t_mapped_ns"] >= 0, fl["t_mapped_ns"], fl["t_host_ns"])
    assert imu_times == list(zip(fl["t_host_ns"].tolist(), pub.tolist(), range(fl.shape[0])))


def test_go2_schema_is_the_idl_file(tmp_path):
    if not mcap_io.IDL_FILE.exists():
        pytest.skip(f"{mcap_io.IDL_FILE} not written yet (owned by hw/go2_msgs.py)")
    rec = Recorder(RecorderConfig(seconds=1))
    _record_session(rec, n_ls=3)
    path = write_mcap(tmp_path / "rec.mcap", rec.snapshot(), {})
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    idl = go2_msgs.idl_schema_text()
    go2 = [s for s in summary.schemas.values() if s.name.startswith("unitree_go::")]
    assert len(go2) == 3 and all(s.data.decode("utf-8") == idl for s in go2)


def test_a2i_idl_matches_the_wire_layout():
    """The IDL we publish and the numpy layout we encode with list the same fields in order."""
    body = re.search(r"struct FootImuSample \{(.*?)\};", A2I_IDL, re.DOTALL).group(1)
    members = re.findall(r"^\s*(\w+)\s+(\w+)(?:\[(\d+)\])?;", body, re.MULTILINE)
    idl_types = {"int64": "<i8", "uint16": "<u2", "uint8": "|u1", "float": "<f4"}
    wire = mcap_io._IMU_WIRE
    assert [m[1] for m in members] == list(wire.names)
    for typ, name, count in members:
        fdt = wire.fields[name][0]
        assert fdt.base.str == idl_types[typ], name
        assert fdt.shape == ((int(count),) if count else ()), name


def test_foot_imu_and_event_cdr_agree_with_pycdr2():
    """Cross-check our XCDR1 bytes against an independent CDR implementation (pycdr2)."""
    rec = Recorder(RecorderConfig(seconds=1, legs=("RL",)))
    rng = np.random.default_rng(11)
    for k in range(5):
        rec.record_imu("RL", 10**15 + k, -1 if k == 2 else 7 * k, 3 * k, 65535 - k, 200 + k,
                       rng.normal(size=3), rng.normal(size=3), rng.normal(size=4))
    rows = rec.snapshot().imu["RL"]
    ours = encode_imu_samples(rows)
    for row, msg in zip(rows, ours):
        ref = RefFootImuSample(int(row["t_host_ns"]), int(row["t_device_ns"]),
                            int(row["t_mapped_ns"]), int(row["seq"]), int(row["node"]),
                            row["gyro"].tolist(), row["accel"].tolist(),
                            row["quat_wxyz"].tolist()).serialize()
        assert msg == ref
        assert RefFootImuSample.deserialize(msg).seq == int(row["seq"])
    back = decode_imu_samples(ours)
    assert all(np.array_equal(back[f], rows[f]) for f in rows.dtype.names)

    text = "SOLVE done: CC 0.97 ✓".encode()
    msg = encode_event(123456789, -4, text)
    assert msg == RefEvent(123456789, -4, text.decode()).serialize()
    assert decode_event(msg) == (123456789, -4, text)
    with pytest.raises(ValueError):
        decode_event(msg[:-3])
    with pytest.raises(ValueError):
        decode_imu_samples([ours[0][:40]])


def test_write_is_atomic_and_leaves_no_temp(tmp_path, monkeypatch):
    rec = Recorder(RecorderConfig(seconds=1))
    _record_session(rec, n_ls=5)
    snap = rec.snapshot()
    path = tmp_path / "rec.mcap"
    path.write_bytes(b"previous recording")

    def boom(self, name, data):
        raise OSError("disk full")

    monkeypatch.setattr(mcap_io.Writer, "add_metadata", boom)
    with pytest.raises(OSError, match="disk full"):
        write_mcap(path, snap, {})
    assert path.read_bytes() == b"previous recording"
    assert [p.name for p in tmp_path.iterdir()] == ["rec.mcap"]
    monkeypatch.undo()
    write_mcap(path, snap, {})
    _assert_same(snap, read_mcap(path))


def test_bad_inputs_are_refused(tmp_path):
    rec = Recorder(RecorderConfig(seconds=1))
    rec.record_lowstate(5, b"", np.zeros(12), np.zeros(12), np.zeros(12), [1, 0, 0, 0],
                        [0, 0, 0], [0, 0, 0], 0)
    with pytest.raises(ValueError, match="without CDR bytes"):
        write_mcap(tmp_path / "a.mcap", rec.snapshot(), {})
    rec = Recorder(RecorderConfig(seconds=1))
    rec.record_imu("FL", -5, 0, -1, 0, 0, [0, 0, 0], [0, 0, 0], [1, 0, 0, 0])
    with pytest.raises(ValueError, match="negative timestamp"):
        write_mcap(tmp_path / "b.mcap", rec.snapshot(), {})
    rec = Recorder(RecorderConfig(seconds=1))
    with pytest.raises(ValueError, match="compression"):
        write_mcap(tmp_path / "c.mcap", rec.snapshot(), {}, compression="gzip")
    with pytest.raises(ValueError, match="metadata"):
        write_mcap(tmp_path / "d.mcap", rec.snapshot(), {"x": object()})
    rec.record_lowstate(5, bytes(1000), np.zeros(12), np.zeros(12), np.zeros(12), [1, 0, 0, 0],
                        [0, 0, 0], [0, 0, 0], 0)
    path = write_mcap(tmp_path / "e.mcap", rec.snapshot(), {})  # stored as received...
    with pytest.raises(ValueError, match="1180"):
        read_mcap(path)  # ...but it is no LowState_, so it cannot be decoded
    assert not list(tmp_path.glob(".*.tmp"))


def test_docs_reading_snippet_runs(tmp_path):
    """The plain-``mcap`` reading example of docs/recording.md works on a real recording."""
    text = DOC.read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", text, re.DOTALL)
    snippet = next(b for b in blocks if "make_reader" in b and "FootImuSample" in b)
    rec = Recorder(RecorderConfig(seconds=1, legs=("FL", "RR")))
    _record_session(rec, n_ls=10)
    path = write_mcap(tmp_path / "session.mcap", rec.snapshot(), {"leg": "FL"})
    scope = {"PATH": str(path)}
    exec(compile(snippet, str(DOC), "exec"), scope)  # noqa: S102 - our own doc, on purpose
    imu = rec.snapshot().imu["FL"]
    assert np.allclose(scope["gyro"], imu["gyro"])
    assert np.array_equal(scope["t_host_ns"], imu["t_host_ns"])
    assert scope["q"].shape == (10, 12)
    assert np.array_equal(scope["q"], rec.snapshot().lowstate["q"])
