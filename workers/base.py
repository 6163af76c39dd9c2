"""The one worker base: session, subscriptions with latest-frame-wins inboxes, the
loop, stats once a second, liveliness, end of stream and clean exit on SIGTERM.

A worker subclass declares what it consumes and produces and implements
:meth:`Worker.handle` (a filter stage) or :meth:`Worker.produce` (a source). It
publishes with :meth:`Worker.publish`; everything else lives here.

End of stream: a source publishes :class:`~app.messages.EndOfStream` after its last
frame. A stage that has received it from every upstream worker handles what is still
in its inbox, calls :meth:`Worker.flush`, publishes its final stats and its own end
of stream, and exits 0. SIGTERM/SIGINT end a source the same way and make any other
worker finish at once (files completed, final stats published).
"""
from __future__ import annotations

import logging
import signal
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import ClassVar

from app.bus import Keys, Publisher, decode_sample, open_session
from app.config import Layout, WorkerSpec
from app.files import write_json
from app.messages import Ack, EndOfStream, Message, MessageError, Stats
from app.stats import StageLedger

__all__ = ["Worker", "Inbox"]

STATS_PERIOD_S = 1.0
END_GRACE_S = 0.3


class Inbox:
    """Bounded per-key queues filled from zenoh's thread, emptied by the worker loop.

    Each concrete key (e.g. one camera's frames) keeps at most ``depth`` samples; a
    newer sample pushes out the oldest, which is counted as dropped. ``get`` returns
    the oldest waiting sample over all keys, so cameras are served in arrival order.
    """

    def __init__(self, depth: int = 1, on_drop=None):
        self.depth = max(1, int(depth))
        self.queues: dict[str, deque] = {}
        self.cond = threading.Condition()
        self.seq = 0
        self.on_drop = on_drop

    def put(self, key: str, item) -> None:
        with self.cond:
            q = self.queues.get(key)
            if q is None:
                q = self.queues[key] = deque()
            if len(q) >= self.depth:
                q.popleft()
                if self.on_drop:
                    self.on_drop()
            self.seq += 1
            q.append((self.seq, item))
            self.cond.notify()

    def get(self, timeout: float):
        """The oldest waiting ``(key, item)``, or None after ``timeout`` seconds."""
        with self.cond:
            if not any(self.queues.values()):
                self.cond.wait(timeout)
            best = None
            for key, q in self.queues.items():
                if q and (best is None or q[0][0] < self.queues[best][0][0]):
                    best = key
            if best is None:
                return None
            return best, self.queues[best].popleft()[1]

    def pending(self) -> int:
        with self.cond:
            return sum(len(q) for q in self.queues.values())

    def wake(self) -> None:
        with self.cond:
            self.cond.notify_all()


