"""The real-time-factor monitor's core: the pipeline as the workers' stats describe it.

Per stage: frames per second in and out, latency from capture (p50/p95 over the last
seconds), drops, CPU use and how busy the stage is (fraction of wall time spent
processing). For the pipeline: the real-time factor ``RTF = fps / f_R`` (thesis
Eq. 4.27) of its deepest stage against the target 1.0, and the bottleneck: the
stage that is busiest (a stage near 100 % busy cannot take more frames).

A stage whose stats stopped coming (for :data:`SILENT_S`, not ended, not compiling) is
**silent**: its last rates are not repeated as if it still ran (they count as 0, so the
RTF says the pipeline stands still and the silent stage is the bottleneck), and every
output (the table, the journal lines) says so.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

from app.messages import Stats

__all__ = ["StageRow", "PipelineView", "REAL_TIME"]

REAL_TIME = 0.95   # RTF at or above this counts as keeping up
SILENT_S = 3.0     # a worker whose stats are older than this is marked silent
COMPILE_SETTLE_S = 2.5   # after a stage's kernel compile, until its rates (2 s windows) are of frames again


def _compiled_ago(figures: dict, now: float) -> float | None:
    """Seconds since the worker's last kernel compile ended (0 while it compiles), or None."""
    if figures.get("compiling"):
        return 0.0
    spans = figures.get("compile_spans") or []
    try:
        return max(0.0, now - float(spans[-1][1])) if spans else None
    except (TypeError, ValueError, IndexError):
        return None


@dataclass
class StageRow:
    name: str
    stage: str
    order: int | None
    fps_in: float
    fps_out: float
    latency_p50: float
    latency_p95: float
    dropped: int
    missing: int
    cpu: float
    busy: float
    final: bool
    age_s: float
    frames_out: int = 0   # put out since the stage started
    compiled_ago_s: float | None = None   # since its last kernel compile ended (0: compiling now)
    shares: int = 1       # one of this many workers taking the frames in turn (app.frame_shares)

    @property
    def stage_fps(self) -> float:
        """The rate of the stage it is part of (a worker taking one frame in n: n times its own)."""
        return self.fps_out * self.shares

    @property
    def processing(self) -> bool:
        return self.order is not None

    @property
    def silent(self) -> bool:
        """No stats for :data:`SILENT_S` from a stage that has not ended and is not compiling."""
        return not self.final and self.age_s > SILENT_S and self.compiled_ago_s != 0.0


