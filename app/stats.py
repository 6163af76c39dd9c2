"""Per-stage accounting: which frames came in and went out, latency from capture,
processing time, rates and CPU use. Pure Python; the worker base feeds it and
publishes :meth:`StageLedger.figures` once a second.

Definitions (CONTRACT §2, extended):

- ``frames_in``: distinct frame indices the stage received;
- ``frames_out``: distinct frame indices it published a result for;
- ``frames_dropped``: received but not published (``in - out`` at the end; during a
  run, only frames older than the newest output count);
- ``frames_missing``: produced by the source but never received here (known at the
  end of the stream), so ``frames_in + frames_missing`` is the source's frame count;
- latency: wall-clock time from the frame's capture to the stage's output (over the
  last ``RECENT`` outputs while running, over all of them in the final figures, up to
  the last :data:`KEPT_MS` to 2 x :data:`KEPT_MS`: a ledger's memory and the cost of saving it
  do not grow with the days a room runs, see :class:`FrameSet`; a run longer than about
  45 minutes at 25 fps has the final percentiles of its last 45 to 90 minutes).
"""
from __future__ import annotations

import os
import time
from array import array
from collections import deque

import numpy as np

from app.frame_shares import count_own, owns

__all__ = ["StageLedger", "FrameSet", "summarise", "steady_fps", "percentiles"]

WINDOW_S = 2.0
RECENT = 5000   # outputs (~3 min at 25 fps) behind the running latency percentiles
HORIZON = 1024  # frame numbers a ledger keeps one by one (older ones are folded into counts)
#: latencies and processing times kept for the final percentiles (~44 min at 25 fps): at most
#: 2 x 2 x 8 x KEPT_MS bytes (2 MB) a ledger, reached in 1.5 h at 25 fps (it was 32 MB, reached
#: after 22 h: the memory of a room's workers grew for a day)
KEPT_MS = 1 << 16
MAX_ABSENT = 64     # absent frames remembered below a frame set's folded base


def percentiles(values_ms) -> dict:
    """``{"mean", "p50", "p95", "max"}`` of a list of milliseconds (zeros when empty)."""
    a = np.asarray(values_ms, dtype=np.float64)
    if a.size == 0:
        return {"mean": 0.0, "p50": 0.0, "p95": 0.0, "max": 0.0}
    p50, p95 = np.percentile(a, [50, 95])
    return {"mean": round(float(a.mean()), 3), "p50": round(float(p50), 3),
            "p95": round(float(p95), 3), "max": round(float(a.max()), 3)}


