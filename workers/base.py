"""The one worker base: session, subscriptions with bounded inboxes, admission of what
arrives from the bus, the loop, stats once a second, liveliness, end of stream, and
what a worker carries across a restart.

A worker subclass declares what it consumes and produces and implements
:meth:`Worker.handle` (a filter stage) or :meth:`Worker.produce` (a source). It
publishes with :meth:`Worker.publish`; everything else lives here.

End of stream is a fact about input (DESIGN §5). A source publishes
:class:`~app.messages.EndOfStream` when its input ends: the recording is over, or it
was asked to stop (SIGINT: the launcher's first stop request, Ctrl-C). A stage
publishes its own once every worker upstream of it in the layout has ended: sent its
end of stream *and* left the bus (its liveliness token is gone). A worker that crashes
or is terminated (SIGTERM, its launcher gone) sends final stats but no end of stream,
exits with :data:`EXIT_TERMINATED`, and the launcher restarts it; a forged end of
stream from a worker that keeps running is discarded.

Offline (a recording) nothing is dropped: inboxes are deep, outputs block instead of
dropping, and the source is paced by the stages' acknowledgements, so a run gives the
same results on an idle and on a loaded machine. What a worker carries across a crash
(counts, the stage's state and snapshots, outputs sent again to a consumer that
restarted, repeats skipped, its last frame put out again) is :mod:`workers.restarts`,
so a restart loses no frame. Live, inboxes are latest-frame-wins and every drop is
counted.

Everything received is validated (codec, the type's ``validate()``, the frame window
and epoch of its stream, and the stage's own :meth:`Worker.admit`); what fails is
counted per key and reason and dropped, with a rate-limited log line.
"""
from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import ClassVar

from app.admission import FrameWindow, Rejections, epoch_outside_run
from app.frame_shares import FrameOrder, frame_share, owns, stage_shares
from app.bus import Inlet, Keys, Publisher, decode_sample, open_session, undeclare_quietly
from app.compiles import CompileClock
from app.files import write_json
from app.layout import Layout, WorkerSpec   # the layout's types, not its loader (which imports the workers)
from app.messages import Ack, EndOfStream, Heartbeat, Message, MessageError, Stats
from app.stats import StageLedger
from workers.restarts import Restarts

__all__ = ["Worker", "Inbox", "configure_logging", "FILE_ONLY", "EXIT_ENDED", "EXIT_INPUT", "EXIT_STALLED", "EXIT_TERMINATED", "ENDED_ENV", "LAUNCHER_PID_ENV"]

STATS_PERIOD_S = 1.0
HEARTBEAT_PERIOD_S = 1.0   # a heartbeat from the worker's own thread (the launcher's watchdog, app.watchdog)
STATE_PERIOD_S = 0.5
END_GRACE_S = 0.1      # quiet time after the upstream left the bus (its data came before it left)
EOS_CONFIRM_S = 10.0     # an end of stream counts when its sender leaves the bus within this time (a loaded
                         # machine may take seconds to carry the liveliness change of a worker on another host)
LOSSLESS_DEPTH = 256     # inbox depth per key offline (flow control keeps it far below)
MAX_KEYS = 64            # distinct keys an inbox holds queues for
RECENT_FRAMES = 50       # frames behind a worker's running figures (``extra_figures``): bounded, so that a
                         # worker's memory does not grow with the days a room runs
SUBSCRIBER_WAIT_S = 5.0  # offline: a new publisher waits at most this long for the bus to route its key to a consumer

EXIT_ENDED = 0           # the worker's input ended; its end of stream was sent
EXIT_INPUT = 2           # bad input: a one-line reason in <out>/logs/<name>.error
EXIT_STALLED = 3         # offline, the run cannot go on (app.errors.Stalled): the reason in <out>/logs/<name>.error
EXIT_TERMINATED = 143    # stopped before its input ended (SIGTERM, launcher gone): restartable
ENDED_ENV = "SMARTROOM_ENDED"              # the launcher's list of workers already ended
LAUNCHER_PID_ENV = "SMARTROOM_LAUNCHER_PID"


class Inbox:
    """Bounded per-key queues filled from zenoh's thread, emptied by the worker loop.

    Each concrete key (e.g. one camera's frames) keeps at most ``depth`` samples; a
    newer sample pushes out the oldest, which is counted as dropped. ``get`` returns
    the oldest waiting sample over all keys, so cameras are served in arrival order.
    At most ``max_keys`` keys get a queue (a wildcard subscription cannot be made to
    grow without bound); samples on further keys are refused (``put`` returns False).
    """

    def __init__(self, depth: int = 1, on_drop=None, max_keys: int = MAX_KEYS):
        self.depth = max(1, int(depth))
        self.max_keys = max_keys
        self.queues: dict[str, deque] = {}
        self.cond = threading.Condition()
        self.seq = 0
        self.on_drop = on_drop

    def put(self, key: str, item) -> bool:
        with self.cond:
            q = self.queues.get(key)
            if q is None:
                if len(self.queues) >= self.max_keys:
                    return False
                q = self.queues[key] = deque()
            if len(q) >= self.depth:
                q.popleft()
                if self.on_drop:
                    self.on_drop()
            self.seq += 1
            q.append((self.seq, item))
            self.cond.notify()
            return True

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


