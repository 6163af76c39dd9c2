"""What a launcher knows of the other hosts of a multi-host room (issue 25).

A layout places each worker on a host; the launcher of one host follows the others'
workers by their liveliness on the bus and by their heartbeats:

- **Seen**: it says once which workers of the other hosts are on the bus (or, every
  :data:`NOTE_PERIOD_S`, which are not yet).
- **Links down and back**: a host whose workers have all left the bus (before they ended
  their stream) is down; the launcher says "link to host H down for N s" every
  :data:`NOTE_PERIOD_S`, "back after N s" when any is back, and keeps each outage. A
  launcher of one host's share (``smartroom run --host``) follows its own link to the hub
  the same way (the host :data:`HUB`). A link down for ``peer_timeout_s``, or a host
  whose workers never came on the bus in that time, ends the run.
- **Clock skew**: a heartbeat's stamp (the sender's clock) against this host's clock when
  it arrives (a LAN's delay, a millisecond, included); frame stamps of the hosts are
  compared (latencies, a frame's views), so a skew above half a frame is said once per
  host.

Pure Python over clocks passed in; fed from zenoh's threads (:meth:`Hosts.alive`,
:meth:`Hosts.heartbeat`, under a lock) and checked from the launcher's loop
(:meth:`Hosts.check`).
"""
from __future__ import annotations

import sys
import threading
import time
from collections import deque

__all__ = ["Hosts", "HUB", "NOTE_S", "NOTE_PERIOD_S", "PEER_TIMEOUT_S", "host_label"]

PEER_TIMEOUT_S = 600.0  # a host (or the hub) gone this long ends the run (restarts: peer_timeout_s)
HUB = "hub"            # a host share's own link to the hub, or a worker's started by itself
NOTE_S = 2.0           # a link down longer than this is said (and kept as an outage)
NOTE_PERIOD_S = 10.0   # how often a link still down, or workers not yet seen, are said again
SKEW_BEATS = 15        # heartbeats per host behind the skew (their median)


def host_label(host: str) -> str:
    """How a worker's host is named in what the launcher says ("hub-host" for the one the
    layout calls local: the host that runs the hub)."""
    return "hub-host" if host in ("local", "localhost", "127.0.0.1") else host


class _Link:
    """One link's state: up or down since when, said when."""

    def __init__(self):
        self.seen = False
        self.down_since: float | None = None
        self.said = 0.0


