"""Background/foreground segmentation of one camera (thesis §2.2.3).

The thesis uses Stauffer-Grimson's adaptive mixture of Gaussians per pixel with
shadow suppression (Landabaso et al.). OpenCV's MOG2 is that model (Zivkovic's
improved Stauffer-Grimson) with a chromaticity/brightness shadow test: pixels it
labels as shadow (value 127) are background here. A small morphological opening
and closing removes speckle and fills pinholes.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["SegmentationParams", "CameraSegmenter"]


@dataclass
class SegmentationParams:
    history: int = 500              # frames of MOG2 memory
    var_threshold: float = 16.0     # squared Mahalanobis distance for foreground
    shadows: bool = True            # detect shadows (and treat them as background)
    shadow_threshold: float = 0.5   # MOG2 tau: how much darker a shadow may be
    learning_rate: float = -1.0     # -1: MOG2's automatic 1/history
    open_px: int = 3                # opening kernel (removes speckle); 0 = none
    close_px: int = 5               # closing kernel (fills holes); 0 = none

    @classmethod
    def from_params(cls, params: dict) -> "SegmentationParams":
        names = cls.__dataclass_fields__
        return cls(**{k: v for k, v in params.items() if k in names})


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
        if background is not None:
            self.learn_background([background])

    def learn_background(self, images) -> None:
        """Train the model on empty-room images (each one at full learning rate)."""
        images = list(images)
        for i, img in enumerate(images):
            self.model.apply(img, learningRate=1.0 / (i + 1))

    def apply(self, image: np.ndarray) -> np.ndarray:
        """Foreground mask (H, W) bool of one frame; the model keeps adapting."""
        raw = self.model.apply(image, learningRate=self.params.learning_rate)
        fg = (raw == 255).astype(np.uint8)
        if self._open is not None:
            fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, self._open)
        if self._close is not None:
            fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, self._close)
        return fg.view(bool)
