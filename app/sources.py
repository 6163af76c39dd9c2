"""Where frames come from: a recording folder read as if live, or live cameras.

Both give ``(index, {camera: BGR image})`` in frame order; the grabber worker and
``smartroom record`` share them.
"""
from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from app.errors import InputError
from app.recording import Recording
from calibration import Calibration

__all__ = ["RecordingSource", "LiveSource", "parse_live"]

log = logging.getLogger("smartroom.sources")


class RecordingSource:
    """Frames of a recording folder, optionally limited to some cameras and frames."""

    live = False

    def __init__(self, path, cameras=None, start: int = 0, frames: int | None = None, skip_bad: bool = False,
                 lost: dict | None = None, transform=None):
        self.recording = Recording(path)
        self.calibration = self.recording.calibration
        self.cameras = list(cameras) if cameras else self.recording.cameras
        for c in self.cameras:
            self.calibration.camera(c)  # unknown camera -> one-line error
        self.fps = self.recording.fps
        if not 0 <= start < self.recording.frame_count:
            raise InputError(f"{path}: start frame {start} is outside 0..{self.recording.frame_count - 1}")
        self.start = start
        stop = self.recording.frame_count if frames is None else min(self.recording.frame_count, start + frames)
        self.stop = stop
        self.expected = stop - start
        self.skip_bad = skip_bad
        self.lost = {} if lost is None else lost   # camera -> undecodable frames skipped
        self.transform = transform                 # (camera, image) -> image, in the decoding threads

    def frames(self):
        yield from self.recording.frames(self.cameras, self.start, self.stop, skip_bad=self.skip_bad, lost=self.lost,
                                         transform=self.transform)

    def close(self):
        pass


def parse_live(items) -> dict:
    """``["cam0=0", "cam1=rtsp://..."]`` -> ``{"cam0": 0, "cam1": "rtsp://..."}``."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise InputError(f"--live {item}: expected CAMERA=DEVICE_INDEX_OR_URL")
        cam, src = item.split("=", 1)
        out[cam] = int(src) if src.isdigit() else src
    return out


class _CameraThread(threading.Thread):
    """Reads one live camera as fast as it delivers, keeping only the newest image
    (a video file given as a camera is read at the camera's fps)."""

    def __init__(self, name: str, source, width: int, height: int, fps: float, reopen_s: float = 2.0):
        super().__init__(daemon=True, name=f"camera-{name}")
        self.cam, self.source, self.size = name, source, (width, height)
        self.period = 1.0 / fps
        self.reopen_s = reopen_s
        self.lock = threading.Lock()
        self.latest: np.ndarray | None = None
        self.fresh = False
        self.failed_since: float | None = None
        self.why = ""
        self.stopped = threading.Event()
        self.cap = None
        self.delivered = False   # an image came at least once

    def _open(self):
        cap = cv2.VideoCapture(self.source)
        if not cap.isOpened():
            return None
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.size[0])
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.size[1])
        return cap

    def run(self):
        while not self.stopped.is_set():
            if self.cap is None:
                self.cap = self._open()
                if self.cap is None:
                    self._failed("cannot be opened")
                    self.stopped.wait(self.reopen_s)
                    continue
                # a video file (it knows its length, or is a file: a playlist of them does not
                # say its length) is read at the camera's rate, not at once
                self.paced = (self.cap.get(cv2.CAP_PROP_FRAME_COUNT) > 0
                              or (isinstance(self.source, str) and Path(self.source).is_file()))
                self.next_read = time.monotonic()
            if self.paced:  # a file played as a camera delivers at the camera's rate
                self.stopped.wait(max(0.0, self.next_read - time.monotonic()))
                self.next_read = max(self.next_read + self.period, time.monotonic() - self.period)
            ok, img = self.cap.read()
            if not ok or img is None:
                self.cap.release()
                self.cap = None
                self._failed("stopped delivering frames")
                self.stopped.wait(self.reopen_s)
                continue
            if img.shape[1::-1] != self.size:
                img = cv2.resize(img, self.size, interpolation=cv2.INTER_AREA)
            with self.lock:
                self.latest, self.fresh = img, True
                self.delivered = True
            if self.failed_since is not None:
                log.warning("camera %s is back", self.cam)
                self.failed_since = None
        if self.cap is not None:
            self.cap.release()

    def _failed(self, why: str):
        self.why = why
        if self.failed_since is None:
            self.failed_since = time.time()
            # a camera lost mid-run is news; one that has not opened yet is said by LiveSource
            # once its open_timeout is over (an error naming every camera, or a camera left out)
            level = logging.WARNING if self.delivered else logging.INFO
            log.log(level, "camera %s (%s) %s; the others go on, retrying every %.0f s", self.cam, self.source, why,
                    self.reopen_s)

    def take(self) -> np.ndarray | None:
        with self.lock:
            if not self.fresh:
                return None
            self.fresh = False
            return self.latest


