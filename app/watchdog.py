"""The launcher's watchdog: which worker is hung (issue: a room left alone for weeks).

Liveliness says a worker's process is on the bus, not that its loop turns: a process
stopped with SIGSTOP, swapped out for good or stuck in a call that never returns keeps
its token (until its session's lease runs out) and everything behind it waits. Every
worker therefore sends a :class:`~app.messages.Heartbeat` once a second from a thread of
its own, saying how long ago its loop last turned, how many messages wait in its inbox
and whether it is busy with something that may hold the loop for long (its set-up,
compiling kernels). A worker is **hung** when, for ``watchdog_s`` seconds,

- no heartbeat came at all (the whole process stands still: SIGSTOP, or the
  interpreter itself is stuck), or
- its heartbeats say the loop has not turned while messages were waiting and it was not
  busy with its set-up or a compile.

A silence shorter than that (a stage stopped for 20 s, then continued) is no restart,
but it is kept (:meth:`Watchdog.silences`, ``stats.json``'s ``silences``): every gap of
more than :data:`SILENCE_NOTE_S` between two heartbeats.

A worker that has not sent its first heartbeat since it was (re)started is given
``watchdog_s`` from its start, and at least :data:`FIRST_BEAT_S` (importing numpy, numba
and OpenCV on a kiosk's cold disk, or beside a busy pipeline, takes seconds). The launcher kills a hung worker (SIGKILL: a stopped
process ignores everything else) and restarts it like one that crashed, with the reason
"hung" in ``stats.json``'s ``restarts``. Before any SIGKILL of a worker (hung, or still
running after SIGTERM) it sends :data:`STACKS_SIGNAL`: every worker has Python's
``faulthandler`` write all its threads' stacks to stderr on it (the launcher's stderr),
so a hang leaves its cause behind.

Pure Python over a clock passed in (unit-tested alone); the launcher feeds it.
"""
from __future__ import annotations

import signal
import time
from dataclasses import dataclass

from app.messages import Heartbeat

__all__ = ["Watchdog", "DEFAULT_WATCHDOG_S", "STACKS_SIGNAL", "STACKS_WAIT_S"]

DEFAULT_WATCHDOG_S = 30.0   # a loop standing still this long with input waiting is hung
FIRST_BEAT_S = 60.0         # the least a (re)started worker is given for its first heartbeat
SILENCE_NOTE_S = 5.0        # a gap between heartbeats longer than this is kept as a silence
MAX_SILENCES = 20           # per worker, the latest
STACKS_SIGNAL = signal.SIGUSR1   # a worker writes every thread's stack to stderr on it
STACKS_WAIT_S = 0.5         # given to write them before the SIGKILL


@dataclass
class _Pulse:
    pid: int
    started: float            # when the launcher started this incarnation
    last: float | None = None  # when its last heartbeat arrived
    beat: Heartbeat | None = None


class Watchdog:
    """Heartbeats per worker and the verdict :meth:`hung`."""

    def __init__(self, watchdog_s: float = DEFAULT_WATCHDOG_S, clock=time.monotonic, wall=time.time):
        self.watchdog_s = float(watchdog_s)
        self.clock = clock
        self.wall = wall
        self._pulses: dict[str, _Pulse] = {}
        self._silences: dict[str, list[dict]] = {}

    def started(self, name: str, pid: int) -> None:
        """The launcher started (or restarted) ``name`` as process ``pid``: only its
        heartbeats count from now on."""
        self._pulses[name] = _Pulse(pid=int(pid), started=self.clock())

    def stopped(self, name: str) -> None:
        """``name``'s process is gone (ended, crashed, killed): nothing to watch."""
        self._pulses.pop(name, None)

    def beat(self, hb: Heartbeat) -> bool:
        """A heartbeat arrived (validated); False when it is not of a watched incarnation
        (a process of an earlier run or incarnation, or a forger without the pid)."""
        pulse = self._pulses.get(hb.worker)
        if pulse is None or hb.pid != pulse.pid:
            return False
        now = self.clock()
        if pulse.last is not None and now - pulse.last > SILENCE_NOTE_S:
            gap = now - pulse.last
            kept = self._silences.setdefault(hb.worker, [])
            kept.append({"until": round(self.wall(), 3), "s": round(gap, 1)})
            del kept[:-MAX_SILENCES]
        pulse.last, pulse.beat = now, hb
        return True

    def silences(self) -> dict[str, list[dict]]:
        """Per worker, its gaps between heartbeats longer than :data:`SILENCE_NOTE_S`
        (``until``: wall-clock end, ``s``: length) that ended without a restart."""
        return {n: list(v) for n, v in self._silences.items() if v}

    def hung(self, name: str) -> str | None:
        """Why ``name`` counts as hung now (one short phrase), or None."""
        pulse = self._pulses.get(name)
        if pulse is None:
            return None
        now = self.clock()
        if pulse.last is None:
            silent = now - pulse.started
            if silent > max(self.watchdog_s, FIRST_BEAT_S):
                return f"no heartbeat in the {silent:.0f} s since it started"
            return None
        silent = now - pulse.last
        if silent > self.watchdog_s:
            return f"no heartbeat for {silent:.0f} s (the process stands still)"
        hb = pulse.beat
        if hb is not None and not hb.busy and hb.pending > 0:
            age = hb.loop_age + (now - pulse.last)
            if age > self.watchdog_s:
                return f"its loop has not turned for {age:.0f} s with {hb.pending} messages waiting"
        return None

    def silent_s(self, name: str) -> float | None:
        """Seconds since ``name``'s last heartbeat (None: none yet, or not watched)."""
        pulse = self._pulses.get(name)
        if pulse is None or pulse.last is None:
            return None
        return self.clock() - pulse.last
