"""Offline flow control: a source never runs ahead of the pipeline (DESIGN §3, §5).

On a recording nothing may be dropped and the results must not depend on how busy the
machine is, so a source (the grabber, or any other source kind) sends frame ``i`` only
once the pipeline has room for it. The rules, in the order they are applied:

1. **Ready before the first frame.** The source sends nothing until every worker of the
   layout is on the bus (its liveliness token is there): a stage that loads slowly
   (tables, kernels compiled on a cold cache) or starts later on another host must not
   miss the start of the stream. It says every ``ready_timeout`` who it waits for.
2. **A window behind the slowest stage.** Frame ``i`` waits until every acknowledging
   worker (the stages, and sinks that acknowledge) has finished frame ``i - window``.
3. **Given-up frames do not block.** A stage is held only to the frames its upstream
   stages have put out: one whose upstream gave a frame up (too few cameras, say) is not
   waited for on that frame (:meth:`FlowControl.required`).
4. **A stage that is away pauses the stream.** A worker that has left the bus (crashed,
   being restarted by the launcher, on a host whose link is down) is waited for until it
   is back or the wait is a stall (rule 6), so no frame goes past it: an outage shorter
   than ``stall_timeout_s`` is waited out. Sinks that keep results (the recorder) are
   waited for the same way although they acknowledge nothing. (Frames used to go on
   without a worker away for 60 s: a link down for 70 s lost them.)
5. **Back from a crash: catch up first.** Once it is back, new frames are held
   :data:`RESUME_HOLD_S` (the workers before it send it again what was in flight to it,
   :mod:`workers.restarts`) and until it has caught up, at most another
   :data:`MISSING_WAIT_S` (if its upstream restarted with it, nothing comes again, and the
   frames it lacks are counted as missing, per worker in :attr:`FlowControl.went_without`,
   the source's ``went_on_without`` figure: the launcher reports such a run incomplete).
6. **A stall ends the run.** A frame held for ``stall_timeout_s`` (not counting the time
   nobody at all is on the bus: this host's link to the hub is down, an outage waited out
   up to ``restarts: peer_timeout_s``, :mod:`workers.base`) by a worker that is on
   the bus yet finishes nothing (or a worker that never comes on the bus) is a stall: the
   source raises :class:`~app.errors.Stalled` naming the worker and the frame, the launcher
   stops the run (exit 1, ``complete: false``, the reason in ``stats.json``), and the result
   files hold every frame up to there. A stalled offline run never hangs.

Acknowledgements (:class:`~app.messages.Ack`) are validated like every message: one of
another stream (epoch), of a worker that does not acknowledge, or malformed is counted
and dropped. :class:`FlowControl` holds the rules over plain sets and numbers (no bus,
a clock passed in: unit-tested alone); :class:`SourceFlow` is its shell on a source
worker's session.
"""
from __future__ import annotations

import threading
import time

from app.errors import Stalled
from app.frame_shares import frame_share, last_own
from workers.restarts import REPLAY_DELAY_S

__all__ = ["FlowControl", "SourceFlow", "MISSING_WAIT_S", "RESUME_HOLD_S", "NOTE_PERIOD_S"]

MISSING_WAIT_S = 60.0   # how long a stage back from a crash is waited for to catch up
RESUME_HOLD_S = 4 * REPLAY_DELAY_S   # new frames wait this long after a worker is back from a crash
NOTE_PERIOD_S = 10.0    # how often a wait is said in the log
SENDING_AGAIN = "workers sending frames again"


