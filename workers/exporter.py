"""Exporter: writes the captured people as BVH / C3D / TRC / CSV while the run goes on
(a sink of ``poses``; the formats are :mod:`app.export`'s, the live bookkeeping is
:class:`app.export.live.LiveExport`).

Parameters: ``formats`` (any of bvh, c3d, trc, csv), ``out`` (a folder, relative to the
run's results folder unless absolute), ``up`` ("" for each format's default, "y"
for OpenSim-style y-up, "z" for the room's own axes; BVH is always y-up) and
``min_frames`` (tracks reported in fewer frames are left out; -1, the default, is one
second of frames, as ``smartroom export``; 0 keeps every track). The files are
complete, with their final names, only once the run's input has ended; meanwhile the
TRC and CSV files grow as readable ``.partial`` prefixes.
"""
from __future__ import annotations

import time
from pathlib import Path

from app.errors import InputError
from app.export import FORMATS
from app.messages import Poses
from app.pose_shares import SharedPoses
from workers import producers_of
from workers.base import Worker

FLUSH_PERIOD_S = 0.5


class Exporter(Worker):
    KIND = "exporter"
    CONSUMES = ("poses",)
    ACCEPTS = (Poses,)
    INBOX_DEPTH = 1000   # keep results rather than drop them (bounded all the same)
    DEFAULTS = {
        "formats": list(FORMATS),   # which files to write
        "out": "export",            # folder, relative to the results folder unless absolute
        "up": "",                   # "" per-format default (TRC y-up, C3D/CSV z-up), or "y" / "z"
        "min_frames": -1,           # tracks reported in fewer frames are left out (-1: 1 s of frames; 0: none)
    }
    CHOICES = {"up": ("", "y", "z")}
    RANGES = {"min_frames": (-1, 1 << 40)}

    @classmethod
    def acknowledges(cls, spec, layout) -> bool:
        """Offline, the source waits for the exporter too (like the recorder: exported
        results are never dropped), when the layout has a stage that produces poses."""
        return bool(producers_of(layout, "poses"))

    def setup(self) -> None:
        from app.export.live import LiveExport
        formats = self.params["formats"]
        bad = [f for f in formats if f not in FORMATS]
        if bad or not formats:
            raise InputError(f"exporter {self.name}: formats must be some of {', '.join(FORMATS)}, got {formats!r}")
        if self.params["up"] not in ("", "y", "z"):
            raise InputError(f"exporter {self.name}: up must be y, z or empty, got {self.params['up']!r}")
        if "c3d" in formats:
            from app.export.c3d import ezc3d_module
            ezc3d_module()
        folder = Path(self.params["out"])
        if not folder.is_absolute():
            if not self.layout.run.out:
                raise InputError(f"exporter {self.name}: a relative out folder needs the run's --out")
            folder = Path(self.layout.run.out) / folder
        fps = self.layout.run.fps
        if not fps:
            raise InputError(f"exporter {self.name}: the run has no frame rate")
        resume = getattr(self, "incarnation", 0) > 0
        self.export = LiveExport(folder, formats, fps, self.params["up"], resume=resume)
        self.shares = SharedPoses(producers_of(self.layout, "poses"))
        self._flushed = time.monotonic()

    def handle(self, key: str, msg: Poses) -> None:
        for joined in self.shares.add(msg):   # several pose workers: one record a frame
            self._add(joined)

    def _add(self, msg: Poses) -> None:
        from app.export.poses import pose_record
        self.export.add(pose_record(msg.frame, msg.t, msg.tracks, msg.joints, msg.active))
        self.ledger.emitted(msg.frame, msg.stamp)

    def tick(self) -> None:
        if hasattr(self, "export") and time.monotonic() - self._flushed >= FLUSH_PERIOD_S:
            self.export.flush()
            self._flushed = time.monotonic()

    def close(self) -> None:
        if not hasattr(self, "export"):
            return
        if getattr(self, "input_ended", True):   # the true end of the run: complete the files
            for joined in self.shares.flush():
                self._add(joined)
            from app.export.poses import default_min_frames, short_tracks_line
            n = self.params["min_frames"]
            n = default_min_frames(self.export.fps) if n < 0 else n
            paths, short = self.export.finish(n)
            if short:
                self.log.info("%s (min_frames)", short_tracks_line(short, n))
            self.log.info("exported %d file(s) to %s", len(paths), self.export.folder)
        else:                                    # stopped early: a restart carries on
            self.export.abandon()
