"""The zenoh bus: opening a session and every key expression the pipeline uses.

Keys are ``smartroom/<room>/<stage>/...``; they are built here and nowhere else.
The bus is a star: the launcher's session is a zenoh router (the hub) that listens on
the layout's endpoints (loopback TCP by default, no multicast scouting), and every
worker, on this host or another, is a zenoh client of it. The hub routes every message
and every declaration (subscriptions, liveliness), so a worker that joins late, from
another host or over TLS, reaches every other worker through the one link it opened.
A mesh of peers linked by zenoh's gossip (the bus before) lost messages for good when
one of its N^2 links failed to form (zenoh 1.10 makes one attempt per gossip and its
peers do not relay): under load about one run in ten had a pair of workers that never
heard each other. Zenoh moves large payloads between processes of one host through its
shared-memory transport, through the hub too; a client whose link to the hub breaks
reconnects by itself.
"""
from __future__ import annotations

import json
import logging
import re
import socket
import threading
import time
from dataclasses import dataclass, field, replace

import zenoh

from app.bus_section import AclConfig, AuthConfig, TlsConfig, check_endpoints
from app.errors import InputError
from app.messages import Message, MessageError, decode

__all__ = ["BusConfig", "Keys", "open_session", "free_port", "Publisher", "Inlet", "MessageError"]

CLIENT_CONNECT_S = 30.0   # a worker waits this long for the hub when its session opens


@dataclass
class BusConfig:
    """Where the session listens and connects (zenoh endpoint strings), and how it
    admits other hosts: zenoh's TLS (mutual, with the room's CA) and user/password
    authentication (see app/bus_section.py, which parses the layout's bus section)."""

    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    connect: list[str] = field(default_factory=list)
    multicast: bool = False
    shm: bool = True    # zenoh's shared-memory transport between processes of one host
    tls: TlsConfig | None = None
    auth: AuthConfig | None = None
    acl: AclConfig | None = None    # the hub's access control (app.bus_acl), made from the layout
    #: a room whose workers all run on the hub's host admits them through a private socket
    #: and lets no one else publish in it (app.bus_acl.outsiders_read_only)
    private: bool = True

    def to_zenoh(self, mode: str = "peer") -> zenoh.Config:
        """zenoh's configuration of a session in ``mode``: ``router`` (the hub), ``client``
        (a worker) or ``peer`` (a probe or benchmark on its own)."""
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if mode == "client":   # wait for the hub a while instead of failing at once (it may start later)
            conf.insert_json5("connect/timeout_ms", json.dumps(int(CLIENT_CONNECT_S * 1000)))
        conf.insert_json5("scouting/multicast/enabled", "true" if self.multicast else "false")
        conf.insert_json5("transport/shared_memory/enabled", "true" if self.shm else "false")
        if self.tls is not None:
            conf.insert_json5("transport/link/tls", json.dumps(self.tls.to_zenoh()))
        if self.auth is not None:
            conf.insert_json5("transport/auth/usrpwd", json.dumps(self.auth.to_zenoh()))
        return conf

    def for_worker(self) -> "BusConfig":
        """A worker is a client of the hub: it connects to what the hub listens on (over
        TLS, with the same certificate and credentials, when the bus uses it) and listens
        on nothing; open it with ``open_session(bus, mode="client")``."""
        return replace(self, listen=[], connect=list(self.connect or self.listen))


