"""Recorder: writes the contract's result files (CONTRACT §2).

``tracks.jsonl`` and ``poses.jsonl`` are written line by line into ``.partial`` files
and renamed when the run ends (in frame order); a file exists only when the layout
has a stage that produces it. ``stats.json`` is rewritten atomically (write, then
rename) once a second and completed at the end with every stage's final figures and
the pipeline real-time factor. With ``voxels: true`` the reconstruction is kept too,
in ``voxels.bin`` (see :mod:`app.results`), for evaluation and replay.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

from app.files import partial_path, write_json
from app.messages import JOINTS, Poses, Stats, Tracks, Voxels
from app.results import VoxelWriter
from app.stats import summarise
from workers import worker_class
from workers.base import Worker


def _r(v, nd=4):
    return [round(float(x), nd) for x in v]


class _JsonLines:
    """Lines written to ``<name>.partial``, renamed (sorted by frame if needed) on close."""

    def __init__(self, path: Path):
        self.path = path
        self.tmp = partial_path(path)
        self.fh = open(self.tmp, "w", encoding="utf-8")
        self.last_frame = -1
        self.ordered = True
        self.lines = 0

    def write(self, frame: int, record: dict) -> None:
        if frame <= self.last_frame:
            self.ordered = False
        self.last_frame = max(self.last_frame, frame)
        self.fh.write(json.dumps(record, separators=(",", ":")) + "\n")
        self.lines += 1

    def close(self) -> None:
        self.fh.close()
        if not self.ordered:
            with open(self.tmp, encoding="utf-8") as fh:
                rows = {json.loads(line)["frame"]: line for line in fh if line.strip()}
            with open(self.tmp, "w", encoding="utf-8") as fh:
                fh.writelines(rows[f] for f in sorted(rows))
        os.replace(self.tmp, self.path)


class Recorder(Worker):
    KIND = "recorder"
    CONSUMES = ("tracks", "poses", "stats")
    ACCEPTS = (Tracks, Poses, Voxels)
    INBOX_DEPTH = 1000   # keep results rather than drop them (bounded all the same)
    DEFAULTS = {
        "voxels": False,   # also keep every frame's voxels in voxels.bin
    }

    def subscriptions(self) -> list[str]:
        keys = super().subscriptions()
        return keys + [self.keys.voxels()] if self.params["voxels"] else keys

    def setup(self) -> None:
        if not self.layout.run.out:
            from app.errors import InputError
            raise InputError("the recorder needs an output folder (--out)")
        self.out = Path(self.layout.run.out)
        self.out.mkdir(parents=True, exist_ok=True)
        produced = {s for w in self.layout.workers for s in worker_class(w.kind).PRODUCES}
        self.tracks = _JsonLines(self.out / "tracks.jsonl") if "tracks" in produced else None
        self.poses = _JsonLines(self.out / "poses.jsonl") if "poses" in produced else None
        self.voxels = VoxelWriter(self.out / "voxels.bin") if self.params["voxels"] and "voxels" in produced else None
        self.stages: dict[str, dict] = {}
        self._last_write = 0.0

    def handle(self, key: str, msg) -> None:
        if isinstance(msg, Tracks) and self.tracks is not None:
            self.tracks.write(msg.frame, {
                "frame": int(msg.frame), "t": round(msg.t, 4),
                "tracks": [{"id": int(i), "position": _r(p)} for i, p in zip(msg.ids, msg.positions)]})
        elif isinstance(msg, Poses) and self.poses is not None:
            poses = []
            for k, track in enumerate(msg.tracks):
                poses.append({
                    "track": int(track),
                    "joints": {j: _r(msg.joints[k, n]) for n, j in enumerate(JOINTS)},
                    "active": {j: bool(msg.active[k, n]) for n, j in enumerate(JOINTS)}})
            self.poses.write(msg.frame, {"frame": int(msg.frame), "t": round(msg.t, 4), "poses": poses})
        elif isinstance(msg, Voxels) and self.voxels is not None:
            self.voxels.write(msg)
        else:
            return
        self.ledger.emitted(msg.frame, msg.stamp)

    def on_stats(self, msg: Stats) -> None:
        if msg.worker == self.name:
            return
        self.stages[msg.worker] = {"stage": msg.stage, "order": msg.figures.get("order"),
                                   "final": msg.final, "figures": msg.figures}
        if time.monotonic() - self._last_write > 1.0:
            self.write_stats()

    def write_stats(self, final: bool = False) -> None:
        frames, _, fps = self.stream_info()
        fps = fps or self.layout.run.fps or 0.0
        summary = summarise(self.stages, fps, frames if self.stream is not None else None)
        summary["complete"] = final
        summary["workers"] = {name: s["figures"] for name, s in self.stages.items()}
        write_json(self.out / "stats.json", summary)
        self._last_write = time.monotonic()

    def close(self) -> None:
        for f in (self.tracks, self.poses, getattr(self, "voxels", None)):
            if f is not None:
                f.close()
        if hasattr(self, "out"):
            self.write_stats(final=True)