class LiveSource:
    """Live cameras (``cv2.VideoCapture`` device indices or URLs) sampled at the
    calibration's fps. A camera that stops is left out of the frames it misses (the
    reconstruction's tolerance covers a missing view) and is reopened periodically."""

    live = True

    def __init__(self, sources: dict, calibration: Calibration, frames: int | None = None,
                 stop: threading.Event | None = None, open_timeout: float = 10.0, lost_timeout: float = 30.0,
                 start: int = 0):
        self.calibration = calibration
        self.stop_event = stop or threading.Event()
        self.open_timeout = open_timeout
        self.lost_timeout = lost_timeout
        self.failure: str | None = None   # why the stream ended early (every camera gone)
        self.failed: set[str] = set()   # cameras that never delivered or stopped delivering
        self.cameras = list(sources)
        for c in self.cameras:
            calibration.camera(c)
        self.fps = calibration.fps
        self.expected = frames
        # OpenCV's own lines about a camera it cannot open would repeat at every retry, on
        # the terminal and past the log files: the cameras' threads say it once (log)
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        self.threads = {c: _CameraThread(c, sources[c], calibration.camera(c).width, calibration.camera(c).height,
                                         self.fps) for c in self.cameras}
        self.start = start   # a restarted grabber carries the frame numbers on
        self._closed = threading.Event()

    def frames(self):
        """Frames until the limit, a stop, or :meth:`close`. No camera delivering within
        ``open_timeout`` is an error naming every camera; a camera that never delivers
        while others do is flagged (``failed``) and the others go on. When every camera
        has delivered nothing for ``lost_timeout`` (each is retried meanwhile) the stream
        ends, with the reason in ``failure``."""
        for t in self.threads.values():
            t.start()
        index, tick, period, t0 = self.start, 0, 1.0 / self.fps, time.monotonic()
        delivered: set[str] = set()
        last_image = t0
        while (not self._closed.is_set() and not self.stop_event.is_set()
               and (self.expected is None or index - self.start < self.expected)):
            self.stop_event.wait(max(0.0, t0 + tick * period - time.monotonic()))
            tick += 1
            images = {c: img for c, t in self.threads.items() if (img := t.take()) is not None}
            delivered |= set(images)
            now = time.monotonic()
            if images:
                last_image = now
            elif delivered and now - last_image > self.lost_timeout:
                self.failure = "every live camera stopped delivering for %.0f s: %s" % (self.lost_timeout, "; ".join(
                    f"{c} ({t.source}) {t.why or 'silent'}" for c, t in self.threads.items()))
                log.error("%s; ending the stream", self.failure)
                return
            waited = now - t0
            if waited > self.open_timeout:
                if not delivered:
                    raise InputError("no live camera delivered an image in %.0f s: %s" % (self.open_timeout, "; ".join(
                        f"{c} ({t.source}) {t.why or 'delivered nothing'}" for c, t in self.threads.items())))
                never = set(self.threads) - delivered
                if never - self.failed:
                    log.error("camera %s never delivered an image; going on without it",
                              ", ".join(sorted(never - self.failed)))
                self.failed = never | {c for c, t in self.threads.items() if t.failed_since is not None}
            if images:
                yield index, images
                index += 1

    def close(self):
        """Stop the camera threads and release the cameras (before the interpreter
        exits: a capture released during shutdown aborts the process)."""
        self._closed.set()
        for t in self.threads.values():
            t.stopped.set()
        for t in self.threads.values():
            if t.is_alive():
                t.join(timeout=5.0)