def free_port() -> int:
    """A TCP port on loopback that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def open_session(bus: BusConfig, mode: str = "peer", access_control: dict | None = None) -> zenoh.Session:
    """Open a zenoh session (``mode``: see :meth:`BusConfig.to_zenoh`); a bad endpoint
    (syntax, a host that does not resolve, an address that cannot be bound, a hub that
    cannot be reached) is an :class:`InputError` of one line, not a zenoh error.
    ``access_control``: zenoh's ``access_control`` section (the hub's, :mod:`app.bus_acl`)."""
    check_endpoints(bus.listen, bus.connect, bus.tls, resolve=True)
    try:
        conf = bus.to_zenoh(mode)
        if access_control is not None:
            conf.insert_json5("access_control", json.dumps(access_control))
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        # zenoh appends " at /path/file.rs:NN." to each cause: keep the words, drop the places
        reason = re.sub(r"\s+at /\S+?\.rs:\d+\.?", "", " ".join(str(exc).split())) or type(exc).__name__
        endpoints = ", ".join([f"listen {ep}" for ep in bus.listen] + [f"connect {ep}" for ep in bus.connect])
        raise InputError(f"bus ({endpoints}): zenoh cannot open a session: {reason}") from None


class Keys:
    """Key expressions of one room."""

    def __init__(self, room: str):
        if not room or any(c in room for c in "/*$?#"):
            raise ValueError(f"room name {room!r} must be a plain word")
        self.root = f"smartroom/{room}"

    def frame(self, camera: str = "*") -> str:
        return f"{self.root}/frame/{camera}"

    def mask(self, camera: str = "*") -> str:
        return f"{self.root}/mask/{camera}"

    def voxels(self) -> str:
        return f"{self.root}/voxels"

    def blobs(self) -> str:
        return f"{self.root}/blobs"

    def tracks(self) -> str:
        return f"{self.root}/tracks"

    def poses(self) -> str:
        return f"{self.root}/poses"

    def poses_json(self) -> str:
        """Each frame's ``poses.jsonl`` record as JSON (the streamer's ``json`` protocol):
        the pose feed for clients that do not link our codec (docs/streaming/zenoh-feed.md)."""
        return f"{self.root}/poses/json"

    def keypoints(self) -> str:
        return f"{self.root}/keypoints"

    def markers(self, camera: str = "*") -> str:
        return f"{self.root}/markers/{camera}"

    def stats(self, worker: str = "*") -> str:
        return f"{self.root}/stats/{worker}"

    def eos(self, worker: str = "*") -> str:
        return f"{self.root}/eos/{worker}"

    def ack(self, worker: str = "*") -> str:
        return f"{self.root}/ack/{worker}"

    def heartbeat(self, worker: str = "*") -> str:
        return f"{self.root}/heartbeat/{worker}"

    def alive(self, worker: str = "*") -> str:
        return f"{self.root}/alive/{worker}"

    def everything(self) -> str:
        """Every key of the room."""
        return f"{self.root}/**"

    def stage(self, stage: str, camera: str = "*") -> str:
        """The key expression of what a stage publishes (per camera for frames, masks and markers)."""
        per_camera = {"frame": self.frame, "mask": self.mask, "markers": self.markers}
        if stage in per_camera:
            return per_camera[stage](camera)
        return f"{self.root}/{stage}"

    def relative(self, key) -> str:
        """A key without the ``smartroom/<room>/`` prefix (for counts and log lines)."""
        key = str(key)
        return key[len(self.root) + 1:] if key.startswith(self.root + "/") else key

    @staticmethod
    def last(key: str) -> str:
        """The last chunk of a key (camera or worker name)."""
        return str(key).rsplit("/", 1)[-1]


class Publisher:
    """A zenoh publisher of messages. Data uses ``DROP`` congestion control (a slow
    consumer loses frames, never stalls the producer); control messages (end of
    stream, final stats) use ``BLOCK`` so they always arrive."""

    def __init__(self, session: zenoh.Session, key: str, droppable: bool = True):
        cc = zenoh.CongestionControl.DROP if droppable else zenoh.CongestionControl.BLOCK
        self.key = key
        self._pub = session.declare_publisher(key, congestion_control=cc)

    def await_subscriber(self, timeout: float) -> bool:
        """Wait until the session knows a subscriber of this key (zenoh's matching status),
        at most ``timeout`` seconds; whether one is known. A session that has not yet
        learnt of a subscriber (a worker on another host that has just joined) sends its
        first messages nowhere."""
        deadline = time.monotonic() + timeout
        while not self._pub.matching_status.matching:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.005)
        return True

    def put(self, msg: Message) -> int:
        return self.put_payload(msg.to_bytes())

    def put_payload(self, payload: bytes) -> int:
        """Publish an already encoded message (a stage sending its outputs again)."""
        self._pub.put(payload)
        return len(payload)

    def undeclare(self):
        self._pub.undeclare()


def undeclare_quietly(entity) -> None:
    """Undeclare a subscriber, token or publisher that is being closed anyway (one the
    session already dropped raises; that changes nothing)."""
    try:
        entity.undeclare()
    except Exception:  # noqa: BLE001 - closing anyway
        pass


def decode_sample(sample) -> Message:
    """Decode a zenoh sample's payload (raises :class:`MessageError`)."""
    return decode(sample.payload.to_bytes())


class Inlet:
    """Subscriptions whose messages may wait a few milliseconds (stats, ends of stream,
    heartbeats, acknowledgements), drained together by one thread every :attr:`period_s`.

    Zenoh-python runs a subscription's Python callback on a thread of its own, woken for
    each message: under a flood of junk on the bus (issue 25) every message costs a
    thread's wake-up and a hand-over of the interpreter lock to it, which the process's
    main thread pays for too. Here each subscription queues its samples in zenoh's FIFO
    (no Python, no lock) and one thread takes whatever has queued, in batches, for at
    most :attr:`period_s` of delay. In a worker-like probe process that halved the CPU
    of a junk message (28 -> 15 µs); in the whole pipeline's flood bench the real-time
    factor's cost did not measurably change (docs/benchmarks.md, "Junk on the bus").
    Nothing is dropped: a full FIFO holds its sender back, as a slow callback does.
    Data keys keep zenoh's callbacks: a frame does not wait (a drain every 1 ms would
    cost an idle process 1-2 % of a core).
    """

    CAPACITY = 10_000    # samples a subscription holds between two drains
    BATCH = 1_000        # at most this many a subscription per pass (the others are not starved)

    def __init__(self, session: zenoh.Session, period_s: float = 0.002, name: str = "inlet"):
        self.session = session
        self.period_s = period_s
        self._subs: list = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._drain, name=name, daemon=True)
        self._log = logging.getLogger(f"smartroom.{name}")

    def subscribe(self, key: str, handler):
        """Hand every sample of ``key`` to ``handler`` (on the inlet's thread); the subscriber."""
        sub = self.session.declare_subscriber(key, zenoh.handlers.FifoChannel(self.CAPACITY))
        self._subs = [*self._subs, (sub, handler)]   # a new list: the thread iterates the one it took
        if self._thread.ident is None and not self._stop.is_set():   # started with the first key
            self._thread.start()
        return sub

    def unsubscribe(self, sub) -> None:
        self._subs = [(s, h) for s, h in self._subs if s is not sub]
        undeclare_quietly(sub)

    def _drain(self) -> None:
        while not self._stop.is_set():
            if not self.drain_once():
                time.sleep(self.period_s)   # cheaper than an event's wait: this runs 100s of times a second

    def drain_once(self) -> int:
        """Hand over what has queued; how many samples."""
        n = 0
        for sub, handler in self._subs:
            for _ in range(self.BATCH):
                try:
                    sample = sub.try_recv()
                except Exception:  # noqa: BLE001 - undeclared while closing
                    break
                if sample is None:
                    break
                n += 1
                try:
                    handler(sample)
                except Exception:  # noqa: BLE001 - a handler's bug must not stop the others
                    self._log.exception("handling a message on %s", sample.key_expr)
        return n

    def close(self, drain: bool = False) -> None:
        """Stop the thread, hand over what has queued where ``drain``, and undeclare."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        if drain:
            self.drain_once()
        subs, self._subs = self._subs, []
        for sub, _ in subs:
            undeclare_quietly(sub)