class FrameSet:
    """A growable bitmap of frame indices (cheap for hours of frames).

    With a ``horizon`` (a worker's ledger, :data:`HORIZON`) only the newest frame numbers
    are kept one by one, between ``horizon`` and 1.5 x ``horizon`` of them: older ones are
    folded into :attr:`folded` (how many of them were in the set) and the first
    :data:`MAX_ABSENT` absent ones are remembered. Its size, and so the cost of saving it
    (:meth:`state`), stays the same after an hour and after a month of frames; a frame
    below the folded base counts as present (nothing that old comes again but a forgery).
    """

    def __init__(self, horizon: int | None = None):
        self.bits = bytearray()      # bits[k]: frame base + k
        self.count = 0
        self.base = 0
        self.folded = 0              # members below base
        self.absent: list[int] = []  # the first non-members below base (at most MAX_ABSENT)
        self.horizon = horizon

    def add(self, i: int) -> bool:
        if i < self.base or i < 0:
            return False
        k = i - self.base
        if k >= len(self.bits):
            self.bits.extend(b"\0" * max(k + 1 - len(self.bits), len(self.bits), 1024))
        if self.bits[k]:
            return False
        self.bits[k] = 1
        self.count += 1
        if self.horizon and k >= self.horizon + self.horizon // 2:
            self._fold(i - self.horizon)
        return True

    def _fold(self, base: int) -> None:
        """Forget the frames below ``base`` one by one (their count and first gaps stay)."""
        n = base - self.base
        if n <= 0:
            return
        head = bytes(self.bits[:n]).ljust(n, b"\0")
        members = head.count(1)
        if len(self.absent) < MAX_ABSENT and members < n:
            gaps = np.flatnonzero(np.frombuffer(head, dtype=np.uint8) == 0)[:MAX_ABSENT - len(self.absent)]
            self.absent += (gaps + self.base).tolist()
        self.folded += members
        del self.bits[:n]
        self.base = base

    def __contains__(self, i: int) -> bool:
        if i < self.base:
            return i >= 0 and i not in self.absent
        k = i - self.base
        return k < len(self.bits) and bool(self.bits[k])

    def __len__(self) -> int:
        return self.count

    @property
    def end(self) -> int:
        """One past the largest frame number the bitmap covers."""
        return self.base + len(self.bits)

    def missing(self, first: int, stop: int, limit: int = 50) -> list[int]:
        """The first ``limit`` frame numbers in ``[first, stop)`` that are not in the set."""
        out = [i for i in self.absent if first <= i < stop][:limit]
        lo, hi = max(first, self.base), min(stop, self.end)
        if len(out) < limit and hi > lo:
            bits = np.frombuffer(bytes(self.bits[lo - self.base:hi - self.base]), dtype=np.uint8)
            out += (np.flatnonzero(bits == 0)[:limit - len(out)] + lo).tolist()
        start = max(first, self.end)
        out += list(range(start, min(stop, start + limit - len(out))))
        return out[:limit]

    def count_below(self, i: int) -> int:
        return self.folded + self.bits[:max(0, i - self.base)].count(1)

    def ranges(self) -> list[list[int]]:
        """The kept frames as ``[[start, stop), ...]`` runs (compact: frames come in runs)."""
        a = np.frombuffer(bytes(self.bits), dtype=np.uint8).astype(np.int8)
        if not a.size:
            return []
        edges = np.flatnonzero(np.diff(np.concatenate(([0], a, [0])))) + self.base
        return edges.reshape(-1, 2).tolist()

    def state(self):
        """What :meth:`from_state` takes back: the runs alone while nothing is folded (the
        older form), else ``{"base", "folded", "absent", "ranges"}``."""
        if not self.base:
            return self.ranges()
        return {"base": self.base, "folded": self.folded, "absent": list(self.absent), "ranges": self.ranges()}

    @classmethod
    def from_state(cls, state, horizon: int | None = None) -> "FrameSet":
        if not isinstance(state, dict):
            s = cls.from_ranges(state)
            s.horizon = horizon
            return s
        s = cls.from_ranges(state.get("ranges"), base=state.get("base"))
        s.horizon = horizon
        folded = state.get("folded")
        s.folded = folded if isinstance(folded, int) and 0 <= folded <= s.base else 0
        absent = state.get("absent")
        s.absent = [i for i in absent if isinstance(i, int) and 0 <= i < s.base][:MAX_ABSENT] \
            if isinstance(absent, list) else []
        s.count += s.folded
        return s

    @classmethod
    def from_ranges(cls, ranges, base=None) -> "FrameSet":
        s = cls()
        s.base = base if isinstance(base, int) and 0 <= base <= (1 << 40) else 0
        for start, stop in ranges or []:
            if isinstance(start, int) and isinstance(stop, int) and s.base <= start < stop <= (1 << 40):
                start, stop = start - s.base, stop - s.base
                if stop > len(s.bits):
                    s.bits.extend(b"\0" * (stop - len(s.bits)))
                s.bits[start:stop] = b"\1" * (stop - start)
        s.count = s.bits.count(1)
        return s


