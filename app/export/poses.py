"""The captured people of a run as arrays: ``poses.jsonl`` (CONTRACT §2) read into one
:class:`TrackPoses` per track, and the frame rate of the run.

Every exporter works from these arrays, so the live exporter (which builds the same
records from the bus) and ``smartroom export`` (which reads them from the file) write
the same bytes.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.errors import InputError
from app.files import read_jsonl, read_yaml
from app.messages import JOINTS

__all__ = ["TrackPoses", "PoseSeries", "pose_record", "series_from_records", "load_poses", "results_fps",
           "default_min_frames", "short_tracks_line"]

DECIMALS = 4  # metres: 0.1 mm, as the recorder writes poses.jsonl


def _r(v) -> list:
    return [round(float(x), DECIMALS) for x in v]


def pose_record(frame: int, t: float, tracks, joints, active) -> dict:
    """One ``poses.jsonl`` object (CONTRACT §2) from the arrays of a Poses message."""
    return {"frame": int(frame), "t": round(float(t), 4), "poses": [
        {"track": int(track),
         "joints": {j: _r(joints[k, n]) for n, j in enumerate(JOINTS)},
         "active": {j: bool(active[k, n]) for n, j in enumerate(JOINTS)}}
        for k, track in enumerate(tracks)]}


@dataclass
class TrackPoses:
    """One person over frames ``first .. first + len(joints) - 1`` (contiguous).

    ``joints`` (F, 15, 3) metres in :data:`JOINTS` order, ``active`` (F, 15); frames
    where the track is absent (or not processed) have every joint inactive and NaN
    positions.
    """

    track: int
    first: int
    joints: np.ndarray
    active: np.ndarray

    @property
    def frames(self) -> np.ndarray:
        return self.first + np.arange(len(self.joints))


@dataclass
class PoseSeries:
    """Every track of a run and the frame range ``first .. last`` the run's records cover."""

    fps: float
    first: int
    last: int
    tracks: dict[int, TrackPoses]

    @property
    def count(self) -> int:
        return self.last - self.first + 1 if self.last >= self.first else 0

    def lengths(self) -> dict[int, int]:
        """Frames each track was reported in."""
        return {k: int(np.isfinite(tp.joints[:, 0, 0]).sum()) for k, tp in self.tracks.items()}

    def without_short(self, min_frames: int) -> tuple["PoseSeries", dict[int, int]]:
        """The series without the tracks reported in fewer than ``min_frames`` frames (a
        tracker's brief false starts: a shadow, two people merging and parting), and the
        tracks left out with their lengths. The run's frame range stays."""
        lengths = self.lengths()
        short = {k: n for k, n in sorted(lengths.items()) if n < min_frames}
        kept = {k: tp for k, tp in self.tracks.items() if k not in short}
        return PoseSeries(self.fps, self.first, self.last, kept), short

    def select(self, track: int | None) -> "PoseSeries":
        if track is None:
            return self
        if track not in self.tracks:
            known = ", ".join(map(str, sorted(self.tracks))) or "none"
            raise InputError(f"track {track} is not in the results (tracks: {known})")
        return PoseSeries(self.fps, self.first, self.last, {track: self.tracks[track]})


def default_min_frames(fps: float) -> int:
    """The shortest track exported by default: about one second of frames."""
    return max(1, int(round(fps)))


def short_tracks_line(short: dict[int, int], min_frames: int) -> str:
    """The one line that says which tracks were left out as too short."""
    which = ", ".join(f"{k} ({n} frame{'s' if n != 1 else ''})" for k, n in short.items())
    return (f"left out {len(short)} track{'s' if len(short) != 1 else ''} of fewer than {min_frames} frames: "
            f"{which}")