class Worker(Restarts):
    """Base of every worker process (see module docstring)."""

    KIND: ClassVar[str] = ""
    STAGE: ClassVar[str] = ""            # label in stats (default: KIND)
    ORDER: ClassVar[int | None] = None   # position in the chain; None for sinks (recorder, viewer, monitor)
    CONSUMES: ClassVar[tuple[str, ...]] = ()
    PRODUCES: ClassVar[tuple[str, ...]] = ()
    PER_CAMERA: ClassVar[tuple[str, ...]] = ("frame", "mask", "markers")
    DISPLAY: ClassVar[bool] = False      # an interactive view: not started with --headless
    DEFAULTS: ClassVar[dict] = {}
    #: allowed ranges of numeric parameters ``{name: (lo, hi)}``, checked by the config loader
    RANGES: ClassVar[dict] = {}
    #: allowed values of text parameters ``{name: (choice, ...)}``, checked by the config loader
    CHOICES: ClassVar[dict] = {}
    INBOX_DEPTH: ClassVar[int] = 1       # latest-frame-wins by default (live)
    ACCEPTS: ClassVar[tuple] = ()        # message types handle() takes (others are bad messages)
    DROP_OUTPUT: ClassVar[bool] = True   # live data outputs use congestion control DROP
    #: a frame is finished once handle() returns; stages that hold frames back (assembling
    #: cameras) set False and call :meth:`finished` themselves
    ACK_ON_HANDLE: ClassVar[bool] = True
    #: a sink whose output must not miss frames (the recorder, exporters): offline, the
    #: source pauses while it is away (restarting) instead of sending frames past it
    KEEPS_RESULTS: ClassVar[bool] = False
    #: a restarted worker skips the frames its earlier incarnation put out (False: a sink
    #: that knows per output what it has, the recorder)
    SKIPS_FINISHED: ClassVar[bool] = True
    #: several workers of the kind may take the frames in turn (``share: [k, n]``,
    #: :mod:`app.frame_shares`): a stateless stage that scales out by frame
    FRAME_SHARES: ClassVar[bool] = False

    def __init__(self, spec: WorkerSpec, layout: Layout):
        self.spec = spec
        self.name = spec.name
        self.params = dict(spec.params)
        self.layout = layout
        self.keys = Keys(layout.room)
        self.log = logging.getLogger(f"smartroom.{self.name}")
        self.ledger = StageLedger(trace=layout.run.trace)
        #: offline (a recording): nothing may be dropped, so results do not depend on load
        self.lossless = bool(layout.run.recording) and not self.DISPLAY
        depth = max(self.INBOX_DEPTH, LOSSLESS_DEPTH) if self.lossless else self.INBOX_DEPTH
        self.inbox = Inbox(depth, on_drop=self.ledger.dropped_item)
        self.rejections = Rejections(self.log)
        self.windows: dict[str, FrameWindow] = {}
        self._members = layout.names   # the names whose stats and ends count
        self.stop_event = threading.Event()
        self.session = None
        self.alive: set[str] = set()         # workers whose liveliness token is on the bus
        self._died: dict[str, float] = {}    # worker -> when its token went away
        self._publishers: dict[str, Publisher] = {}
        self._upstream_eos: dict[str, tuple[EndOfStream, float]] = {}
        self._ended_upstream: set[str] = set()
        self._source_eos: EndOfStream | None = None
        self._eos_since = 0.0                 # when this worker began to listen for ends
        self._subs = []
        self.inlet: Inlet | None = None   # control keys (ends, stats, acknowledgements), drained in batches
        self._token = None
        self._last_stats = 0.0
        self._last_state = 0.0
        self._turned = time.monotonic()       # when the loop last turned (the heartbeat says how long ago)
        self._phase = "setup"                 # "setup" until the loop starts (the heartbeat's busy)
        self._idle = 0.0
        # epoch of the input being handled (outputs inherit it); a source's own is its start
        # (a worker refuses epochs from before the run: app.admission.epoch_outside_run)
        self._epoch = 0 if self.CONSUMES else time.time_ns() // 1_000_000
        self._epoch_seen = False
        self._signal: int | None = None
        self.input_ended = False             # True once this worker's input has truly ended
        self.early_signals: list[int] = []   # stop signals received while the process loaded (worker command)
        self.exit_code = EXIT_ENDED
        self._lock = threading.Lock()
        self._publish_lock = threading.Lock()
        self.compiles = CompileClock(on_start=self._compiling)   # numba kernels compiled in this process
        self._said_compiling = 0.0
        self.setup_s: float | None = None
        #: (k, n): this worker takes the frames with frame % n == k (app.frame_shares)
        self.frame_share = frame_share(self.params) if self.FRAME_SHARES else None
        self._orders = self._frame_orders()   # key -> FrameOrder: inputs from workers sharing their frames
        self._init_restarts()

    def _frame_orders(self) -> dict:
        """A :class:`~app.frame_shares.FrameOrder` per consumed key whose producers share
        their frames (their outputs interleave; this worker takes them in frame order)."""
        from workers import producers_of, worker_class

        orders = {}
        for stage in self.consumes(self.spec):
            if stage in self.PER_CAMERA or stage == "stats":
                continue
            specs = [self.layout.worker(n) for n in producers_of(self.layout, stage)]
            if specs and all(worker_class(w.kind).FRAME_SHARES for w in specs):
                shares = stage_shares(specs)
                if shares:
                    orders[self.keys.stage(stage)] = FrameOrder(next(iter(shares.values()))[1])
        return orders

    # -- what subclasses provide ------------------------------------------------------
    @property
    def stage(self) -> str:
        return self.STAGE or self.KIND

    def cameras(self) -> list[str] | None:
        """Cameras this worker handles (None: not camera-specific)."""
        cams = self.params.get("cameras")
        return None if cams in (None, "all") else list(cams)

    def run_calibration(self):
        """The run's calibration: the recording's ``calibration.yaml``, else the layout's
        calibration file (live cameras); None with neither."""
        from calibration import load_calibration

        run = self.layout.run
        if run.recording:
            return load_calibration(Path(run.recording) / "calibration.yaml")
        if run.calibration:
            return load_calibration(run.calibration)
        return None

    def subscriptions(self) -> list[str]:
        """Key expressions to subscribe to (default: the consumed stages)."""
        keys = []
        consumed = self.consumes(self.spec)
        for stage in [*self.CONSUMES, *sorted(consumed - set(self.CONSUMES))]:
            if stage == "stats":
                continue  # stats are delivered through on_stats
            if stage in self.PER_CAMERA and self.cameras() is not None:
                keys += [self.keys.stage(stage, c) for c in self.cameras()]
            else:
                keys.append(self.keys.stage(stage))
        return keys

    def setup(self) -> None:
        """Load what the worker needs before it is announced alive (tables, models)."""

    def admit(self, key: str, msg: Message) -> str | None:
        """A valid message this stage still cannot use (e.g. an unknown camera): the
        reason, or None to handle it."""
        return None

    def handle(self, key: str, msg: Message) -> None:
        """Process one input message (filter stages)."""
        raise NotImplementedError

    def produce(self) -> bool:
        """Publish the next output (sources). Return False when there is nothing more."""
        raise NotImplementedError

    def new_epoch(self, epoch: int) -> None:
        """The source restarted (a new epoch, whose frame numbers may start again): forget
        frame numbers kept from the old one (called before the first message of the new one)."""

    def flush(self) -> None:
        """End of stream: process what is pending (e.g. incomplete multi-camera frames)."""

    def close(self) -> None:
        """Release resources and complete files (``self.input_ended`` says whether the
        stream truly ended: only then are result files final)."""

    def on_stats(self, msg: Stats) -> None:
        """Stats of any worker (only for kinds that consume ``stats``)."""

    def tick(self) -> None:
        """Called on every turn of the loop (at least every 50 ms when idle)."""

    # -- services for subclasses ---------------------------------------------------
    def publish(self, key: str, msg: Message, counts: bool = True) -> None:
        pub = self._publisher(key)
        if self._caught_up:
            self.log.warning("caught up on frames %d-%d (%d) without publishing them", self._caught_up[0],
                             self._caught_up[-1], len(self._caught_up))
            self._caught_up = []
        if not msg.epoch:
            msg.epoch = self._epoch
        payload = msg.to_bytes()
        with self._publish_lock:
            if msg.frame == self._lose and self.incarnation == 0:
                self._killed_after_handle = True     # FAILPOINT_ENV: lost on the way to the bus
            else:
                pub.put_payload(payload)
            if self.lossless:
                self._keep_for_replay(msg.frame, msg.epoch, key, payload)
        again = msg.frame == self._redo   # counted by the earlier incarnation
        if again:
            self._redo = None
            self.log.warning("put out frame %d again (its outputs may not have left before the restart)", msg.frame)
        if counts and not again:
            self.ledger.emitted(msg.frame, msg.stamp)

    def _publisher(self, key: str) -> Publisher:
        pub = self._publishers.get(key)
        if pub is None:
            droppable = self.DROP_OUTPUT and not self.lossless
            pub = self._publishers[key] = Publisher(self.session, key, droppable=droppable)
            # offline nothing may be lost: the first message waits until the bus has routed
            # this key to a consumer (a stage on another host that has just joined sent its
            # first masks nowhere, and the run waited for them forever)
            if self.lossless and self._consumers() and not pub.await_subscriber(SUBSCRIBER_WAIT_S):
                self.log.warning("no consumer of %s on the bus after %.0f s: publishing anyway", key,
                                 SUBSCRIBER_WAIT_S)
        return pub

    def finished(self, frame: int) -> None:
        """This stage is done with ``frame`` (put out, or given up): an unpaced or
        offline source may send the frames after it."""
        if self._ack is not None and (frame > self._acked or self._ack_epoch != self._epoch):
            self._acked, self._ack_epoch = frame, self._epoch
            self._ack.put(Ack(frame=frame, stamp=time.time(), worker=self.name, epoch=self._epoch,
                              out=max(-1, self.ledger.newest_out)))

    def wait_for_others(self, timeout: float) -> set[str]:
        """Wait until every other worker of the layout that runs here is on the bus (a
        source, so that no stage misses the start of its stream); the ones still missing."""
        from workers import worker_class

        others = {w.name for w in self.layout.workers if w.name != self.name
                  and not (self.layout.run.headless and worker_class(w.kind).DISPLAY)}
        deadline = time.monotonic() + timeout
        while not others <= self.alive and time.monotonic() < deadline and not self.stopping:
            time.sleep(0.02)
        return others - self.alive

    def wait_until_ready(self, timeout: float) -> float:
        """A live source before its first frame: :meth:`wait_for_others` at most ``timeout``,
        then it starts without the missing ones (said in one line); the seconds waited.
        Offline the flow control waits instead (:meth:`workers.flow.SourceFlow.ready`)."""
        t0 = time.perf_counter()
        missing = self.wait_for_others(timeout)
        if missing:
            self.log.warning("starting without %s (not alive after %.0f s)", ", ".join(sorted(missing)), timeout)
        return time.perf_counter() - t0

    def status(self, text: str) -> None:
        """Say what the worker is doing before frames flow (compiling kernels, building a
        background): shown by the monitor and the launcher's progress line."""
        self.log.info("%s", text)
        if self.session is not None:
            self._control_pub(self.keys.stats(self.name)).put(
                Stats(frame=-1, stamp=time.time(), worker=self.name, stage=self.stage, final=False,
                      figures={"status": text, "order": self.ORDER}))

    def _compiling(self) -> None:
        """A kernel compile begins (numba, a first run): said as the worker's status (its
        loop stands still meanwhile, so no stats come), at most every few seconds."""
        now = time.monotonic()
        if now - self._said_compiling > STATS_PERIOD_S * 3:
            self._said_compiling = now
            self.status("compiling kernels (a first run only: they are cached for the next)")

    def reject(self, key: str, reason: str, detail: str = "") -> None:
        """Count and drop a message this worker cannot use."""
        self.rejections.add(self.keys.relative(key), reason, detail)
        self.ledger.bad_messages = self.rejections.total

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

    @classmethod
    def consumes(cls, spec: WorkerSpec) -> set[str]:
        """The stages this worker, as configured, takes in."""
        return set(cls.CONSUMES)

    @classmethod
    def produces(cls, spec: WorkerSpec) -> set[str]:
        """The stages this worker, as configured, publishes."""
        return set(cls.PRODUCES)

    @classmethod
    def acknowledges(cls, spec: WorkerSpec, layout: Layout) -> bool:
        """Whether this worker, in ``layout``, tells an unpaced or offline source which
        frames it has finished (the source never runs more than a window ahead of it)."""
        return bool(cls.ORDER and cls.PRODUCES)

    def upstream(self) -> list[str]:
        """Names of the workers whose end of stream this one waits for."""
        from workers import upstream_of
        return upstream_of(self.layout, self.spec)

    # -- signals, the launcher, liveliness -------------------------------------------
    def _install_signals(self) -> None:
        def stop(signum, _frame):   # no logging here: a handler may interrupt a log call
            if self._signal is None:
                self._signal = signum
            self.stop_event.set()
            self.inbox.wake()
        signal.signal(signal.SIGTERM, stop)
        signal.signal(signal.SIGINT, stop)
        for signum in list(self.early_signals):   # received while the worker loaded
            stop(signum, None)

    def _start_heartbeat(self) -> None:
        """Say once a second, from a thread of its own, that the process lives and how long
        ago its loop turned (:class:`~app.messages.Heartbeat`, the launcher's watchdog)."""
        # never dropped (congestion control BLOCK): a flood on the bus must not make a live worker look hung
        pub = Publisher(self.session, self.keys.heartbeat(self.name), droppable=False)
        pid = os.getpid()

        def beat():
            while not self.stop_event.wait(HEARTBEAT_PERIOD_S):
                busy = self._phase or ("compiling" if self.compiles.compiling else "")
                try:
                    pub.put(Heartbeat(frame=-1, stamp=time.time(), worker=self.name, pid=pid,
                                      loop_age=max(0.0, time.monotonic() - self._turned),
                                      pending=self.inbox.pending(), busy=busy))
                except Exception:  # noqa: BLE001 - the session is closing: the loop ends anyway
                    return
        threading.Thread(target=beat, daemon=True, name="heartbeat").start()

    def _watch_hub(self) -> None:
        """A worker started by itself (``smartroom worker``, another host's share of a
        layout) says when its link to the hub goes down and comes back, waits out an
        outage of up to ``restarts: peer_timeout_s``, and stops after that (its launcher's
        host is gone for good: no orphans on the camera PC)."""
        from app.hosts import PEER_TIMEOUT_S, Hosts

        link = Hosts({}, float(self.layout.restarts.get("peer_timeout_s", PEER_TIMEOUT_S)), None,
                     say=lambda text: self.log.warning("%s", text))

        def watch():
            while not self.stop_event.wait(0.5):
                try:
                    linked = bool(list(self.session.info.routers_zid()))
                except Exception:  # noqa: BLE001 - the session is closing
                    return
                gone = link.check((), hub_linked=linked)
                if gone:
                    self.log.error("%s: stopping", gone)
                    self._signal = self._signal or signal.SIGHUP
                    self.stop_event.set()
                    self.inbox.wake()
                    return
        threading.Thread(target=watch, daemon=True, name="hub-watch").start()

    def _watch_launcher(self) -> None:
        """A worker started by a launcher exits when that launcher is gone (no orphans)."""
        pid = os.environ.get(LAUNCHER_PID_ENV)
        if not pid or not pid.isdigit():
            return
        pid = int(pid)

        def watch():
            while not self.stop_event.wait(0.2):
                if os.getppid() != pid:
                    self._signal = self._signal or signal.SIGHUP
                    self.stop_event.set()
                    self.inbox.wake()
                    return
        threading.Thread(target=watch, daemon=True, name="launcher-watch").start()

    def _on_liveliness(self, sample) -> None:
        import zenoh
        name = self.keys.last(sample.key_expr)
        with self._lock:
            back = False
            if sample.kind == zenoh.SampleKind.DELETE:
                self.alive.discard(name)
                self._died[name] = time.monotonic()
            else:
                back = name in self._died and name not in self.alive
                self.alive.add(name)
        if back and self.lossless and self._replay and name in self._consumers():
            threading.Thread(target=self._resend, args=(name,), name=f"resend-{name}", daemon=True).start()
        self.inbox.wake()

    def _seed_ended(self) -> None:
        """Upstream workers that ended before this incarnation started (from the launcher)."""
        try:
            ended = json.loads(os.environ.get(ENDED_ENV) or "[]")
        except ValueError:
            return
        for e in ended if isinstance(ended, list) else []:
            if isinstance(e, dict) and e.get("worker") in self._wait_for:
                self._ended_upstream.add(e["worker"])
                if isinstance(e.get("frames"), int) and (self._source_eos is None or e["frames"] > self._source_eos.frames):
                    self._source_eos = EndOfStream(worker=e["worker"], frames=e["frames"], first=int(e.get("first", 0)),
                                                   fps=float(e.get("fps", 0.0)))

    # -- what arrives ------------------------------------------------------------------
    def _on_sample(self, sample) -> None:
        """Zenoh's thread: a message is decoded and validated before it is queued, so junk
        is counted and dropped here and never takes the place of a real message in the
        bounded inbox (a flood of junk on a key used to push real frames out of it)."""
        key = str(sample.key_expr)
        msg = self._valid(key, sample)
        if msg is not None and (outside := epoch_outside_run(msg.epoch, self.layout.run.started_ms)):
            self.reject(key, outside, f"frame {msg.frame}, epoch {msg.epoch}")
            return            # a forger's epoch takes no place in the inbox
        if msg is not None and not owns(self.frame_share, msg.frame):
            return            # another worker's frame (share): not this worker's input
        if msg is not None and not self.inbox.put(key, msg):
            self.reject(key, "too many keys")

    def _on_control(self, sample) -> None:
        key = str(sample.key_expr)
        name = self.keys.last(key)
        if name not in self._members:   # told from the key, before decoding
            self.reject(key, "not a worker of the layout")   # any process may publish on the bus
            return
        try:
            msg = decode_sample(sample)
            msg.validate()
        except MessageError as exc:
            self.reject(key, "malformed", str(exc))
            return
        if isinstance(msg, (EndOfStream, Stats)) and msg.worker != name:   # (so a worker of the layout)
            what = "end of stream" if isinstance(msg, EndOfStream) else "stats"
            self.reject(key, f"{what} under another worker's name")
            return
        if isinstance(msg, EndOfStream):
            if "stats" in self.CONSUMES:  # the end of stream carries the worker's final figures
                self.on_stats(Stats(frame=msg.frame, stamp=msg.stamp, worker=msg.worker, stage=msg.stage,
                                    final=True, figures=msg.figures))
            if msg.worker not in self._wait_for:
                return   # another stage's end: not this worker's input
            self._heard_end(msg, time.monotonic())
            self.inbox.wake()
        elif isinstance(msg, Stats):
            self.on_stats(msg)
        else:
            self.reject(key, f"unexpected {type(msg).__name__}")

    def _heard_end(self, msg: EndOfStream, now: float) -> None:
        """An upstream worker's end of stream arrived at ``now``. The arrival kept is the
        one that confirms it (:meth:`_upstream_ended`): an end heard around its sender's
        leaving stays, so the launcher's repeats of it, heard long after while this worker
        was busy with its last frames, cannot make it look forged (a run used to wait for
        it for good)."""
        with self._lock:
            kept = self._upstream_eos.get(msg.worker)
            died = self._died.get(msg.worker) if msg.worker not in self.alive else None
            if kept is not None and died is not None and abs(died - kept[1]) <= EOS_CONFIRM_S:
                now = kept[1]
            self._upstream_eos[msg.worker] = (msg, now)

    def _upstream_ended(self, name: str, now: float) -> bool:
        """``name`` has ended: it sent its end of stream and left the bus around then."""
        if name in self._ended_upstream:
            return True
        with self._lock:
            got = self._upstream_eos.get(name)
            if got is None:
                return False
            eos, arrived = got
            if name in self.alive:
                if now - arrived > EOS_CONFIRM_S:   # still running: a forged end of stream
                    del self._upstream_eos[name]
                    self.rejections.add(self.keys.relative(self.keys.eos(name)), "end of stream from a running worker")
                return False
            died = self._died.get(name, arrived)
            # it crashed long after a forged end of stream; unless it left before this worker
            # listened for ends (its own end went by, and this is the launcher saying it again)
            if abs(died - arrived) > EOS_CONFIRM_S and died >= self._eos_since:
                del self._upstream_eos[name]
                return False
        self._ended_upstream.add(name)
        if self._source_eos is None or eos.frames > self._source_eos.frames:
            self._source_eos = eos
        return True

    def _valid(self, key: str, sample) -> Message | None:
        """The message of a sample if it decodes, validates, is of a type this stage takes
        and names the camera of its key; else None (counted)."""
        try:
            msg = decode_sample(sample)
            msg.validate()
        except MessageError as exc:
            self.reject(key, "malformed", str(exc))
            return None
        if self.ACCEPTS and not isinstance(msg, self.ACCEPTS):
            self.reject(key, f"unexpected {type(msg).__name__}")
            return None
        camera = getattr(msg, "camera", None)
        if camera is not None and self.keys.last(key) != camera:
            self.reject(key, "camera does not match its key", str(camera)[:40])
            return None
        return msg

    def _admit(self, key: str, msg: Message) -> Message | None:
        """A valid message (:meth:`_valid`) in the frame window of its stream that the
        stage can use; else None (counted)."""
        window = self.windows.get(key)
        if window is None:   # live, a stage that stood still jumps to the newest frames
            window = self.windows[key] = FrameWindow(follow_ahead=not self.lossless)
        skipped = window.skipped
        reason = window.admit(msg.epoch, msg.frame) or self.admit(key, msg)
        if window.skipped > skipped:
            self.log.warning("fell behind on %s: jumped to frame %d, %d frames skipped", self.keys.relative(key),
                             msg.frame, window.skipped - skipped)
        if reason:
            self.reject(key, reason, f"frame {msg.frame}, epoch {msg.epoch}")
            return None
        return msg

    # -- stats and state -----------------------------------------------------------------
    def _figures(self, final: bool = False) -> dict:
        frames, first, _ = self.stream_info()
        # a worker that takes no frames (the monitor reads stats only) misses none of them
        takes_frames = self.is_source or any(stage != "stats" for stage in self.CONSUMES)
        known = takes_frames and (self._source_eos is not None or self.is_source)
        figures = self.ledger.figures(final=final, expected=frames if known else None, first=first,
                                      share=self.frame_share)
        if self.frame_share is not None:
            figures["frame_share"] = list(self.frame_share)
        figures["order"] = self.ORDER
        figures["restarts"] = self.incarnation
        figures["resent"] = self.resent
        figures["repeats_skipped"] = self.repeats_skipped
        if self.not_sent_again:
            figures["not_sent_again"] = self.not_sent_again
        figures["rejected"] = self.rejections.figures()
        if any(w.skipped for w in self.windows.values()):   # live: jumped to the newest after standing still
            figures["frames_skipped"] = max(w.skipped for w in self.windows.values())
        figures.update(self.compiles.figures())
        if self.setup_s is not None:
            figures["setup_s"] = round(self.setup_s, 3)
        if self._snapshot_ms:   # the cost of the state arrays (state_arrays, savez, rename), median ms
            figures["snapshot_ms"] = round(float(sorted(self._snapshot_ms)[len(self._snapshot_ms) // 2]), 2)
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

    def _periodic(self) -> None:
        self.compiles.install(only_if_loaded=True)   # numba imported on a path first taken
        now = time.monotonic()
        if now - self._last_stats >= STATS_PERIOD_S:
            self._publish_stats()
        if now - self._last_state >= STATE_PERIOD_S:
            self._save_state()

    # -- the loops -------------------------------------------------------------------------
    def _ended(self) -> bool:
        """Every upstream worker has ended and nothing came for ``END_GRACE_S`` since:
        data and end of stream travel on different keys, so the last data may trail."""
        now = time.monotonic()
        ended = [self._upstream_ended(n, now) for n in sorted(self._wait_for)]   # each confirmed as it comes
        if not self._wait_for or self.inbox.pending() or not all(ended):
            self._quiet_since = None
            return False
        if self._quiet_since is None:
            self._quiet_since = now
        return now - self._quiet_since >= END_GRACE_S

    def _loop_filter(self) -> None:
        self._quiet_since = None
        while not self.stopping:
            self._turned = time.monotonic()
            item = self.inbox.get(timeout=0.05)
            if item is not None:
                key, msg = item
                msg = self._admit(key, msg)
                if msg is None or self._repeated(key, msg):
                    continue
                order = self._orders.get(key)
                for key, msg in [(key, msg)] if order is None else order.add(key, msg):
                    self._take(key, msg)
            elif self._ended():
                for order in self._orders.values():   # what waited for frames before it that never came
                    for key, msg in order.flush():
                        self._take(key, msg)
                self.input_ended = True
                break
            self._periodic()
            self.tick()

    def _take(self, key: str, msg: Message) -> None:
        """One admitted input, handled and counted."""
        self._follow_epoch(msg)
        self.ledger.received(msg.frame, msg.stamp)
        t0, c0 = time.perf_counter(), time.process_time()
        self.handle(key, msg)
        if self._killed_after_handle:   # FAILPOINT_ENV
            os.kill(os.getpid(), signal.SIGKILL)
        self.ledger.processed(time.perf_counter() - t0, msg.frame, time.process_time() - c0)
        if self.ACK_ON_HANDLE:
            self.finished(msg.frame)

    def _follow_epoch(self, msg: Message) -> None:
        if msg.epoch != self._epoch:
            if self._epoch_seen:
                self.log.warning("the source restarted (epoch %d)", msg.epoch)
                self.new_epoch(msg.epoch)
            self._epoch_seen = True
        self._epoch = msg.epoch

    def _loop_source(self) -> None:
        if not self.stopping:
            self._source_again()
        while not self.stopping:
            self._turned = time.monotonic()
            t0, c0 = time.perf_counter(), time.process_time()
            self._idle = 0.0
            more = self.produce()
            if more:
                self.out_epoch = self._epoch
            if self._killed_after_handle:   # FAILPOINT_ENV
                os.kill(os.getpid(), signal.SIGKILL)
            self.ledger.processed(time.perf_counter() - t0 - self._idle, cpu=time.process_time() - c0)
            self._periodic()
            self.tick()
            if not more:
                self.input_ended = not self.stopping   # produce() gives up at once when told to stop
                break
        if self._signal == signal.SIGINT:
            self.input_ended = True   # a source asked to stop (Ctrl-C, the launcher): its input has ended

    def run(self) -> int:
        """Run the worker until its stream ends or it is told to stop; the exit code."""
        self._install_signals()
        self._watch_launcher()
        self.compiles.install(only_if_loaded=True)   # kernels' modules are imported with the kind
        self.session = open_session(self.layout.bus.for_worker(), mode="client")
        self.inlet = Inlet(self.session, name=f"{self.name}-inlet")
        self._start_heartbeat()
        if not os.environ.get(LAUNCHER_PID_ENV):
            self._watch_hub()
        try:
            self._wait_for = set(self.upstream())
            self._seed_ended()
            self._restore_state()
            self._save_state()
            self._subs.append(self.session.liveliness().declare_subscriber(
                self.keys.alive(), self._on_liveliness, history=True))
            # subscribed before the set-up: what arrives while the stage still loads (tables,
            # kernels compiled on a cold cache) waits in its inbox instead of going nowhere
            for key in self.subscriptions():
                self._subs.append(self.session.declare_subscriber(key, self._on_sample))
            t0 = time.time()
            self.setup()
            self.setup_s = time.time() - t0   # tables, background models, kernels: start-up, reported apart
            self.compiles.install(only_if_loaded=True)   # numba imported by the set-up
            # ends of stream: a stage takes its upstream's only, and listens under their names
            # (junk on another worker's key never reaches it); a stage that takes the stats
            # takes every worker's (an end carries the final figures), on one subscription
            # each for ends and stats, and tells a name outside the layout from the key;
            # all of them through the inlet (a few ms late; a thread's wake-up per batch, not per message)
            if "stats" in self.CONSUMES:
                ends = [self.keys.eos(), self.keys.stats()]
            else:
                ends = [self.keys.eos(name) for name in sorted(self._wait_for)]
            for key in ends:
                self.inlet.subscribe(key, self._on_control)
            self._eos_since = time.monotonic()   # ends sent before this were missed (the launcher repeats them)
            # an unpaced or offline source sends frames as fast as the stages acknowledge them
            self._ack, self._acked, self._ack_epoch = None, -1, None
            if (self.lossless or not self.layout.run.pace) and self.acknowledges(self.spec, self.layout):
                self._ack = Publisher(self.session, self.keys.ack(self.name), droppable=False)
            self._token = self.session.liveliness().declare_token(self.keys.alive(self.name))
            self.log.info("ready (%s)", ", ".join(self.subscriptions()) or "source")
            self._turned, self._phase = time.monotonic(), ""
            if self.is_source:
                self._loop_source()
            else:
                self._loop_filter()
            if self.input_ended:
                self.flush()
        finally:
            self._finish()
        if self._signal is not None and not self.input_ended:
            why = {signal.SIGTERM: "SIGTERM", signal.SIGINT: "SIGINT"}.get(self._signal, "its launcher is gone")
            # the launcher says why it stopped a worker, and restarts one stopped from outside
            self.log.info("stopped (%s) before its input ended; no end of stream sent", why)
            self.exit_code = EXIT_TERMINATED
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
            self._save_state()
            if self.session is not None and not self.session.is_closed():
                try:
                    figures = self._figures(final=True)
                    figures["ended"] = self.input_ended
                    stats = Stats(frame=self.ledger.last_frame, stamp=time.time(), worker=self.name,
                                  stage=self.stage, final=True, figures=figures)
                    self._control_pub(self.keys.stats(self.name)).put(stats)
                    if self.PRODUCES and self.input_ended:   # only an ended input ends the stream
                        frames, first, fps = self.stream_info()
                        self._control_pub(self.keys.eos(self.name)).put(
                            EndOfStream(frame=self.ledger.last_frame, stamp=time.time(), worker=self.name,
                                        stage=self.stage, frames=frames, first=first, fps=fps, figures=figures,
                                        epoch=self._epoch))
                    self._leave()   # its consumers count its end once it has left
                    time.sleep(0.2)  # let the last messages leave before the session closes
                finally:
                    if self.inlet is not None:
                        self.inlet.close()
                    for s in self._subs:
                        undeclare_quietly(s)
                    self._leave()
                    self.session.close()

    def _leave(self) -> None:
        """Leave the bus (drop the liveliness token). A consumer counts an end of stream
        once its sender has left, so a worker leaves as soon as its last messages are sent,
        not after lingering for them to go out: each stage of an offline run used to end
        0.2 s after the one before it, 1.2 s on the way down the default layout."""
        token, self._token = self._token, None
        if token is not None:
            token.undeclare()

    def stream_info(self) -> tuple[int, int, float]:
        """``(frames, first index, fps)`` of the stream, as the source announced it
        (sources override this with what they produced)."""
        eos = self._source_eos
        if eos is not None:
            return eos.frames, eos.first, eos.fps
        return self.ledger.last_frame + 1, 0, 0.0


LOG_BYTES = 1 << 20      # a worker's log file rotates at 1 MiB ...
LOG_BACKUPS = 3          # ... keeping 3 older ones: at most 4 MiB a worker, however long the room runs


class _JournalFormatter(logging.Formatter):
    """One line per record (date, time, worker, pid, level, message); the lines of a
    traceback follow it indented, so a reader (or grep, or journald) keeps them together."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        first, _, rest = text.partition("\n")
        return first + ("".join("\n  " + line for line in rest.split("\n")) if rest else "")


#: ``extra`` of a log record meant for the log file only (its one-line form is said on the terminal)
FILE_ONLY = {"file_only": True}


def configure_logging(name: str, level: int = logging.INFO, log_dir=None) -> Path | None:
    """Log lines on stderr at ``level`` (the terminal: warnings unless --verbose) and, with
    ``log_dir`` (the run's ``<out>/logs``), everything from INFO up into ``<name>.log``,
    rotated at :data:`LOG_BYTES` with :data:`LOG_BACKUPS` older files; the log file's path."""
    from logging.handlers import RotatingFileHandler

    root = logging.getLogger()
    root.setLevel(min(level, logging.INFO) if log_dir else level)
    terminal = logging.StreamHandler(sys.stderr)
    terminal.setLevel(level)
    terminal.addFilter(lambda record: not getattr(record, "file_only", False))
    terminal.setFormatter(logging.Formatter(f"%(asctime)s.%(msecs)03d [{name}] %(levelname)s %(message)s",
                                            datefmt="%H:%M:%S"))
    root.addHandler(terminal)
    if not log_dir:
        return None
    path = Path(log_dir) / f"{name}.log"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handler = RotatingFileHandler(path, maxBytes=LOG_BYTES, backupCount=LOG_BACKUPS, encoding="utf-8")
    except OSError as exc:
        logging.getLogger(f"smartroom.{name}").warning("cannot write the log file %s (%s)", path, exc.strerror)
        return None
    handler.setLevel(logging.INFO)
    handler.setFormatter(_JournalFormatter(f"%(asctime)s.%(msecs)03d {name}[%(process)d] %(levelname)s "
                                           "%(name)s: %(message)s", datefmt="%Y-%m-%d %H:%M:%S"))
    root.addHandler(handler)
    return path