class StageLedger:
    """Counts, latencies and timings of one worker."""

    def __init__(self, clock=time.time, trace: bool = False):
        self.clock = clock
        #: per frame ``[capture stamp, first received, first output]`` when tracing (benchmarks)
        self.trace: dict[int, list] | None = {} if trace else None
        self.seen = FrameSet(HORIZON)
        self.done = FrameSet(HORIZON)
        self.items_in = 0
        self.items_out = 0
        self.items_dropped = 0
        self.bad_messages = 0
        self.latency_ms = array("d")   # every output's latency (compact: hours of frames)
        self.process_ms = array("d")
        self.first_stamp = None
        self.first_in = None
        self.first_emit = None      # the first output: a stage's rate counts from there
        self.last_emit = None
        self.last_frame = -1
        self.newest_out = -1
        self._events = deque()      # (time, kind, latency_ms) for the rate window
        self._busy = deque()        # (end time, seconds busy)
        self._cpu0 = (time.monotonic(), time.process_time())
        self._cpu_start = self._cpu0
        self.process_total = 0.0
        # the process's CPU (all its threads: zenoh's decoding its input too) from its first
        # input to its last output, earlier incarnations' added: what the stage costs a frame
        self.cpu_carried = 0.0
        self._cpu_from = self._cpu_to = None
        self._proc_frame = None
        self.started = clock()
        #: ``journal(kind, frame)`` is told of every frame first seen ("i") or done ("o")
        self.journal = None

    # -- feeding ------------------------------------------------------------------
    def received(self, frame: int, stamp: float) -> None:
        now = self.clock()
        self.items_in += 1
        if self.first_in is None:
            self.first_in = now
        if self._cpu_from is None:
            self._cpu_from = time.process_time()
        if stamp and (self.first_stamp is None or stamp < self.first_stamp):
            self.first_stamp = stamp
        if self.seen.add(frame):
            if self.journal is not None:
                self.journal("i", frame)
            self._events.append((now, "in", 0.0))
            if self.trace is not None:
                self.trace[frame] = [stamp, now, None]
        self.last_frame = max(self.last_frame, frame)

    def emitted(self, frame: int, stamp: float) -> None:
        now = self.clock()
        self.items_out += 1
        if self.first_emit is None:
            self.first_emit = now
        self.last_emit = now
        if self.done.add(frame):
            if self.journal is not None:
                self.journal("o", frame)
            lat = (now - stamp) * 1e3 if stamp else 0.0
            self.latency_ms.append(lat)
            if len(self.latency_ms) > 2 * KEPT_MS:   # memory flat however long the room runs
                del self.latency_ms[:KEPT_MS]
            if self.trace is not None:
                self.trace.setdefault(frame, [stamp, now, None])[2] = now
            self._events.append((now, "out", lat))
            self.newest_out = max(self.newest_out, frame)

    def processed(self, seconds: float, frame: int | None = None, cpu: float = 0.0) -> None:
        """Time spent handling one item (``cpu``: the process's CPU seconds meanwhile: a
        source's CPU is counted from its first item's start); the items of one frame (its
        cameras) add up to that frame's processing time."""
        self._busy.append((self.clock(), seconds))
        self.process_total += seconds
        cpu_now = time.process_time()
        if self._cpu_from is None:            # a source: from its first frame's start
            self._cpu_from = cpu_now - max(0.0, cpu)
        self._cpu_to = cpu_now
        if frame is not None and frame == self._proc_frame and self.process_ms:
            self.process_ms[-1] += seconds * 1e3
        else:
            self.process_ms.append(seconds * 1e3)
            if len(self.process_ms) > 2 * KEPT_MS:
                del self.process_ms[:KEPT_MS]
            self._proc_frame = frame

    def dropped_item(self, n: int = 1) -> None:
        self.items_dropped += n

    # -- across restarts ------------------------------------------------------------
    def state(self) -> dict:
        """What a restarted incarnation of the worker carries on from (counts and the
        frames seen and done; latencies start afresh)."""
        return {"seen": self.seen.state(), "done": self.done.state(), "items_in": self.items_in,
                "items_out": self.items_out, "items_dropped": self.items_dropped,
                "bad_messages": self.bad_messages, "last_frame": self.last_frame,
                "newest_out": self.newest_out, "first_stamp": self.first_stamp, "first_emit": self.first_emit,
                "last_emit": self.last_emit,
                "process_total": self.process_total, "cpu_total": self.cpu_total}

    @property
    def cpu_total(self) -> float:
        """CPU seconds of the process from its first input to its last output (every
        incarnation)."""
        here = self._cpu_to - self._cpu_from if self._cpu_from is not None and self._cpu_to is not None else 0.0
        return self.cpu_carried + max(0.0, here)

    def restore(self, state: dict, journal: list[tuple[str, int]] = ()) -> None:
        """Take over an earlier incarnation's :meth:`state` and the frames its journal
        recorded after that state was saved."""
        self.seen = FrameSet.from_state(state.get("seen"), HORIZON)
        self.done = FrameSet.from_state(state.get("done"), HORIZON)
        for name in ("items_in", "items_out", "items_dropped", "bad_messages", "last_frame", "newest_out"):
            v = state.get(name)
            if isinstance(v, int):
                setattr(self, name, v)
        for name in ("first_stamp", "first_emit", "last_emit"):
            v = state.get(name)
            if isinstance(v, (int, float)):
                setattr(self, name, float(v))
        self.process_total = float(state.get("process_total") or 0.0)
        self.cpu_carried = float(state.get("cpu_total") or 0.0)
        for kind, frame in journal:
            if kind == "i" and self.seen.add(frame):
                self.items_in += 1
                self.last_frame = max(self.last_frame, frame)
            elif kind == "o" and self.done.add(frame):
                self.items_out += 1
                self.newest_out = max(self.newest_out, frame)

    def bad_message(self) -> None:
        self.bad_messages += 1

    # -- reading ------------------------------------------------------------------
    def _trim(self, now: float) -> None:
        while self._events and self._events[0][0] < now - WINDOW_S:
            self._events.popleft()
        while self._busy and self._busy[0][0] < now - WINDOW_S:
            self._busy.popleft()

    @staticmethod
    def _span(values: array, final: bool) -> np.ndarray:
        """All values at the end; the latest ``RECENT`` during a run, so the stats sent
        every second cost the same after hours as after minutes."""
        a = np.frombuffer(values, dtype=np.float64) if len(values) else np.zeros(0)
        return a if final else a[-RECENT:]

    def figures(self, final: bool = False, expected: int | None = None, first: int = 0,
                share: tuple[int, int] | None = None) -> dict:
        """The stage's figures now; ``expected`` frames from ``first`` (the source's count)
        turns never-received frames into ``frames_missing``; ``share`` ``(k, n)``: the
        worker takes only the frames with ``frame % n == k`` (:mod:`app.frame_shares`),
        the others are not its missing frames."""
        now = self.clock()
        self._trim(now)
        span = min(WINDOW_S, max(1e-6, now - self.started))
        busy_span = min(span, max(1e-6, now - self.first_in)) if self.first_in is not None else span
        win_in = sum(1 for e in self._events if e[1] == "in")
        win_lat = [e[2] for e in self._events if e[1] == "out"]
        frames_in, frames_out = self.seen.count, self.done.count
        if final:
            dropped = frames_in - frames_out
        else:
            dropped = self.seen.count_below(self.newest_out) - self.done.count_below(self.newest_out)
        mono, cpu = time.monotonic(), time.process_time()
        since = self._cpu_start if final else self._cpu0   # the whole run at the end
        cpu_percent = 100.0 * (cpu - since[1]) / max(1e-6, mono - since[0])
        self._cpu0 = (mono, cpu)
        active = None   # from the first output: the start-up before it (loading, compiling) is not the rate
        if self.first_emit is not None and self.last_emit is not None:
            active = self.last_emit - self.first_emit
        fig = {
            "frames_in": frames_in,
            "frames_out": frames_out,
            "frames_dropped": max(0, dropped),
            "frames_missing": max(0, count_own(share, first, expected) - frames_in)
            if (final and expected is not None) else 0,
            # while running: frames before the newest one received that never arrived
            "frames_lost": max(0, count_own(share, first, self.last_frame + 1 - first) - frames_in) if frames_in else 0,
            "items_in": self.items_in,
            "items_out": self.items_out,
            "items_dropped": self.items_dropped,
            "bad_messages": self.bad_messages,
            "fps_in": round(win_in / span, 3),
            "fps_out": round(len(win_lat) / span, 3),
            # N frames span N-1 frame intervals from the first output to the last
            "fps": round((frames_out - 1) / active, 3) if active and frames_out > 1 else 0.0,
            "latency_ms": percentiles(self._span(self.latency_ms, final)),
            "latency_window_ms": percentiles(win_lat),
            "process_ms": percentiles(self._span(self.process_ms, final)),
            # the share of the window since the first frame arrived: a stage that waited for
            # frames (start-up) is not idle, and must not look less busy than one ahead of it
            "busy": round(min(1.0, sum(b[1] for b in self._busy) / busy_span), 3),
            "busy_total": round(min(1.0, self.process_total / max(1e-6, now - (self.first_in or now))), 3)
            if self.first_in is not None else 0.0,
            "cpu_percent": round(cpu_percent, 1),
            # CPU per frame (every thread of the process, from its first input to its last
            # output; start-up not counted): summed over a stage's workers it shows how well
            # the stage scales out
            "cpu_ms_per_frame": round(self.cpu_total * 1e3 / max(1, frames_in, frames_out), 3),
            "last_frame": self.last_frame,
            "first_stamp": self.first_stamp,
            "first_emit": self.first_emit,
            "last_emit": self.last_emit,
            "elapsed_s": round(now - self.started, 3),
            "pid": os.getpid(),
            "host": os.uname().nodename,
        }
        if final:
            n = 1 if share is None else share[1]
            fig["missing_frames"] = [f for f in self.seen.missing(first, first + (expected or 0), limit=50 * n)
                                     if owns(share, f)][:50]
            fig["dropped_frames"] = [i for i in range(self.seen.base, self.seen.end)
                                     if i in self.seen and i not in self.done][:50]
        return fig