class Worker:
    """Base of every worker process (see module docstring)."""

    KIND: ClassVar[str] = ""
    STAGE: ClassVar[str] = ""            # label in stats (default: KIND)
    ORDER: ClassVar[int | None] = None   # position in the chain; None for sinks (recorder, viewer, monitor)
    CONSUMES: ClassVar[tuple[str, ...]] = ()
    PRODUCES: ClassVar[tuple[str, ...]] = ()
    PER_CAMERA: ClassVar[tuple[str, ...]] = ("frame", "mask")
    DISPLAY: ClassVar[bool] = False      # an interactive view: not started with --headless
    DEFAULTS: ClassVar[dict] = {}
    INBOX_DEPTH: ClassVar[int] = 1       # latest-frame-wins by default
    ACCEPTS: ClassVar[tuple] = ()        # message types handle() takes (others are bad messages)
    DROP_OUTPUT: ClassVar[bool] = True   # data outputs use congestion control DROP

    def __init__(self, spec: WorkerSpec, layout: Layout):
        self.spec = spec
        self.name = spec.name
        self.params = dict(spec.params)
        self.layout = layout
        self.keys = Keys(layout.room)
        self.log = logging.getLogger(f"smartroom.{self.name}")
        self.ledger = StageLedger(trace=layout.run.trace)
        self.inbox = Inbox(self.INBOX_DEPTH, on_drop=self.ledger.dropped_item)
        self.stop_event = threading.Event()
        self.session = None
        self._publishers: dict[str, Publisher] = {}
        self._upstream_done: dict[str, EndOfStream] = {}
        self._source_eos: EndOfStream | None = None
        self._subs = []
        self._token = None
        self._last_stats = 0.0
        self._idle = 0.0
        self.exit_code = 0

    # -- what subclasses provide ------------------------------------------------------
    @property
    def stage(self) -> str:
        return self.STAGE or self.KIND

    def cameras(self) -> list[str] | None:
        """Cameras this worker handles (None: not camera-specific)."""
        cams = self.params.get("cameras")
        return None if cams in (None, "all") else list(cams)

    def subscriptions(self) -> list[str]:
        """Key expressions to subscribe to (default: the consumed stages)."""
        keys = []
        for stage in self.CONSUMES:
            if stage == "stats":
                continue  # stats are delivered through on_stats
            if stage in self.PER_CAMERA and self.cameras() is not None:
                keys += [self.keys.stage(stage, c) for c in self.cameras()]
            else:
                keys.append(self.keys.stage(stage))
        return keys

    def setup(self) -> None:
        """Load what the worker needs before it is announced alive (tables, models)."""

    def handle(self, key: str, msg: Message) -> None:
        """Process one input message (filter stages)."""
        raise NotImplementedError

    def produce(self) -> bool:
        """Publish the next output (sources). Return False when there is nothing more."""
        raise NotImplementedError

    def flush(self) -> None:
        """End of stream: process what is pending (e.g. incomplete multi-camera frames)."""

    def close(self) -> None:
        """Release resources and complete files."""

    def on_stats(self, msg: Stats) -> None:
        """Stats of any worker (only for kinds that consume ``stats``)."""

    def tick(self) -> None:
        """Called on every turn of the loop (at least every 50 ms when idle)."""

    # -- services for subclasses ---------------------------------------------------
    def publish(self, key: str, msg: Message, counts: bool = True) -> None:
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = Publisher(self.session, key, droppable=self.DROP_OUTPUT)
        pub.put(msg)
        if counts:
            self.ledger.emitted(msg.frame, msg.stamp)

    def sleep(self, seconds: float) -> None:
        """Wait (a source pacing itself); wakes on stop, and is not counted as busy."""
        t0 = time.perf_counter()
        self.stop_event.wait(max(0.0, seconds))
        self._idle += time.perf_counter() - t0

    @property
    def is_source(self) -> bool:
        return not self.CONSUMES

    @property
    def stopping(self) -> bool:
        return self.stop_event.is_set()

    @property
    def stream(self) -> EndOfStream | None:
        """The source's end-of-stream message once known (frame count, fps)."""
        return self._source_eos

    def upstream(self) -> list[str]:
        """Names of the workers whose end of stream this one waits for."""
        from workers import upstream_of
        return upstream_of(self.layout, self.spec)

    # -- the process ------------------------------------------------------------------
    def _install_signals(self) -> None:
        def stop(signum, _frame):
            self.log.info("signal %d: finishing", signum)
            self.stop_event.set()
            self.inbox.wake()
        signal.signal(signal.SIGTERM, stop)
        signal.signal(signal.SIGINT, stop)

    def _on_sample(self, sample) -> None:
        self.inbox.put(str(sample.key_expr), sample)

    def _on_control(self, sample) -> None:
        try:
            msg = decode_sample(sample)
        except MessageError as exc:
            self.ledger.bad_message()
            self.log.warning("bad control message on %s: %s", sample.key_expr, exc)
            return
        if isinstance(msg, EndOfStream):
            if "stats" in self.CONSUMES:  # the end of stream carries the worker's final figures
                self.on_stats(Stats(frame=msg.frame, stamp=msg.stamp, worker=msg.worker, stage=msg.stage,
                                    final=True, figures=msg.figures))
            if msg.worker in self._wait_for and msg.worker not in self._upstream_done:
                if self._source_eos is None or msg.frames > self._source_eos.frames:
                    self._source_eos = msg
                self._upstream_done[msg.worker] = msg
                self.inbox.wake()
        elif isinstance(msg, Stats):
            self.on_stats(msg)

    def _figures(self, final: bool = False) -> dict:
        frames, first, _ = self.stream_info()
        known = self._source_eos is not None or self.is_source
        figures = self.ledger.figures(final=final, expected=frames if known else None, first=first)
        figures["order"] = self.ORDER
        figures.update(self.extra_figures())
        return figures

    def _publish_stats(self) -> None:
        self._control_pub(self.keys.stats(self.name)).put(
            Stats(frame=self.ledger.last_frame, stamp=time.time(), worker=self.name,
                  stage=self.stage, final=False, figures=self._figures()))
        self._last_stats = time.monotonic()

    def _control_pub(self, key: str) -> Publisher:
        """Publishers of stats and end of stream: never dropped (congestion control BLOCK)."""
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = Publisher(self.session, key, droppable=False)
        return pub

    def extra_figures(self) -> dict:
        """Stage-specific figures added to every stats message."""
        return {}

    def _maybe_stats(self) -> None:
        if time.monotonic() - self._last_stats >= STATS_PERIOD_S:
            self._publish_stats()

    def _ended(self) -> bool:
        """Every upstream worker has ended and nothing came for ``END_GRACE_S`` since:
        data and end of stream travel on different keys, so the last data may trail."""
        if not self._wait_for or len(self._upstream_done) < len(self._wait_for) or self.inbox.pending():
            self._quiet_since = None
            return False
        now = time.monotonic()
        if self._quiet_since is None:
            self._quiet_since = now
        return now - self._quiet_since >= END_GRACE_S

    def _loop_filter(self) -> None:
        self._quiet_since = None
        while not self.stopping:
            item = self.inbox.get(timeout=0.05)
            if item is not None:
                key, sample = item
                try:
                    msg = decode_sample(sample)
                except MessageError as exc:
                    self.ledger.bad_message()
                    self.log.warning("skipping malformed message on %s: %s", key, exc)
                    continue
                if self.ACCEPTS and not isinstance(msg, self.ACCEPTS):
                    self.ledger.bad_message()
                    self.log.warning("skipping a %s on %s", type(msg).__name__, key)
                    continue
                self.ledger.received(msg.frame, msg.stamp)
                t0 = time.perf_counter()
                self.handle(key, msg)
                self.ledger.processed(time.perf_counter() - t0, msg.frame)
                if self._ack is not None and self.ledger.newest_out > self._acked:
                    self._acked = self.ledger.newest_out  # the newest frame this stage has put out
                    self._ack.put(Ack(frame=self._acked, stamp=msg.stamp, worker=self.name))
            elif self._ended():
                break
            self._maybe_stats()
            self.tick()

    def _loop_source(self) -> None:
        while not self.stopping:
            t0 = time.perf_counter()
            self._idle = 0.0
            more = self.produce()
            self.ledger.processed(time.perf_counter() - t0 - self._idle)
            self._maybe_stats()
            self.tick()
            if not more:
                break

    def run(self) -> int:
        """Run the worker until its stream ends or it is told to stop; the exit code."""
        self._install_signals()
        self.session = open_session(self.layout.bus.for_worker())
        try:
            self._wait_for = set(self.upstream())
            self.setup()
            for key in self.subscriptions():
                self._subs.append(self.session.declare_subscriber(key, self._on_sample))
            self._subs.append(self.session.declare_subscriber(self.keys.eos(), self._on_control))
            if "stats" in self.CONSUMES:
                self._subs.append(self.session.declare_subscriber(self.keys.stats(), self._on_control))
            # an unpaced source sends frames as fast as the stages acknowledge them
            self._ack, self._acked = None, -1
            if not self.layout.run.pace and self.ORDER and self.PRODUCES:
                self._ack = Publisher(self.session, self.keys.ack(self.name), droppable=False)
            self._token = self.session.liveliness().declare_token(self.keys.alive(self.name))
            self.log.info("ready (%s)", ", ".join(self.subscriptions()) or "source")
            if self.is_source:
                self._loop_source()
            else:
                self._loop_filter()
            self.flush()
        finally:
            self._finish()
        return self.exit_code

    def _write_trace(self) -> None:
        """Per-frame timings for benchmarks: ``<out>/trace/<name>.json`` (write, then rename)."""
        if self.ledger.trace is None or not self.layout.run.out:
            return
        folder = Path(self.layout.run.out) / "trace"
        folder.mkdir(parents=True, exist_ok=True)
        data = {"worker": self.name, "stage": self.stage, "order": self.ORDER,
                "frames": [[f, *v] for f, v in sorted(self.ledger.trace.items())],
                "process_ms": [round(v, 3) for v in self.ledger.process_ms]}
        write_json(folder / f"{self.name}.json", data, indent=None)

    def _finish(self) -> None:
        try:
            self.close()
            self._write_trace()
        finally:
            if self.session is not None and not self.session.is_closed():
                try:
                    figures = self._figures(final=True)
                    if self.PRODUCES:  # the end of stream carries the final figures
                        frames, first, fps = self.stream_info()
                        self._control_pub(self.keys.eos(self.name)).put(
                            EndOfStream(frame=self.ledger.last_frame, stamp=time.time(), worker=self.name,
                                        stage=self.stage, frames=frames, first=first, fps=fps, figures=figures))
                    else:
                        self._control_pub(self.keys.stats(self.name)).put(
                            Stats(frame=self.ledger.last_frame, stamp=time.time(), worker=self.name,
                                  stage=self.stage, final=True, figures=figures))
                    time.sleep(0.2)  # let the last messages leave before the session closes
                finally:
                    for s in self._subs:
                        s.undeclare()
                    if self._token is not None:
                        self._token.undeclare()
                    self.session.close()

    def stream_info(self) -> tuple[int, int, float]:
        """``(frames, first index, fps)`` of the stream, as the source announced it
        (sources override this with what they produced)."""
        eos = self._source_eos
        if eos is not None:
            return eos.frames, eos.first, eos.fps
        return self.ledger.last_frame + 1, 0, 0.0


def configure_logging(name: str, level: int = logging.INFO) -> None:
    logging.basicConfig(level=level, stream=sys.stderr,
                        format=f"%(asctime)s.%(msecs)03d [{name}] %(levelname)s %(message)s",
                        datefmt="%H:%M:%S")
