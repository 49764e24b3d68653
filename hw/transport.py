"""Zenoh transport for the Go2's DDS topics (raw CDR bytes, never decoded here).

On the robot a ``zenoh-bridge-dds`` maps each DDS topic to the Zenoh key of the same
name and forwards the serialized payload unchanged (4-byte encapsulation header
included). The mock robot (``hw/mock``) publishes and consumes the same bytes on the
same keys. This module moves those bytes; ``hw`` message modules decode them.

Receive stamps are ``time.monotonic_ns()`` taken in the subscriber callback (integer ns,
the host's one monotonic clock).

Delivery policy
---------------
Every publisher uses congestion control BLOCK and reliable delivery: a state or command
sample is never dropped silently by Zenoh. The price: when the peer's link is congested
``put`` waits for the transmit queue instead of returning at once, up to
``TransportConfig.block_timeout_s``, after which Zenoh closes the link. The 50 Hz loop's
deadline monitor sees that wait as an overrun; that is the intended failure (late and
visible) rather than a command lost without trace (DROP lost samples in measurements
here whenever a callback ran late). Express mode (no batching) is on for every
publisher; ``rt/lowcmd`` goes at priority REAL_TIME.

Exclusive publishing of ``rt/lowcmd``
-------------------------------------
Two controllers writing ``rt/lowcmd`` (the robot's sport mode, another controller,
a second copy of this program) fight over the motors. ``Transport.publisher`` refuses
to publish an exclusive key (``rt/lowcmd`` by default) while anyone else does, unless
``force=True``. Two independent detectors:

a. Liveliness: every publisher made here declares a token ``a2i/pub/<key>/<uuid>``.
   Before the first publish the transport declares its own token, then queries the
   tokens on ``a2i/pub/<key>/*``; any other token is a conflict. Declaring first makes
   two controllers starting at the same instant both see each other (both refuse).
b. Listen window: a subscriber on the key itself (remote origin only) listens for
   ``TransportConfig.conflict_window_s`` (default 0.3 s) before the first publish; any
   sample is someone else's command. This catches publishers that are not ours, such
   as a ``zenoh-bridge-dds`` forwarding a DDS writer of ``rt/lowcmd``. A publisher
   that writes less often than once per window escapes (b) but not (a) if it is ours.

Two controllers starting at the same instant both see each other's token and both
refuse. After the check the listen subscriber stays on: ``Publisher.conflict`` becomes
a one-line reason (sticky) as soon as a sample from another session arrives, i.e. when
commands are actually being mixed; the caller's safety supervisor polls it (``put``
itself stays fast and never raises for it). A newcomer that is refused never publishes,
so it does not disturb the active publisher. With ``force=True`` the conflict
found at start is kept in ``Publisher.forced_over`` and the detectors are switched off
(the operator has taken responsibility for the other publisher).
"""

from __future__ import annotations

import atexit
import json
import logging
import queue as _queue
import re
import threading
import time
import uuid
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple, Self

import zenoh

__all__ = [
    "KEY_LOWCMD",
    "KEY_LOWSTATE",
    "KEY_WIRELESS",
    "LIVELINESS_PREFIX",
    "LatestValue",
    "LowCmdConflict",
    "Publisher",
    "RxSample",
    "SampleQueue",
    "Transport",
    "TransportConfig",
    "TransportError",
]

log = logging.getLogger(__name__)

KEY_LOWSTATE = "rt/lowstate"
KEY_LOWCMD = "rt/lowcmd"
KEY_WIRELESS = "rt/wirelesscontroller"
LIVELINESS_PREFIX = "a2i/pub"