class FlowControl:
    """The rules of the module docstring over the acknowledgements received, the workers
    on the bus and a clock. :meth:`blockers` says who holds a frame; :meth:`wait` blocks
    until nobody does (or raises :class:`Stalled`)."""

    def __init__(self, stages: list[str], upstream: dict[str, list[str]], keepers: list[str], window: int,
                 stall_timeout_s: float, clock=time.monotonic, log=None, shares: dict | None = None):
        self.stages = list(stages)          # workers that acknowledge frames
        self.shares = dict(shares or {})    # worker -> (k, n): it takes the frames with frame % n == k
        self.upstream = {n: list(upstream.get(n, ())) for n in self.stages}
        self.keepers = list(keepers)        # sinks that keep results: waited for while away
        self.window = int(window)
        self.stall_timeout_s = float(stall_timeout_s)
        self.clock = clock
        self.log = log
        self.acks: dict[str, int] = {}      # worker -> newest frame it finished
        self.outs: dict[str, int] = {}      # worker -> newest frame it put out
        self.cond = threading.Condition()
        self._started = False
        self._was_alive: set[str] = set()
        self._missing_since: dict[str, float] = {}
        self._back_since: dict[str, float] = {}   # workers back from a crash, catching up
        self._hold_until = 0.0
        self.went_without: dict[str, int] = {}   # worker -> frames that went on without it

    # -- what arrives --------------------------------------------------------------
    def start(self, index: int, alive: set[str]) -> None:
        """The first frame of this epoch is ``index``: nothing of it is in flight yet
        (frames an earlier incarnation sent were acknowledged in its epoch)."""
        with self.cond:
            self.acks = {n: index - 1 for n in self.stages}
            self.outs = {n: index - 1 for n in self.stages}
            self._was_alive = set(alive)
            self._started = True

    def acknowledge(self, worker: str, frame: int, out: int) -> None:
        """``worker`` has finished ``frame`` and put out frames up to ``out``."""
        with self.cond:
            self.acks[worker] = max(frame, self.acks.get(worker, -1))
            self.outs[worker] = max(out, self.outs.get(worker, -1))
            self.cond.notify_all()

    # -- the rules -------------------------------------------------------------------
    def required(self, name: str, need: int) -> int:
        """The frame ``name`` must have finished: ``need``, or less when a stage before it
        has put out nothing that recent (it gave those frames up) (rule 3); a worker that
        takes the frames in turn with others, its newest frame up to ``need``."""
        need = last_own(self.shares.get(name), need)
        for u in self.upstream.get(name, ()):
            need = min(need, self.outs.get(u, -1))
        return need

    def blockers(self, index: int, alive: set[str], now: float) -> list[str]:
        """Who holds frame ``index`` now (rules 2-5); empty: it may go. Called with the
        condition held, it also keeps the bookkeeping of workers away and back."""
        need = index - self.window
        for n in alive - self._was_alive:
            self._back_since[n] = now
            # hold new frames until the kept ones were sent again: a sink that keeps results
            # acknowledges nothing, and would get them after newer frames, or not at all
            # once they had left the workers' replay buffers
            self._hold_until = max(self._hold_until, now + RESUME_HOLD_S)
        self._was_alive = set(alive)
        for n, since in list(self._back_since.items()):
            if self.acks.get(n, -1) >= self.required(n, need):
                del self._back_since[n]
            elif now - since > MISSING_WAIT_S:
                # what it missed never came again (its upstream restarted with it): go on
                # from here; the frames it lacks are counted as missing
                if self.log is not None:
                    self.log.warning("%s has not caught up %.0f s after its restart; going on without the "
                                     "frames it missed", n, MISSING_WAIT_S)
                del self._back_since[n]
                lacks = max(0, self.required(n, need) - self.acks.get(n, -1))
                self.went_without[n] = self.went_without.get(n, 0) + lacks
                for m in self.stages:
                    self.acks[m] = max(self.acks.get(m, -1), index - 1)
                    self.outs[m] = max(self.outs.get(m, -1), index - 1)
        for n in self.stages + self.keepers:
            if n in alive:
                self._missing_since.pop(n, None)
            else:
                self._missing_since.setdefault(n, now)
        waiting = [n for n in self.stages if n in alive and self.acks.get(n, -1) < self.required(n, need)]
        waiting += [n for n in self.stages + self.keepers if n not in alive]
        if now < self._hold_until:
            waiting.append(SENDING_AGAIN)
        return waiting

    def wait(self, index: int, alive, stopping) -> float:
        """Block until frame ``index`` may go (``alive()``: the workers on the bus now;
        ``stopping()``: give up at once); the seconds waited. Raises :class:`Stalled`
        once the frame has waited ``stall_timeout_s`` (rule 6)."""
        if not self._started:
            self.start(index, alive())
        t0 = last = self.clock()
        held = 0.0   # the stall clock: it stands still while nobody at all is on the bus (the link is down)
        next_note = t0 + NOTE_PERIOD_S
        with self.cond:
            while not stopping():
                now = self.clock()
                here = set(alive())
                if here or not self.stages + self.keepers:
                    held += now - last
                last = now
                waiting = self.blockers(index, here, now)
                if not waiting:
                    break
                if held >= self.stall_timeout_s:
                    raise Stalled(self.stall_reason(index, waiting, held))
                if now >= next_note and self.log is not None:
                    next_note = now + NOTE_PERIOD_S
                    self.log.warning("frame %d waits for %s to finish frame %d", index, ", ".join(waiting),
                                     index - self.window)
                self.cond.wait(0.05)
        return self.clock() - t0

    def stall_reason(self, index: int, waiting: list[str], waited: float) -> str:
        need = index - self.window
        parts = []
        for n in waiting:
            if n == SENDING_AGAIN:
                parts.append(n)
            elif n in self._missing_since:
                parts.append(f"{n} (not on the bus for {waited:.0f} s)")
            else:
                parts.append(f"{n} (on the bus; finished frame {self.acks.get(n, -1)}, needs "
                             f"{self.required(n, need)})")
        return (f"stalled: frame {index} waited {waited:.0f} s for {', '.join(parts)}; the results hold "
                f"the frames before (a stage that needs longer per frame: raise stall_timeout_s)")


