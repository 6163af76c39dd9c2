"""Qualisys QTM calibration export (``.qca`` / ``.qca.txt``, XML).

Convention, from Pose2Sim's ``read_qca`` / ``calib_qca_fun`` (perfanalytics/pose2sim,
``Pose2Sim/calibration.py``), the QTM RT-protocol camera fields, and real exports:

- ``cameras/camera``: one per camera; ``serial`` is the camera's name. Only video cameras
  are kept (``model`` containing "Video", or ``none``) when the file has any; marker-only
  (infrared) cameras have no video to match.
- ``intrinsic``: ``focalLengthU/V``, ``centerPointU/V`` in *sensor units*, 1/64 pixel of
  the full sensor, so pixels are the value / 64. The principal point is relative to the
  full sensor: the video's window ``fov_video`` (``left top right bottom``, inclusive
  sensor pixels) is subtracted, ``cx = centerPointU / 64 - left``. The image is
  ``right - left + 1`` by ``bottom - top + 1`` pixels (Pose2Sim writes ``right - left``,
  one pixel short). ``video_resolution`` (e.g. ``720p``) scales all of that by
  ``720 / 1080`` and a sensor binning factor (``--binning``) divides it.
- Distortion ``radialDistortion1..3``, ``tangentalDistortion1..2`` are OpenCV's
  ``k1 k2 k3 p1 p2`` as they are (dimensionless; Pose2Sim divides them by 64 too, which
  makes them ~0: we do not, the magnitudes in real files, ~0.1, are those of k1).
- ``transform``: ``x y z`` the camera centre in millimetres; ``r11..r33`` a matrix ``M``
  (row i, column j from ``rij``) taking world vectors to QTM's camera frame, whose y axis
  points up and z axis backwards. OpenCV's camera (y down, z forward) is that frame
  turned 180 degrees about x: ``R = diag(1, -1, -1) M``, ``t = -R C``.
- ``viewrotation`` (0, 90, 180, 270) is the rotation QTM applies to the camera's view;
  it is applied to the camera (clockwise, :func:`calibration.transform.turned`) so the
  calibration matches a video exported in that orientation, and the import says so;
  ``--view-rotation ignore`` keeps the sensor's orientation.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.formats.common import FormatError, Imported, fail, make_camera, numbers, read_xml
from calibration.transform import turned

__all__ = ["read_qualisys"]

FLIP = np.diag([1.0, -1.0, -1.0])


def _attr(el, key, path, where) -> float:
    v = el.get(key)
    if v is None:
        raise fail(path, where, f"{key} is missing")
    return float(numbers(v, 1, path, f"{where} {key}")[0])


def read_qualisys(path, binning: int = 1, view_rotation: str = "apply") -> Imported:
    p = Path(path)
    root = read_xml(p)
    cams = root.findall(".//cameras/camera")
    if not cams:
        raise FormatError(f"{p}: no cameras/camera element (not a QTM calibration)")
    video = [c for c in cams if "video" in (c.get("model") or "").lower() or (c.get("model") or "none") == "none"]
    notes = []
    if video and len(video) < len(cams):
        skipped = [c.get("serial", "?") for c in cams if c not in video]
        notes.append(f"{p.name}: kept the {len(video)} video cameras, skipped marker cameras {', '.join(skipped)}")
    chosen = video or cams
    out = []
    for i, c in enumerate(chosen):
        serial = c.get("serial")
        if not serial:
            raise fail(p, f"camera[{i}]", "serial is missing")
        where = f"camera {serial}"
        intr, tr, fov = c.find("intrinsic"), c.find("transform"), c.find("fov_video")
        for el, tag in ((intr, "intrinsic"), (tr, "transform"), (fov, "fov_video")):
            if el is None:
                raise fail(p, where, f"{tag} is missing")
        res = (c.get("video_resolution") or "").strip().lower().rstrip("p")
        scale = 1.0 / binning
        if res:
            try:
                scale *= int(res) / 1080.0
            except ValueError:
                raise fail(p, where, f"video_resolution {c.get('video_resolution')!r} is not like 1080p") from None
        left, top = _attr(fov, "left", p, where + " fov_video"), _attr(fov, "top", p, where + " fov_video")
        right, bottom = _attr(fov, "right", p, where + " fov_video"), _attr(fov, "bottom", p, where + " fov_video")
        w, h = round((right - left + 1) * scale), round((bottom - top + 1) * scale)
        fu, fv = _attr(intr, "focalLengthU", p, where), _attr(intr, "focalLengthV", p, where)
        cu, cv = _attr(intr, "centerPointU", p, where), _attr(intr, "centerPointV", p, where)
        K = np.array([[fu / 64 * scale, 0.0, (cu / 64 - left) * scale],
                      [0.0, fv / 64 * scale, (cv / 64 - top) * scale], [0.0, 0.0, 1.0]])
        g = lambda k: float(intr.get(k) or 0.0)  # noqa: E731  absent terms are zero
        dist = [g("radialDistortion1"), g("radialDistortion2"), g("tangentalDistortion1"),
                g("tangentalDistortion2"), g("radialDistortion3")]
        M = np.array([[_attr(tr, f"r{a}{b}", p, where + " transform") for b in (1, 2, 3)] for a in (1, 2, 3)])
        centre = np.array([_attr(tr, k, p, where + " transform") for k in ("x", "y", "z")]) / 1000.0
        R = FLIP @ M
        cam = make_camera(p, i, serial, int(w), int(h), K, dist, R, -R @ centre)
        rot = int(float(c.get("viewrotation") or 0)) % 360
        if rot and view_rotation == "apply":
            cam = turned(cam, rot)
            notes.append(f"{p.name}: camera {serial}: viewrotation {rot} applied (image turned {rot} degrees "
                         f"clockwise, now {cam.width}x{cam.height}; --view-rotation ignore keeps the sensor's)")
        out.append(cam)
    notes.append(f"{p.name}: sensor units / 64 = pixels, principal point minus the fov_video offsets, "
                 "millimetres to metres, QTM camera frame turned 180 degrees about x")
    return Imported(out, None, notes)

