"""Start a layout's workers as OS processes, watch them, restart the ones that die,
and end the run cleanly.

The launcher opens the hub zenoh session every worker connects to, writes the
resolved layout next to the results (``<out>/layout.yaml``), starts each local worker
as ``python -m app.cli worker NAME --layout <out>/layout.yaml``, shows progress from
the workers' stats, and waits:

- a worker exiting 0 has finished its stream;
- exit 2 is bad input (its one-line reason is in ``<out>/logs/<name>.error``): the
  run cannot go on, the other workers are stopped so their files are completed, and
  the launcher exits 2 with that reason;
- any other exit is a crash: the worker is restarted with exponential backoff
  (logged), at most ``MAX_RESTARTS`` times.

Ctrl-C or SIGTERM stops the sources first, so the end of stream flows through every
stage and the result files are completed; a second Ctrl-C stops everything at once.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from app.bus import BusConfig, Keys, decode_sample, free_port, open_session
from app.config import Layout
from app.messages import MessageError, Stats

__all__ = ["Launcher", "ERROR_DIR"]

MAX_RESTARTS = 5
DRAIN_TIMEOUT_S = 60.0   # after the sources end, how long without any progress before stopping all
STOP_GRACE_S = 15.0      # after Ctrl-C, how long the end of stream may take before SIGTERM
KILL_GRACE_S = 5.0
ERROR_DIR = "logs"
LAUNCHED_ENV = "SMARTROOM_LAUNCHED"   # set for workers the launcher starts


@dataclass
class _Proc:
    name: str
    source: bool
    popen: subprocess.Popen | None = None
    restarts: int = 0
    next_start: float = 0.0
    rc: int | None = None
    done: bool = False
    failures: list = field(default_factory=list)


def _hub_bus(bus: BusConfig) -> BusConfig:
    """The hub listens where the layout says; port 0 becomes a free port now."""
    listen = []
    for ep in bus.listen:
        if ep.endswith(":0"):
            ep = ep[:-1] + str(free_port())
        listen.append(ep)
    return BusConfig(listen=listen, connect=list(bus.connect), multicast=bus.multicast, shm=bus.shm)


def _connect_endpoints(listen: list[str]) -> list[str]:
    return [ep.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]") for ep in listen]


class Launcher:
    def __init__(self, layout: Layout, verbose: bool = False, progress=None):
        from workers import worker_class

        self.layout = layout.copy()
        self.verbose = verbose
        self.out = Path(self.layout.run.out)
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / ERROR_DIR).mkdir(exist_ok=True)
        hub = _hub_bus(self.layout.bus)
        self.hub_bus = hub
        self.layout.bus = BusConfig(listen=hub.listen, connect=_connect_endpoints(hub.listen),
                                    multicast=hub.multicast, shm=hub.shm)
        self.layout_path = self.out / "layout.yaml"
        self.layout.save(self.layout_path)
        self.procs: list[_Proc] = []
        for w in self.layout.workers:
            cls = worker_class(w.kind)
            if not w.local or (cls.DISPLAY and self.layout.run.headless):
                continue
            self.procs.append(_Proc(name=w.name, source=not cls.CONSUMES))
        self.progress = progress
        self.stats: dict[str, Stats] = {}
        self._stop_requests = 0
        self._stop_time = None
        self._lock = threading.Lock()

    # -- processes ----------------------------------------------------------------
    def _spawn(self, p: _Proc) -> None:
        cmd = [sys.executable, "-m", "app.cli", "worker", p.name, "--layout", str(self.layout_path)]
        if self.verbose:
            cmd.append("--verbose")
        env = dict(os.environ, PYTHONUNBUFFERED="1", **{LAUNCHED_ENV: "1"})
        p.popen = subprocess.Popen(cmd, env=env, start_new_session=True)
        p.rc = None

    def _signal(self, p: _Proc, sig) -> None:
        if p.popen is not None and p.popen.poll() is None:
            try:
                p.popen.send_signal(sig)
            except ProcessLookupError:
                pass

    def request_stop(self) -> None:
        """First call: end the sources (the stream ends everywhere). Later: stop all."""
        with self._lock:
            self._stop_requests += 1
            first = self._stop_requests == 1
            self._stop_time = self._stop_time or time.monotonic()
        for p in self.procs:
            if p.source or not first:
                self._signal(p, signal.SIGTERM)

    def _on_stats(self, sample) -> None:
        try:
            msg = decode_sample(sample)
        except MessageError:
            return
        if isinstance(msg, Stats):
            self.stats[msg.worker] = msg
            if self.progress is not None:
                self.progress.update(self.stats)

    # -- the run ------------------------------------------------------------------
    def run(self) -> int:
        """Start everything and wait for the end; the exit code of the run."""
        session = open_session(self.hub_bus)
        sub = session.declare_subscriber(Keys(self.layout.room).stats(), self._on_stats)
        previous = {s: signal.signal(s, lambda *_: self.request_stop()) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            for p in self.procs:
                self._spawn(p)
            return self._wait()
        finally:
            for s, h in previous.items():
                signal.signal(s, h)
            self._terminate_all()
            sub.undeclare()
            session.close()
            if self.progress is not None:
                self.progress.close()

    def _wait(self) -> int:
        input_error = None
        last_progress = time.monotonic()
        last_frames = -1
        while True:
            now = time.monotonic()
            for p in self.procs:
                if p.done or p.popen is None:
                    if p.popen is None and not p.done and now >= p.next_start:
                        self._spawn(p)
                    continue
                rc = p.popen.poll()
                if rc is None:
                    continue
                p.rc = rc
                if rc == 0 or self._stop_requests:
                    p.done = True
                elif rc == 2:
                    p.done = True
                    input_error = input_error or self._error_line(p.name)
                    self.request_stop()
                elif p.restarts >= MAX_RESTARTS:
                    p.done = True
                    print(f"smartroom: worker {p.name} died (exit {rc}) {p.restarts + 1} times; giving up on it",
                          file=sys.stderr)
                else:
                    delay = min(30.0, 2.0 ** p.restarts)
                    p.restarts += 1
                    p.next_start = now + delay
                    p.popen = None
                    print(f"smartroom: worker {p.name} died (exit {rc}); restarting in {delay:.0f} s "
                          f"(restart {p.restarts}/{MAX_RESTARTS})", file=sys.stderr)
            if all(p.done for p in self.procs):
                break
            frames = sum(s.figures.get("frames_out", 0) + s.figures.get("frames_in", 0) for s in self.stats.values())
            if frames != last_frames:
                last_frames, last_progress = frames, now
            sources_done = all(p.done for p in self.procs if p.source)
            if sources_done and now - last_progress > DRAIN_TIMEOUT_S:
                print(f"smartroom: no progress for {DRAIN_TIMEOUT_S:.0f} s after the sources ended; stopping",
                      file=sys.stderr)
                self.request_stop()
                self.request_stop()
            if self._stop_time is not None and now - self._stop_time > STOP_GRACE_S:
                self.request_stop()
                self._stop_time = now
            time.sleep(0.05)
        if input_error:
            from app.errors import InputError
            raise InputError(input_error)
        crashed = [p.name for p in self.procs if p.rc not in (0, None) and not self._stop_requests]
        return 1 if crashed else 0

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
                p.popen.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.popen.kill()
                p.popen.wait()
