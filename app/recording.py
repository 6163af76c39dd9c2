"""Recording folders (CONTRACT §1): reading them as if their cameras were live, and
writing them (the simulator and ``smartroom record``).

    <recording>/calibration.yaml
    <recording>/videos/<cam>.mp4|.avi   or   <recording>/frames/<cam>/000000.png|.jpg
    <recording>/background/<cam>.png    (optional)
    <recording>/groundtruth.jsonl       (optional)
"""
from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from app.errors import InputError
from app.files import read_jsonl
from calibration import Calibration, load_calibration, save_calibration

__all__ = ["RecordingError", "Recording", "RecordingWriter", "SourceInfo", "VIDEO_EXTENSIONS", "IMAGE_EXTENSIONS",
           "recording_problem", "size_mismatch", "size_mismatches", "fps_mismatches", "find_source", "open_source",
           "inspect_source"]

VIDEO_EXTENSIONS = (".mp4", ".avi")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


def fingerprint(rec) -> str:
    """A short id of a recording's content: its calibration and frame count (results
    name it, so they are never scored against another recording)."""
    import hashlib
    h = hashlib.sha1((rec.path / "calibration.yaml").read_bytes())
    h.update(str(rec.frame_count).encode())
    return h.hexdigest()[:12]


class RecordingError(InputError):
    """A recording folder is missing something or holds something malformed."""


