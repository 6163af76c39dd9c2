"""The colour marker detector (thesis §6.4.1.1, §6.6.2): marker pixels are those whose
chroma is near the markers' colour, a Mahalanobis test in the (Cr, Cb) plane of YCrCb
(brightness left out, so a marker in shade is still a marker), learnt from a few
labelled pixels; each blob of marker pixels is one detection, at its centroid.

:class:`ChromaModel` is the learnt colour (mean and covariance of (Cr, Cb), a threshold
on the squared distance: 5 sigma by default, and a minimum luma so that dark noise is
not coloured); :func:`detect_markers` returns the detections of one image, (Q, 2)
pixels. The model is a small JSON file (``smartroom markers learn``).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from app.errors import InputError

__all__ = ["ChromaModel", "learn_chroma", "detect_markers", "marker_mask"]


@dataclass
class ChromaModel:
    mean: np.ndarray           # (2,) Cr, Cb
    cov: np.ndarray            # (2, 2)
    threshold: float = 25.0    # squared Mahalanobis distance (5 sigma: shading and sensor noise spread a marker)
    min_luma: int = 40
    min_area: int = 2          # pixels of a blob
    max_area: int = 2000

    def to_json(self) -> str:
        return json.dumps({"mean": [float(v) for v in self.mean], "cov": [[float(v) for v in r] for r in self.cov],
                           "threshold": self.threshold, "min_luma": self.min_luma, "min_area": self.min_area,
                           "max_area": self.max_area}, indent=1)

    @classmethod
    def load(cls, path) -> "ChromaModel":
        try:
            d = json.loads(Path(path).read_text())
            model = cls(np.asarray(d["mean"], float).reshape(2), np.asarray(d["cov"], float).reshape(2, 2),
                        float(d.get("threshold", 25.0)), int(d.get("min_luma", 40)), int(d.get("min_area", 2)),
                        int(d.get("max_area", 2000)))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputError(f"marker colour model {path}: not readable ({exc})") from None
        if not np.all(np.isfinite(model.cov)) or np.linalg.det(model.cov) <= 0:
            raise InputError(f"marker colour model {path}: its covariance is not positive definite")
        return model


def learn_chroma(image: np.ndarray, points, radius: int = 2, threshold: float = 25.0) -> ChromaModel:
    """The chroma model of the pixels within ``radius`` of the labelled ``points`` (N, 2)
    (x, y) of a BGR ``image`` (a few clicks on markers)."""
    ycc = cv2.cvtColor(image, cv2.COLOR_BGR2YCrCb).astype(np.float64)
    h, w = ycc.shape[:2]
    samples = []
    for x, y in np.asarray(points, float).reshape(-1, 2):
        x0, x1 = int(max(0, round(x) - radius)), int(min(w, round(x) + radius + 1))
        y0, y1 = int(max(0, round(y) - radius)), int(min(h, round(y) + radius + 1))
        samples.append(ycc[y0:y1, x0:x1, 1:].reshape(-1, 2))
    s = np.concatenate(samples) if samples else np.zeros((0, 2))
    if len(s) < 5:
        raise InputError(f"marker colour: {len(s)} labelled pixels are too few (click on a few markers)")
    cov = np.cov(s.T) + np.eye(2) * 1.0     # a floor: a flat-coloured sample has no spread
    return ChromaModel(s.mean(axis=0), cov, float(threshold))


def marker_mask(image: np.ndarray, model: ChromaModel) -> np.ndarray:
    """Pixels (bool, H x W) whose chroma is within the model's threshold."""
    ycc = cv2.cvtColor(image, cv2.COLOR_BGR2YCrCb)
    d = ycc[..., 1:].astype(np.float32) - model.mean.astype(np.float32)
    inv = np.linalg.inv(model.cov).astype(np.float32)
    m2 = inv[0, 0] * d[..., 0] ** 2 + 2 * inv[0, 1] * d[..., 0] * d[..., 1] + inv[1, 1] * d[..., 1] ** 2
    return (m2 < model.threshold) & (ycc[..., 0] >= model.min_luma)


def detect_markers(image: np.ndarray, model: ChromaModel) -> np.ndarray:
    """Centroids (Q, 2) (x, y pixels) of the blobs of marker pixels of a BGR image."""
    mask = marker_mask(image, model).astype(np.uint8)
    n, _, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    area = stats[1:, cv2.CC_STAT_AREA]
    keep = (area >= model.min_area) & (area <= model.max_area)
    return centroids[1:][keep].astype(np.float64)
