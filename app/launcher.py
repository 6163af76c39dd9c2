"""Start a layout's workers as OS processes, watch them, restart the ones that die,
and end the run cleanly and honestly.

The launcher opens the hub zenoh session every worker connects to, writes the
resolved layout next to the results (``<out>/layout.yaml``), starts each local worker
as ``python -m app.cli worker NAME --layout <out>/layout.yaml``, shows progress from
the workers' stats, keeps ``<out>/stats.json`` up to date, and waits:

- exit 0: the worker's input ended and it sent its end of stream;
- exit 2: bad input (its one-line reason is in ``<out>/logs/<name>.error``): the run
  cannot go on; the other workers are stopped and the launcher exits 2 with that reason;
- exit 3: a stall (offline, a stage that finishes nothing: :mod:`workers.flow`, the
  reason in the same file): the other workers are stopped, the run is incomplete (exit 1)
  and its files hold every frame up to there;
- anything else (a crash, SIGKILL, SIGTERM from outside): the worker is restarted
  after a back-off (0.25 s doubling per recent crash, at most 8 s). A stage crashing
  :attr:`RestartPolicy.storm` times within :attr:`RestartPolicy.window_s` is a storm:
  the run is stopped and reported incomplete. A stage that crashes once an hour
  runs forever (the budget refills). Its counters carry on (``<out>/state/``).

**One host's share** (``smartroom run --host H --connect ENDPOINT``, :attr:`Launcher.host`):
the launcher starts, watches and restarts only the workers the layout places on host
``H``, opens no hub of its own but connects to the one of the host that runs the hub,
says which workers of the other hosts it sees on the bus, waits out an outage of its
link to the hub and stops its workers once the hub has been unreachable for
``restarts: peer_timeout_s``.

Workers of another host (``host:`` in the layout, started there with ``smartroom
run --host`` or ``smartroom worker``) are followed by their liveliness: when all of a host's workers leave the bus
the launcher says "link to host H down", waits (a remote source that has not ended its
stream keeps the run open, however long the outage), says when they are back and keeps
each outage in ``stats.json`` (``outages``); a host gone for ``restarts: peer_timeout_s``
(600 s) ends the run, incomplete.

A worker that is still running but **hung** (no heartbeat, or a loop that has not turned
with input waiting, for ``restarts: watchdog_s`` seconds: :mod:`app.watchdog`) is killed
and restarted the same way, its failure recorded with the reason ``hung``.

Stopping: the first Ctrl-C / SIGTERM asks the sources to end their input (SIGINT),
so the end of stream flows through every stage and every file is completed; workers
still running ``STOP_GRACE_S`` later get SIGTERM (no end of stream: their files stay
``.partial``), and SIGKILL ``KILL_GRACE_S`` after that. A second Ctrl-C goes straight
to SIGTERM. Workers exit by themselves when the launcher dies (they watch its pid).

``stats.json`` says what happened: per stage the frames expected, processed, dropped
and lost in transit, restarts; ``complete`` with the ``reasons`` when it is false
(a stage gave up, a worker failed, the disk filled, bad input). The exit code is 0
only for a complete run.
"""
from __future__ import annotations

import dataclasses
import errno
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from app.bus import BusConfig, Inlet, Keys, Publisher, decode_sample, free_port, open_session
from app.config import Layout
from app.errors import InputError
from app.files import write_json
from app.forkserver import SPAWN_ENV, ForkServer
from app.frame_shares import count_own
from app.messages import EndOfStream, Heartbeat, MessageError, Stats
from app.stats import summarise
from app.hosts import PEER_TIMEOUT_S, Hosts, host_label
from app.watchdog import DEFAULT_WATCHDOG_S, STACKS_SIGNAL, STACKS_WAIT_S, Watchdog
from workers.base import ENDED_ENV, EXIT_INPUT, EXIT_STALLED, LAUNCHER_PID_ENV

__all__ = ["Launcher", "RestartPolicy", "ERROR_DIR"]

DRAIN_TIMEOUT_S = 60.0   # after the sources end, how long without any progress before stopping all
STOP_GRACE_S = 15.0      # after a stop request, how long the end of stream may take before SIGTERM
KILL_GRACE_S = 5.0       # after SIGTERM, how long before SIGKILL
STATS_PERIOD_S = 1.0
RESERVE_BYTES = 1 << 20  # kept free for the final stats.json when the disk fills
ERROR_DIR = "logs"
LAUNCHED_ENV = "SMARTROOM_LAUNCHED"   # set for workers the launcher starts


