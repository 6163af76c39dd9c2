"""Streamer: the captured people, live, to the tools people use (a sink of ``poses``).

One protocol per streamer (a layout may have several), ``params.protocol``:

- ``vmc``: the Virtual Motion Capture protocol (OSC over UDP) to ``host:port``, one
  avatar per receiver: person slot ``s`` (:class:`app.streaming.slots.Slots`, ``people``
  slots, default 1) goes to ``port + s`` (:mod:`app.streaming.osc`,
  :mod:`app.streaming.humanoid`);
- ``osc``: plain OSC, every person's joint positions in one bundle a frame to
  ``host:port`` (``up``: the room's z-up axes, or y-up);
- ``lsl``: a Lab Streaming Layer outlet named ``name`` (default ``smartroom-<room>``)
  with ``people`` slots (default 6) of 15 joints (:mod:`app.streaming.lsl`);
- ``json``: each frame's ``poses.jsonl`` record (CONTRACT §2) as UTF-8 JSON on the
  zenoh key ``smartroom/<room>/poses/json``, for clients that do not link our codec
  (docs/streaming/zenoh-feed.md).

A streamer never slows the pipeline: it acknowledges no frame (the source never waits
for it), UDP datagrams go out through a non-blocking socket (a full socket buffer or
an unreachable receiver drops the frame's packet, counted in ``send_failed``), and an
LSL outlet keeps at most a minute of samples for a slow inlet. Live, the streamer's inbox
holds 8 frames; a streamer further behind drops the oldest, counted in ``items_dropped``.
A receiver that starts mid-run gets the stream from then on. The frames of several pose workers sharing the
tracks are joined first (:class:`app.pose_shares.SharedPoses`), as the result writers do.
Figures: ``packets`` sent, ``send_failed``, ``left_out`` (person-frames beyond the slots),
``send_ms`` (p50/p95 of a frame's arrival in the handler to its last packet sent) and, for
LSL, ``lsl_inlets`` (whether an inlet takes the samples: liblsl hands an inlet samples
only from a moment after it reports itself connected).
"""
from __future__ import annotations

import json
import socket
import time

from app.errors import InputError
from app.export.poses import pose_record
from app.messages import Poses
from app.pose_shares import SharedPoses
from app.streaming.humanoid import HingeMemory, humanoid_poses
from app.streaming.lsl import lsl_sample
from app.streaming.slots import Slots
from workers import producers_of
from workers.base import Worker

PROTOCOLS = ("vmc", "osc", "lsl", "json")
DEFAULT_PEOPLE = {"vmc": 1, "lsl": 6}
LATENCY_WINDOW = 2000     # frames kept for the send_ms percentiles (bounded: a room runs for weeks)


