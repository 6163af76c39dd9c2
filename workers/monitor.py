"""Real-time-factor monitor: every worker's stats, live in the terminal.

On a terminal it redraws a table once a second (one row per stage, the pipeline RTF
against 1.0 with a verdict, the bottleneck). With ``--headless`` or when its output
is not a terminal it prints one line per second instead (kiosk / systemd journal).
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
        "period": 1.0,     # seconds between updates
        "mode": "auto",    # auto (table on a terminal unless --headless), table, or lines
    }
    RANGES = {"period": (0.05, 3600.0)}
    CHOICES = {"mode": ("auto", "table", "lines")}

    def setup(self) -> None:
        self.view = PipelineView(self.layout.run.fps)
        mode = self.params["mode"]
        if mode == "auto":
            mode = "table" if sys.stdout.isatty() and not self.layout.run.headless else "lines"
        self.mode = mode
        self._next = time.monotonic() + self.params["period"]

    def on_stats(self, msg: Stats) -> None:
        self.view.update(msg)

    def tick(self) -> None:
        now = time.monotonic()
        if now >= self._next:
            self._next = now + self.params["period"]
            self.show()

    def show(self) -> None:
        if self.mode == "table":
            sys.stdout.write("\x1b[H\x1b[2J" + self.view.table() + "\n")
        else:
            sys.stdout.write("monitor: " + self.view.line() + "\n")
        sys.stdout.flush()

    def flush(self) -> None:
        self.show()
