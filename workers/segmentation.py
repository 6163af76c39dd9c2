"""Segmentation worker: one background model per camera, one or many cameras per
process. Publishes each camera's bit-packed foreground mask (at ``1/scale`` of the
image size; by default the scale matched to the layout's voxel size) with the
downscaled colour image that voxel colouring needs.

The background model starts from the recording's ``background/<cam>.png`` when there
is one; otherwise from the per-pixel temporal median of frames spread across the
recording (real sessions rarely have empty-room shots; where people passed in most of
those frames, the room the frames agree on, ``passers_by``), and people who stood still
through most of the recording, and so are in that median, are found with the other
cameras' views of the room and painted out of it (``still_people``,
:mod:`app.background_views`); live cameras learn it from the stream.

A restarted worker on a recording first runs its cameras' models through the frames its
earlier incarnation took (read again from the recording, reduced as the grabber sent
them; at most ``rebuild_images``) before it takes its first frame, so its masks, and
the results after them, are those of a run that never stopped (OpenCV's MOG2 has no way
to save its model). Live, the models start afresh.

``markers``: a colour markers' chroma model (``smartroom markers learn``; ``recording``:
the recording's ``markers.json``): the worker also detects the markers in each frame and
publishes them (:class:`~app.messages.Markers`, as a markers worker does, in this
process; the grabber then sends full-size frames).
"""
from __future__ import annotations

import time

from app.messages import Frame, Mask
from app.recording import Recording
from app.segmentation import (CameraSegmenter, SegmentationParams, camera_segmenter, matched_scale,
                              recording_backgrounds, shrink, warm_up)
from workers.base import Worker

DEFAULT_SCALE = 2


def scales(spec, layout, calibration) -> tuple[int, int]:
    """``(mask scale, colour scale)`` of a segmentation worker of ``layout``: its
    ``scale`` parameter, or (0, auto) the scale matched to the voxel size of the
    layout's reconstruction; ``colour_scale`` -1 follows the mask, 0 sends no colour.
    The reconstruction worker builds its tables with the same function."""
    scale = spec.params.get("scale", DEFAULT_SCALE)
    if not scale:
        sizes = [w.params["voxel_size"] for w in layout.workers if w.kind == "reconstruction"]
        scale = matched_scale(calibration, min(sizes)) if sizes and calibration is not None else DEFAULT_SCALE
    colour = spec.params.get("colour_scale", -1)
    return int(scale), int(scale if colour < 0 else colour)


def frame_scale(layout, calibration) -> int:
    """How much smaller than the camera a source may send the frames: the largest power of
    two that divides every mask and colour scale of the layout's segmentation workers
    (:func:`scales`), every keypoints and markers worker's ``scale`` (1 for a segmentation
    worker that detects markers) and every camera's width and height
    (HD frames are 25 MB a set; the segmentation reduces them anyway). 1: full size."""
    from math import gcd

    from workers import producers_of

    need = 0
    for name in producers_of(layout, "mask"):
        mask, colour = scales(layout.worker(name), layout, calibration)
        need = gcd(need, mask)
        if colour:
            need = gcd(need, colour)
    for name in producers_of(layout, "keypoints"):   # the keypoint detector's crops want detail
        need = gcd(need, int(layout.worker(name).params.get("scale", 1)))
    for name in producers_of(layout, "markers"):     # markers are a few pixels across
        spec = layout.worker(name)
        need = gcd(need, 1 if spec.kind == "segmentation" else int(spec.params.get("scale", 1)))
    scale = 1
    while need and need % (scale * 2) == 0 and all(
            c.width % (scale * 2) == 0 and c.height % (scale * 2) == 0 for c in calibration.cameras):
        scale *= 2
    return scale


