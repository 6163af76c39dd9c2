"""Real-time-factor monitor: every worker's stats, live in the terminal.

On a terminal (``--headless`` or not) it redraws a table once a second (one row per
stage, the pipeline RTF against 1.0 with a verdict, the bottleneck). When its output is
not a terminal (a kiosk, the systemd journal, a file) it prints short lines instead,
every ``line_period`` seconds: one for the pipeline (``monitor: rtf=.. verdict=..``) and
one per stage (``monitor: pose: in=.. out=.. p50=..ms ...``).
"""
from __future__ import annotations

import sys
import time

from app.messages import Stats
from app.monitor import PipelineView
from workers.base import Worker


class Monitor(Worker):
    KIND = "monitor"
    CONSUMES = ("stats",)
    DEFAULTS = {
        "period": 1.0,         # seconds between redraws of the table (a terminal)
        "line_period": 10.0,   # seconds between the lines (not a terminal: a journal, a file)
        "mode": "auto",        # auto (the table on a terminal, lines otherwise), table, or lines
    }
    RANGES = {"period": (0.05, 3600.0), "line_period": (0.05, 86400.0)}
    CHOICES = {"mode": ("auto", "table", "lines")}

    def setup(self) -> None:
        self.view = PipelineView(self.layout.run.fps)
        mode = self.params["mode"]
        if mode == "auto":
            mode = "table" if sys.stdout.isatty() else "lines"
        self.mode = mode
        self.every = self.params["period"] if mode == "table" else self.params["line_period"]
        self._next = time.monotonic() + self.every

    def on_stats(self, msg: Stats) -> None:
        self.view.update(msg)

    def tick(self) -> None:
        now = time.monotonic()
        if now >= self._next:
            self._next = now + self.every
            self.show()

    def show(self) -> None:
        if self.mode == "table":
            sys.stdout.write("\x1b[H\x1b[2J" + self.view.table() + "\n")
        else:
            sys.stdout.write("".join(f"monitor: {ln}\n" for ln in [self.view.line(), *self.view.stage_lines()]))
        sys.stdout.flush()

    def flush(self) -> None:
        self.show()
