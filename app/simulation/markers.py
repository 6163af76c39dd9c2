"""Coloured markers painted on the simulated people (thesis §6.6.2: small coloured balls
on the joints, seen by ordinary cameras), so the marker pipeline runs from images.

A marker sits at each of the 15 contract joints (the ground truth's ``joints`` are the
markers' true positions): a disc of ``MARKER_RADIUS`` metres at the joint's depth, of
one saturated colour (``MARKER_BGR``, a yellow like the thesis's balls), painted where
the camera sees it: not hidden by its person's own body (the capsule flesh of
:func:`app.markers.synthetic.visible_markers`) and with its person frontmost at that
pixel (the renderer's labels: another person or the furniture in front hides it).
"""
from __future__ import annotations

import cv2
import numpy as np

from app.messages import JOINTS

__all__ = ["MARKER_BGR", "MARKER_RADIUS", "paint_markers"]

MARKER_BGR = (0, 220, 250)     # yellow
MARKER_RADIUS = 0.03           # m


def paint_markers(image: np.ndarray, labels: np.ndarray, camera, people: list[tuple[int, np.ndarray, float]],
                  rng: np.random.Generator | None = None) -> list[tuple[int, int]]:
    """Paint the markers of ``people`` (``(id, joints (15, 3), stature)``) on ``image``
    (in place); the ``(person index, joint)`` painted."""
    from app.markers.synthetic import visible_markers

    if not people:
        return []
    X = np.array([j for _, j, _ in people], float).reshape(-1, len(JOINTS), 3)
    seen = visible_markers(X, [s for _, _, s in people], camera)
    uv, z = camera.project(X.reshape(-1, 3), return_depth=True)
    uv, z = uv.reshape(len(X), len(JOINTS), 2), z.reshape(len(X), len(JOINTS))
    h, w = labels.shape
    painted = []
    for p, (pid, _, _) in enumerate(people):
        for j in range(len(JOINTS)):
            if not seen[p, j]:
                continue
            u, v = uv[p, j]
            iu, iv = int(round(u)), int(round(v))
            if not (0 <= iu < w and 0 <= iv < h) or labels[iv, iu] != pid:
                continue
            r = max(1.5, MARKER_RADIUS * camera.K[0, 0] / z[p, j])
            colour = MARKER_BGR if rng is None else tuple(int(np.clip(c + rng.normal(0, 6), 0, 255))
                                                         for c in MARKER_BGR)
            cv2.circle(image, (int(round(u * 16)), int(round(v * 16))), int(round(r * 16)), colour, -1,
                       lineType=cv2.LINE_AA, shift=4)
            painted.append((p, j))
    return painted
