"""Exports written while a run goes on (the core of the ``exporter`` worker; no bus here).

Every pose record (the ``poses.jsonl`` object of a frame) is appended to a journal,
``export.jsonl.partial``, and to readable prefixes of the formats that allow one: the
CSV (``poses.csv.partial``, a header and one row per frame and track) and a TRC per
track (``track<K>.trc.partial``, whose NumFrames is a fixed-width field rewritten in
place as rows are added). At the true end of the run :meth:`LiveExport.finish` writes
every format through :func:`app.export.export_series`, the very function behind
``smartroom export``, from the records, so the live files equal the offline export of
the run's ``poses.jsonl``; each is written as ``.partial`` and renamed, and the journal
is removed; tracks shorter than ``min_frames`` are left out, as by ``smartroom export``.
Until then only ``.partial`` files exist: a run killed mid-way leaves no
file that looks complete. A restarted exporter (``resume``) reads the journal back and
carries on.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from app.export import DEFAULT_UP, FORMATS, export_series
from app.export.csv import csv_header, csv_rows
from app.export.poses import series_from_records
from app.export.trc import trc_header, trc_rows
from app.files import partial_path
from app.messages import JOINTS

__all__ = ["LiveExport", "JOURNAL"]

JOURNAL = "export.jsonl.partial"
COUNT_WIDTH = 10   # characters of the live TRC's NumFrames fields (left-aligned, space-padded)


def _arrays(pose: dict):
    joints = np.array([pose["joints"][j] for j in JOINTS], float)
    act = pose.get("active") or {}
    return joints, np.array([bool(act.get(j, True)) for j in JOINTS])


class _TrcPrefix:
    """One track's growing TRC: header once, rows appended, frame count patched in place."""

    def __init__(self, path: Path, fps: float, first: int, up: str):
        self.fps, self.first, self.next, self.up = fps, first, first, up
        head = trc_header(path.name[:-len(".partial")], fps, first, "0".ljust(COUNT_WIDTH)).encode()
        lines = head.split(b"\n")
        base = len(lines[0]) + len(lines[1]) + 2
        cells = lines[2].split(b"\t")
        starts = np.cumsum([0] + [len(c) + 1 for c in cells])
        self.count_at = [base + int(starts[2]), base + int(starts[7])]   # NumFrames, OrigNumFrames
        self.fh = open(path, "wb")
        self.fh.write(head)
        self.written = 0

    def add(self, frame: int, joints: np.ndarray, active: np.ndarray) -> None:
        if frame < self.next:
            return   # late (out of order): only the final file has it
        gap = np.arange(self.next, frame)
        if len(gap):   # frames the track was absent from: empty cells
            self.fh.write(trc_rows(gap, self.fps, np.full((len(gap), len(JOINTS), 3), np.nan),
                                   np.zeros((len(gap), len(JOINTS)), bool), self.up).encode())
        self.fh.write(trc_rows(np.array([frame]), self.fps, joints[None], active[None], self.up).encode())
        self.next = frame + 1

    def flush(self) -> None:
        count = self.next - self.first
        if count != self.written:
            end = self.fh.tell()
            for at in self.count_at:
                self.fh.seek(at)
                self.fh.write(str(count).ljust(COUNT_WIDTH).encode())
            self.fh.seek(end)
            self.written = count
        self.fh.flush()

    def close(self) -> None:
        self.flush()
        self.fh.close()


class LiveExport:
    """The exports of one run, built up frame by frame (see module docstring)."""

    def __init__(self, folder, formats, fps: float, up: str = "", resume: bool = False):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.formats = [f for f in FORMATS if f in formats]
        self.fps = float(fps)
        self.up = {f: (up if up and f != "bvh" else DEFAULT_UP[f]) for f in FORMATS}
        self.records: dict[int, dict] = {}
        self.trc: dict[int, _TrcPrefix] = {}
        self.csv = None
        self.csv_next = None
        journal = self.folder / JOURNAL
        old = self._read_journal(journal) if resume else []
        self.journal = open(journal, "a" if resume else "w", encoding="utf-8")
        for rec in old:
            self._add(rec)

    @staticmethod
    def _read_journal(path: Path) -> list[dict]:
        out = []
        if path.is_file():
            with open(path, encoding="utf-8") as fh:
                for line in fh:
                    try:
                        out.append(json.loads(line))
                    except json.JSONDecodeError:
                        break   # the line being written when the earlier incarnation died
        return out

    def add(self, record: dict) -> None:
        """One frame's ``poses.jsonl`` record."""
        self.journal.write(json.dumps(record, separators=(",", ":")) + "\n")
        self._add(record)

    def _add(self, record: dict) -> None:
        frame = int(record["frame"])
        self.records[frame] = record
        if "csv" in self.formats:
            if self.csv is None:
                self.csv = open(partial_path(self.folder / "poses.csv"), "w", encoding="utf-8")
                self.csv.write(csv_header())
            if self.csv_next is None or frame >= self.csv_next:
                arrays = [_arrays(p) for p in record["poses"]]
                if arrays:
                    self.csv.write(csv_rows(frame, self.fps, [p["track"] for p in record["poses"]],
                                            np.array([a[0] for a in arrays]), np.array([a[1] for a in arrays]),
                                            self.up["csv"]))
                self.csv_next = frame + 1
        if "trc" in self.formats:
            for pose in record["poses"]:
                k = int(pose["track"])
                if k not in self.trc:
                    self.trc[k] = _TrcPrefix(partial_path(self.folder / f"track{k}.trc"), self.fps, frame,
                                             self.up["trc"])
                self.trc[k].add(frame, *_arrays(pose))

    def flush(self) -> None:
        """Make the prefixes readable up to the newest frame."""
        self.journal.flush()
        if self.csv is not None:
            self.csv.flush()
        for t in self.trc.values():
            t.flush()

    def _close_files(self) -> None:
        self.flush()
        self.journal.close()
        if self.csv is not None:
            self.csv.close()
        for t in self.trc.values():
            t.close()

    def abandon(self) -> None:
        """Stopped before the end (a restart will resume): keep the ``.partial`` files."""
        self._close_files()

    def finish(self, min_frames: int = 0) -> tuple[list[Path], dict[int, int]]:
        """The true end: write every format (``.partial``, then rename) for the tracks of
        ``min_frames`` frames or more; the paths written and the tracks left out (their
        lengths), as ``smartroom export`` does."""
        self._close_files()
        series = series_from_records(list(self.records.values()), self.fps, where=str(self.folder / JOURNAL))
        series, short = series.without_short(min_frames)
        paths = []
        if series.tracks:
            for fmt in self.formats:
                paths += export_series(series, fmt, self.folder, self.up[fmt])
        for stale in [partial_path(self.folder / "poses.csv")] + \
                [partial_path(self.folder / f"track{k}.trc") for k in self.trc]:
            if stale.exists():   # a prefix export_series did not replace (no tracks)
                stale.unlink()
        os.remove(self.folder / JOURNAL)
        return paths, short
