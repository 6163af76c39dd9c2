"""Background/foreground segmentation of one camera (thesis §2.2.3).

The thesis uses Stauffer-Grimson's adaptive mixture of Gaussians per pixel with
shadow suppression (Landabaso et al.). OpenCV's MOG2 is that model (Zivkovic's
improved Stauffer-Grimson) with a chromaticity/brightness shadow test: pixels it
labels as shadow (value 127) are background here. A small morphological opening
and closing removes speckle and fills pinholes.

Speed: the mask is computed at ``1/scale`` of the camera resolution (default half:
320x240 for a 640x480 camera), a resolution matched to the projected footprint of
a 2-4 cm voxel at room distances, which costs a quarter of the full-size model.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import cv2
import numpy as np

__all__ = ["SegmentationParams", "CameraSegmenter", "estimate_background", "working_size"]


@dataclass
class SegmentationParams:
    scale: int = 2                  # the mask is 1/scale of the image size
    history: int = 500              # frames of MOG2 memory
    var_threshold: float = 16.0     # squared Mahalanobis distance for foreground
    shadows: bool = True            # detect shadows (and treat them as background)
    shadow_threshold: float = 0.5   # MOG2 tau: a shadow is at most this much darker
    learning_rate: float = -1.0     # -1: 1/history (MOG2's fast start-up rate when it has no background)
    open_px: int = 3                # opening kernel (removes speckle); 0 = none
    close_px: int = 5               # closing kernel (fills holes); 0 = none

    @classmethod
    def from_params(cls, params: dict) -> "SegmentationParams":
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in params.items() if k in names})


def working_size(width: int, height: int, scale: int) -> tuple[int, int]:
    """Size (w, h) of an image downscaled by an integer factor."""
    scale = max(1, int(scale))
    return width // scale, height // scale


def _shrink(image: np.ndarray, scale: int) -> np.ndarray:
    if scale <= 1:
        return image
    h, w = image.shape[:2]
    return cv2.resize(image, working_size(w, h, scale), interpolation=cv2.INTER_AREA)


def estimate_background(images) -> np.ndarray:
    """Empty-room image estimated as the per-pixel temporal median of frames spread
    over a recording (people move, so each pixel is background most of the time)."""
    stack = np.stack(list(images))
    return np.median(stack, axis=0).astype(np.uint8)


class CameraSegmenter:
    """Mixture-of-Gaussians background model of one camera."""

    def __init__(self, params: SegmentationParams, background: np.ndarray | None = None):
        self.params = params
        self.model = cv2.createBackgroundSubtractorMOG2(
            history=params.history, varThreshold=params.var_threshold, detectShadows=params.shadows)
        if params.shadows:
            self.model.setShadowThreshold(params.shadow_threshold)
        self._open = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (params.open_px,) * 2) if params.open_px else None
        self._close = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (params.close_px,) * 2) if params.close_px else None
        # MOG2's automatic rate is 1/min(2n, history) after n frames: right for a model
        # that starts empty, far too fast for one trained on the empty room (a person
        # standing still would melt into the background within frames).
        self.rate = params.learning_rate
        if background is not None:
            self.learn_background([background])

    def learn_background(self, images) -> None:
        """Train the model on empty-room images (running mean over them)."""
        for i, img in enumerate(images):
            self.model.apply(_shrink(img, self.params.scale), learningRate=1.0 / (i + 1))
        if self.params.learning_rate < 0:
            self.rate = 1.0 / max(1, self.params.history)

    def apply(self, image: np.ndarray) -> np.ndarray:
        """Foreground mask (H/scale, W/scale) bool of one frame; the model keeps adapting."""
        raw = self.model.apply(_shrink(image, self.params.scale), learningRate=self.rate)
        fg = (raw == 255).astype(np.uint8)
        if self._open is not None:
            fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, self._open)
        if self._close is not None:
            fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, self._close)
        return fg.view(bool)
