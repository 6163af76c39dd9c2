"""When this process compiles kernels (numba), as wall-clock spans.

A first run compiles every numba kernel (later runs load them from the cache): one-off
seconds, on the first frames through each stage or later on a path first taken (the
pose stage's first tracked person). The worker base records them here so that what the
run reports about its speed is about the run and not about the compiler: the monitor
says "starting" while a stage compiles, and ``stats.json``'s real-time factor leaves the
time the pipeline waited for a compile out (:func:`app.stats.summarise`), reporting it
apart. Uses numba's own event (``numba:compile``, only real compiles, not cache loads).
"""
from __future__ import annotations

import sys
import threading
import time

__all__ = ["CompileClock", "union_seconds"]

MAX_SPANS = 64   # compiles happen at start and on new paths: a handful, kept merged


class CompileClock:
    """Compile spans of this process: ``[start, end]`` wall-clock seconds, nested compiles
    (a kernel's callees) inside their caller's span; ``on_start`` is called when a
    top-level compile begins (the worker says "compiling kernels")."""

    def __init__(self, clock=time.time, on_start=None):
        self.clock = clock
        self.on_start = on_start
        self.spans: list[list[float]] = []
        self.total_s = 0.0
        self._depth = 0
        self._began = 0.0
        self._lock = threading.Lock()
        self.installed = False

    def install(self, only_if_loaded: bool = False) -> "CompileClock":
        """Listen to numba's compile events in this process, once. ``only_if_loaded``:
        only once numba is imported (a worker that uses no kernel does not pay numba's
        import, ~0.7 s and ~90 MB; call again later, it is cheap)."""
        if self.installed or (only_if_loaded and "numba" not in sys.modules):
            return self
        try:
            from numba.core import event
        except ImportError:   # pragma: no cover - numba is a dependency
            return self
        self.installed = True
        clock = self

        class _Listener(event.Listener):
            def on_start(self, ev):
                clock.started()

            def on_end(self, ev):
                clock.ended()
        event.register("numba:compile", _Listener())
        return self

    def started(self) -> None:
        with self._lock:
            self._depth += 1
            if self._depth > 1:
                return
            self._began = self.clock()
        if self.on_start is not None:
            self.on_start()

    def ended(self) -> None:
        with self._lock:
            self._depth = max(0, self._depth - 1)
            if self._depth:
                return
            end = self.clock()
            self.total_s += end - self._began
            if self.spans and self._began - self.spans[-1][1] < 0.5:
                self.spans[-1][1] = end   # one compile after another: one span
            else:
                self.spans.append([self._began, end])
            del self.spans[:-MAX_SPANS]

    @property
    def compiling(self) -> bool:
        return self._depth > 0

    def figures(self) -> dict:
        """``compile_s`` (total), ``compile_spans`` and ``compiling`` (now), for the stats."""
        with self._lock:
            spans = [[round(a, 3), round(b, 3)] for a, b in self.spans]
            if self._depth:
                spans.append([round(self._began, 3), round(self.clock(), 3)])
            return {"compile_s": round(self.total_s, 3), "compile_spans": spans, "compiling": self._depth > 0}


def union_seconds(spans, start: float, end: float) -> float:
    """Seconds of ``[start, end]`` covered by the union of ``spans`` (``[a, b]`` pairs)."""
    total, reach = 0.0, start
    for a, b in sorted((max(a, start), min(b, end)) for a, b in spans):
        if b <= reach:
            continue
        total += b - max(a, reach)
        reach = b
    return total