_MODES = ("peer", "client")
# proto/address[#params]; address must carry a port (host:port or [v6]:port).
_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic|ws)/(\[[0-9A-Fa-f:.]+\]|[^/\[\]:]+):(\d{1,5})(#.*)?$")


class TransportError(ConnectionError):
    """The Zenoh session could not be opened (endpoint unreachable, port taken...)."""


class LowCmdConflict(RuntimeError):
    """Another publisher of an exclusive key (``rt/lowcmd``) is present."""


def _check_endpoint(ep: str, what: str) -> None:
    m = _ENDPOINT_RE.match(ep)
    if m is None or not 0 <= int(m.group(3)) <= 65535:
        raise ValueError(f"{what} endpoint {ep!r} is not of the form proto/host:port "
                         "(e.g. tcp/127.0.0.1:7447)")


def _is_loopback(ep: str) -> bool:
    host = _ENDPOINT_RE.match(ep).group(2).strip("[]")
    return host == "localhost" or host == "::1" or host.startswith("127.")


@dataclass
class TransportConfig:
    """How to join the Zenoh network.

    mode: "peer" (default) or "client" (needs a router at ``connect``).
    connect: endpoints to connect to, e.g. ``["tcp/192.168.123.18:7447"]``. When given,
        ``open`` fails with ``TransportError`` unless one is reached within
        ``connect_timeout_s`` (s).
    listen: endpoints to listen on, e.g. ``["tcp/127.0.0.1:7447"]`` (the mock robot).
        At least one of connect / listen is required: multicast scouting is always off,
        so without an explicit endpoint nobody could ever meet this session.
    gossip: gossip scouting: peers learn each other's listen endpoints through the
        node they share and link directly. Needed because a peer does not route between
        two other peers: two controllers both connected to the robot's bridge would not
        see each other (nor each other's rt/lowcmd) without a direct link.
    auto_listen: a peer given only ``connect`` also listens on an ephemeral port
        (``tcp/127.0.0.1:0`` when every connect endpoint is loopback, else
        ``tcp/0.0.0.0:0``) so that gossip can link it to the other peers.
    block_timeout_s: longest a BLOCK put may wait on a congested link before Zenoh
        closes that link (s).
    conflict_window_s: listen window before the first publish of an exclusive key (s).
    """

    mode: str = "peer"
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    gossip: bool = True
    auto_listen: bool = True
    connect_timeout_s: float = 2.0
    block_timeout_s: float = 0.5
    conflict_window_s: float = 0.3

    def validate(self) -> None:
        if self.mode not in _MODES:
            raise ValueError(f"mode must be one of {_MODES}, got {self.mode!r}")
        for ep in self.connect:
            _check_endpoint(ep, "connect")
        for ep in self.listen:
            _check_endpoint(ep, "listen")
        if not self.connect and not self.listen:
            raise ValueError("give at least one connect or listen endpoint "
                             "(multicast scouting is off), e.g. connect=['tcp/127.0.0.1:7447']")
        if self.mode == "client" and not self.connect:
            raise ValueError("client mode needs a connect endpoint (a router or bridge)")
        for name in ("connect_timeout_s", "block_timeout_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if not self.conflict_window_s >= 0:
            raise ValueError(f"conflict_window_s must be >= 0, got {self.conflict_window_s!r}")

    def effective_listen(self) -> list[str]:
        """Listen endpoints after ``auto_listen``."""
        if self.listen or not self.auto_listen or self.mode != "peer" or not self.connect:
            return list(self.listen)
        loopback = all(_is_loopback(ep) for ep in self.connect)
        return ["tcp/127.0.0.1:0" if loopback else "tcp/0.0.0.0:0"]

    def to_dict(self) -> dict:
        """The Zenoh JSON5 configuration (as a dict) this config stands for."""
        self.validate()
        return {
            "mode": self.mode,
            "connect": {
                "endpoints": list(self.connect),
                "timeout_ms": round(self.connect_timeout_s * 1000),
                # Fail open() instead of retrying silently in the background: a deploy
                # that cannot reach the robot must say so at once.
                "exit_on_failure": True,
            },
            "listen": {"endpoints": self.effective_listen(), "exit_on_failure": True},
            "scouting": {
                "multicast": {"enabled": False},
                "gossip": {"enabled": bool(self.gossip)},
            },
            "transport": {"link": {"tx": {"queue": {"congestion_control": {
                "block": {"wait_before_close": round(self.block_timeout_s * 1e6)},
            }}}}},
        }

    def to_json5(self) -> str:
        return json.dumps(self.to_dict(), indent=2)


class RxSample(NamedTuple):
    """One received sample: payload bytes, host receive stamp (monotonic ns), 1-based count."""

    payload: bytes
    t_ns: int
    count: int


class LatestValue:
    """Latest payload on one key, for the control loop.

    ``get()`` is a single attribute read (atomic under the GIL): it never waits on the
    receive thread. ``wait_new`` blocks on a condition variable.
    """

    def __init__(self, key: str):
        self.key = key
        self._value: tuple[bytes | None, int, int] = (None, 0, 0)
        self._cond = threading.Condition()
        self._sub = None

    def _on_sample(self, sample) -> None:
        t_ns = time.monotonic_ns()
        payload = sample.payload.to_bytes()
        with self._cond:
            self._value = (payload, t_ns, self._value[2] + 1)
            self._cond.notify_all()

    def get(self) -> tuple[bytes | None, int, int]:
        """(payload, receive stamp ns, count); (None, 0, 0) before the first sample."""
        return self._value

    @property
    def count(self) -> int:
        return self._value[2]

    def wait_new(self, after_count: int, timeout: float) -> tuple[bytes | None, int, int] | None:
        """Wait up to ``timeout`` s for count > ``after_count``; the value, or None on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._value[2] <= after_count:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
            return self._value


class SampleQueue:
    """Every sample on one key into a bounded FIFO (for the recorder).

    When full, the incoming sample is rejected and counted in ``dropped`` (a warning is
    logged once per queue): what is already queued stays contiguous, the gap is explicit.
    """

    def __init__(self, key: str, maxlen: int):
        if maxlen < 1:
            raise ValueError(f"maxlen must be >= 1, got {maxlen}")
        self.key = key
        self.maxlen = maxlen
        self._q: _queue.SimpleQueue[RxSample] = _queue.SimpleQueue()
        self._size = 0  # written only by the receive thread (+) and the consumer (-)
        self._size_lock = threading.Lock()
        self.received = 0
        self.dropped = 0
        self._warned = False
        self._sub = None

    def _on_sample(self, sample) -> None:
        t_ns = time.monotonic_ns()
        self.received += 1
        with self._size_lock:
            full = self._size >= self.maxlen
            if not full:
                self._size += 1
        if full:
            self.dropped += 1
            if not self._warned:
                self._warned = True
                log.warning("queue on %r full (%d): dropping new samples, counted in .dropped",
                            self.key, self.maxlen)
            return
        self._q.put(RxSample(sample.payload.to_bytes(), t_ns, self.received))

    def __len__(self) -> int:
        return self._size

    def get(self, timeout: float | None = None) -> RxSample | None:
        """Next sample, waiting up to ``timeout`` s (None: forever); None on timeout."""
        try:
            s = self._q.get(timeout=timeout)
        except _queue.Empty:
            return None
        with self._size_lock:
            self._size -= 1
        return s

    def drain(self, max_n: int | None = None) -> list[RxSample]:
        """Everything queued now (at most ``max_n``), without waiting."""
        out: list[RxSample] = []
        while max_n is None or len(out) < max_n:
            try:
                out.append(self._q.get_nowait())
            except _queue.Empty:
                break
        with self._size_lock:
            self._size -= len(out)
        return out


class Publisher:
    """A declared publisher of one key (BLOCK, express); see the module docstring."""

    def __init__(self, key: str, zpub, token, monitors: list, exclusive: bool):
        self.key = key
        self.exclusive = exclusive
        self._zpub = zpub
        self._token = token
        self._monitors = monitors
        self._conflict: str | None = None
        self.forced_over: str | None = None  # the conflict overridden with force=True
        self.published = 0

    @property
    def conflict(self) -> str | None:
        """One-line reason if another publisher of this key appeared; else None."""
        return self._conflict

    def _flag(self, reason: str) -> None:
        if self._conflict is None:
            self._conflict = reason
            log.error("%s", reason)

    def put(self, payload: bytes) -> None:
        self._zpub.put(payload)
        self.published += 1

    def close(self) -> None:
        for m in self._monitors:
            _undeclare(m)
        self._monitors = []
        _undeclare(self._token)
        _undeclare(self._zpub)


def _undeclare(obj) -> None:
    if obj is None:
        return
    try:
        obj.undeclare()
    except zenoh.ZError:
        pass  # already undeclared, or the session is closed


def _zerror_line(e: Exception) -> str:
    # Zenoh errors end with " at <rust source path>:<line>." ; keep the human part.
    msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    return re.sub(r"\s+at /\S+\.rs:\d+\.?$", "", msg).strip()


def _callback(fn: Callable):
    """Wrap ``fn`` to run directly on Zenoh's receive thread.

    zenoh-python's default for a Python callable is a dedicated non-daemon Python thread
    per subscriber: one more thread hop per sample, and an interpreter that hangs at exit
    (threading joins those threads before atexit handlers run) if a subscriber is left
    declared. ``indirect=False`` (marked unstable upstream) avoids both; where it is not
    available the shutdown hook below closes every transport before that join.
    """
    try:
        return zenoh.handlers.Callback(fn, indirect=False)
    except TypeError:
        return fn


_live_transports: weakref.WeakSet[Transport] = weakref.WeakSet()


def _close_all_at_exit() -> None:
    for t in list(_live_transports):
        t.close()


# threading._register_atexit hooks run before the interpreter joins non-daemon threads;
# plain atexit hooks only after (too late if a zenoh callback thread is still alive).
_register = getattr(threading, "_register_atexit", None)
if _register is not None:
    _register(_close_all_at_exit)
else:  # pragma: no cover - other Python implementations
    atexit.register(_close_all_at_exit)


class Transport:
    """One Zenoh session plus the subscribers and publishers declared through it.

    Use as a context manager, or call ``open()`` / ``close()``. Payloads are ``bytes``.
    """

    def __init__(self, config: TransportConfig):
        config.validate()
        self.config = config
        self._session: zenoh.Session | None = None
        self._subs: list = []
        self._publishers: dict[str, Publisher] = {}
        self._latest: dict[str, LatestValue] = {}
        self._lock = threading.Lock()
        self.callback_errors = 0

    # -- lifecycle -------------------------------------------------------------------
    def open(self) -> Self:
        if self._session is not None:
            return self
        text = self.config.to_json5()
        log.debug("zenoh config: %s", text)
        try:
            zconf = zenoh.Config.from_json5(text)
            self._session = zenoh.open(zconf)
        except zenoh.ZError as e:
            eps = self.config.connect or self.config.listen
            raise TransportError(
                f"cannot open zenoh {self.config.mode} session on {', '.join(eps)} "
                f"({_zerror_line(e)}): is zenoh-bridge-dds / a2i-mock running there?"
            ) from None
        _live_transports.add(self)
        return self

    def close(self) -> None:
        """Undeclare everything and close the session; idempotent."""
        with self._lock:
            session, self._session = self._session, None
            pubs, self._publishers = list(self._publishers.values()), {}
            subs, self._subs = self._subs, []
            self._latest = {}
        if session is None:
            return
        for p in pubs:
            p.close()
        for s in subs:
            _undeclare(s)
        try:
            session.close()
        except zenoh.ZError:
            pass
        _live_transports.discard(self)

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError("transport is not open (call open() or use `with`)")
        return self._session

    @property
    def is_open(self) -> bool:
        return self._session is not None

    # -- receiving -------------------------------------------------------------------
    def _declare_sub(self, key: str, cb: Callable) -> None:
        sub = self.session.declare_subscriber(key, _callback(cb))
        with self._lock:
            self._subs.append(sub)

    def latest(self, key: str) -> LatestValue:
        """Latest-value holder for ``key`` (one per key per transport)."""
        with self._lock:
            lv = self._latest.get(key)
        if lv is None:
            lv = LatestValue(key)
            self._declare_sub(key, self._guard(key, lv._on_sample))
            with self._lock:
                self._latest[key] = lv
        return lv

    def queue(self, key: str, maxlen: int) -> SampleQueue:
        """Bounded FIFO of every sample on ``key``; overflow counted in ``.dropped``."""
        q = SampleQueue(key, maxlen)
        self._declare_sub(key, self._guard(key, q._on_sample))
        return q

    def subscribe(self, key: str, callback: Callable[[bytes, int], None]) -> None:
        """Call ``callback(payload, t_ns)`` on the receive thread for every sample.

        Keep it short: it runs on Zenoh's receive thread with the GIL held. Exceptions
        are logged (first one with traceback) and counted in ``callback_errors``.
        """

        def on_sample(sample) -> None:
            t_ns = time.monotonic_ns()
            callback(sample.payload.to_bytes(), t_ns)

        self._declare_sub(key, self._guard(key, on_sample))

    def _guard(self, key: str, fn: Callable) -> Callable:
        def cb(sample) -> None:
            try:
                fn(sample)
            except Exception:
                self.callback_errors += 1
                if self.callback_errors == 1:
                    log.exception("subscriber callback on %r raised (further ones counted "
                                  "in callback_errors)", key)
        return cb

    # -- publishing ------------------------------------------------------------------
    def publisher(self, key: str, force: bool = False,
                  exclusive: bool | None = None) -> Publisher:
        """Declare (once) the publisher of ``key`` and return it.

        exclusive: refuse while another publisher of ``key`` is present (default: True
            for ``rt/lowcmd`` only). Raises ``LowCmdConflict`` with the reason, unless
            ``force=True`` (then the conflict is logged and the publisher is returned).
        Blocks for ``config.conflict_window_s`` when exclusive.
        """
        with self._lock:
            existing = self._publishers.get(key)
        if existing is not None:
            return existing
        if exclusive is None:
            exclusive = key == KEY_LOWCMD
        s = self.session
        me = uuid.uuid4().hex
        token_key = f"{LIVELINESS_PREFIX}/{key}/{me}"
        monitors: list = []
        pub_holder: list[Publisher] = []
        early: list[str] = []

        def flag(reason: str) -> None:
            if pub_holder:
                pub_holder[0]._flag(reason)
            elif not early:
                early.append(reason)

        def on_token(sample) -> None:
            other = str(sample.key_expr)
            if other != token_key and sample.kind == zenoh.SampleKind.PUT:
                flag(f"another project publisher of {key!r} is alive ({other})")

        def on_foreign(sample) -> None:
            flag(f"someone else is publishing on {key!r} (a sample of "
                 f"{len(sample.payload)} B arrived from another session): sport mode "
                 "or another controller still running?")

        token = s.liveliness().declare_token(token_key)
        try:
            if exclusive:
                # (b) first, so the window also covers the liveliness round trip.
                t0 = time.monotonic()
                monitors.append(s.declare_subscriber(
                    key, _callback(on_foreign), allowed_origin=zenoh.Locality.REMOTE))
                # (a) tokens already alive: a history subscriber plus an explicit query
                # (history delivery is asynchronous; the query returns when answered).
                lsub = s.liveliness().declare_subscriber(
                    f"{LIVELINESS_PREFIX}/{key}/*", _callback(on_token), history=True)
                try:
                    timeout = max(self.config.conflict_window_s, 0.1)
                    for reply in s.liveliness().get(f"{LIVELINESS_PREFIX}/{key}/*",
                                                    timeout=timeout):
                        if reply.ok is not None:
                            on_token(reply.ok)
                    left = self.config.conflict_window_s - (time.monotonic() - t0)
                    if left > 0:
                        time.sleep(left)
                finally:
                    # Only the start-up check uses tokens: a newcomer that sees ours
                    # refuses by itself, so an active publisher need not react to it.
                    _undeclare(lsub)
            zpub = s.declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=(zenoh.Priority.REAL_TIME if key == KEY_LOWCMD
                          else zenoh.Priority.DATA_HIGH),
                express=True,
            )
        except BaseException:
            for m in monitors:
                _undeclare(m)
            _undeclare(token)
            raise
        pub = Publisher(key, zpub, token, monitors, exclusive)
        pub_holder.append(pub)
        if early:
            if not force:
                pub.close()
                raise LowCmdConflict(f"refusing to publish {key!r}: {early[0]} "
                                     "(pass force=True to override)")
            # The operator took responsibility: stop watching, keep the reason.
            log.warning("publishing %r despite a conflict (force=True): %s", key, early[0])
            pub.forced_over = early[0]
            for m in pub._monitors:
                _undeclare(m)
            pub._monitors = []
        with self._lock:
            self._publishers[key] = pub
        return pub

    def put(self, key: str, payload: bytes) -> None:
        """Publish on a key whose publisher was declared with ``publisher(key)``."""
        pub = self._publishers.get(key)
        if pub is None:
            if self._session is None:
                raise RuntimeError("transport is not open (call open() or use `with`)")
            raise ValueError(f"no publisher declared for {key!r}: call publisher({key!r}) first")
        pub.put(payload)
