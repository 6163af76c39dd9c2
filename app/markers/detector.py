"""The colour marker detector (thesis §6.4.1.1, §6.6.2): marker pixels are those whose
chroma is near the markers' colour, a Mahalanobis test in the (Cr, Cb) plane of YCrCb
(brightness left out, so a marker in shade is still a marker), learnt from a few
labelled pixels; each blob of marker pixels is one detection, at its centroid.

:class:`ChromaModel` is the learnt colour (mean and covariance of (Cr, Cb), a threshold
on the squared distance: 5 sigma by default, and a minimum luma so that dark noise is
not coloured); :func:`detect_markers` returns the detections of one image, (Q, 2)
pixels, :func:`frame_markers` those of a frame the grabber may have reduced, in the
camera's calibrated pixels. The model is a small JSON file (``smartroom markers learn``;
a simulated recording made with markers carries its own, ``markers.json``).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from app.errors import InputError

__all__ = ["ChromaModel", "learn_chroma", "detect_markers", "marker_mask", "chroma_table", "frame_markers", "model_for_run"]


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


def chroma_table(model: ChromaModel) -> np.ndarray:
    """The model's test for every (Cr, Cb) pair: (65536,) uint8, indexed ``Cr * 256 + Cb``
    (one look-up a pixel instead of the quadratic form: 1 ms instead of 7 for 640x480)."""
    table = getattr(model, "_table", None)
    if table is None:
        cr, cb = np.meshgrid(np.arange(256.0), np.arange(256.0), indexing="ij")
        d0, d1 = cr - model.mean[0], cb - model.mean[1]
        inv = np.linalg.inv(model.cov)
        m2 = inv[0, 0] * d0 ** 2 + 2 * inv[0, 1] * d0 * d1 + inv[1, 1] * d1 ** 2
        table = model._table = (m2 < model.threshold).astype(np.uint8).ravel()
    return table


def marker_mask(image: np.ndarray, model: ChromaModel) -> np.ndarray:
    """Pixels (bool, H x W) whose chroma is within the model's threshold."""
    ycc = cv2.cvtColor(image, cv2.COLOR_BGR2YCrCb)
    index = (ycc[..., 1].astype(np.uint16) << 8) | ycc[..., 2]
    return chroma_table(model)[index].astype(bool) & (ycc[..., 0] >= model.min_luma)


def detect_markers(image: np.ndarray, model: ChromaModel) -> np.ndarray:
    """Centroids (Q, 2) (x, y pixels) of the blobs of marker pixels of a BGR image."""
    mask = marker_mask(image, model).astype(np.uint8)
    n, _, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    area = stats[1:, cv2.CC_STAT_AREA]
    keep = (area >= model.min_area) & (area <= model.max_area)
    return centroids[1:][keep].astype(np.float64)


def frame_markers(image: np.ndarray, model: ChromaModel, scale: int = 1) -> np.ndarray:
    """The detections (Q, 2) float32 of an image reduced ``scale`` times from the camera's
    calibrated size, in the calibrated pixels (pixel centres map as ``(x + 0.5) s - 0.5``)."""
    found = detect_markers(image, model)
    return ((found + 0.5) * scale - 0.5).astype(np.float32) if scale != 1 else found.astype(np.float32)


RECORDING_MODEL = "markers.json"


def model_for_run(path: str, recording: str | None, who: str) -> ChromaModel:
    """The chroma model a worker detects with: the file ``path``, or with ``""`` or
    ``"recording"`` the recording's ``markers.json``; neither is a one-line
    :class:`InputError` naming ``who``."""
    if path and path != "recording":
        return ChromaModel.load(path)
    if recording and (Path(recording) / RECORDING_MODEL).is_file():
        return ChromaModel.load(Path(recording) / RECORDING_MODEL)
    raise InputError(f"{who}: no marker colour model (the parameter, or the recording's {RECORDING_MODEL}; "
                     "make one with `smartroom markers learn`)")