class Streamer(Worker):
    KIND = "streamer"
    CONSUMES = ("poses",)
    ACCEPTS = (Poses,)
    #: live, a few frames wait while the process is held up (a busy machine's scheduler)
    #: rather than being dropped at once; behind for longer, the oldest are dropped, counted
    INBOX_DEPTH = 8
    DEFAULTS = {
        "protocol": "vmc",      # vmc | osc | lsl | json
        "host": "127.0.0.1",    # receiver (vmc, osc)
        "port": 39539,          # receiver's UDP port (vmc: the first slot's; VMC's usual port)
        "people": -1,           # person slots (vmc: receivers, lsl: channel groups); -1: vmc 1, lsl 6
        "up": "z",              # osc: the room's z-up axes or y-up
        "name": "",             # lsl: the stream's name ("" -> smartroom-<room>)
    }
    CHOICES = {"protocol": PROTOCOLS, "up": ("z", "y")}
    RANGES = {"port": (1, 65535), "people": (-1, 64)}

    def setup(self) -> None:
        self.protocol = self.params["protocol"]
        if self.protocol not in PROTOCOLS:
            raise InputError(f"streamer {self.name}: protocol must be one of {', '.join(PROTOCOLS)}, "
                             f"got {self.protocol!r}")
        people = int(self.params["people"])
        self.slots = Slots(DEFAULT_PEOPLE.get(self.protocol, 0) if people < 0 else people)
        if self.protocol in ("vmc", "lsl") and self.slots.count < 1:
            raise InputError(f"streamer {self.name}: {self.protocol} needs at least one person slot (people)")
        self.shares = SharedPoses(producers_of(self.layout, "poses"))
        self.packets = 0
        self.send_failed = 0
        self._send_ms: list[float] = []
        if self.protocol in ("vmc", "osc"):
            self._open_udp()
        elif self.protocol == "lsl":
            self._open_lsl()
        else:
            from app.bus import Publisher
            self._json_pub = Publisher(self.session, self.keys.poses_json(), droppable=True)

    def _open_udp(self) -> None:
        try:   # python-osc is an optional extra: a clear error now, not at the first frame
            from app.streaming import osc
        except ImportError as exc:
            raise InputError(f"streamer {self.name}: {self.protocol} needs python-osc: "
                             f"pip install 'smartroom[stream]' ({exc})") from None
        self.osc = osc
        host, port = str(self.params["host"]), int(self.params["port"])
        last = port + max(self.slots.count, 1) - 1 if self.protocol == "vmc" else port
        if last > 65535:
            raise InputError(f"streamer {self.name}: ports {port}..{last} (one per person slot) pass 65535")
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        except OSError as exc:
            raise InputError(f"streamer {self.name}: host {host!r} does not resolve ({exc})") from None
        family, _, _, _, address = infos[0]
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.address = address[0]
        self.hinges = HingeMemory()

    def _open_lsl(self) -> None:
        from app.streaming.lsl import LslClock, open_outlet, pylsl_module
        pylsl = pylsl_module()
        name = self.params["name"] or f"smartroom-{self.layout.room}"
        self.outlet = open_outlet(name, f"smartroom/{self.layout.room}/{self.name}", self.slots.count,
                                  self.layout.run.fps or 0.0, self.layout.room)
        self.lsl_clock = LslClock(pylsl)

    # -- frames ----------------------------------------------------------------------
    def handle(self, key: str, msg: Poses) -> None:
        for joined in self.shares.add(msg):
            self._send(joined)

    def _send(self, msg: Poses) -> None:
        t0 = time.perf_counter()
        if self.protocol == "vmc":
            self._send_vmc(msg)
        elif self.protocol == "osc":
            self._udp(self.osc.joints_packet(msg.frame, msg.t, msg.tracks, msg.joints, msg.active, self.params["up"]),
                      int(self.params["port"]))
        elif self.protocol == "lsl":
            sample = lsl_sample(self.slots.count, self.slots.assign(msg.tracks), msg.joints, msg.active, msg.tracks)
            self.outlet.push_sample(sample, self.lsl_clock(msg.stamp))
            self.packets += 1
        else:
            record = pose_record(msg.frame, msg.t, msg.tracks, msg.joints, msg.active)
            self._json_pub.put_payload(json.dumps(record, separators=(",", ":")).encode())
            self.packets += 1
        self._send_ms.append((time.perf_counter() - t0) * 1e3)
        del self._send_ms[:-LATENCY_WINDOW]
        self.ledger.emitted(msg.frame, msg.stamp)

    def _send_vmc(self, msg: Poses) -> None:
        assignment = self.slots.assign(msg.tracks)
        self.hinges.keep(msg.tracks)
        if not assignment:
            return
        index = [k for _, k in assignment]
        avatar = humanoid_poses(msg.joints[index], msg.tracks[index], self.hinges)
        for (slot, _), packet in zip(assignment, self.osc.vmc_packets(avatar, msg.t)):
            self._udp(packet, int(self.params["port"]) + slot)

    def _udp(self, packet: bytes, port: int) -> None:
        try:
            self.sock.sendto(packet, (self.address, port))
            self.packets += 1
        except OSError:   # a full buffer (BlockingIOError), an unreachable receiver: this packet only
            self.send_failed += 1

    # -- figures and end -------------------------------------------------------------
    def extra_figures(self) -> dict:
        import numpy as np
        figures = {"protocol": self.protocol, "packets": getattr(self, "packets", 0),
                   "send_failed": getattr(self, "send_failed", 0)}
        if hasattr(self, "slots"):
            figures["left_out"] = self.slots.left_out
        if hasattr(self, "outlet"):   # an inlet connected and taking samples (liblsl: a consumer of the outlet)
            figures["lsl_inlets"] = bool(self.outlet.have_consumers())
        ms = getattr(self, "_send_ms", None)
        if ms:
            figures["send_ms"] = {"p50": round(float(np.percentile(ms, 50)), 3),
                                  "p95": round(float(np.percentile(ms, 95)), 3)}
        return figures

    def close(self) -> None:
        if hasattr(self, "shares") and getattr(self, "input_ended", False):
            for joined in self.shares.flush():
                self._send(joined)
        if hasattr(self, "sock"):
            self.sock.close()
        if hasattr(self, "outlet"):
            del self.outlet