class Hosts:
    """The other hosts' workers (``remote``: host -> worker names) as the bus shows them."""

    def __init__(self, remote: dict[str, list[str]], peer_timeout_s: float, fps: float | None,
                 clock=time.monotonic, wall=time.time, say=None):
        self.remote = {h: list(ns) for h, ns in remote.items()}
        self.host_of = {n: h for h, ns in self.remote.items() for n in ns}
        self.peer_timeout_s = float(peer_timeout_s)
        self.half_frame = 0.5 / (fps or 25.0)
        self.clock, self.wall = clock, wall
        self.say = say or (lambda text: print(f"smartroom: {text}", file=sys.stderr))
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._links: dict[str, _Link] = {}
        self.outages: list[dict] = []
        self._skews: dict[str, deque] = {}
        self._skew_said: set[str] = set()
        self._all_seen = False
        self._started = self._seen_said = clock()

    # -- fed from zenoh's threads ----------------------------------------------------
    def alive(self, name: str, present: bool) -> None:
        with self._lock:
            (self._alive.add if present else self._alive.discard)(name)

    def heartbeat(self, name: str, stamp: float) -> None:
        host = self.host_of.get(name)
        if host is None:
            return
        with self._lock:
            kept = self._skews.setdefault(host, deque(maxlen=SKEW_BEATS))
            kept.append(self.wall() - stamp)
            if len(kept) < 5 or host in self._skew_said:
                return
            skew = sorted(kept)[len(kept) // 2]
            if abs(skew) <= self.half_frame:
                return
            self._skew_said.add(host)
        self.say(f"the clock of host {host} is {abs(skew) * 1e3:.0f} ms {'behind' if skew > 0 else 'ahead of'} "
                 f"this one's (more than half a frame, {self.half_frame * 1e3:.0f} ms): synchronise them "
                 "(NTP, chrony)")

    # -- checked from the launcher's loop ----------------------------------------------
    def check(self, ended, hub_linked: bool | None = None) -> str | None:
        """Say what changed; the reason to end the run (a link down for ``peer_timeout_s``)
        or None. ``ended``: workers that sent their end of stream (they left, not lost);
        ``hub_linked``: a host share's own link to the hub (None: this host runs the hub)."""
        now = self.clock()
        with self._lock:
            alive = set(self._alive)
        if hub_linked is not None:
            why = self._link(HUB, hub_linked, now, "link to the hub", "the hub unreachable")
            if why or not hub_linked:   # with this host's own link down, the others' are not news
                return why
        self._say_seen(alive, now)
        for host, names in self.remote.items():
            up = bool(alive & set(names)) or all(n in ended for n in names)
            who = f"host {host} ({', '.join(names)})"
            why = self._link(host, up, now, f"link to host {host}", f"{who} gone from the bus", who)
            if why:
                return why
        return None

    def _link(self, key: str, up: bool, now: float, what: str, gone: str, who: str = "") -> str | None:
        """One link's rule (``what``: how it is said; ``gone``: the reason once it has been
        down for ``peer_timeout_s``; ``who``: a host that may never come)."""
        link = self._links.setdefault(key, _Link())
        if up:
            link.seen = True
            if link.down_since is not None and now - link.down_since > NOTE_S:
                self.outages.append({"host": key, "until": round(self.wall(), 3),
                                     "s": round(now - link.down_since, 1)})
                self.say(f"{what} back after {now - link.down_since:.0f} s")
            link.down_since = None
            return None
        if not link.seen and key != HUB:   # a host not started yet is not an outage, but it may never come
            waited = now - self._started
            if waited > self.peer_timeout_s:
                return f"{who} never came on the bus in {waited:.0f} s (restarts: peer_timeout_s)"
            return None
        if link.down_since is None:
            link.down_since = now
        down = now - link.down_since
        if down > NOTE_S and now - link.said >= NOTE_PERIOD_S:
            link.said = now
            self.say(f"{what} down for {down:.0f} s (waiting up to {self.peer_timeout_s:.0f} s)")
        if down > self.peer_timeout_s:
            return f"{gone} for {down:.0f} s (restarts: peer_timeout_s {self.peer_timeout_s:.0f} s)"
        return None

    def _say_seen(self, alive: set[str], now: float) -> None:
        if self._all_seen or not self.remote:
            return
        names = [n for ns in self.remote.values() for n in ns]
        missing = [n for n in names if n not in alive]
        where = "; ".join(f"{h}: {', '.join(n for n in ns if n in alive) or '-'}" for h, ns in sorted(self.remote.items()))
        if not missing:
            self._all_seen = True
            self.say(f"every worker of the other hosts is on the bus ({where})")
        elif now - self._seen_said >= NOTE_PERIOD_S:
            self._seen_said = now
            self.say(f"workers of other hosts on the bus: {where}; not yet: {', '.join(missing)}")

    def figures(self) -> dict:
        """``outages`` (kept, and links still down: ``down_s``) and ``clock_skew_s`` (per
        host, median seconds its clock is behind this one's) for ``stats.json``."""
        now = self.clock()
        out: dict = {}
        down = [{"host": k, "down_s": round(now - link.down_since, 1)} for k, link in self._links.items()
                if link.down_since is not None]
        if self.outages or down:
            out["outages"] = list(self.outages) + down
        with self._lock:
            skews = {h: round(sorted(v)[len(v) // 2], 4) for h, v in self._skews.items() if v}
        if skews:
            out["clock_skew_s"] = skews
        return out