class PipelineView:
    """Latest stats of every worker, and what they say about the pipeline."""

    def __init__(self, recording_fps: float | None = None, clock=time.time):
        self.recording_fps = recording_fps
        self.clock = clock
        self._stats: dict[str, tuple[float, Stats]] = {}
        self._lock = threading.Lock()

    def update(self, msg: Stats) -> None:
        with self._lock:
            self._stats[msg.worker] = (self.clock(), msg)
            fps = msg.figures.get("fps_recording")
            if fps:
                self.recording_fps = fps

    def rows(self) -> list[StageRow]:
        from app.stats import steady_fps
        now = self.clock()
        with self._lock:
            items = list(self._stats.items())
        compiles = [span for _, (_, msg) in items for span in (msg.figures.get("compile_spans") or [])]
        rows = []
        for name, (seen, msg) in items:
            f = msg.figures
            lat = f.get("latency_window_ms") or {}
            if msg.final or not lat.get("p50"):
                lat = f.get("latency_ms") or {}
            final = msg.final
            rows.append(StageRow(
                name=name, stage=msg.stage, order=f.get("order"),
                # a stage that ended: its rate over its run, as stats.json says it (compiles left out)
                fps_in=steady_fps(f, compiles) if final else f.get("fps_in", 0.0),
                fps_out=steady_fps(f, compiles) if final else f.get("fps_out", 0.0),
                latency_p50=lat.get("p50", 0.0), latency_p95=lat.get("p95", 0.0),
                dropped=f.get("frames_dropped", 0),
                missing=f.get("frames_missing", 0) if final else f.get("frames_lost", 0),
                cpu=f.get("cpu_percent", 0.0), busy=f.get("busy_total" if final else "busy", 0.0),
                final=final, age_s=now - seen, frames_out=int(f.get("frames_out", 0) or 0),
                compiled_ago_s=_compiled_ago(f, now),
                shares=int(f["frame_share"][1]) if isinstance(f.get("frame_share"), list) else 1))
            if rows[-1].silent:   # its last figures are old: it does not run at them now
                rows[-1].fps_in = rows[-1].fps_out = 0.0
        rows.sort(key=lambda r: (r.order is None, r.order or 0, r.name))
        return rows

    @staticmethod
    def shown(rows: list[StageRow]) -> list[StageRow]:
        """Processing stages, and sinks only once they handle frames (the recorder)."""
        return [r for r in rows if r.processing or r.fps_in > 0]

    def limiting(self, rows=None) -> StageRow | None:
        """The processing stage with the lowest output rate (ties: the deepest)."""
        procs = [r for r in (rows if rows is not None else self.rows()) if r.processing]
        return min(procs, key=lambda r: (r.stage_fps, -r.order)) if procs else None

    def rtf(self, rows=None) -> float | None:
        """None while no frame has gone through yet (start-up: "waiting")."""
        rows = rows if rows is not None else self.rows()
        last = self.limiting(rows)
        if last is None or not self.recording_fps:
            return None
        # start-up lasts until every stage has put out its first frame (a stage still loading
        # its kernels on its first frame is not the bottleneck of a running pipeline), and
        # while a stage compiles kernels, until its rates are of frames after the compile
        if not all(r.fps_out > 0 or r.frames_out > 0 or r.final for r in rows if r.processing):
            return None
        if any(r.compiled_ago_s is not None and r.compiled_ago_s < COMPILE_SETTLE_S and not r.final
               for r in rows if r.processing):
            return None
        return last.stage_fps / self.recording_fps

    def bottleneck(self, rows=None) -> StageRow | None:
        """The busiest processing stage (ties: the one that drops more, then the one that puts
        out fewer frames: of two stages working flat out, the slower holds the pipeline)."""
        procs = [r for r in (rows if rows is not None else self.rows()) if r.processing]
        if not procs:
            return None
        return max(procs, key=lambda r: (r.silent, round(r.busy, 2), r.dropped, -r.stage_fps))

    def tracks(self) -> int | None:
        """People tracked now (the ``tracks`` figure of the tracking stage), or None."""
        with self._lock:
            counts = [msg.figures["tracks"] for _, msg in self._stats.values() if "tracks" in msg.figures]
        return int(max(counts)) if counts else None

    def urls(self) -> list[str]:
        """Pages the workers serve (the viewer's ``url`` figure), so the table keeps them on screen."""
        with self._lock:
            items = sorted(self._stats.items())
        return [f"{name}: {msg.figures['url']}" for name, (_, msg) in items
                if isinstance(msg.figures.get("url"), str) and msg.figures["url"]]

    def statuses(self) -> list[str]:
        """What workers say they are doing before frames flow (compiling, building a background)."""
        with self._lock:
            items = sorted(self._stats.items())
        return [f"{name}: {msg.figures['status']}" for name, (_, msg) in items
                if isinstance(msg.figures.get("status"), str)]

    def late_views(self) -> dict:
        """Views given up on per camera (live reconstruction), all stages together."""
        late: dict[str, int] = {}
        with self._lock:
            for _, msg in self._stats.values():
                for cam, n in (msg.figures.get("late_views") or {}).items():
                    if isinstance(n, int):
                        late[cam] = late.get(cam, 0) + n
        return late

    def verdict(self, rtf: float | None) -> str:
        if rtf is None:
            return "waiting"
        return "real-time" if rtf >= REAL_TIME else f"behind ({100 * rtf:.0f}% of real time)"

    def line(self) -> str:
        """The pipeline in one short journal line: ``rtf=.. verdict=.. bottleneck=.. busy=..
        tracks=..`` (the stages' own lines are :meth:`stage_lines`)."""
        rows = self.rows()
        rtf = self.rtf(rows)
        neck = self.bottleneck(rows)
        head = [f"rtf={rtf:.2f}" if rtf is not None else "rtf=-", f"verdict={self.verdict(rtf).split(' ')[0]}"]
        if neck is not None and rtf is not None:
            head.append(f"bottleneck={neck.name} busy={neck.busy:.2f}")
        silent = [r for r in rows if r.silent and (r.processing or r.frames_out)]
        if silent:
            head.append("silent=" + ",".join(f"{r.name}:{r.age_s:.0f}s" for r in silent))
        if self.tracks() is not None:
            head.append(f"tracks={self.tracks()}")
        late = self.late_views()
        if late:
            head.append("late=" + ",".join(f"{c}:{n}" for c, n in sorted(late.items())))
        statuses = self.statuses() if rtf is None else []
        if statuses:
            head.append("starting=" + ",".join(s.split(":", 1)[0] for s in statuses))
        return " ".join(head)

    def stage_lines(self) -> list[str]:
        """One short line per stage (rates, latency, drops, CPU, busy), then what the
        starting workers are doing, in words."""
        rows = self.rows()
        lines = [f"{r.name}: in={r.fps_in:.1f} out={r.fps_out:.1f} p50={r.latency_p50:.0f}ms p95={r.latency_p95:.0f}ms "
                 f"drop={r.dropped} lost={r.missing} cpu={r.cpu:.0f}% busy={r.busy:.2f}"
                 + (f" silent={r.age_s:.0f}s" if r.silent else "") for r in self.shown(rows)]
        return lines + (self.statuses() if self.rtf(rows) is None else [])

    def table(self) -> str:
        """The live terminal view."""
        rows = self.rows()
        rtf = self.rtf(rows)
        neck = self.bottleneck(rows)
        fps = f"{self.recording_fps:g} fps recording" if self.recording_fps else "recording fps unknown"
        head = f"smartroom monitor | {fps} | RTF {rtf:.2f} (target 1.00): {self.verdict(rtf).upper()}" \
            if rtf is not None else f"smartroom monitor | {fps} | waiting for stages"
        lines = [head]
        lines += [f"view  {u}" for u in self.urls()]
        lines += [f"SILENT: {r.name}: no stats for {r.age_s:.0f} s" for r in rows
                  if r.silent and (r.processing or r.frames_out)]
        if neck is not None and rtf is not None:
            lines.append(f"bottleneck: {neck.name} (busy {100 * neck.busy:.0f}%, {neck.dropped} frames dropped)")
        tracked = self.tracks()
        if tracked is not None:
            lines.append(f"people tracked: {tracked}")
        late = self.late_views()
        if late:
            lines.append("late views given up: " + ", ".join(f"{c} {n}" for c, n in sorted(late.items())))
        if rtf is None:
            lines += [f"starting  {s}" for s in self.statuses()]
        cols = (f"{'stage':<16}{'fps in':>8}{'fps out':>9}{'lat p50':>9}{'lat p95':>9}{'drops':>7}{'lost':>6}"
                f"{'cpu %':>7}{'busy':>6}")
        lines += ["", cols, "-" * len(cols)]
        for r in self.shown(rows):
            mark = " (ended)" if r.final else (f" (silent {r.age_s:.0f} s)" if r.silent else "")
            lines.append(f"{r.name:<16}{r.fps_in:>8.1f}{r.fps_out:>9.1f}{r.latency_p50:>7.1f}ms{r.latency_p95:>7.1f}ms"
                         f"{r.dropped:>7}{r.missing:>6}{r.cpu:>7.0f}{100 * r.busy:>5.0f}%{mark}")
        return "\n".join(lines)