@dataclass
class RestartPolicy:
    """When to restart a crashed worker: back-off doubling with the crashes of the last
    ``window_s`` seconds; ``storm`` crashes within that window stop the run."""

    window_s: float = 30.0
    storm: int = 5
    first_delay_s: float = 0.25
    max_delay_s: float = 8.0
    watchdog_s: float = DEFAULT_WATCHDOG_S   # a hung worker (app.watchdog) is restarted after this
    peer_timeout_s: float = PEER_TIMEOUT_S   # another host's workers gone this long: the run ends

    def delay(self, recent: int) -> float:
        return min(self.max_delay_s, self.first_delay_s * 2.0 ** max(0, recent - 1))


@dataclass
class _Proc:
    name: str
    source: bool
    popen: subprocess.Popen | None = None
    restarts: int = 0
    crashes: deque = field(default_factory=deque)
    next_start: float = 0.0
    rc: int | None = None
    done: bool = False
    ended: bool = False          # exited 0: its input ended
    failures: list = field(default_factory=list)
    hung: str | None = None      # why the watchdog killed it (its exit is then a restart, reason "hung")


def _hub_bus(bus: BusConfig) -> BusConfig:
    """The hub listens where the layout says; port 0 becomes a free port now."""
    listen = []
    for ep in bus.listen:
        if ep.endswith(":0"):
            ep = ep[:-1] + str(free_port())
        listen.append(ep)
    return dataclasses.replace(bus, listen=listen)


PRIVATE_PREFIX = "smartroom-bus-"   # the private sockets' folders (a room on one host)


def sweep_private_sockets(folder: str, min_age_s: float = 60.0) -> int:
    """Remove the private-socket folders in ``folder`` that launchers killed outright
    (SIGKILL, power cut) left behind: this user's, older than ``min_age_s``, whose socket
    nobody listens on any more; how many."""
    import socket

    removed = 0
    try:
        entries = [e for e in os.scandir(folder) if e.name.startswith(PRIVATE_PREFIX) and e.is_dir()]
    except OSError:
        return 0
    for e in entries:
        try:
            st = e.stat()
            if st.st_uid != os.getuid() or time.time() - st.st_mtime < min_age_s:
                continue
            sock = os.path.join(e.path, "hub.sock")
            if os.path.exists(sock):
                with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
                    probe.settimeout(0.5)
                    try:
                        probe.connect(sock)
                        continue            # a hub listens there: a live run's
                    except (ConnectionRefusedError, FileNotFoundError):
                        pass
            shutil.rmtree(e.path, ignore_errors=True)
            removed += 1
        except OSError:
            continue
    return removed


def _connect_endpoints(listen: list[str]) -> list[str]:
    return [ep.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]") for ep in listen]


def _exit_text(rc: int) -> str:
    if rc < 0:
        try:
            return f"killed by {signal.Signals(-rc).name}"
        except ValueError:
            return f"killed by signal {-rc}"
    return {143: "terminated (SIGTERM)", 1: "crashed"}.get(rc, f"exit {rc}")