def steady_fps(f: dict, compile_spans) -> float:
    """A stage's rate from its first output to its last, without the time the pipeline
    waited for kernels to compile meanwhile (any stage's: offline, the flow control holds
    every stage while one compiles)."""
    from app.compiles import union_seconds
    n, a, b = f.get("frames_out", 0), f.get("first_emit"), f.get("last_emit")
    if not (isinstance(a, (int, float)) and isinstance(b, (int, float))) or n < 2 or b <= a:
        return float(f.get("fps", 0.0) or 0.0)
    span = (b - a) - union_seconds(compile_spans, a, b)
    return round((n - 1) / span, 3) if span > 0 else float(f.get("fps", 0.0) or 0.0)


def summarise(stages: dict, recording_fps: float, frames: int | None = None, started: float | None = None,
              paced: bool = False) -> dict:
    """The pipeline summary of ``stats.json`` from each worker's last figures.

    ``stages`` maps worker name to ``{"stage", "order", "figures"}``. A stage's
    throughput is the frames it put out over the wall time from its first output to its
    last, less the time spent compiling kernels meanwhile (one-off: a first run compiles,
    later runs load them). The pipeline's throughput is that of its last processing stage
    (``final_stage``): the frames delivered at the end of the pipeline, so a frame
    dropped or lost anywhere before counts against it; its real-time factor is
    ``RTF = fps / f_R`` (thesis Eq. 4.27). ``bottleneck`` names the slowest stage. The
    start-up is reported apart (``startup``): from ``started`` (the run's start, wall
    clock) to the first frame delivered, each worker's set-up (tables, background models)
    and the kernels' compile time; ``rtf_with_startup`` is the frames delivered over the
    whole run's time, start-up included. ``paced``: the source sent frames at the
    recording's rate (live cameras, a paced recording): a source held during a compile
    catches up afterwards, so the span less the compile can be shorter than the frames'
    own time; the RTF of a paced run is at most 1 then.
    """
    compile_spans = [span for s in stages.values() for span in (s["figures"].get("compile_spans") or [])
                     if isinstance(span, list) and len(span) == 2]
    per_stage = {}
    for name, s in stages.items():
        f = s["figures"]
        if s.get("order") is None and not f.get("frames_in"):
            continue  # a sink that handles no frames (monitor, viewer) is not a stage
        per_stage[name] = {
            "stage": s.get("stage", name),
            "order": s.get("order"),
            "frames_in": f.get("frames_in", 0),
            "frames_out": f.get("frames_out", 0),
            "frames_dropped": f.get("frames_dropped", 0),
            "frames_missing": f.get("frames_missing", 0),
            "latency_mean_ms": f.get("latency_ms", {}).get("mean", 0.0),
            "latency_p50_ms": f.get("latency_ms", {}).get("p50", 0.0),
            "latency_p95_ms": f.get("latency_ms", {}).get("p95", 0.0),
            "process_mean_ms": f.get("process_ms", {}).get("mean", 0.0),
            "process_p95_ms": f.get("process_ms", {}).get("p95", 0.0),
            "fps": steady_fps(f, compile_spans),
            "cpu_percent": f.get("cpu_percent", 0.0),
            "cpu_ms_per_frame": f.get("cpu_ms_per_frame", 0.0),
            "bad_messages": f.get("bad_messages", 0),
            "setup_s": f.get("setup_s"),
            "compile_s": f.get("compile_s", 0.0),
            "final": bool(s.get("final", False)),
        }
        if isinstance(f.get("frame_share"), list):   # one of n workers taking the frames in turn
            per_stage[name]["frame_share"] = f["frame_share"]
    out = {"recording_fps": recording_fps, "frames": frames, "stages": per_stage}
    procs = [n for n, s in per_stage.items() if s["order"] is not None]
    if procs:
        def rate(n):   # a worker taking one frame in k carries k times its own rate
            share = per_stage[n].get("frame_share")
            return per_stage[n]["fps"] * (share[1] if share else 1)
        slowest = min(procs, key=lambda n: (rate(n), -per_stage[n]["order"]))
        deepest = max(procs, key=lambda n: per_stage[n]["order"])
        fps = per_stage[deepest]["fps"]
        delivered = per_stage[deepest]["frames_out"]
        last = stages[deepest]["figures"]
        out.update({
            "final_stage": deepest,
            "bottleneck": slowest,
            "fps": fps,
            # frames delivered at the end of the pipeline, over the frames the source sent
            "frames_delivered": delivered,
            "delivered_ratio": round(delivered / frames, 4) if frames else None,
            "rtf": (round(min(fps / recording_fps, 1.0) if paced else fps / recording_fps, 4)
                    if recording_fps else None),
            "end_to_end_latency_ms": last.get("latency_ms", {}),
        })
        first, end = last.get("first_emit"), last.get("last_emit")
        if started is not None and isinstance(first, (int, float)):
            from app.compiles import union_seconds
            out["startup"] = {
                "s": round(first - started, 3),   # from the run's start to the first frame delivered
                "setup_s": {n: s["figures"]["setup_s"] for n, s in sorted(stages.items())
                            if isinstance(s["figures"].get("setup_s"), (int, float))},
                "compile_s": round(union_seconds(compile_spans, started, float("inf")), 3),
                "compile_after_first_frame_s": round(union_seconds(compile_spans, first, end), 3)
                if isinstance(end, (int, float)) else 0.0,
            }
            if recording_fps and isinstance(end, (int, float)) and end > started and delivered:
                out["rtf_with_startup"] = round(delivered / (end - started) / recording_fps, 4)
    return out