def _check_record(rec, where: str) -> None:
    if not isinstance(rec, dict) or not isinstance(rec.get("frame"), int) or not isinstance(rec.get("poses"), list):
        raise InputError(f"{where}: expected {{frame, t, poses: [...]}}")
    for p in rec["poses"]:
        if not isinstance(p, dict) or not isinstance(p.get("track"), int) or not isinstance(p.get("joints"), dict):
            raise InputError(f"{where}: a pose needs track (integer) and joints")
        missing = [j for j in JOINTS if j not in p["joints"]]
        if missing:
            raise InputError(f"{where}: track {p['track']} lacks joint {missing[0]!r}")
        for j in JOINTS:
            v = p["joints"][j]
            if not (isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) for x in v)):
                raise InputError(f"{where}: track {p['track']} joint {j!r} is not [x, y, z]")


def series_from_records(records: list[dict], fps: float, where: str = "poses") -> PoseSeries:
    """Arrays from ``poses.jsonl`` objects (any order; a repeated frame keeps its last record)."""
    by_frame: dict[int, dict] = {}
    for n, rec in enumerate(records):
        _check_record(rec, f"{where}: record {n + 1}")
        by_frame[rec["frame"]] = rec
    if not by_frame:
        return PoseSeries(fps, 0, -1, {})
    first, last = min(by_frame), max(by_frame)
    spans: dict[int, list[int]] = {}
    for f, rec in by_frame.items():
        for p in rec["poses"]:
            s = spans.setdefault(p["track"], [f, f])
            s[0], s[1] = min(s[0], f), max(s[1], f)
    tracks = {}
    for k, (a, b) in sorted(spans.items()):
        n = b - a + 1
        tracks[k] = TrackPoses(k, a, np.full((n, len(JOINTS), 3), np.nan), np.zeros((n, len(JOINTS)), bool))
    for f, rec in by_frame.items():
        for p in rec["poses"]:
            tp = tracks[p["track"]]
            i = f - tp.first
            tp.joints[i] = [p["joints"][j] for j in JOINTS]
            act = p.get("active") or {}
            tp.active[i] = [bool(act.get(j, True)) for j in JOINTS]
    return PoseSeries(float(fps), first, last, tracks)


def results_fps(results) -> float:
    """The recording's frame rate for a results folder: the run section of its
    ``layout.yaml``, else ``stats.json``, else the recording's ``calibration.yaml``."""
    results = Path(results)
    layout = results / "layout.yaml"
    run = {}
    if layout.is_file():
        data = read_yaml(layout, "layout") or {}
        run = data.get("run") or {} if isinstance(data, dict) else {}
        if isinstance(run.get("fps"), (int, float)) and run["fps"] > 0:
            return float(run["fps"])
    stats = results / "stats.json"
    if stats.is_file():
        try:
            fps = json.loads(stats.read_text()).get("recording_fps")
        except (ValueError, AttributeError):
            fps = None
        if isinstance(fps, (int, float)) and fps > 0:
            return float(fps)
    for calib in ([Path(run["recording"]) / "calibration.yaml"] if run.get("recording") else []) + \
            ([Path(run["calibration"])] if run.get("calibration") else []):
        if calib.is_file():
            fps = (read_yaml(calib, "calibration") or {}).get("fps")
            if isinstance(fps, (int, float)) and fps > 0:
                return float(fps)
    raise InputError(f"{results}: no frame rate found (layout.yaml run.fps, stats.json or the recording's "
                     "calibration); "
                     "give --fps")


def load_poses(results, fps: float | None = None) -> PoseSeries:
    """``RESULTS/poses.jsonl`` (or a poses.jsonl file itself) as arrays."""
    path = Path(results)
    folder = path.parent if path.suffix == ".jsonl" else path
    file = path if path.suffix == ".jsonl" else path / "poses.jsonl"
    if not folder.is_dir():
        raise InputError(f"{folder}: results folder not found")
    if not file.is_file():
        raise InputError(f"{file}: not found (the run had no pose stage?)")
    if fps is None:
        fps = results_fps(folder)
    elif fps <= 0:
        raise InputError(f"--fps must be positive, got {fps}")
    return series_from_records(read_jsonl(file), fps, where=str(file))
