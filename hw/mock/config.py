"""Configuration of the mock robot (``MockConfig``), loadable from JSON or YAML.

Every field has a default; a config file names only what it changes. Unknown keys are an
error (a typo must not silently fall back to a default). Units SI unless a name says
otherwise (``_deg``, ``_ppm``, ``_hz``). See ``docs/mock-robot.md`` for the reference.

Foot IMUs: ``foot_imus`` maps a leg (FL, FR, RL, RR) or ``"all"`` to a
:class:`FootImuMockConfig` dict; ``"all"`` is applied first, then the leg's own entry.
Fields left ``None`` are drawn from the seed (:meth:`MockConfig.resolve_imus`): a uniformly
random mounting rotation, a time offset uniform in ``[-max_time_offset_s, max_time_offset_s]``
(in realtime its magnitude: :meth:`MockConfig.resolve_imus`), a random sampling phase, the
device clock's start value.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.joints import LEGS, check_leg
from calib.metrics import rotation_from_rpy_deg
from hw.joystick import KEY_NAMES
from hw.transport import TransportConfig
from sim.sensors import FootImuConfig, random_mounting

__all__ = [
    "CLOCKS",
    "FootImuMockConfig",
    "JoystickPress",
    "MockConfig",
    "ResolvedImu",
    "load_config",
]

CLOCKS = ("realtime", "lockstep")
POSES = ("lying", "standing")
IMU_PORT_MODES = ("per_leg", "shared")
FRAME_BITS = 57 * 10  # one A2I v1 frame on an 8N1 line (docs/imu-protocol.md)
MAX_LINK_LOAD = 0.8  # a port is not planned above 80 % of its baud rate


def _check_whole(name: str, v, lo: int, hi: int) -> None:
    """ValueError (one line) unless ``v`` is a whole number in [lo, hi] (1.0 is, 1.5, inf and
    True are not)."""
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) \
            or v != int(v) or not lo <= v <= hi:
        raise ValueError(f"{name} must be a whole number in {lo}..{hi}, got {v!r}")


@dataclass
class FootImuMockConfig:
    """One foot IMU of the mock. ``None`` = drawn from the seed (see the module docstring).

    rotation_rpy_deg: mounting R_I^F as roll, pitch, yaw in degrees (R = Rz Ry Rx).
    rotation_matrix: mounting R_I^F (3x3, IMU-frame vectors into the foot frame); give at
        most one of the two.
    time_offset_s: t_d = t_I - t_E, s. rate_hz: sample rate. gyro_noise_density rad/s/sqrt(Hz)
    (None: the paper's middle level, 0.03 deg/s/sqrt(Hz)); gyro_bias rad/s (3,);
    gyro_bias_random_walk rad/s^2/sqrt(Hz); accel_noise_density m/s^2/sqrt(Hz); accel_bias
    m/s^2 (3,). dropout_prob: probability that a sample is never sent (its seq is skipped).
    garbage_prob: probability, per frame, of writing 1..garbage_max_bytes random bytes (never
    0xA2, so never a false sync) before it (fault tests). node_id: u8 (None: FL 1, FR 2,
    RL 3, RR 4). clock_offset_s: device clock reading at the mock's start, realtime clock only
    (None: random in [10, 1000] s). clock_drift_ppm: device clock rate error, realtime only.
    mass_kg: the node's mass (board, case, mount) strapped to the foot, 4 cm up the calf from
    the foot centre (``sim.effects.FootPayload``); 0: weightless.
    """

    enabled: bool = True
    rotation_rpy_deg: list[float] | None = None
    rotation_matrix: list[list[float]] | None = None
    time_offset_s: float | None = None
    rate_hz: float = 400.0
    gyro_noise_density: float | None = None
    gyro_bias: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    gyro_bias_random_walk: float = 0.0
    accel_noise_density: float = 0.002
    accel_bias: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    dropout_prob: float = 0.0
    garbage_prob: float = 0.0
    garbage_max_bytes: int = 16
    node_id: int | None = None
    clock_offset_s: float | None = None
    clock_drift_ppm: float = 0.0
    mass_kg: float = 0.0


@dataclass(frozen=True)
class JoystickPress:
    """A scripted remote press: ``keys`` held from sim time ``t_s`` for ``duration_s`` (s)."""

    t_s: float
    keys: tuple[str, ...]
    duration_s: float = 0.3


@dataclass(frozen=True)
class ResolvedImu:
    """A foot IMU with every random choice made: the sensor model's config plus the wire side."""

    leg: str
    sensor: FootImuConfig  # rotation R_I^F, time_offset t_d, rate, noise, phase, seed
    node_id: int
    garbage_prob: float
    garbage_max_bytes: int
    clock_offset_s: float
    clock_drift_ppm: float
    seed: int


@dataclass
class MockConfig:
    """Everything the mock robot needs (reference: ``docs/mock-robot.md``)."""

    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = field(default_factory=list)
    clock: str = "realtime"
    physics_hz: float = 1000.0
    lowstate_hz: float = 500.0
    wireless_hz: float = 50.0
    lockstep_quantum_s: float = 0.004
    lockstep_idle_repeat_s: float = 0.1
    lockstep_port_wait_s: float = 0.25
    tick_epoch_s: float = 1.0
    base: str = "free"
    initial_pose: str = "lying"
    floor_slope_deg: float = 0.0
    floor_slope_azimuth_deg: float = 0.0
    floor_timeconst_s: float = 0.02
    model_xml: str | None = None
    seed: int = 0
    imu_ports: str = "per_leg"
    imu_baud: int = 921600
    max_time_offset_s: float = 0.1
    foot_imus: dict[str, dict] = field(default_factory=dict)
    joystick: list[JoystickPress] = field(default_factory=list)
    truth_path: str | None = None
    encoder_resolution: float = 2.0 * math.pi / 2**15
    encoder_q_noise_std: float = 0.0
    encoder_dq_noise_std: float = 0.0
    body_gyro_noise_density: float = 0.0
    body_accel_noise_density: float = 0.0
    motor_temperature_c: int = 35
    resync_after_s: float = 0.05

    def __post_init__(self) -> None:
        # accept the file forms when built in code too
        for name in ("listen", "connect"):
            if isinstance(getattr(self, name), str):
                setattr(self, name, [getattr(self, name)])
        self.joystick = [_press(p) for p in (self.joystick or [])]
        if self.foot_imus is None:
            self.foot_imus = {}

    # ------------------------------------------------------------------ derived numbers
    @property
    def physics_dt(self) -> float:
        return 1.0 / self.physics_hz

    def steps_per(self, rate_hz: float) -> int:
        """Physics steps per period of ``rate_hz``."""
        return round(self.physics_hz / rate_hz)

    @property
    def quantum_steps(self) -> int:
        return round(self.lockstep_quantum_s * self.physics_hz)

    def transport_config(self) -> TransportConfig:
        return TransportConfig(listen=list(self.listen), connect=list(self.connect))

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Raise ValueError (one line) on any inconsistent field."""
        if self.clock not in CLOCKS:
            raise ValueError(f"clock must be one of {CLOCKS}, got {self.clock!r}")
        if self.base not in ("free", "fixed"):
            raise ValueError(f"base must be 'free' or 'fixed', got {self.base!r}")
        if self.initial_pose not in POSES:
            raise ValueError(f"initial_pose must be one of {POSES}, got {self.initial_pose!r}")
        if not (isinstance(self.floor_slope_deg, int | float)
                and 0 <= self.floor_slope_deg < math.degrees(0.5)):
            raise ValueError(f"floor_slope_deg must be in [0, {math.degrees(0.5):.1f}), got "
                             f"{self.floor_slope_deg!r}")
        if not (isinstance(self.floor_slope_azimuth_deg, int | float)
                and math.isfinite(self.floor_slope_azimuth_deg)):
            raise ValueError(f"floor_slope_azimuth_deg must be a finite number, got "
                             f"{self.floor_slope_azimuth_deg!r}")
        if self.floor_slope_deg and self.base != "free":
            raise ValueError("a floor slope needs base: free")
        for name in ("physics_hz", "lowstate_hz", "wireless_hz", "lockstep_quantum_s",
                     "tick_epoch_s", "imu_baud", "resync_after_s"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
        for name, lo, hi in (("seed", 0, 2**63 - 1), ("motor_temperature_c", 0, 255),
                             ("imu_baud", 1, 2**31 - 1)):
            _check_whole(name, getattr(self, name), lo, hi)
        if not isinstance(self.foot_imus, dict):
            kind = type(self.foot_imus).__name__  # a ValueError, as every bad config value
            raise ValueError(  # noqa: TRY004
                f"foot_imus must be a mapping of legs (or 'all') to settings, got {kind}")
        if not (isinstance(self.floor_timeconst_s, int | float)
                and 2.0 / self.physics_hz <= self.floor_timeconst_s <= 0.2):
            raise ValueError(f"floor_timeconst_s must be in [2 physics steps, 0.2] s, got "
                             f"{self.floor_timeconst_s!r}")
        if self.model_xml is not None and not (isinstance(self.model_xml, str)
                                               and Path(self.model_xml).is_file()):
            raise ValueError(f"model_xml must name an MJCF file of the Go2, got {self.model_xml!r}")
        if self.imu_ports not in IMU_PORT_MODES:
            raise ValueError(f"imu_ports must be one of {IMU_PORT_MODES}, got {self.imu_ports!r}")
        # waits, s: below an hour (a thread's timeout past the clock's range kills it)
        if not (isinstance(self.lockstep_idle_repeat_s, int | float)
                and 0 <= self.lockstep_idle_repeat_s < 3600):
            raise ValueError("lockstep_idle_repeat_s must be in [0, 3600) s (0 disables the "
                             f"repeat), got {self.lockstep_idle_repeat_s!r}")
        if not (isinstance(self.lockstep_port_wait_s, int | float)
                and 0 <= self.lockstep_port_wait_s < 3600):
            raise ValueError("lockstep_port_wait_s must be in [0, 3600) s (0: a full IMU port "
                             f"drops the frame), got {self.lockstep_port_wait_s!r}")
        if not 0 <= self.max_time_offset_s < self.tick_epoch_s:
            raise ValueError("max_time_offset_s must be in [0, tick_epoch_s)")
        for name, rate in (("lowstate_hz", self.lowstate_hz), ("wireless_hz", self.wireless_hz)):
            n = self.physics_hz / rate
            if rate > self.physics_hz or abs(n - round(n)) > 1e-9:
                raise ValueError(f"{name} must divide physics_hz ({self.physics_hz:g}), "
                                 f"got {rate:g}")
        q = self.lockstep_quantum_s * self.physics_hz
        ls = self.steps_per(self.lowstate_hz)
        if abs(q - round(q)) > 1e-6 or round(q) % ls:
            raise ValueError("lockstep_quantum_s must be a whole number of lowstate periods")
        if abs(self.tick_epoch_s * 1000 - round(self.tick_epoch_s * 1000)) > 1e-6:
            raise ValueError("tick_epoch_s must be a whole number of milliseconds")
        for name in ("encoder_resolution", "encoder_q_noise_std", "encoder_dq_noise_std",
                     "body_gyro_noise_density", "body_accel_noise_density"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        self.transport_config_checked()
        for p in self.joystick:
            if not (math.isfinite(p.t_s) and p.t_s >= 0 and p.duration_s > 0):
                raise ValueError(f"joystick press {p}: t_s must be >= 0 and duration_s > 0")
            for k in p.keys:
                if k not in KEY_NAMES:
                    raise ValueError(f"joystick press: unknown key {k!r} "
                                     f"(expected {', '.join(KEY_NAMES)})")
        imus = self.resolve_imus()
        if self.imu_ports == "shared" and imus:
            load = sum(r.sensor.rate for r in imus.values()) * FRAME_BITS
            if load > MAX_LINK_LOAD * self.imu_baud:
                raise ValueError(
                    f"{len(imus)} foot IMUs on one {self.imu_baud}-baud port need "
                    f"{load / self.imu_baud:.0%} of it (> {MAX_LINK_LOAD:.0%}): lower rate_hz, "
                    "raise imu_baud or use imu_ports: per_leg")
        for r in imus.values():
            if r.sensor.rate * FRAME_BITS > MAX_LINK_LOAD * self.imu_baud:
                raise ValueError(f"{r.leg}: {r.sensor.rate:g} Hz does not fit a "
                                 f"{self.imu_baud}-baud port")
            if self.clock == "lockstep" and abs(r.sensor.time_offset) >= self.tick_epoch_s:
                raise ValueError(f"{r.leg}: |time_offset_s| must be < tick_epoch_s")
        ids = [r.node_id for r in imus.values()]
        if len(set(ids)) != len(ids):
            raise ValueError(f"foot IMU node ids must differ, got {ids}")

    def transport_config_checked(self) -> None:
        if not self.listen and not self.connect:
            return  # in-process use, no transport
        self.transport_config().validate()

    # ------------------------------------------------------------------ foot IMUs
    def imu_entries(self) -> dict[str, FootImuMockConfig]:
        """The per-leg entries after merging ``"all"`` into each leg (ValueError on bad keys)."""
        known = {f.name for f in dataclasses.fields(FootImuMockConfig)}
        for key, d in self.foot_imus.items():
            if key != "all":
                check_leg(key)
            if not isinstance(d, dict):
                raise ValueError(f"foot_imus.{key} must be a mapping")  # noqa: TRY004
            bad = sorted(set(d) - known)
            if bad:
                raise ValueError(f"unknown key {bad[0]!r} in foot_imus.{key} "
                                 f"(known: {', '.join(sorted(known))})")
        upper = {str(k).upper() if k != "all" else k: v for k, v in self.foot_imus.items()}
        if len(upper) != len(self.foot_imus):  # "FL" and "fl": one would be lost
            raise ValueError(f"foot_imus names a leg twice: {', '.join(map(str, self.foot_imus))}")
        out = {}
        for leg in LEGS:
            merged = {**upper.get("all", {}), **upper.get(leg, {})}
            out[leg] = FootImuMockConfig(**merged)
        return out

    def resolve_imus(self) -> dict[str, ResolvedImu]:
        """Enabled foot IMUs, every ``None`` drawn from ``seed`` (same seed, same IMUs).

        In realtime a drawn time offset is made non-negative (its magnitude): an IMU that
        reports a motion before the encoders do is realised by delaying every lowstate
        (``MockRobot.output_delay_s``, ``docs/mock-robot.md``), which the control loop sees as
        latency. Seed 101's -77 ms tipped the tripod over as it shifted its weight off RL
        (lockstep, with no such delay: every leg held). A negative offset given in the config
        is kept."""
        entries = self.imu_entries()
        seeds = np.random.SeedSequence(int(self.seed)).spawn(len(LEGS))
        out: dict[str, ResolvedImu] = {}
        for i, leg in enumerate(LEGS):
            e = entries[leg]
            # Draws happen for every leg, enabled or not, so that disabling one leg does not
            # change the others' mountings.
            leg_seed = int(seeds[i].generate_state(1)[0])
            rng = np.random.default_rng(leg_seed)
            if not e.enabled:
                continue
            if not (isinstance(e.rate_hz, int | float) and e.rate_hz > 0):
                raise ValueError(f"foot_imus.{leg}.rate_hz must be > 0, got {e.rate_hz!r}")
            base = random_mounting(leg_seed, max_offset=self.max_time_offset_s,
                                   rate=float(e.rate_hz))
            over: dict = {}
            if e.rotation_rpy_deg is not None and e.rotation_matrix is not None:
                raise ValueError(f"foot_imus.{leg}: give rotation_rpy_deg or rotation_matrix, "
                                 "not both")
            if e.rotation_rpy_deg is not None:
                rpy = np.asarray(e.rotation_rpy_deg, dtype=float)
                if rpy.shape != (3,) or not np.all(np.isfinite(rpy)):
                    raise ValueError(f"foot_imus.{leg}.rotation_rpy_deg must be 3 numbers")
                over["rotation"] = rotation_from_rpy_deg(*rpy)
            elif e.rotation_matrix is not None:
                over["rotation"] = np.asarray(e.rotation_matrix, dtype=float)
            if e.time_offset_s is not None:
                over["time_offset"] = float(e.time_offset_s)
            elif self.clock == "realtime":
                over["time_offset"] = abs(base.time_offset)
            if e.gyro_noise_density is not None:
                over["gyro_noise_density"] = float(e.gyro_noise_density)
            over.update(
                gyro_bias=np.asarray(e.gyro_bias, dtype=float),
                gyro_bias_random_walk=float(e.gyro_bias_random_walk),
                accel_noise_density=float(e.accel_noise_density),
                accel_bias=np.asarray(e.accel_bias, dtype=float),
                dropout_prob=float(e.dropout_prob),
            )
            try:
                sensor = dataclasses.replace(base, **over)
            except ValueError as exc:
                raise ValueError(f"foot_imus.{leg}: {exc}") from None
            if abs(sensor.time_offset) > 10.0:
                raise ValueError(f"foot_imus.{leg}.time_offset_s is implausible "
                                 f"({sensor.time_offset} s)")
            if not 0.0 <= e.garbage_prob <= 1.0:
                raise ValueError(f"foot_imus.{leg}.garbage_prob must be in [0, 1]")
            _check_whole(f"foot_imus.{leg}.garbage_max_bytes", e.garbage_max_bytes, 1, 4096)
            if e.node_id is not None:
                _check_whole(f"foot_imus.{leg}.node_id", e.node_id, 0, 255)
            node = i + 1 if e.node_id is None else int(e.node_id)
            clock0 = (float(rng.uniform(10.0, 1000.0)) if e.clock_offset_s is None
                      else float(e.clock_offset_s))
            if not (math.isfinite(clock0) and clock0 >= 0):
                raise ValueError(f"foot_imus.{leg}.clock_offset_s must be >= 0")
            if not (math.isfinite(e.clock_drift_ppm) and abs(e.clock_drift_ppm) < 1000):
                raise ValueError(f"foot_imus.{leg}.clock_drift_ppm must be within +-1000")
            if not (isinstance(e.mass_kg, int | float) and 0 <= e.mass_kg < 1):
                raise ValueError(f"foot_imus.{leg}.mass_kg must be in [0, 1) kg, got {e.mass_kg!r}")
            out[leg] = ResolvedImu(leg=leg, sensor=sensor, node_id=node,
                                   garbage_prob=float(e.garbage_prob),
                                   garbage_max_bytes=int(e.garbage_max_bytes),
                                   clock_offset_s=clock0,
                                   clock_drift_ppm=float(e.clock_drift_ppm), seed=leg_seed)
        return out

    def foot_payloads(self) -> dict[str, float]:
        """kg on each foot whose IMU is enabled and has a ``mass_kg`` (call after validate)."""
        return {leg: float(e.mass_kg) for leg, e in self.imu_entries().items()
                if e.enabled and e.mass_kg > 0}

    # ------------------------------------------------------------------ (de)serialisation
    @classmethod
    def from_dict(cls, d: dict) -> MockConfig:
        """Build from a plain mapping (as read from JSON/YAML); unknown keys raise ValueError."""
        if not isinstance(d, dict):
            raise ValueError("a mock config must be a mapping at the top level")  # noqa: TRY004
        known = {f.name for f in dataclasses.fields(cls)}
        bad = sorted(set(d) - known)
        if bad:
            raise ValueError(f"unknown key {bad[0]!r} in mock config "
                             f"(known: {', '.join(sorted(known))})")
        cfg = cls(**d)
        cfg.validate()
        return cfg

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["joystick"] = [{"t_s": p.t_s, "keys": list(p.keys), "duration_s": p.duration_s}
                         for p in self.joystick]
        return d


def _press(p) -> JoystickPress:
    if isinstance(p, JoystickPress):
        return p
    if isinstance(p, dict):
        extra = set(p) - {"t_s", "keys", "duration_s"}
        if extra or "t_s" not in p or "keys" not in p:
            raise ValueError(f"joystick press {p!r}: expected keys t_s, keys[, duration_s]")
        t, keys, dur = p["t_s"], p["keys"], p.get("duration_s", 0.3)
    elif isinstance(p, list | tuple) and len(p) in (2, 3):
        t, keys, dur = (*p, 0.3) if len(p) == 2 else p
    else:
        raise ValueError(f"joystick press {p!r}: expected [t_s, keys, duration_s]")
    if isinstance(keys, str):
        keys = keys.replace("+", " ").split()
    return JoystickPress(float(t), tuple(str(k) for k in keys), float(dur))


def load_config(path: str | Path, **overrides) -> MockConfig:
    """Read a JSON (``.json``) or YAML (``.yaml``/``.yml``, needs PyYAML) mock config, apply
    ``overrides`` (non-None keyword values replace fields), validate. ValueError (one line) on
    an unreadable file, bad syntax, an unknown key or a bad value."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise ValueError(f"cannot read config {str(p)!r}: {e.strerror or e}") from None
    if p.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"config {str(p)!r} is not valid JSON: {e}") from None
    else:
        try:
            import yaml
        except ImportError:
            raise ValueError(f"config {str(p)!r}: YAML needs PyYAML (pip install pyyaml), "
                             "or give a .json file") from None
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise ValueError(f"config {str(p)!r} is not valid YAML: "
                             f"{str(e).splitlines()[0]}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ValueError(f"config {str(p)!r} must be a mapping at the top level")  # noqa: TRY004
    data.update({k: v for k, v in overrides.items() if v is not None})
    try:
        return MockConfig.from_dict(data)
    except TypeError as e:
        raise ValueError(f"config {str(p)!r}: {e}") from None
