"""Go2 codec timings: numpy-dtype fast path vs a naive per-field ``struct`` implementation.

Run: ``.venv/bin/python bench/bench_codec.py``. Prints a table (median and best of several repeats,
microseconds per call) and the naive/fast ratios. Both implementations are run in the same
process on the same frames, and their outputs are checked equal first.
"""

from __future__ import annotations

import struct
import timeit

import numpy as np

from hw import crc as crcmod
from hw import go2_msgs as g

H = g.HEADER_LEN
_LS = {lf[0]: lf[3] + H for lf in g._cdr_leaves(g.LOW_STATE, 0, ())[0]}
_LC = {lf[0]: lf[3] + H for lf in g._cdr_leaves(g.LOW_CMD, 0, ())[0]}
SDK_LOWCMD_FMT = struct.Struct("<4B4IH2x" + "B3x5f3I" * 20 + "4B" + "55Bx2I")
_F = struct.Struct("<f")
_U4 = struct.Struct("<I")
_B = struct.Struct("<B")


# ----------------------------------------------------------------------------- naive reference
def naive_decode_lowstate(buf: bytes) -> dict:
    """Per-field struct.unpack_from into Python lists (what a hand-written decoder does)."""
    out = {}
    for key, st in (("q", _F), ("dq", _F), ("ddq", _F), ("tau_est", _F), ("temperature", _B),
                    ("lost", _U4)):
        out[key] = [st.unpack_from(buf, _LS[("motor_state", k, key)])[0] for k in range(12)]
    for key, n in (("quaternion", 4), ("gyroscope", 3), ("accelerometer", 3), ("rpy", 3)):
        out[key] = list(struct.unpack_from(f"<{n}f", buf, _LS[("imu_state", key)]))
    out["foot_force"] = list(struct.unpack_from("<4h", buf, _LS[("foot_force",)]))
    out["tick"] = _U4.unpack_from(buf, _LS[("tick",)])[0]
    out["wireless_remote"] = buf[_LS[("wireless_remote",)]:_LS[("wireless_remote",)] + 40]
    return out


class NaiveLowCmd:
    """LowCmd_ by struct.pack_into per field, C image by the SDK's struct format, table CRC."""

    def __init__(self):
        self.buf = bytearray(g.LOWCMD_SIZE)
        self.buf[:4] = b"\x00\x01\x00\x00"
        self.vals = {"head": [0xFE, 0xEF], "level_flag": 0xFF}
        self.motors = [{"mode": 1, "q": g.POS_STOP_F, "dq": g.VEL_STOP_F, "tau": 0.0,
                        "kp": 0.0, "kd": 0.0} for _ in range(20)]

    def set_motors(self, q, dq, kp, kd, tau):
        for k in range(12):
            m = self.motors[k]
            m["q"], m["dq"], m["kp"], m["kd"], m["tau"] = (float(q[k]), float(dq[k]),
                                                           float(kp[k]), float(kd[k]),
                                                           float(tau[k]))

    def finalize(self) -> bytes:
        b = self.buf
        b[_LC[("head",)]:_LC[("head",)] + 2] = bytes(self.vals["head"])
        b[_LC[("level_flag",)]] = self.vals["level_flag"]
        flat = [*self.vals["head"], self.vals["level_flag"], 0, 0, 0, 0, 0, 0]
        for k, m in enumerate(self.motors):
            b[_LC[("motor_cmd", k, "mode")]] = m["mode"]
            for key in ("q", "dq", "tau", "kp", "kd"):
                _F.pack_into(b, _LC[("motor_cmd", k, key)], m[key])
            flat += [m["mode"], m["q"], m["dq"], m["tau"], m["kp"], m["kd"], 0, 0, 0]
        flat += [0] * (4 + 55) + [0, 0]
        img = SDK_LOWCMD_FMT.pack(*flat)
        words = np.frombuffer(img, "<u4")[:-1]
        crc = crcmod.crc32_mpeg2_table(words.astype(">u4").tobytes())
        _U4.pack_into(b, _LC[("crc",)], crc)
        return bytes(b)


# ----------------------------------------------------------------------------- fast path
def fast_decode_lowstate(buf: bytes) -> tuple:
    v = g.decode_lowstate(buf)
    return (v.q, v.dq, v.ddq, v.tau_est, v.temperature, v.lost, v.quaternion, v.gyroscope,
            v.accelerometer, v.rpy, v.foot_force, v.tick, v.wireless_remote)


def _time(fn, number: int, repeat: int = 7) -> tuple[float, float]:
    runs = np.array(timeit.repeat(fn, number=number, repeat=repeat)) / number * 1e6
    return float(np.median(runs)), float(runs.min())


def main() -> None:
    rng = np.random.default_rng(0)
    sb = g.LowStateBuffer()
    sb.set_motors(rng.normal(size=12), rng.normal(size=12), rng.normal(size=12))
    sb.set_imu([1, 0, 0, 0], rng.normal(size=3), rng.normal(size=3), rng.normal(size=3))
    sb.set_tick(1234)
    state = sb.finalize()
    q, dq, kp, kd, tau = (rng.normal(size=12).astype(np.float32) for _ in range(5))

    # same answers first
    nd, fd = naive_decode_lowstate(state), fast_decode_lowstate(state)
    assert np.array_equal(nd["q"], fd[0]) and nd["tick"] == fd[11]
    fast_cmd, naive_cmd = g.LowCmdBuffer(), NaiveLowCmd()
    fast_cmd.set_motors(q, dq, kp, kd, tau)
    naive_cmd.set_motors(q, dq, kp, kd, tau)
    assert fast_cmd.finalize() == naive_cmd.finalize()

    def fast_cmd_cycle():
        fast_cmd.set_motors(q, dq, kp, kd, tau)
        return fast_cmd.finalize()

    def naive_cmd_cycle():
        naive_cmd.set_motors(q, dq, kp, kd, tau)
        return naive_cmd.finalize()

    cmd_frame = fast_cmd.finalize()
    words = rng.integers(0, 2**32, 202, dtype=np.uint32)
    be = words.astype(">u4").tobytes()
    rows = [
        ("LowState decode + 13 accessors", lambda: naive_decode_lowstate(state),
         lambda: fast_decode_lowstate(state), 2000),
        ("LowCmd set 12 motors + CRC + bytes", naive_cmd_cycle, fast_cmd_cycle, 500),
        ("CRC 202 words (table py / zlib)", lambda: crcmod.crc32_mpeg2_table(be),
         lambda: crcmod.crc32_words(words), 500),
        ("CRC 202 words (bitwise SDK loop)", lambda: crcmod.crc32_core(words),
         lambda: crcmod.crc32_words(words), 20),
        ("lowcmd_crc(frame) from CDR bytes", None, lambda: g.lowcmd_crc(cmd_frame), 2000),
    ]
    print(f"{'operation':38s} {'naive med':>10s} {'fast med':>9s} {'fast best':>9s} {'ratio':>7s}")
    print(f"{'':38s} {'(us)':>10s} {'(us)':>9s} {'(us)':>9s} {'':>7s}")
    for name, naive, fast, n in rows:
        f_med, f_best = _time(fast, n)
        if naive is None:
            print(f"{name:38s} {'-':>10s} {f_med:9.2f} {f_best:9.2f} {'-':>7s}")
            continue
        n_med, _ = _time(naive, max(n // 10, 3))
        print(f"{name:38s} {n_med:10.2f} {f_med:9.2f} {f_best:9.2f} {n_med / f_med:6.1f}x")


if __name__ == "__main__":
    main()