class SourceFlow:
    """:class:`FlowControl` on a source worker's session: the acknowledging workers of its
    layout, their acknowledgements from the bus, the readiness wait (rule 1)."""

    def __init__(self, worker, window: int, stall_timeout_s: float, ready_note_s: float):
        from workers import upstream_of, worker_class

        self.worker = worker
        layout = worker.layout
        self.epoch = worker.epoch
        self.ready_note_s = float(ready_note_s)
        headless = layout.run.headless
        stages = [w.name for w in layout.workers
                  if w.name != worker.name and worker_class(w.kind).acknowledges(w, layout)
                  and not (headless and worker_class(w.kind).DISPLAY)]
        keepers = [w.name for w in layout.workers
                   if worker_class(w.kind).KEEPS_RESULTS and w.name not in stages]
        upstream = {n: [u for u in upstream_of(layout, layout.worker(n)) if u in stages] for n in stages}
        shares = {n: frame_share(layout.worker(n).params) for n in stages
                  if worker_class(layout.worker(n).kind).FRAME_SHARES}
        shares = {n: s for n, s in shares.items() if s is not None}
        most = max((n for _, n in shares.values()), default=1)
        if window < most:
            worker.log.warning("window %d is less than the %d workers taking the frames in turn: they work one "
                               "at a time (set the grabber's window to at least that)", window, most)
        self.control = FlowControl(stages, upstream, keepers, window, stall_timeout_s, log=worker.log,
                                   shares=shares)
        self._sub = None

    def ready(self, first: int) -> float:
        """Rule 1: wait until every worker of the layout is on the bus; the seconds waited.
        Raises :class:`Stalled` after ``stall_timeout_s``."""
        w = self.worker
        t0 = time.monotonic()
        missing = w.wait_for_others(min(self.ready_note_s, self.control.stall_timeout_s))
        while missing and not w.stopping:
            waited = time.monotonic() - t0
            if waited >= self.control.stall_timeout_s:
                hosts = {s.name: s.host for s in w.layout.workers if not s.local}
                names = ", ".join(f"{n} (host {hosts[n]})" if n in hosts else n for n in sorted(missing))
                raise Stalled(f"stalled: frame {first} waited {waited:.0f} s for {names} to come on the bus "
                              f"(still loading, or not started on its host; raise stall_timeout_s to wait longer)")
            w.log.warning("frame %d waits for %s to be on the bus (%s)", first, ", ".join(sorted(missing)),
                          "still loading, or not started on its host")
            left = self.control.stall_timeout_s - waited
            missing = w.wait_for_others(max(0.05, min(max(self.ready_note_s, 10.0), left)))
        return time.monotonic() - t0

    def hold(self, index: int) -> float:
        """Rules 2-6 for frame ``index``; the seconds waited."""
        w = self.worker
        if self._sub is None:
            self._sub = w.inlet.subscribe(w.keys.ack(), self._on_ack)   # a few ms late at most
        return self.control.wait(index, lambda: set(w.alive), lambda: w.stopping)

    def _on_ack(self, sample) -> None:
        from app.bus import decode_sample
        from app.messages import Ack, MessageError

        w = self.worker
        name = w.keys.last(sample.key_expr)
        if name not in self.control.stages:   # told from the key, before decoding
            w.reject(str(sample.key_expr), "acknowledgement of another stream")
            return
        try:
            msg = decode_sample(sample)
            msg.validate()
        except MessageError:
            w.reject(str(sample.key_expr), "malformed")
            return
        if not isinstance(msg, Ack) or msg.worker != name or msg.epoch != self.epoch:
            w.reject(str(sample.key_expr), "acknowledgement of another stream")
            return
        self.control.acknowledge(msg.worker, msg.frame, msg.out)

    def close(self) -> None:
        if self._sub is not None:
            self.worker.inlet.unsubscribe(self._sub)
            self._sub = None
