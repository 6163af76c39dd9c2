"""A learned 2D body-keypoint detector run top-down on each tracked person (issue 23).

The model is BlazePose's full landmark network (``pose_landmark_full.tflite``, Apache-2.0,
6.4 MB), the one pose model that an installable package ships inside its distribution:
the wheel of ``mediapipe==0.10.14`` (later mediapipe releases download their models at
run time, which a kiosk without network cannot). We never import mediapipe (its
dependencies pin ``protobuf<5`` and pull ``opencv-contrib-python``, which clashes with
our ``opencv-python-headless``): it is installed with ``--no-deps`` and only its model
file is read; the network runs in LiteRT (``ai-edge-litert``, the TensorFlow Lite
runtime, on the CPU, one thread per detector). ``pip install 'smartroom[keypoints]'``
brings LiteRT; README and docs/keypoints.md give the one extra line for the model.

Top-down (Fontmarty et al. draw part of the particles from detections of body parts,
seed 001 §III-A; here the detections are a learned model's): each track's body, a
vertical cylinder of the person's stature on the floor, is projected into a camera; the
square around it, turned so that the body stands upright in it, is warped to the
network's 256 x 256 input; the 33 landmarks come back to full-image pixels with a
confidence each (the landmark's visibility times the crop's pose score), and are mapped
to the contract's 15 joints (:data:`app.messages.JOINTS`): the pelvis is the middle of
the hips, the neck the middle of the shoulders, the head the middle of the ears (the
head's centre, as the ground truth's head joint).
"""
from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from app.errors import InputError
from app.messages import JOINTS

__all__ = ["KeypointsUnavailable", "find_model", "KeypointDetector", "Crop", "person_crop", "crop_top", "to_joints",
           "INSTALL_HINT", "INPUT"]

INPUT = 256                 # the network's square input side (pixels)
MODEL_FILE = "modules/pose_landmark/pose_landmark_full.tflite"
INSTALL_HINT = ("pip install 'smartroom[keypoints]' && pip install --no-deps mediapipe==0.10.14 "
                "(the model file only; docs/keypoints.md)")

#: BlazePose landmark indices averaged into each contract joint
_BLAZEPOSE = {
    "pelvis": (23, 24), "neck": (11, 12), "head": (7, 8),
    "l_shoulder": (11,), "l_elbow": (13,), "l_wrist": (15,),
    "r_shoulder": (12,), "r_elbow": (14,), "r_wrist": (16,),
    "l_hip": (23,), "l_knee": (25,), "l_ankle": (27,),
    "r_hip": (24,), "r_knee": (26,), "r_ankle": (28,),
}
_MAP = np.zeros((len(JOINTS), 33), dtype=np.float64)
for _j, _name in enumerate(JOINTS):
    for _k in _BLAZEPOSE[_name]:
        _MAP[_j, _k] = 1.0 / len(_BLAZEPOSE[_name])
#: the first and last landmark of each joint (the same one for a joint of one landmark)
_ENDS = np.array([(_BLAZEPOSE[n][0], _BLAZEPOSE[n][-1]) for n in JOINTS], dtype=np.int64)


class KeypointsUnavailable(InputError):
    """The keypoint cue was asked for but its runtime or model is not installed."""


def find_model(path: str | Path | None = None) -> Path:
    """The landmark model: ``path`` when given, else the file the mediapipe 0.10.14
    distribution ships (found without importing mediapipe). One-line error otherwise."""
    if path:
        p = Path(path).expanduser()
        if not p.is_file():
            raise KeypointsUnavailable(f"keypoints: model file {p} not found")
        return p
    spec = importlib.util.find_spec("mediapipe")
    for root in (spec.submodule_search_locations or []) if spec is not None else []:
        p = Path(root) / MODEL_FILE
        if p.is_file():
            return p
    raise KeypointsUnavailable(f"keypoints: the BlazePose model is not installed: {INSTALL_HINT}")


def _interpreter(model: Path, threads: int):
    try:
        from ai_edge_litert.interpreter import Interpreter
    except ImportError:
        raise KeypointsUnavailable(f"keypoints: the LiteRT runtime (ai-edge-litert) is not installed: "
                                   f"{INSTALL_HINT}") from None
    it = Interpreter(model_path=str(model), num_threads=max(1, int(threads)))
    it.allocate_tensors()
    return it


class Crop(NamedTuple):
    """A person's square in one image: ``A`` (2, 3) maps image pixels to the network's
    input pixels; ``side`` its side in image pixels."""
    A: np.ndarray
    side: float


def crop_top(z_centroid: float) -> float:
    """The top of a tracked body (m) for its crop, from its centroid's height: the hull's
    centroid lies at about half the person's top, standing, sitting or crouching."""
    return float(np.clip(2.0 * z_centroid, 1.0, 2.2)) + 0.1