class Launcher:
    def __init__(self, layout: Layout, verbose: bool = False, progress=None, policy: RestartPolicy | None = None,
                 host: str | None = None, connect: list[str] | None = None):
        from workers import worker_class

        self.layout = layout.copy()
        self.verbose = verbose
        self.policy = policy or RestartPolicy(**layout.restarts)
        self.host = host   # None: this host runs the hub and the workers placed here
        self.out = Path(self.layout.run.out)
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / ERROR_DIR).mkdir(exist_ok=True)
        self._private_dir: str | None = None
        if host is None:
            hub = _hub_bus(self.layout.bus)
            connect = _connect_endpoints(hub.listen)
            if hub.private and hub.tls is None and all(w.local for w in self.layout.workers):
                # a room on one host: its workers come in through a socket of this run's own
                # (its folder is made when the hub opens), and nothing linked otherwise may
                # publish in the room (app.bus_acl)
                tmp = tempfile.gettempdir()
                tmp = tmp if len(tmp) <= 64 else "/tmp"   # a Unix socket's path has room for ~100 bytes
                sweep_private_sockets(tmp)
                self._private_dir = os.path.join(tmp, f"{PRIVATE_PREFIX}{secrets.token_hex(6)}")
                private = f"unixsock-stream/{self._private_dir}/hub.sock"
                hub = dataclasses.replace(hub, listen=[*hub.listen, private])
                connect = [private]
            self.hub_bus = hub
            self.layout.bus = dataclasses.replace(hub, connect=connect)
            # the sources' epochs are their start times: none of this run's is older than this
            # (app.admission.FrameWindow refuses one that is, a forger's); other hosts read it
            # from this layout
            self.layout.run = dataclasses.replace(self.layout.run, started_ms=time.time_ns() // 1_000_000)
        else:   # one host's share: its workers and this launcher are clients of the hub elsewhere
            if not connect:
                raise InputError(f"--host {host}: give the hub's endpoint with --connect (e.g. tcp/10.0.0.1:7447)")
            if host not in {w.host for w in self.layout.workers}:
                hosts = sorted({w.host for w in self.layout.workers})
                raise InputError(f"--host {host}: no worker of the layout is on that host (hosts: {', '.join(hosts)})")
            self.hub_bus = None
            self.layout.bus = dataclasses.replace(self.layout.bus, listen=[], connect=list(connect))
        self.layout_path = self.out / "layout.yaml"
        self.layout.save(self.layout_path)
        self.procs: list[_Proc] = []
        #: workers of other hosts by host, and the sources among them (their end of stream ends the input)
        remote: dict[str, list[str]] = {}
        self.remote_sources = []
        for w in self.layout.workers:
            if not self._mine(w):
                remote.setdefault(host_label(w.host), []).append(w.name)
                if not worker_class(w.kind).CONSUMES:
                    self.remote_sources.append(w.name)
        self.hosts = Hosts(remote, self.policy.peer_timeout_s, self.layout.run.fps)
        for w in self.layout.workers:
            cls = worker_class(w.kind)
            if not self._mine(w) or (cls.DISPLAY and self.layout.run.headless):
                continue
            self.procs.append(_Proc(name=w.name, source=not cls.CONSUMES))
        self.progress = progress
        # written from zenoh's thread, read from the run's: replaced whole, never changed in place
        self.stats: dict[str, Stats] = {}
        self._members = self.layout.names   # only the layout's workers report
        self.eos: dict[str, EndOfStream] = {}
        self.reasons: list[str] = []
        self.input_error: str | None = None
        self.stopped_by_user = False
        self._stop_level = 0        # 0 running, 1 sources asked to end, 2 SIGTERM sent, 3 SIGKILL sent
        self._stop_time: float | None = None
        self._lock = threading.Lock()
        self.watchdog = Watchdog(self.policy.watchdog_s)   # fed from zenoh's thread under _lock
        self._last_stats_write = 0.0
        self._reserve = self.out / ".reserve"
        self.started = time.time()   # the run's start-up is counted from here (stats.json "startup")
        self._forks = None

    def _mine(self, w) -> bool:
        """A worker this launcher starts: its host's (``--host``), else the local ones."""
        return w.host == self.host if self.host is not None else w.local

    # -- processes ----------------------------------------------------------------
    def _spawn(self, p: _Proc) -> None:
        argv = ["worker", p.name, "--layout", str(self.layout_path)] + (["--verbose"] if self.verbose else [])
        ended = [{"worker": q.name, "frames": e.frames, "first": e.first, "fps": e.fps}
                 for q in self.procs if q.ended and (e := self.eos.get(q.name)) is not None]
        env = dict(os.environ, PYTHONUNBUFFERED="1", **{LAUNCHED_ENV: "1", LAUNCHER_PID_ENV: str(os.getpid()),
                                                        ENDED_ENV: json.dumps(ended)})
        p.popen = None
        if self._forks is not None:
            try:
                p.popen = self._forks.start(argv, env, os.getcwd())
            except OSError as exc:
                self._no_forks(exc)
        if p.popen is None:
            p.popen = subprocess.Popen([sys.executable, "-m", "app.cli", *argv], env=env, start_new_session=True)
        p.rc = None
        p.hung = None
        with self._lock:
            self.watchdog.started(p.name, p.popen.pid)

    def _start_forks(self) -> None:
        """Workers forked from a warm parent (:mod:`app.forkserver`) unless
        ``SMARTROOM_SPAWN=exec``; its imports overlap the bus's start."""
        if os.environ.get(SPAWN_ENV, "fork") != "exec":
            try:
                self._forks = ForkServer()
            except OSError as exc:
                self._no_forks(exc)

    def _no_forks(self, exc: OSError) -> None:
        """The fork server cannot be used: fresh processes from now on."""
        print(f"smartroom: the fork server failed ({exc}); workers start as fresh processes", file=sys.stderr)
        if self._forks is not None:
            self._forks.close()
        self._forks = None

    def _signal(self, p: _Proc, sig) -> None:
        if p.popen is not None and p.popen.poll() is None:
            try:
                p.popen.send_signal(sig)
            except ProcessLookupError:
                pass

    def _kill(self, p: _Proc) -> None:
        """SIGKILL, after asking for the worker's stacks (:data:`~app.watchdog.STACKS_SIGNAL`,
        written to stderr): a worker killed because it would not stop says where it was."""
        self._signal(p, STACKS_SIGNAL)
        deadline = time.monotonic() + STACKS_WAIT_S
        while time.monotonic() < deadline and p.popen.poll() is None:
            time.sleep(0.05)
        try:
            p.popen.kill()
        except ProcessLookupError:
            pass

    def request_stop(self, hard: bool = False, user: bool = True) -> None:
        """First call: the sources end their input (the stream ends everywhere); a second
        call, or ``hard``: every worker is terminated."""
        with self._lock:
            self.stopped_by_user = self.stopped_by_user or user
            level = 2 if hard or self._stop_level >= 1 else 1
            if level <= self._stop_level:
                return
            self._stop_level = level
            self._stop_time = time.monotonic()
        for p in self.procs:
            if level == 1 and p.source:
                self._signal(p, signal.SIGINT)
            elif level == 2:
                self._signal(p, signal.SIGTERM)

    def _on_control(self, sample) -> None:
        name = Keys.last(sample.key_expr)
        if name not in self._members:   # any process may publish on the bus: not a stage of this run
            return                      # (told from the key, before anything is decoded)
        try:
            msg = decode_sample(sample)
            msg.validate()
        except MessageError:
            return
        if getattr(msg, "worker", None) != name:
            return
        if isinstance(msg, Heartbeat):
            with self._lock:
                self.watchdog.beat(msg)   # only the pid the launcher started counts
            self.hosts.heartbeat(name, msg.stamp)   # another host's clock against this one's
        elif isinstance(msg, EndOfStream):
            self.eos[name] = msg
        elif isinstance(msg, Stats):
            old = self.stats.get(name)
            if old is not None and old.final and not msg.final and old.figures.get("pid") == msg.figures.get("pid"):
                return
            self.stats = {**self.stats, name: msg}   # a new table: readers iterate the one they took
            if self.progress is not None:
                self.progress.update(self.stats)

    def _on_alive(self, sample) -> None:
        import zenoh
        self.hosts.alive(Keys.last(sample.key_expr), sample.kind != zenoh.SampleKind.DELETE)

    def _hub_linked(self) -> bool | None:
        """A host share's link to the hub (zenoh knows a router); None where this host runs it."""
        if self.host is None:
            return None
        try:
            return bool(list(self._session.info.routers_zid()))
        except Exception:  # noqa: BLE001 - the session is closing
            return True

    # -- the run ------------------------------------------------------------------
    def _open_bus(self):
        """This launcher's zenoh session: the hub (a router) where this host runs it, else
        a client of the hub elsewhere."""
        if self.host is None:
            acl = None
            if self.hub_bus.acl is not None:   # who may publish what, from the layout (app.bus_acl)
                from app.bus_acl import certificate_name, room_access_control
                acl = room_access_control(self.layout, certificate_name(self.hub_bus.tls.cert))
            elif self._private_dir is not None:
                from app.bus_acl import outsiders_read_only
                acl = outsiders_read_only(self.layout.room)
                os.mkdir(self._private_dir, 0o700)   # its socket: for this user's processes only
            self._session = open_session(self.hub_bus, mode="router", access_control=acl)
        else:
            self._session = open_session(self.layout.bus.for_worker(), mode="client")
        return self._session

    def run(self) -> int:
        """Start everything and wait for the end; the exit code of the run."""
        self.started = time.time()
        self._start_forks()
        try:
            session = self._open_bus()
        except BaseException:
            if self._forks is not None:
                self._forks.close()
            if self._private_dir is not None:
                shutil.rmtree(self._private_dir, ignore_errors=True)
            raise
        self._eos_pubs: dict = {}
        keys = Keys(self.layout.room)
        inlet = Inlet(session, period_s=0.005, name="launcher-inlet")   # control keys, taken in batches
        for key in (keys.stats(), keys.eos(), keys.heartbeat()):
            inlet.subscribe(key, self._on_control)
        subs = []
        if self.hosts.remote or self.host is not None:
            subs.append(session.liveliness().declare_subscriber(keys.alive(), self._on_alive, history=True))
        previous = {s: signal.signal(s, lambda *_: self.request_stop()) for s in (signal.SIGINT, signal.SIGTERM)}
        self._make_reserve()
        try:
            for p in self.procs:
                self._spawn(p)
            self._wait()
        finally:
            for s, h in previous.items():
                signal.signal(s, h)
            self._terminate_all()
            if self._forks is not None:
                self._forks.close()
            time.sleep(0.1)   # the last final stats
            inlet.close(drain=True)
            for sub in subs:
                sub.undeclare()
            for pub in self._eos_pubs.values():
                pub.undeclare()
            session.close()
            if self._private_dir is not None:
                shutil.rmtree(self._private_dir, ignore_errors=True)
            if self.progress is not None:
                self.progress.close()
            self._write_stats(final=True)
        if self.input_error:
            from app.errors import InputError
            raise InputError(self.input_error)
        return 0 if self.complete else 1

    def _crashed(self, p: _Proc, rc: int, now: float) -> None:
        failure = {"time": round(time.time(), 3), "exit": rc}
        if p.hung:
            failure["reason"] = "hung"
            failure["detail"] = p.hung
        p.failures.append(failure)
        p.crashes.append(now)
        while p.crashes and now - p.crashes[0] > self.policy.window_s:
            p.crashes.popleft()
        recent = len(p.crashes)
        if recent >= self.policy.storm:
            p.done = True
            reason = (f"worker {p.name} crashed {recent} times within {self.policy.window_s:.0f} s "
                      f"(last: {_exit_text(rc)}); restart storm stopped")
            self.reasons.append(reason)
            print(f"smartroom: {reason}; stopping the run", file=sys.stderr)
            self.request_stop(hard=True, user=False)
            return
        delay = self.policy.delay(recent)
        p.restarts += 1
        p.next_start = now + delay
        p.popen = None
        what = f"was hung ({p.hung}) and was killed" if p.hung else f"died ({_exit_text(rc)})"
        print(f"smartroom: worker {p.name} {what}; restarting in {delay:.2g} s "
              f"(restart {p.restarts}; {recent} in the last {self.policy.window_s:.0f} s)", file=sys.stderr)

    def _wait(self) -> None:
        last_progress = time.monotonic()
        last_frames = -1
        while True:
            now = time.monotonic()
            for p in self.procs:
                if p.done:
                    continue
                if p.popen is None:
                    if now >= p.next_start and self._stop_level < 2:
                        self._spawn(p)
                    elif self._stop_level >= 2:
                        p.done = True
                    continue
                rc = p.popen.poll()
                if rc is None:
                    if self._stop_level == 0 and p.hung is None:
                        self._watch(p)
                    continue
                p.rc = rc
                with self._lock:
                    self.watchdog.stopped(p.name)
                if rc == 0:
                    p.done = p.ended = True
                elif rc == EXIT_INPUT:
                    p.done = True
                    self.input_error = self.input_error or self._error_line(p.name)
                    self.request_stop(hard=True, user=False)
                elif rc == EXIT_STALLED:   # offline, the run cannot go on: stop it, say why
                    p.done = True
                    reason = f"{p.name}: {self._error_line(p.name)}"
                    self.reasons.append(reason)
                    print(f"smartroom: {reason}; stopping", file=sys.stderr)
                    self.request_stop(hard=True, user=False)
                elif self._stop_level >= 2:
                    p.done = True
                else:
                    self._crashed(p, rc, now)
            if all(p.done for p in self.procs):
                break
            frames = sum(s.figures.get("frames_out", 0) + s.figures.get("frames_in", 0) for s in self.stats.values())
            if frames != last_frames:
                last_frames, last_progress = frames, now
            # a source on another host keeps the run open until its end of stream arrives
            sources_done = (all(p.done for p in self.procs if p.source)
                            and all(n in self.eos for n in self.remote_sources))
            if self.hosts.remote or self.host is not None:
                gone = self.hosts.check(self.eos, self._hub_linked())
                if gone and self._stop_level == 0:   # a host, or the hub, gone for peer_timeout_s
                    self.reasons.append(gone)
                    print(f"smartroom: {gone}; stopping", file=sys.stderr)
                    self.request_stop(hard=True, user=False)
            if sources_done and self._stop_level == 0 and now - last_progress > DRAIN_TIMEOUT_S:
                stuck = [p.name for p in self.procs if not p.done]
                reason = f"no progress for {DRAIN_TIMEOUT_S:.0f} s after the sources ended (waiting: {', '.join(stuck)})"
                self.reasons.append(reason)
                print(f"smartroom: {reason}; stopping", file=sys.stderr)
                self.request_stop(hard=True, user=False)
            self._escalate(now)
            if now - self._last_stats_write >= STATS_PERIOD_S:
                self._write_stats(final=False)
                self._repeat_ends()
            time.sleep(0.05)

    def _watch(self, p: _Proc) -> None:
        """Kill a hung worker (SIGKILL: a stopped process takes nothing else); its exit is
        then restarted like a crash, the reason "hung" recorded."""
        with self._lock:
            why = self.watchdog.hung(p.name)
        if why is None:
            return
        p.hung = why
        print(f"smartroom: worker {p.name} is hung: {why}; killing it (its stacks follow)", file=sys.stderr)
        self._kill(p)

    def _repeat_ends(self) -> None:
        """Say again, once a second, the end of stream of every worker that has ended
        (exited 0): a downstream worker restarted after the original message went by
        learns from it that its input has ended."""
        for p in self.procs:
            eos = self.eos.get(p.name)
            if p.ended and eos is not None:
                key = Keys(self.layout.room).eos(p.name)
                pub = self._eos_pubs.get(key)
                if pub is None:
                    pub = self._eos_pubs[key] = Publisher(self._session, key, droppable=False)
                pub.put(eos)

    def _escalate(self, now: float) -> None:
        """A stop that takes too long: SIGTERM once, then SIGKILL once."""
        if self._stop_time is None:
            return
        waited = now - self._stop_time
        if self._stop_level == 1 and waited > STOP_GRACE_S:
            print(f"smartroom: the stream did not end within {STOP_GRACE_S:.0f} s; terminating the workers",
                  file=sys.stderr)
            self.reasons.append(f"the end of stream did not reach every stage within {STOP_GRACE_S:.0f} s")
            self.request_stop(hard=True, user=False)
        elif self._stop_level == 2 and waited > KILL_GRACE_S:
            with self._lock:
                self._stop_level = 3
            for p in self.procs:
                if p.popen is not None and p.popen.poll() is None:
                    print(f"smartroom: worker {p.name} still running {KILL_GRACE_S:.0f} s after SIGTERM; killed"
                          " (its stacks follow)", file=sys.stderr)
                    self._kill(p)

    def _error_line(self, name: str) -> str:
        f = self.out / ERROR_DIR / f"{name}.error"
        try:
            return f.read_text(encoding="utf-8").strip().splitlines()[0]
        except (OSError, IndexError):
            return f"worker {name} stopped on bad input"

    def _terminate_all(self) -> None:
        alive = [p for p in self.procs if p.popen is not None and p.popen.poll() is None]
        for p in alive:
            self._signal(p, signal.SIGTERM)
        deadline = time.monotonic() + KILL_GRACE_S
        for p in alive:
            try:
                p.rc = p.popen.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._kill(p)
                p.rc = p.popen.wait()

    # -- what happened ---------------------------------------------------------------
    def _stream_errors(self) -> list[str]:
        """Streams that ended early for a reason a source reported (every camera lost)."""
        return [f"{name}: {s.figures['stream_error']}" for name, s in self.stats.items()
                if isinstance(s.figures.get("stream_error"), str)]

    def _frames_passed(self) -> list[str]:
        """Offline, frames the source sent on past a stage that was away too long, and
        frames a restarted stage carried on without (the stage before it restarted with it:
        nothing sent them again), frames built without a view waited for in vain
        (``frames_stalled``, :mod:`app.reconstruction.assembly`): nothing may be lost on a
        recording, the run is incomplete."""
        if not self.layout.run.recording:
            return []
        out = []
        for name, s in sorted(self.stats.items()):
            passed = s.figures.get("went_on_without")
            for worker, n in sorted(passed.items()) if isinstance(passed, dict) else ():
                if isinstance(n, int) and n > 0:
                    out.append(f"{worker}: {n} frames went on without it (away longer than the source "
                               f"waits, {name} said)")
            n = s.figures.get("frames_stalled")
            if isinstance(n, int) and n > 0:
                out.append(f"{name}: {n} frames built without a camera's mask it waited for in vain "
                           f"(its producer on the bus sent nothing for 30 s)")
            n = s.figures.get("not_sent_again")
            if isinstance(n, int) and n > 0:
                out.append(f"{name}: {n} frames after its restored state were not sent again (a stage before "
                           f"it restarted with it): carried on without them")
        return out

    @property
    def complete(self) -> bool:
        return (not self.reasons and not self.input_error and not self._stream_errors()
                and not self._frames_passed() and all(p.ended for p in self.procs))

    def _make_reserve(self) -> None:
        try:
            with open(self._reserve, "wb") as fh:
                fh.write(b"\0" * RESERVE_BYTES)
        except OSError:
            pass

    def summary(self, final: bool) -> dict:
        stages = {name: {"stage": s.stage, "order": s.figures.get("order"), "final": s.final, "figures": s.figures}
                  for name, s in self.stats.items() if "frames_in" in s.figures}
        fps = self.layout.run.fps or 0.0
        source = next((self.eos[p.name] for p in self.procs if p.source and p.name in self.eos), None)
        expected = source.frames if source is not None else None
        first = source.first if source is not None else 0
        out = summarise(stages, fps, expected, started=self.started, paced=bool(self.layout.run.pace))
        restarts = {p.name: p.restarts for p in self.procs}
        for name, s in out["stages"].items():
            s["restarts"] = restarts.get(name, s.get("restarts", 0))
            s["frames_expected"] = expected
            if final and expected is not None and not s["final"]:
                # it never sent its final figures (killed, hung): what it never received is missing
                own = count_own(tuple(s["frame_share"]) if s.get("frame_share") else None, first, expected)
                s["frames_missing"] = max(s["frames_missing"], own - s["frames_in"])
        out["workers"] = {name: st["figures"] for name, st in stages.items()}
        if final:
            reasons = list(self.reasons) + self._stream_errors() + self._frames_passed()
            if self.input_error:
                reasons.append(self.input_error)
            for p in self.procs:
                if not p.ended and p.rc not in (None, 0) and not self.stopped_by_user and not reasons:
                    reasons.append(f"worker {p.name} ended without finishing its stream ({_exit_text(p.rc)})")
            out["complete"] = not reasons and all(p.ended for p in self.procs)
            if reasons:
                out["reasons"] = reasons
            out["stopped_by_user"] = self.stopped_by_user
            out["exits"] = {p.name: p.rc for p in self.procs}
            out["restarts"] = {p.name: {"count": p.restarts, "failures": p.failures[-20:]}
                               for p in self.procs if p.restarts or p.failures}
        else:
            out["complete"] = False
            out["running"] = True
        with self._lock:
            silences = self.watchdog.silences()
        if silences:   # a stage that stood still for a while (stopped, swapped out) and went on
            out["silences"] = silences
        out.update(self.hosts.figures())   # outages of links to other hosts, their clocks' skews
        return out

    def _write_stats(self, final: bool) -> None:
        self._last_stats_write = time.monotonic()
        path = self.out / "stats.json"
        data = self.summary(final)
        try:
            write_json(path, data)
        except OSError as exc:
            if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                raise
            if not final:
                return
            self._reserve.unlink(missing_ok=True)   # the space kept for this moment
            data["complete"] = False
            data.setdefault("reasons", []).append("the disk is full")
            write_json(path, data)
        if final:
            self._reserve.unlink(missing_ok=True)
