"""Text reports of a run: the progress line while it runs, the summary table at the end."""
from __future__ import annotations

import sys
import time

__all__ = ["Progress", "summary_table"]


def _deepest(stats: dict):
    """The last processing stage: its output counts the frames done."""
    procs = [s for s in stats.values() if s.figures.get("order") is not None]
    return max(procs, key=lambda s: s.figures["order"]) if procs else None


class Progress:
    """Frames done, rate and eta from the workers' stats; a live line on a terminal,
    one line every ``period`` seconds otherwise (journal friendly)."""

    def __init__(self, total: int | None, fps: float, stream=sys.stderr, period: float = 10.0):
        self.total, self.fps, self.stream = total, fps, stream
        self.tty = stream.isatty()
        self.period = 0.5 if self.tty else period
        self.last = 0.0
        self.t0 = time.monotonic()
        self.shown = False

    def update(self, stats: dict) -> None:
        now = time.monotonic()
        if now - self.last < self.period:
            return
        s = _deepest(stats)
        if s is None:
            return
        f = s.figures
        done = f.get("frames_out", 0)
        if not done and not self.tty:
            return   # nothing through yet: a line of zeros says nothing (a journal keeps it)
        self.last = now
        rate = f.get("fps_out", 0.0)
        parts = [f"{s.stage}: frame {done}" + (f"/{self.total}" if self.total else "")]
        if self.total:
            parts[0] += f" ({100.0 * done / max(1, self.total):.0f}%)"
        starting = [f"{n}: {st.figures['status']}" for n, st in sorted(stats.items())
                    if isinstance(st.figures.get("status"), str)]
        if starting:   # a stage loading or compiling: no rate yet to speak of
            parts.append("starting: " + "; ".join(starting))
        else:
            parts.append(f"{rate:.1f} fps")
            if self.fps:
                parts.append(f"RTF {rate / self.fps:.2f}")
            if self.total and rate > 0:
                parts.append(f"eta {max(0.0, (self.total - done) / rate):.0f} s")
        line = " | ".join(parts)
        if self.tty:
            self.stream.write("\r" + line.ljust(78)[:120])
            self.shown = True
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.shown:
            self.stream.write("\n")
            self.stream.flush()


def summary_table(summary: dict) -> str:
    """The per-stage table of ``stats.json`` and the pipeline verdict."""
    stages = summary.get("stages", {})
    rows = sorted(stages.items(), key=lambda kv: (kv[1].get("order") is None, kv[1].get("order") or 0, kv[0]))
    head = f"{'stage':<16}{'in':>7}{'out':>7}{'drop':>6}{'miss':>6}{'fps':>8}{'lat p50':>10}{'lat p95':>10}{'proc':>9}{'cpu%':>7}"
    lines = [head, "-" * len(head)]
    for name, s in rows:   # milliseconds written "ms", as in the monitor's live table
        lines.append(f"{name:<16}{s['frames_in']:>7}{s['frames_out']:>7}{s['frames_dropped']:>6}"
                     f"{s.get('frames_missing', 0):>6}{s['fps']:>8.1f}{s['latency_p50_ms']:>8.1f}ms"
                     f"{s['latency_p95_ms']:>8.1f}ms{s.get('process_mean_ms', 0.0):>7.1f}ms{s.get('cpu_percent', 0.0):>7.0f}")
    rtf = summary.get("rtf")
    if rtf is not None:
        verdict = "real time" if rtf >= 0.95 else "slower than real time"
        lat = summary.get("end_to_end_latency_ms", {})
        lines.append(f"pipeline: {summary.get('fps', 0.0):.1f} fps over a {summary.get('recording_fps', 0):g} fps "
                     f"recording, RTF {rtf:.2f} ({verdict}); end-to-end latency p50 {lat.get('p50', 0):.0f} ms, "
                     f"p95 {lat.get('p95', 0):.0f} ms")
    start = summary.get("startup")
    if start:
        setup = max((start.get("setup_s") or {}).values(), default=0.0)
        text = f"start-up: {start['s']:.1f} s to the first frame delivered (set-up up to {setup:.1f} s"
        if start.get("compile_s"):
            text += f", kernels compiled {start['compile_s']:.1f} s: a first run only"
        text += ")"
        if summary.get("rtf_with_startup") is not None:
            text += f"; RTF {summary['rtf_with_startup']:.2f} with it"
        lines.append(text)
    return "\n".join(lines)
