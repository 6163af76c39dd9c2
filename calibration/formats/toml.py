"""The TOML camera file of aniposelib / Anipose, Pose2Sim, FreeMoCap and Caliscope.

Convention (aniposelib ``cameras.py`` ``Camera.get_dict`` / ``CameraGroup.dump``, which
Pose2Sim's ``toml_write``, FreeMoCap and Caliscope follow): one table per camera, e.g.
``[cam_0]``, with

- ``name`` (Caliscope writes ``port`` instead; the table name is used when neither is there),
- ``size = [width, height]`` in pixels (Pose2Sim may write floats such as ``1088.0``),
- ``matrix`` the 3x3 OpenCV intrinsic matrix, pixel origin at the top-left pixel's centre,
- ``distortions`` OpenCV ``k1 k2 p1 p2 [k3]``,
- ``rotation`` the world-to-camera rotation as a Rodrigues vector (``cv2.Rodrigues``),
- ``translation`` the world-to-camera translation: ``x_cam = R x_world + t``,

and tables without ``matrix`` (``[metadata]``) ignored. Units of ``translation`` are those of
the calibration board: Pose2Sim writes metres, Anipose/aniposelib whatever the board's
square length was given in (often millimetres), so ``--units auto`` guesses and says so.
Tables with ``fisheye = true`` are refused (the fisheye model is not the pinhole model).
"""
from __future__ import annotations

import tomllib
from pathlib import Path


from calibration.camera import Camera
from calibration.formats.common import FormatError, Imported, fail, make_camera, metres_per_unit, numbers, rotation

__all__ = ["read_toml", "write_toml"]


def read_toml(path, units: str = "auto") -> Imported:
    p = Path(path)
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FormatError(f"{p}: file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(f"{p}: not valid TOML ({str(exc).splitlines()[0]})") from None
    tables = [(k, v) for k, v in doc.items() if isinstance(v, dict) and "matrix" in v]
    if not tables:
        raise FormatError(f"{p}: no camera table (a [cam_0] table with matrix, size, rotation, translation)")
    raw = []
    for key, tab in tables:
        for f in ("size", "matrix", "rotation", "translation"):
            if f not in tab:
                raise fail(p, f"[{key}]", f"{f} is missing")
        if tab.get("fisheye", False) is True:
            raise fail(p, f"[{key}]", "fisheye = true: the fisheye lens model is not supported")
        name = tab.get("name", tab.get("port", key))
        size = numbers(tab["size"], 2, p, f"[{key}] size")
        K = numbers(tab["matrix"], 9, p, f"[{key}] matrix").reshape(3, 3)
        dist = numbers(tab.get("distortions", [0.0] * 5), (4, 5), p, f"[{key}] distortions")
        R = rotation(tab["rotation"], p, f"[{key}] rotation")
        t = numbers(tab["translation"], 3, p, f"[{key}] translation")
        raw.append((key, name, size, K, dist, R, t))
    notes: list[str] = []
    scale = metres_per_unit(units, [r[6] for r in raw], p, notes)
    cams = []
    for i, (key, name, size, K, dist, R, t) in enumerate(raw):
        w, h = int(round(size[0])), int(round(size[1]))
        cams.append(make_camera(p, i, name, w, h, K, dist, R, t * scale))
    return Imported(cams, None, notes)


def _list(values) -> str:
    return "[ " + ", ".join(repr(float(v)) for v in values) + ",]"


def write_toml(cameras: list[Camera], path) -> None:
    """Write cameras as aniposelib / Pose2Sim TOML (translation in metres)."""
    import cv2

    from app.files import write_atomic

    out = []
    for i, c in enumerate(cameras):
        rvec = cv2.Rodrigues(c.R)[0].ravel()
        name = c.name.replace("\\", "\\\\").replace('"', '\\"')
        out += [f"[cam_{i}]", f'name = "{name}"', f"size = [ {int(c.width)}, {int(c.height)},]",
                "matrix = [ " + ", ".join(_list(row) for row in c.K) + ",]",
                f"distortions = {_list(c.dist)}", f"rotation = {_list(rvec)}",
                f"translation = {_list(c.t)}", "fisheye = false", ""]
    out += ["[metadata]", "adjusted = false", "error = 0.0", ""]
    write_atomic(Path(path), "\n".join(out))
