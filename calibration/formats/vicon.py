"""Vicon Nexus / Shogun camera calibration (``.xcp``, XML).

Convention, from Pose2Sim's ``read_vicon`` / ``calib_vicon_fun`` (perfanalytics/pose2sim)
and other readers of the format (OpenCap tools, Matlab converters):

- ``Camera`` elements (under ``Cameras``): ``DEVICEID`` is the name (``USERID`` when there is
  no DEVICEID), ``SENSOR_SIZE="w h"`` the image size in pixels, ``PIXEL_ASPECT_RATIO``
  (``fy = fx / ratio``). Only video cameras (``TYPE``/``DISPLAY_TYPE`` containing "video"
  or "Vue") are kept when the file has any.
- the first ``KeyFrames/KeyFrame``: ``FOCAL_LENGTH`` (pixels), ``PRINCIPAL_POINT="u v"``
  (pixels), ``ORIENTATION="x y z w"`` a unit quaternion, scalar last, of the camera's
  orientation in the world (camera to world: ``R = Q^T``), ``POSITION="x y z"`` the camera
  centre in millimetres (``t = -R C``).
- ``VICON_RADIAL2="<model> <cx> <cy> k1 k2 [k3]"``: Vicon's radial terms, taken as OpenCV's
  ``k1 k2 k3`` with no tangential terms, as Pose2Sim does. Vicon's own model maps
  distorted to undistorted pixels about its own centre, so this is an approximation when
  the coefficients are not zero: check the result with ``smartroom calibrate check``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from calibration.formats.common import FormatError, Imported, fail, make_camera, numbers, read_xml

__all__ = ["read_vicon"]


def read_vicon(path) -> Imported:
    p = Path(path)
    root = read_xml(p)
    cams = root.findall(".//Camera")
    if not cams:
        raise FormatError(f"{p}: no Camera element (not a Vicon .xcp file)")

    def is_video(c):
        kind = ((c.get("TYPE") or "") + " " + (c.get("DISPLAY_TYPE") or "")).lower()
        return "video" in kind or "vue" in kind

    video = [c for c in cams if is_video(c)]
    notes = []
    if video and len(video) < len(cams):
        notes.append(f"{p.name}: kept the {len(video)} video cameras, skipped {len(cams) - len(video)} marker cameras")
    out = []
    for i, c in enumerate(video or cams):
        name = c.get("DEVICEID") or c.get("USERID")
        if not name:
            raise fail(p, f"Camera[{i}]", "DEVICEID is missing")
        where = f"camera {name}"
        if c.get("SENSOR_SIZE") is None:
            raise fail(p, where, "SENSOR_SIZE is missing")
        w, h = numbers(c.get("SENSOR_SIZE"), 2, p, f"{where} SENSOR_SIZE")
        aspect = float(numbers(c.get("PIXEL_ASPECT_RATIO") or "1", 1, p, f"{where} PIXEL_ASPECT_RATIO")[0])
        kf = c.find("KeyFrames/KeyFrame")
        if kf is None:
            raise fail(p, where, "KeyFrames/KeyFrame is missing")
        vals = {}
        for key, n in (("FOCAL_LENGTH", 1), ("PRINCIPAL_POINT", 2), ("ORIENTATION", 4), ("POSITION", 3)):
            if kf.get(key) is None:
                raise fail(p, f"{where} KeyFrame", f"{key} is missing")
            vals[key] = numbers(kf.get(key), n, p, f"{where} {key}")
        f = float(vals["FOCAL_LENGTH"][0])
        cu, cv = vals["PRINCIPAL_POINT"]
        K = np.array([[f, 0.0, cu], [0.0, f / aspect, cv], [0.0, 0.0, 1.0]])
        q = vals["ORIENTATION"]
        if abs(np.linalg.norm(q) - 1.0) > 1e-3:
            raise fail(p, f"{where} ORIENTATION", f"is not a unit quaternion (norm {np.linalg.norm(q):.4f})")
        R = Rotation.from_quat(q).as_matrix().T  # scipy: x y z w, scalar last
        dist = np.zeros(5)
        radial = kf.get("VICON_RADIAL2")
        if radial:
            tokens = radial.split()
            k = numbers(" ".join(tokens[3:]), (2, 3), p, f"{where} VICON_RADIAL2")
            dist[0], dist[1] = k[0], k[1]
            if k.size == 3:
                dist[4] = k[2]
        centre = vals["POSITION"] / 1000.0
        out.append(make_camera(p, i, name, int(round(w)), int(round(h)), K, dist, R, -R @ centre))
    notes.append(f"{p.name}: quaternion x y z w (camera to world), position in millimetres; "
                 "Vicon radial terms used as OpenCV k1 k2 k3 (approximate when non-zero)")
    return Imported(out, None, notes)