def person_crop(camera, position, top: float, radius: float = 0.4, margin: float = 1.2,
                min_side: float = 48.0) -> Crop | None:
    """The square of ``camera`` (at the image's size) around a person standing at
    ``position`` (x, y: the track) whose top is ``top`` m above the floor, turned so that
    the body's vertical axis points up in it. None where the camera cannot give a useful
    view: the person behind it or out of the image, the axis shorter than ``min_side``
    pixels (a camera looking straight down, or far away)."""
    x, y = float(position[0]), float(position[1])
    axis = np.array([[x, y, 0.0], [x, y, top]])
    uv, z = camera.project(axis, return_depth=True)
    if not np.all(z > 0.1) or not np.all(np.isfinite(uv)):
        return None
    foot, head = uv
    d = head - foot
    length = float(np.hypot(*d))
    if length < min_side:
        return None
    ring = np.array([[x + radius * math.cos(a), y + radius * math.sin(a), h]
                     for a in np.linspace(0, 2 * math.pi, 8, endpoint=False) for h in (0.0, top * 0.5, top)])
    pts, zr = camera.project(ring, return_depth=True)
    if not np.all(zr > 0.1):
        return None
    up = d / length                         # the body's axis in the image, feet to head
    across = np.array([-up[1], up[0]])
    centre = 0.5 * (foot + head)
    rel = pts - centre
    along_ext = np.abs(rel @ up).max() * 2
    across_ext = np.abs(rel @ across).max() * 2
    side = max(along_ext, across_ext, length) * margin
    inside = (0 <= centre[0] < camera.width) and (0 <= centre[1] < camera.height)
    if not inside:
        return None
    # image -> input: a proper rotation (no mirror: the person's left stays their left)
    # taking `up` to the input's -y and `across` (the image's u for an upright body) to
    # its x, then the scale, centred
    s = INPUT / side
    R = np.stack([across, -up]) * s
    A = np.hstack([R, (INPUT / 2 - R @ centre)[:, None]])
    return Crop(A=A.astype(np.float64), side=float(side))


def to_joints(landmarks: np.ndarray, score: float) -> np.ndarray:
    """``(15, 3)`` u, v, confidence from the network's ``(33, 5)`` landmarks (x, y, z,
    visibility logit, presence logit) already in image pixels, and the crop's pose score."""
    lm = np.asarray(landmarks, dtype=np.float64)
    vis = 1.0 / (1.0 + np.exp(-np.clip(lm[:, 3], -30, 30)))
    out = np.empty((len(JOINTS), 3))
    out[:, :2] = _MAP @ lm[:, :2]
    # a joint made of several landmarks is as sure as its least sure one
    out[:, 2] = np.minimum(vis[_ENDS[:, 0]], vis[_ENDS[:, 1]]) * float(score)
    return out


class KeypointDetector:
    """The landmark network on person crops (one LiteRT interpreter, ``threads`` threads)."""

    def __init__(self, model: str | Path | None = None, threads: int = 1):
        self.model_path = find_model(model)
        self.it = _interpreter(self.model_path, threads)
        self._in = self.it.get_input_details()[0]["index"]
        outs = {d["name"]: d["index"] for d in self.it.get_output_details()}
        self._landmarks = outs["Identity"]
        self._score = outs["Identity_1"]

    def run(self, patch_rgb: np.ndarray) -> tuple[np.ndarray, float]:
        """``(33, 5)`` landmarks in input pixels and the pose score (0-1) of one
        ``INPUT x INPUT`` RGB uint8 patch."""
        x = np.ascontiguousarray(patch_rgb, dtype=np.float32)[None] * np.float32(1.0 / 255.0)
        self.it.set_tensor(self._in, x)
        self.it.invoke()
        lm = self.it.get_tensor(self._landmarks).reshape(-1, 5)[:33].astype(np.float64)
        score = float(1.0 / (1.0 + math.exp(-float(np.clip(self.it.get_tensor(self._score).ravel()[0], -30, 30)))))
        return lm, score

    def detect(self, image_bgr: np.ndarray, crop: Crop) -> np.ndarray:
        """``(15, 3)`` joints (u, v in the image's pixels, confidence) of the person in ``crop``."""
        patch = cv2.warpAffine(image_bgr, crop.A, (INPUT, INPUT), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT)
        lm, score = self.run(cv2.cvtColor(patch, cv2.COLOR_BGR2RGB))
        inv = cv2.invertAffineTransform(crop.A)
        # a landmark the network puts far outside its input (a crop it cannot read) is none
        bad = ~np.all(np.isfinite(lm), axis=1) | np.any(np.abs(lm[:, :2] - INPUT / 2) > INPUT, axis=1)
        lm[bad] = (INPUT / 2, INPUT / 2, 0.0, -30.0, -30.0)
        lm[:, :2] = lm[:, :2] @ inv[:, :2].T + inv[:, 2]
        return to_joints(lm, score if np.isfinite(score) else 0.0)
