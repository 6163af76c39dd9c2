"""HumanEva-I camera calibration files (``C1.cal``, ``BW1.cal``... one per camera).

Convention: HumanEva-I calibrated its cameras with Bouguet's Camera Calibration Toolbox
for Matlab, and each ``.cal`` file lists that toolbox's parameters as whitespace-separated
numbers, in the toolbox's order: ``fc`` (2: fx fy, pixels), ``cc`` (2: principal point,
pixels, the origin at the top-left pixel's centre as in the toolbox), ``alpha_c`` (1: skew
coefficient, ``K[0,1] = alpha_c * fx``), ``kc`` (5: k1 k2 p1 p2 k3, OpenCV's order, which
OpenCV took from the toolbox), ``Rc`` (9: world-to-camera rotation, row by row) and ``Tc``
(3: world-to-camera translation in millimetres), 22 numbers in all. The files do not carry
the image size: HumanEva-I's colour (C1-C3) and grey (BW1-BW4) cameras are 640x480, the
default, else give ``--size WxH``.

This order was written from the dataset's documentation as we know it, without a
HumanEva-I file at hand to compare with: check an import with ``smartroom calibrate
check --recording`` (the floor grid must lie on the floor).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.formats.common import FormatError, Imported, make_camera, numbers

__all__ = ["read_humaneva", "HUMANEVA_SIZE"]

HUMANEVA_SIZE = (640, 480)


def read_humaneva(paths, size=None) -> Imported:
    """One camera per ``.cal`` file, named after the file's stem."""
    cams = []
    for i, path in enumerate(paths):
        p = Path(path)
        if not p.is_file():
            raise FormatError(f"{p}: file not found")
        v = numbers(p.read_text(encoding="utf-8", errors="replace"), 22, p,
                    "fc cc alpha_c kc Rc Tc")
        fc, cc, alpha, kc, Rc, Tc = v[0:2], v[2:4], v[4], v[5:10], v[10:19].reshape(3, 3), v[19:22]
        K = np.array([[fc[0], alpha * fc[0], cc[0]], [0.0, fc[1], cc[1]], [0.0, 0.0, 1.0]])
        w, h = size or HUMANEVA_SIZE
        cams.append(make_camera(p, i, p.name.split(".")[0], int(w), int(h), K, kc, Rc, Tc / 1000.0))
    notes = [f"{len(cams)} HumanEva-I camera(s): Bouguet toolbox order fc cc alpha_c kc Rc Tc, Tc in millimetres, "
             f"image {(size or HUMANEVA_SIZE)[0]}x{(size or HUMANEVA_SIZE)[1]}"]
    return Imported(cams, None, notes)