class Segmentation(Worker):
    KIND = "segmentation"
    ORDER = 1
    CONSUMES = ("frame",)
    PRODUCES = ("mask",)
    ACCEPTS = (Frame,)
    DEFAULTS = {
        "cameras": "all",
        "scale": 0,                  # masks at 1/scale of the image size; 0: matched to the voxel size
        "history": 500,
        "var_threshold": 16.0,
        "shadows": True,
        "shadow_threshold": 0.5,
        "learning_rate": 1e-4,       # per frame (-1: MOG2's automatic 1/history)
        "bootstrap": 100,            # frames at the automatic rate without a background image
        "open_px": 0,
        "close_px": 5,
        "shadow_floor": 0.15,        # dark shadows on the floor down to this brightness ratio (0: MOG2's test only)
        "shadow_residual": 6.0,      # ... colour within this many grey levels of the darkened background
        "fill_holes": 400,           # fill holes in a silhouette up to this area (full-size pixels; 0: none)
        "second_chance": 0.0,        # pixels next to the foreground farther than this from the background (0: off)
        "exposure": 0,               # frames: each frame's brightness matched to its mean over about this many (0: off)
        "colour_scale": -1,          # colour image at 1/colour_scale (-1: as the mask, 0: none)
        "median_frames": 25,         # frames for the median background when there is no image
        "still_people": True,        # ... and people standing still in it found with the other cameras, painted out
        "passers_by": True,          # ... and where people passed in most of its frames, the room the frames agree on
                                     # (False: the masked median alone, the build before 2026-12-02)
        "markers": "",               # the markers' chroma model: also detect them (recording: its markers.json)
        "rebuild_images": 2000,      # restarted on a recording: the models take again at most this many of the
                                     # images before, over the cameras (20 s of 4 cameras at 25 fps, ~7 s of work
                                     # here, well within the grabber's stall_timeout_s); farther in, the last of them
                                     # only, and the masks differ slightly from an undisturbed run (0: start afresh)
    }
    RANGES = {"scale": (0, 16), "history": (1, 100000), "var_threshold": (0.1, 10000.0),
              "shadow_threshold": (0.0, 1.0), "learning_rate": (-1.0, 1.0), "bootstrap": (0, 100000),
              "open_px": (0, 99), "close_px": (0, 99), "colour_scale": (-1, 16), "median_frames": (1, 1000),
              "shadow_floor": (0.0, 1.0), "shadow_residual": (0.0, 255.0), "fill_holes": (0, 10 ** 7),
              "second_chance": (0.0, 255.0), "exposure": (0, 100000), "rebuild_images": (0, 10 ** 7)}

    @classmethod
    def produces(cls, spec) -> set[str]:
        """Masks; the markers too with a ``markers`` model."""
        return set(cls.PRODUCES) | ({"markers"} if spec.params.get("markers") else set())

    def setup(self) -> None:
        from calibration import load_calibration

        run = self.layout.run
        self.recording = Recording(run.recording) if run.recording else None
        calib = self.recording.calibration if self.recording else (load_calibration(run.calibration)
                                                                    if run.calibration else None)
        self.calibration = calib
        self.known_cameras = list(calib.names) if calib is not None else None
        for cam in self.cameras() or []:
            if calib is not None:
                calib.camera(cam)  # an unknown camera is a one-line error
        self.scale, self.colour_scale = scales(self.spec, self.layout, calib)
        self.seg_params = SegmentationParams.from_params({**self.params, "scale": self.scale})
        self.segmenters: dict[str, CameraSegmenter] = {}
        self.backgrounds = None
        self.rebuilt: dict[str, int] = {}   # camera -> frames its model was run through again (restarted)
        # build the models before the first frame arrives (live: a model that learns from the
        # stream), and run the kernels once, so a live run's first frames are not lost to it
        cams = self.cameras() or (self.recording.cameras if self.recording else self.known_cameras) or []
        for cam in cams:
            self._segmenter(cam)
        # a recording: camera -> the next frame its model takes (each frame once, in order)
        self.model_next = self._stream_starts(self.segmenters) if self.recording is not None else {}
        if cams and calib is not None:
            warm_up(self.seg_params, calib.camera(cams[0]))
        self.markers = None
        if self.params["markers"]:
            from app.markers.detector import model_for_run
            self.markers = model_for_run(str(self.params["markers"]), run.recording, "segmentation")

    def _background(self, cam: str):
        if self.recording is None:
            self.log.info("camera %s: live, the background model learns from the stream", cam)
            return None
        if self.backgrounds is None:
            self.backgrounds = recording_backgrounds(self.recording, self.params["median_frames"],
                                                     bool(self.params["still_people"]), self.log, self.status,
                                                     passers_by=bool(self.params["passers_by"]))
        return self.backgrounds[cam]

    def _segmenter(self, cam: str) -> CameraSegmenter:
        seg = self.segmenters.get(cam)
        if seg is None:
            seg = self.segmenters[cam] = camera_segmenter(self.seg_params, self._background(cam), self.calibration, cam)
        return seg

    def _stream_starts(self, cams) -> dict[str, int]:
        """The first frame of each camera's stream on a recording (its grabber's
        ``start``); whether a grabber skips undecodable frames goes to ``_skip_bad``."""
        from workers import cameras_of, producers_of

        grabbers = [self.layout.worker(n) for n in producers_of(self.layout, "frame")]
        self._skip_bad = any(g.params.get("skip_bad_frames", False) for g in grabbers)
        return {cam: min((int(g.params.get("start", 0)) for g in grabbers
                          if cameras_of(g) is None or cam in cameras_of(g)), default=0) for cam in cams}

    def _catch_up_model(self, cam: str, upto: int, scale: int) -> None:
        """Run ``cam``'s model through the recording's frames it lacks before ``upto`` (at
        most the last ``rebuild_images`` over the worker's cameras), as the grabber sent
        them (reduced by ``scale``; a frame it could not decode left out): after a restart,
        the model the earlier incarnation had. (Only this camera's: another camera's frames
        may still be on their way, and a model takes each frame once, in order.)"""
        start = self.model_next[cam]
        cut = max(start, upto - int(self.params["rebuild_images"]) // max(1, len(self.segmenters)))
        t0, phase = time.monotonic(), self._phase
        self._phase = "rebuilding background models"   # busy, not hung (the heartbeat)
        taken = 0
        try:
            seg = self.segmenters[cam]
            for _, images in self.recording.frames([cam], cut, upto, skip_bad=self._skip_bad):
                seg.apply(shrink(images[cam], scale) if scale > 1 else images[cam], prescaled=scale)
                self._turned = time.monotonic()
                taken += 1
        finally:
            self._phase = phase
        self.model_next[cam] = upto
        if taken:   # (none: frames the grabber could not decode either)
            self.rebuilt[cam] = self.rebuilt.get(cam, 0) + taken
        if cut > start:
            self.log.warning("camera %s: the background model took %d of the frames %d-%d again (rebuild_images): "
                             "its masks may differ slightly from an undisturbed run", cam, taken, start, upto - 1)
        elif taken:
            self.log.info("camera %s: background model run through frames %d-%d of the recording again (%.1f s): "
                          "as if never stopped", cam, cut, upto - 1, time.monotonic() - t0)

    def extra_figures(self) -> dict:
        return {"models_rebuilt_frames": dict(self.rebuilt)} if self.rebuilt else {}

    def admit(self, key: str, msg: Frame) -> str | None:
        """Only the cameras of the calibration (and of this worker, when it has a list)."""
        mine = self.cameras()
        known = self.known_cameras
        if (mine is not None and msg.camera not in mine) or (known is not None and msg.camera not in known):
            return "unknown camera"
        if self.scale % msg.scale or (self.colour_scale and self.colour_scale % msg.scale):
            return f"frame reduced by {msg.scale}, which does not divide the mask scale {self.scale}"
        return None

    def handle(self, key: str, msg: Frame) -> None:
        seg = self._segmenter(msg.camera)
        learn = True
        expected = self.model_next.get(msg.camera) if self.lossless else None
        if expected is not None:   # a recording: each frame taken once, in order
            if expected < msg.frame:   # restarted: the frames before
                self._catch_up_model(msg.camera, msg.frame, msg.scale)
            learn = expected <= msg.frame   # else taken already (sent again)
            if learn:
                self.model_next[msg.camera] = msg.frame + 1
        mask = seg.apply(msg.image, prescaled=msg.scale, learn=learn)
        scale = self.colour_scale
        colour = None
        if scale == self.scale:
            colour = seg.small   # the frame the mask was computed on
        elif scale:
            colour = shrink(msg.image, scale // msg.scale)
        if self.markers is not None:
            from app.markers.detector import frame_markers
            from workers.markers import markers_message
            self.publish(self.keys.markers(msg.camera),
                         markers_message(msg, self.name, frame_markers(msg.image, self.markers, msg.scale)))
        self.publish(self.keys.mask(msg.camera),
                     Mask.pack(mask, frame=msg.frame, stamp=msg.stamp, t=msg.t, camera=msg.camera,
                               colour_scale=max(1, scale), colour=colour, cameras=list(msg.cameras)))
