"""Camera grabber: publishes every camera's frame with its index, capture time, epoch
and frame set (the cameras sent for that index).

Reads a recording folder as if live, or live cameras through ``cv2.VideoCapture``.
Before the first frame it waits until every worker of the layout is alive, so no
stage misses the start of the stream.

Offline (a recording) the grabber never runs ahead of the pipeline: the spine's flow
control (:mod:`workers.flow`) holds frame ``i`` until every stage has finished frame
``i - window`` and ends a stalled run with a reason; paced runs also keep the
recording's clock. Frames travel as small as the layout's segmentation allows
(:func:`workers.segmentation.frame_scale`). A restarted grabber carries on after the last
frame it sent, in a new epoch, after sending that frame again in its old one
(:mod:`workers.restarts`). Live cameras are paced by the cameras themselves.
"""
from __future__ import annotations

import time

from app.errors import InputError
from app.messages import Frame
from app.sources import LiveSource, RecordingSource
from calibration import load_calibration
from workers.base import Worker
from workers.flow import SourceFlow


class Grabber(Worker):
    KIND = "grabber"
    ORDER = 0
    PRODUCES = ("frame",)
    DEFAULTS = {
        "cameras": "all",        # cameras this grabber reads (a list, or all)
        "start": 0,              # first frame of a recording
        "ready_timeout": 60.0,   # live: seconds to wait for the other workers before starting anyway (a recording
                                 # waits for all of them, saying so every this many seconds)
        "window": 2,             # offline: frames in flight beyond the slowest stage's last one
        "stall_timeout_s": 120.0,  # offline: a frame held this long by a stage that finishes nothing (or a worker
                                   # that never comes on the bus) ends the run with the reason (exit 1)
        "open_timeout": 10.0,    # live: seconds for a camera to deliver its first image
        "lost_timeout": 30.0,    # live: seconds with no camera delivering before the stream ends
        "skip_bad_frames": False,  # a recording's undecodable frames: stop with an error, or skip them
        "scale": 0,              # send frames at 1/scale (0: as small as the segmentation allows; 1: full size)
        "catch_up_s": 1.0,       # paced recording: a lag up to this (warm-up, a hiccup) is caught up; longer moves the clock
    }
    RANGES = {"start": (0, 1 << 40), "ready_timeout": (0.0, 3600.0), "window": (1, 64),
              "stall_timeout_s": (1.0, 86400.0), "open_timeout": (0.5, 600.0), "lost_timeout": (0.5, 86400.0),
              "scale": (0, 16), "catch_up_s": (0.0, 10.0)}

    def setup(self) -> None:
        run = self.layout.run
        cams = self.cameras()
        self.epoch = time.time_ns() // 1_000_000     # a new epoch per incarnation
        self.scale = 1
        self._epoch = self.epoch
        self.lost: dict[str, int] = {}
        if run.live:
            if not run.calibration:
                raise InputError("live cameras need a calibration file (--calibration)")
            live = {c: s for c, s in run.live.items() if cams is None or c in cams}
            left = None if run.frames is None else max(0, run.frames - (self.resume_at or 0))
            self.source = LiveSource(live, load_calibration(run.calibration), frames=left,
                                     stop=self.stop_event, open_timeout=self.params["open_timeout"],
                                     lost_timeout=self.params["lost_timeout"], start=self.resume_at or 0)
            self.first = 0
        else:
            if not run.recording:
                raise InputError("the grabber has no recording and no live cameras")
            from workers.segmentation import frame_scale

            first = self.params["start"]
            resume = max(first, self.resume_at) if self.resume_at is not None else first
            whole = RecordingSource(run.recording, cams, start=first, frames=run.frames)
            total = whole.stop
            self.scale = int(self.params["scale"]) or frame_scale(self.layout, whole.calibration)
            self.source = RecordingSource(run.recording, cams, start=min(resume, total - 1),
                                          frames=max(0, total - resume), skip_bad=self.params["skip_bad_frames"],
                                          lost=self.lost, transform=self._transform)
            self.first = first
            self.total = total - first
            if resume >= total:
                self.source = None   # everything was sent before the restart
        self._frames = None
        self.flow = SourceFlow(self, self.params["window"], self.params["stall_timeout_s"],
                               self.params["ready_timeout"]) if self.lossless else None
        self.t0 = None

    def _reduce(self, camera: str, image):
        from app.segmentation import shrink
        return shrink(image, self.scale)

    @property
    def _transform(self):
        """What the decoding threads do to an image: reduce it to the send scale, if any."""
        return self._reduce if self.scale > 1 else None

    def put_out_again(self, frame: int, epoch: int) -> None:
        """After a restart, the last frame the earlier incarnation sent, in its epoch."""
        again = RecordingSource(self.layout.run.recording, self.cameras(), start=frame, frames=1,
                                skip_bad=self.params["skip_bad_frames"], transform=self._transform)
        for i, images in again.frames():
            self._send(i, images, time.time(), epoch, again.fps)

    @property
    def produced(self) -> int:
        return self.ledger.done.count

    # -- frames ------------------------------------------------------------------------
    def produce(self) -> bool:
        if self.source is None:
            return False
        if self._frames is None:
            self._frames = iter(self.source.frames())
            if self.incarnation == 0:   # nothing is sent before every worker is on the bus
                self._idle += (self.flow.ready(self.source.start) if self.flow is not None
                               else self.wait_until_ready(self.params["ready_timeout"]))
        try:
            index, images = next(self._frames)
        except StopIteration:
            return False
        if self.flow is not None:
            self._idle += self.flow.hold(index)
            if self.layout.run.pace:
                self._pace(index)
        if self.stopping:
            return False
        stamp = time.time()
        self.ledger.received(index, stamp)
        self._send(index, images, stamp, self.epoch, self.source.fps)
        self.ledger.emitted(index, stamp)   # sent once every camera's image is: a restart sends it again
        return True

    def _send(self, index: int, images: dict, stamp: float, epoch: int, fps: float) -> None:
        """Every camera's image of frame ``index``, each with the frame set (the cameras sent)."""
        cameras = sorted(images)
        for cam, image in images.items():
            self.publish(self.keys.frame(cam), Frame(frame=index, stamp=stamp, t=index / fps, camera=cam,
                                                     cameras=cameras, image=image, epoch=epoch, scale=self.scale),
                         counts=False)

    def _pace(self, index: int) -> None:
        """Sleep until the frame's time on the recording's clock. A lag of up to
        ``catch_up_s`` (the stages' warm-up on the first frames: look-up tables, kernels;
        or a moment's hiccup of a loaded machine) is caught up by sending the next frames
        without waiting, so a pipeline that keeps up plays the recording at its rate
        (before, a start-up lag of ~0.5 s moved the clock for good: paced RTF 0.97 for a
        pipeline that runs 2.6x real time unpaced); a frame later than that (and than one
        period) moves the clock instead of causing a long burst (as a camera that skipped
        would)."""
        now = time.monotonic()
        period = 1.0 / self.source.fps
        if self.t0 is None:
            self.t0 = now - (index - self.source.start) * period
        due = self.t0 + (index - self.source.start) * period
        if now - due > max(period, float(self.params["catch_up_s"])):
            self.t0 += now - due
        elif due > now:
            self.sleep(due - now)

    def stream_info(self) -> tuple[int, int, float]:
        fps = self.source.fps if self.source is not None else (self.layout.run.fps or 0.0)
        return self.produced, self.first, fps

    def extra_figures(self) -> dict:
        figures = {"fps_recording": self.stream_info()[2], "epoch": getattr(self, "epoch", 0)}
        source = getattr(self, "source", None)
        if source is not None:
            figures["expected_frames"] = getattr(self, "total", source.expected)
            failed = getattr(source, "failed", None)
            if failed:
                figures["cameras_failed"] = sorted(failed)
            if getattr(source, "failure", None):
                figures["stream_error"] = source.failure   # the stream ended, but not as it should
        if getattr(self, "lost", None):
            figures["views_lost"] = dict(self.lost)
        flow = getattr(self, "flow", None)
        if flow is not None and flow.control.went_without:   # offline frames sent past a stage that was away
            figures["went_on_without"] = dict(flow.control.went_without)
        return figures

    def close(self) -> None:
        if getattr(self, "flow", None) is not None:
            self.flow.close()
        if getattr(self, "source", None) is not None:
            self.source.close()