class _VideoSource:
    def __init__(self, path: Path, camera, root: Path):
        self.path, self.camera, self.shown = path, camera, str(path.relative_to(root))
        self.cap = cv2.VideoCapture(str(path))
        if not self.cap.isOpened():
            raise RecordingError(f"{self.shown}: cannot be opened as a video")
        self.count = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.fps = float(self.cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.size = (int(self.cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(self.cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        self.pos = 0

    def read(self, index: int) -> np.ndarray | None:
        if index != self.pos:
            self.cap.set(cv2.CAP_PROP_POS_FRAMES, index)
            self.pos = index
        ok, img = self.cap.read()
        if not ok:
            return None
        self.pos += 1
        return img

    def close(self):
        self.cap.release()


class _ImageSource:
    def __init__(self, folder: Path, camera, root: Path):
        self.camera, self.root = camera, root
        self.files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
        self.shown = str(folder.relative_to(root))
        if not self.files:
            raise RecordingError(f"{self.shown}: holds no .png or .jpg images")
        self.count = len(self.files)
        self.fps = 0.0
        first = cv2.imread(str(self.files[0]), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise RecordingError(f"{self.files[0].relative_to(root)}: cannot be read as an image")
        self.size = (first.shape[1], first.shape[0])

    def read(self, index: int) -> np.ndarray | None:
        if index >= self.count:
            return None
        img = cv2.imread(str(self.files[index]), cv2.IMREAD_COLOR)
        if img is None:
            raise RecordingError(f"{self.files[index].relative_to(self.root)}: cannot be read as an image")
        return img

    def close(self):
        pass


@dataclass(frozen=True)
class SourceInfo:
    """One camera's source in a recording: ``shown`` is its path inside the folder."""

    camera: str
    shown: str
    kind: str  # "video" or "frames"
    size: tuple[int, int]
    fps: float  # 0 when unknown (image folders)
    count: int


#: relative difference between a video's fps and the calibration's fps still accepted
#: (29.97 against 30 passes, 25 against 30 or 50 does not)
FPS_TOLERANCE = 0.01


def size_mismatch(info: SourceInfo, camera) -> str | None:
    """The phrase for a camera whose frames differ in size from its calibration, or None."""
    if tuple(info.size) == (camera.width, camera.height):
        return None
    return (f"{info.shown}: frame size {info.size[0]}x{info.size[1]} does not match calibration "
            f"{camera.width}x{camera.height} of camera {camera.name}")


def size_mismatches(calibration: Calibration, sources: dict) -> list[str]:
    """One phrase per camera whose frames differ in size from its calibration."""
    found = (size_mismatch(info, calibration.camera(name)) for name, info in sources.items())
    return [s for s in found if s]


def fps_mismatches(calibration: Calibration, sources: dict) -> list[str]:
    """One phrase per video whose frame rate differs from the calibration's ``fps``."""
    out = []
    for info in sources.values():
        if info.kind == "video" and info.fps > 0 and \
                abs(info.fps - calibration.fps) > FPS_TOLERANCE * calibration.fps:
            out.append(f"{info.shown} is {info.fps:g} fps")
    return out


def recording_problem(path: Path, calibration: Calibration, sources: dict) -> str | None:
    """The one-line error for a recording whose videos do not fit its calibration (every
    mis-sized camera and every video at another frame rate named, with the fix), or None."""
    sizes = size_mismatches(calibration, sources)
    if sizes:
        fix = (f"fix: smartroom calibrate fit --recording {path} (it chooses rescale, crop or turn from the sizes "
               "and says why; --rescale: the video is the calibrated image scaled, --crop: a window of it)")
        turned = [n for n, i in sources.items() if tuple(i.size) == (calibration.camera(n).height,
                                                                     calibration.camera(n).width)]
        if turned:
            fix += f", or --turn 90 / --turn 270 ({', '.join(turned)} look turned a quarter)"
        return "; ".join(sizes) + f" ({len(sizes)} of {len(sources)} cameras); {fix}"
    rates = fps_mismatches(calibration, sources)
    if rates:
        found = sorted({round(i.fps, 3) for i in sources.values() if i.kind == "video" and i.fps > 0})
        return (f"{path / 'calibration.yaml'}: fps {calibration.fps:g}, but " + ", ".join(rates) +
                f"; fix: set fps: {found[0]:g} in calibration.yaml" + (" (the videos also differ among themselves)"
                                                                        if len(found) > 1 else ""))
    counts = {name: info.count for name, info in sources.items()}
    first = next(iter(counts))
    for name, n in counts.items():
        if n != counts[first]:
            return f"{path / sources[name].shown}: {n} frames, but {first} has {counts[first]}"
    return None


def find_source(root: Path, cam: str) -> tuple[str, Path] | None:
    """``("video", videos/<cam>.mp4|.avi)`` or ``("frames", frames/<cam>)`` of a camera in a
    recording folder (paths relative to it; a video first), or None."""
    for ext in VIDEO_EXTENSIONS:
        p = root / "videos" / f"{cam}{ext}"
        if p.is_file():
            return ("video", p.relative_to(root))
    d = root / "frames" / cam
    if d.is_dir():
        return ("frames", d.relative_to(root))
    return None


def open_source(root: Path, kind: str, rel: Path, cam: str):
    """A camera's frames (``read(index)``, ``close()``); a source that cannot be read raises
    :class:`RecordingError` naming the file."""
    if kind == "video":
        return _VideoSource(root / rel, cam, root)
    return _ImageSource(root / rel, cam, root)


def inspect_source(root: Path, kind: str, rel: Path, cam: str) -> SourceInfo:
    """What a camera's video (or image folder) holds: frame size, fps, frame count."""
    src = open_source(root, kind, rel, cam)
    try:
        return SourceInfo(cam, src.shown, kind, src.size, src.fps, src.count)
    finally:
        src.close()


class Recording:
    """A recording folder, validated on opening (``check=False`` only opens it, for tools
    that report what does not fit, such as ``smartroom calibrate check --recording``)."""

    def __init__(self, path, check: bool = True):
        self.path = Path(path)
        if not self.path.is_dir():
            raise RecordingError(f"{self.path}: recording folder not found")
        self.calibration: Calibration = load_calibration(self.path / "calibration.yaml")
        self.fps = self.calibration.fps
        self._sources = {}
        for cam in self.calibration.cameras:
            self._sources[cam.name] = self._find_source(cam.name)
        self.sources = {name: self.inspect(name) for name in self._sources}
        self.problem = recording_problem(self.path, self.calibration, self.sources)
        if self.problem and check:
            raise RecordingError(self.problem)
        counts = {name: info.count for name, info in self.sources.items()}
        self.frame_count = min(counts.values())

    def _find_source(self, cam: str):
        found = find_source(self.path, cam)
        if found is None:
            raise RecordingError(f"{self.path}: camera {cam} has no videos/{cam}.mp4 (or .avi) and no frames/{cam}/ "
                                 "folder")
        return found

    def _open(self, cam: str):
        kind, rel = self._sources[cam]
        return open_source(self.path, kind, rel, cam)

    def inspect(self, cam: str) -> "SourceInfo":
        """What a camera's video (or image folder) holds: frame size, fps, frame count."""
        return inspect_source(self.path, *self._sources[cam], cam)

    @property
    def cameras(self) -> list[str]:
        return self.calibration.names

    def frames(self, cameras=None, start: int = 0, stop: int | None = None, skip_bad: bool = False,
               lost: dict | None = None, transform=None):
        """Yield ``(index, {camera: BGR image})`` from ``start`` up to ``stop`` (exclusive).

        Raises :class:`RecordingError` naming the file when a frame has the wrong size,
        or naming the file and frame when a frame the video announces cannot be decoded
        (a video corrupt in its middle). With ``skip_bad`` such a view is left out of its
        frame instead (the frame carries the other cameras) and counted in ``lost``
        (``{camera: frames lost}``); a frame no camera could give is skipped whole.
        """
        names = list(cameras) if cameras else self.cameras
        stop = self.frame_count if stop is None else min(stop, self.frame_count)
        sources = {n: self._open(n) for n in names}
        lost = {} if lost is None else lost
        # the cameras decode in parallel (OpenCV releases the GIL), each with ``transform``
        pool = ThreadPoolExecutor(len(sources), thread_name_prefix="decode") if len(sources) > 1 else None

        def read(item, i):
            n, src = item
            img = src.read(i)
            if img is None:
                return None
            self.check_image(n, img, src.shown)
            return img if transform is None else transform(n, img)
        try:
            for i in range(start, stop):
                images = {}
                got = (pool.map(read, sources.items(), [i] * len(sources)) if pool is not None
                       else [read(item, i) for item in sources.items()])
                for (n, src), img in zip(sources.items(), got):
                    if img is None:
                        if not skip_bad:
                            raise RecordingError(f"{src.shown}: frame {i} of {self.frame_count} cannot be decoded "
                                                 "(the file is damaged there; --set grabber.skip_bad_frames=true "
                                                 "goes on without it)")
                        lost[n] = lost.get(n, 0) + 1
                        src.pos = -1   # seek on the next read
                        continue
                    images[n] = img
                if images:
                    yield i, images
        finally:
            if pool is not None:
                pool.shutdown()
            for src in sources.values():
                src.close()

    def check_image(self, cam: str, img: np.ndarray, shown: str) -> None:
        c = self.calibration.camera(cam)
        if img.ndim != 3 or img.shape[:2] != (c.height, c.width) or img.shape[2] != 3:
            got = f"{img.shape[1]}x{img.shape[0]}" if img.ndim >= 2 else str(img.shape)
            raise RecordingError(f"{shown}: frame size {got} does not match calibration {c.width}x{c.height} of camera {cam}")

    def sample(self, cam: str, n: int) -> list[np.ndarray]:
        """``n`` frames of one camera spread evenly over the whole recording."""
        src = self._open(cam)
        try:
            idx = np.unique(np.linspace(0, self.frame_count - 1, min(n, self.frame_count)).astype(int))
            return [img for i in idx if (img := src.read(int(i))) is not None]
        finally:
            src.close()

    def background(self, cam: str) -> np.ndarray | None:
        """The empty-room image of a camera, if the recording has one."""
        for ext in IMAGE_EXTENSIONS:
            p = self.path / "background" / f"{cam}{ext}"
            if p.is_file():
                img = cv2.imread(str(p), cv2.IMREAD_COLOR)
                if img is None:
                    raise RecordingError(f"{p.relative_to(self.path)}: cannot be read as an image")
                self.check_image(cam, img, str(p.relative_to(self.path)))
                return img
        return None

    def groundtruth(self) -> list[dict] | None:
        """The parsed ``groundtruth.jsonl`` (one object per frame), or None."""
        p = self.path / "groundtruth.jsonl"
        return read_jsonl(p, RecordingError) if p.is_file() else None


class RecordingWriter:
    """Write a recording folder: into ``<path>.partial`` first, renamed on :meth:`close`,
    so a folder with the final name is always complete."""

    def __init__(self, path, calibration: Calibration, codec: str = "mp4v", overwrite: bool = False):
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise RecordingError(f"{self.path}: already exists (choose another --out or remove it)")
        self.tmp = self.path.with_name(self.path.name + ".partial")
        if self.tmp.exists():
            shutil.rmtree(self.tmp)
        (self.tmp / "videos").mkdir(parents=True)
        self.calibration = calibration
        self.codec = codec
        self._writers: dict[str, cv2.VideoWriter] = {}
        self._gt = None
        self.frames = 0
        save_calibration(calibration, self.tmp / "calibration.yaml")

    def write(self, images: dict) -> None:
        """One frame of every camera (BGR uint8 at the calibrated size)."""
        for cam in self.calibration.cameras:
            img = images[cam.name]
            w = self._writers.get(cam.name)
            if w is None:
                ext = ".avi" if self.codec in ("MJPG", "XVID") else ".mp4"
                w = cv2.VideoWriter(str(self.tmp / "videos" / f"{cam.name}{ext}"),
                                    cv2.VideoWriter_fourcc(*self.codec), float(self.calibration.fps),
                                    (cam.width, cam.height))
                if not w.isOpened():
                    raise RecordingError(f"cannot write {self.codec} video for camera {cam.name}")
                self._writers[cam.name] = w
            w.write(np.ascontiguousarray(img))
        self.frames += 1

    def write_background(self, cam: str, image: np.ndarray) -> None:
        (self.tmp / "background").mkdir(exist_ok=True)
        cv2.imwrite(str(self.tmp / "background" / f"{cam}.png"), image)

    def write_groundtruth(self, record: dict) -> None:
        if self._gt is None:
            self._gt = open(self.tmp / "groundtruth.jsonl", "w", encoding="utf-8")
        self._gt.write(json.dumps(record, separators=(",", ":")) + "\n")

    def file(self, name: str) -> Path:
        """Path of an extra file inside the recording being written."""
        return self.tmp / name

    def close(self) -> Path:
        for w in self._writers.values():
            w.release()
        if self._gt is not None:
            self._gt.close()
        if self.path.exists():
            shutil.rmtree(self.path)
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        for w in self._writers.values():
            w.release()
        if self._gt is not None:
            self._gt.close()
        shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()
