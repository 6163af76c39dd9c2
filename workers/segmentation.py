"""Segmentation worker: one background model per camera, one or many cameras per
process. Publishes each camera's bit-packed foreground mask with the (optionally
downscaled) colour image that voxel colouring needs."""
from __future__ import annotations

import cv2

from app.messages import Frame, Mask
from app.recording import Recording
from app.segmentation import CameraSegmenter, SegmentationParams
from workers.base import Worker


class Segmentation(Worker):
    KIND = "segmentation"
    ORDER = 1
    CONSUMES = ("frame",)
    PRODUCES = ("mask",)
    DEFAULTS = {
        "cameras": "all",
        "history": 500,
        "var_threshold": 16.0,
        "shadows": True,
        "shadow_threshold": 0.5,
        "learning_rate": -1.0,
        "open_px": 3,
        "close_px": 5,
        "colour_scale": 2,   # colour image sent downscaled by this factor (0: no colour)
    }

    def setup(self) -> None:
        self.seg_params = SegmentationParams.from_params(self.params)
        self.segmenters: dict[str, CameraSegmenter] = {}
        self.recording = Recording(self.layout.run.recording) if self.layout.run.recording else None
        if self.recording is not None:  # build the models before the first frame arrives
            for cam in self.cameras() or self.recording.cameras:
                self._segmenter(cam)

    def _segmenter(self, cam: str) -> CameraSegmenter:
        seg = self.segmenters.get(cam)
        if seg is None:
            background = self.recording.background(cam) if self.recording is not None else None
            if background is None:
                self.log.info("camera %s: no background image, the model learns from the stream", cam)
            seg = self.segmenters[cam] = CameraSegmenter(self.seg_params, background)
        return seg

    def handle(self, key: str, msg: Frame) -> None:
        mask = self._segmenter(msg.camera).apply(msg.image)
        scale = self.params["colour_scale"]
        colour = None
        if scale == 1:
            colour = msg.image
        elif scale > 1:
            h, w = msg.image.shape[:2]
            colour = cv2.resize(msg.image, (w // scale, h // scale), interpolation=cv2.INTER_AREA)
        self.publish(self.keys.mask(msg.camera),
                     Mask.pack(mask, frame=msg.frame, stamp=msg.stamp, t=msg.t, camera=msg.camera,
                               colour_scale=max(1, scale), colour=colour))
