"""A recording folder against its calibration, every problem at once (``smartroom calibrate
check --recording``), and the frame rate its videos carry (``smartroom calibrate import
--recording``).

Opening a :class:`~app.recording.Recording` stops at the first thing that does not fit,
which is right for a run; a check goes on and lists them all, one line each naming the
file and the camera: calibration fields, cameras with no video, videos with no camera,
videos that cannot be read, sizes, frame rates (against the calibration and among the
videos), frame counts, background images.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import cv2

from app.errors import InputError
from app.recording import (FPS_TOLERANCE, IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, RecordingError, SourceInfo,
                           find_source, inspect_source, size_mismatch)
from calibration.validate import Checked, check_calibration

__all__ = ["FolderCheck", "check_recording", "folder_sources", "recording_fps"]


def folder_sources(root: Path) -> dict[str, list[Path]]:
    """Every camera source in a recording folder by name: ``videos/<name>.mp4|.avi`` and
    ``frames/<name>/`` (paths relative to the folder)."""
    out: dict[str, list[Path]] = {}
    videos, frames = root / "videos", root / "frames"
    if videos.is_dir():
        for p in sorted(videos.iterdir()):
            if p.is_file() and p.suffix.lower() in VIDEO_EXTENSIONS:
                out.setdefault(p.stem, []).append(p.relative_to(root))
    if frames.is_dir():
        for p in sorted(frames.iterdir()):
            if p.is_dir():
                out.setdefault(p.name, []).append(p.relative_to(root))
    return out


def _disagree(infos: list[SourceInfo]) -> bool:
    rates = [i.fps for i in infos]
    return max(rates) - min(rates) > FPS_TOLERANCE * min(rates)


def _rates(infos: list[SourceInfo]) -> str:
    return ", ".join(f"{Path(i.shown).name} {i.fps:g}" for i in infos) + " fps"


def recording_fps(path) -> tuple[float, list[str]]:
    """The frame rate of a recording folder's videos, and the videos read.

    Raises :class:`InputError` (one line) when the folder has no videos (image folders
    carry no frame rate), when a video carries none, or when the videos disagree."""
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"{root}: recording folder not found")
    videos = {n: [p for p in ps if p.parts[0] == "videos"] for n, ps in folder_sources(root).items()}
    videos = {n: ps[0] for n, ps in videos.items() if ps}
    if not videos:
        if (root / "frames").is_dir():
            raise InputError(f"{root / 'frames'}: image folders carry no frame rate: give --fps")
        raise InputError(f"{root}: no videos/<camera>.mp4 (or .avi) to take the frame rate from: give --fps")
    try:
        infos = [inspect_source(root, "video", rel, name) for name, rel in videos.items()]
    except RecordingError as e:
        raise InputError(f"{root}: {e}") from None
    unknown = [i.shown for i in infos if not i.fps > 0]
    if unknown:
        raise InputError(f"{root / unknown[0]}: the video carries no frame rate: give --fps")
    if _disagree(infos):
        raise InputError(f"{root / 'videos'}: the videos disagree on their frame rate: {_rates(infos)}; "
                         "give --fps (and convert the others to it)")
    rates = sorted(i.fps for i in infos)
    return round(rates[len(rates) // 2], 3), [i.shown for i in infos]


@dataclass
class FolderCheck:
    """A checked recording: the calibration's usable part, the sources of the cameras that
    have one, and every problem (one line each, naming the file and the camera)."""

    path: Path
    calibration: Checked
    sources: dict[str, SourceInfo] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    sizes_wrong: list[str] = field(default_factory=list)  # cameras whose video is not the calibrated size


def _backgrounds(root: Path, cams: dict) -> list[str]:
    out = []
    folder = root / "background"
    if not folder.is_dir():
        return out
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.suffix.lower() not in IMAGE_EXTENSIONS:
            continue
        shown = p.relative_to(root)
        cam = cams.get(p.stem)
        if p.stem not in cams:
            out.append(f"{shown}: no camera {p.stem} in the calibration (cameras: {', '.join(cams) or 'none'})")
            continue
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            out.append(f"{shown}: cannot be read as an image (camera {p.stem})")
        elif cam is not None and img.shape[:2] != (cam.height, cam.width):
            out.append(f"{shown}: size {img.shape[1]}x{img.shape[0]} does not match calibration "
                       f"{cam.width}x{cam.height} of camera {p.stem}")
    return out


def check_recording(path) -> FolderCheck:
    """Every problem of a recording folder against its calibration. A missing folder or an
    unreadable calibration file raises :class:`InputError` (nothing to check against)."""
    root = Path(path)
    if not root.is_dir():
        raise RecordingError(f"{root}: recording folder not found")
    checked = check_calibration(root / "calibration.yaml")
    out = FolderCheck(root, checked, problems=list(checked.problems))
    usable = {c.name: c for c in checked.cameras}
    named = {n: usable.get(n) for n in checked.names}
    found = folder_sources(root)
    for name, rels in found.items():
        if name not in named:
            for rel in rels:
                out.problems.append(f"{rel}: no camera {name} in the calibration (cameras: "
                                    f"{', '.join(named) or 'none'})")
    for name in named:
        where = find_source(root, name)
        if where is None:
            out.problems.append(f"{root}: camera {name} has no videos/{name}.mp4 (or .avi) and no frames/{name}/ "
                                "folder")
            continue
        try:
            info = inspect_source(root, *where, name)
        except RecordingError as e:
            out.problems.append(f"{e} (camera {name})")
            continue
        if info.count <= 0:
            out.problems.append(f"{info.shown}: holds no frames (camera {name})")
            continue
        out.sources[name] = info
    fps = checked.fps
    for name, info in out.sources.items():
        cam = usable.get(name)
        if cam is None:
            continue
        wrong = size_mismatch(info, cam)
        if wrong:
            out.problems.append(wrong)
            out.sizes_wrong.append(name)
        if fps is not None and info.kind == "video" and info.fps > 0 and \
                abs(info.fps - fps) > FPS_TOLERANCE * fps:
            out.problems.append(f"{info.shown}: {info.fps:g} fps, but {checked.path} says fps {fps:g} (camera {name})")
    videos = [i for i in out.sources.values() if i.kind == "video" and i.fps > 0]
    if len(videos) > 1 and _disagree(videos):
        out.problems.append(f"{root / 'videos'}: the videos disagree on their frame rate: {_rates(videos)}")
    counts = Counter(i.count for i in out.sources.values())
    if len(counts) > 1:
        usual = counts.most_common(1)[0][0]
        first = next(i for i in out.sources.values() if i.count == usual)
        for name, info in out.sources.items():
            if info.count != usual:
                out.problems.append(f"{info.shown}: {info.count} frames, but {first.shown} has {usual} (camera {name})")
    out.problems += _backgrounds(root, named)
    return out
