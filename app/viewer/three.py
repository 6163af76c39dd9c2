"""meshcat commands and the three.js JSON objects they carry, as plain dicts.

meshcat's page (three.js r132 behind meshcat 0.3.2) takes ``set_object`` commands
holding three.js "Object" JSON, ``set_transform`` (a column-major 4x4),
``set_property`` and ``delete``, each addressed by a path such as
``/meshcat/smartroom/voxels``. meshcat-python 0.3.2 has no text labels and sends
colours as floats; these builders add what the viewer needs: sprites (labels that
always face the viewer) textured with a PNG rendered here, uint8 colours normalised
on the GPU (a quarter of the bytes), and materials drawn on top of everything
(skeletons inside a voxel body stay visible).
"""
from __future__ import annotations

import base64
import uuid

import cv2
import numpy as np
import umsgpack

__all__ = [
    "set_object", "set_transform", "set_property", "delete", "set_animation", "track", "set_control",
    "points", "line_segments", "line_strip", "triangles", "group", "named", "sprite", "text_image", "hex_colour",
]

_EXT = {np.dtype(np.uint8): ("Uint8Array", 0x12), np.dtype(np.uint32): ("Uint32Array", 0x16),
        np.dtype(np.float32): ("Float32Array", 0x17)}
DOUBLE_SIDE = 2
LINEAR_FILTER = 1006


# -- commands -----------------------------------------------------------------------

def set_object(path: str, obj: dict) -> dict:
    return {"type": "set_object", "path": path, "object": obj}


def set_transform(path: str, matrix) -> dict:
    m = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
    return {"type": "set_transform", "path": path, "matrix": [float(v) for v in m.T.ravel()]}


def set_property(path: str, key: str, value) -> dict:
    return {"type": "set_property", "path": path, "property": key, "value": value}


def delete(path: str) -> dict:
    return {"type": "delete", "path": path}


def set_animation(path: str, tracks: list[dict], fps: float, play: bool = True, repetitions: int = 1,
                  more=()) -> dict:
    """A three.js AnimationClip on the object at ``path`` (meshcat's Animations panel: play,
    pause, reset, a time slider). ``tracks``: :func:`track` dicts, key times in frames;
    ``more``: further ``(path, tracks)`` played with it."""
    clips = [{"path": p, "clip": {"fps": float(fps), "name": "default", "tracks": t}}
             for p, t in [(path, tracks), *more]]
    return {"type": "set_animation", "path": "", "options": {"play": bool(play), "repetitions": int(repetitions)},
            "animations": clips}


def track(target: str, prop: str, kind: str, times, values) -> dict:
    """One keyframe track: ``target`` is a descendant's name (or "" for the object itself),
    ``prop`` e.g. ``visible`` / ``position``, ``kind`` three.js's (``boolean``, ``vector3``)."""
    name = f"{target}.{prop}" if target else f".{prop}"
    return {"name": name, "type": kind,
            "keys": [{"time": float(t), "value": v} for t, v in zip(times, values)]}


def set_control(name: str, callback: str, value=None, lo=None, hi=None, step=None) -> dict:
    """A control in the page's panel (meshcat's ``set_control``): a button running the
    JavaScript function ``callback`` or, with ``value``, a slider calling it with the new
    value. The page evaluates ``callback`` when the control is made."""
    cmd = {"type": "set_control", "name": name, "callback": callback}
    if value is not None:
        cmd.update(value=value, min=lo, max=hi, step=step)
    return cmd


# -- pieces ----------------------------------------------------------------------------

def _uuid() -> str:
    return str(uuid.uuid4())


def hex_colour(rgb) -> int:
    """0xRRGGBB of an RGB colour in [0, 1]."""
    r, g, b = (int(round(float(np.clip(c, 0.0, 1.0)) * 255)) for c in rgb)
    return (r << 16) | (g << 8) | b


def _attribute(a: np.ndarray, normalized: bool = False) -> dict:
    """A BufferGeometry attribute from an (N, k) array (float64 sent as float32)."""
    a = np.asarray(a)
    if a.dtype == np.float64:
        a = a.astype(np.float32)
    name, code = _EXT[a.dtype]
    a = np.ascontiguousarray(a)
    return {"itemSize": 1 if a.ndim == 1 else int(a.shape[1]), "type": name,
            "array": umsgpack.Ext(code, a.tobytes()), "normalized": bool(normalized)}


def _colour_attribute(colours) -> dict:
    c = np.asarray(colours)
    if c.dtype == np.uint8:
        return _attribute(c.reshape(-1, 3), normalized=True)
    return _attribute(np.asarray(c, dtype=np.float32).reshape(-1, 3))


def _geometry(positions, colours=None, index=None) -> dict:
    attrs = {"position": _attribute(np.asarray(positions, dtype=np.float32).reshape(-1, 3))}
    if colours is not None:
        attrs["color"] = _colour_attribute(colours)
    data = {"attributes": attrs}
    if index is not None:
        data["index"] = _attribute(np.asarray(index, dtype=np.uint32).reshape(-1))
    return {"uuid": _uuid(), "type": "BufferGeometry", "data": data}


def _material(kind: str, colour=(1.0, 1.0, 1.0), opacity: float = 1.0, on_top: bool = False, **extra) -> dict:
    m = {"uuid": _uuid(), "type": kind, "color": hex_colour(colour), "opacity": float(opacity),
         "transparent": bool(opacity < 1.0), "side": DOUBLE_SIDE}
    if on_top:
        m.update(depthTest=False, depthWrite=False)
    m.update(extra)
    return m


def _object(kind: str, geometry: dict | None, material: dict, matrix=None, render_order: int = 0,
            extra: dict | None = None, user_data: dict | None = None) -> dict:
    obj = {"uuid": _uuid(), "type": kind, "material": material["uuid"]}
    if user_data:
        obj["userData"] = dict(user_data)   # three.js keeps it on the object: the page can say what it shows
    if geometry is not None:
        obj["geometry"] = geometry["uuid"]
    if matrix is not None:
        obj["matrix"] = [float(v) for v in np.asarray(matrix, dtype=np.float64).reshape(4, 4).T.ravel()]
    if render_order:
        obj["renderOrder"] = int(render_order)
    data = {"metadata": {"version": 4.5, "type": "Object"},
            "geometries": [geometry] if geometry is not None else [],
            "materials": [material], "object": obj}
    if extra:
        data.update(extra)
    return data


# -- objects ---------------------------------------------------------------------------

def points(positions, colours=None, size: float = 0.02, colour=(1.0, 1.0, 1.0), attenuate: bool = True,
           on_top: bool = False, render_order: int = 0, user_data: dict | None = None) -> dict:
    """A point cloud. ``colours`` (N, 3) uint8 or float per point, else one ``colour``;
    ``size`` in metres (``attenuate``) or in pixels; ``user_data``: facts the page keeps
    with the object (the frame it belongs to)."""
    mat = _material("PointsMaterial", colour if colours is None else (1.0, 1.0, 1.0), on_top=on_top,
                    size=float(size), sizeAttenuation=bool(attenuate), vertexColors=colours is not None)
    return _object("Points", _geometry(positions, colours), mat, render_order=render_order, user_data=user_data)


def line_segments(segments, colours=None, colour=(1.0, 1.0, 1.0), opacity: float = 1.0, on_top: bool = False,
                  render_order: int = 0) -> dict:
    """Segments (K, 2, 3); ``colours`` per end point (K, 2, 3) or per segment (K, 3)."""
    seg = np.asarray(segments, dtype=np.float32).reshape(-1, 3)
    cols = None
    if colours is not None:
        c = np.asarray(colours)
        cols = np.repeat(c, 2, axis=0) if c.ndim == 2 and len(c) * 2 == len(seg) else c.reshape(-1, 3)
    mat = _material("LineBasicMaterial", colour if cols is None else (1.0, 1.0, 1.0), opacity, on_top,
                    vertexColors=cols is not None)
    return _object("LineSegments", _geometry(seg, cols), mat, render_order=render_order)


def line_strip(positions, colour=(1.0, 1.0, 1.0), opacity: float = 1.0) -> dict:
    """A polyline through ``positions`` (N, 3)."""
    return _object("Line", _geometry(positions), _material("LineBasicMaterial", colour, opacity))


def triangles(vertices, faces, colour=(1.0, 1.0, 1.0), opacity: float = 1.0, colours=None, on_top: bool = False,
              render_order: int = 0, user_data: dict | None = None) -> dict:
    """An unlit triangle mesh (a floor, a skeleton): one ``colour``, or ``colours`` per
    vertex (V, 3)."""
    mat = _material("MeshBasicMaterial", colour if colours is None else (1.0, 1.0, 1.0), opacity, on_top,
                    vertexColors=colours is not None)
    if not on_top:
        mat["depthWrite"] = opacity >= 1.0
    return _object("Mesh", _geometry(vertices, colours, index=faces), mat, render_order=render_order,
                   user_data=user_data)


def group(children: list[dict], name: str = "", matrix=None, user_data: dict | None = None) -> dict:
    """Objects (each built by the functions here) as the children of one group: one
    ``set_object`` puts all of them on the page at once (and the next replaces them at
    once). A child's ``name`` is set with :func:`named`."""
    obj = {"uuid": _uuid(), "type": "Group", "children": []}
    if name:
        obj["name"] = name
    if matrix is not None:
        obj["matrix"] = [float(v) for v in np.asarray(matrix, dtype=np.float64).reshape(4, 4).T.ravel()]
    if user_data:
        obj["userData"] = dict(user_data)
    data = {"metadata": {"version": 4.5, "type": "Object"}, "geometries": [], "materials": [], "object": obj}
    for child in children:
        for part in ("geometries", "materials", "textures", "images"):
            if child.get(part):
                data.setdefault(part, []).extend(child[part])
        obj["children"].append(child["object"])
    return data


def named(obj: dict, name: str) -> dict:
    """``obj`` (a built object) with a name: the page finds it by that name."""
    obj["object"]["name"] = name
    return obj


def sprite(png: bytes, height: float, aspect: float, position=(0.0, 0.0, 0.0), render_order: int = 10,
           attenuate: bool = False, mime: str = "image/png", user_data: dict | None = None) -> dict:
    """A label: a PNG on a sprite (it always faces the viewer) drawn over everything,
    centred at ``position`` in its node's frame (``mime``: another image type, e.g. a
    camera's JPEG). ``height``: metres when ``attenuate``,
    else a fixed size on screen (about ``height / 1.53`` of the view's height with
    meshcat's 75 degree camera), whatever the distance."""
    image = {"uuid": _uuid(), "url": f"data:{mime};base64," + base64.b64encode(png).decode("ascii")}
    texture = {"uuid": _uuid(), "image": image["uuid"], "wrap": [1001, 1001], "repeat": [1, 1],
               "minFilter": LINEAR_FILTER, "magFilter": LINEAR_FILTER, "generateMipmaps": False}
    mat = _material("SpriteMaterial", on_top=True, map=texture["uuid"], transparent=True,
                    sizeAttenuation=bool(attenuate))
    m = np.diag([height * aspect, height, 1.0, 1.0])
    m[:3, 3] = np.asarray(position, dtype=np.float64).reshape(3)
    return _object("Sprite", None, mat, matrix=m, render_order=render_order,
                   extra={"textures": [texture], "images": [image]}, user_data=user_data)


def text_image(text: str, colour=(1.0, 1.0, 1.0), scale: float = 1.0,
               outline=(0.05, 0.05, 0.05)) -> tuple[bytes, float]:
    """``text`` rendered as a PNG (transparent background, outlined letters) and its
    width/height ratio."""
    from app.drawing import outlined_text
    font, thick = cv2.FONT_HERSHEY_DUPLEX, max(1, int(round(2 * scale)))
    fs = 1.2 * scale
    (w, h), base = cv2.getTextSize(text, font, fs, thick)
    ring = thick + 1
    pad = ring + thick + 2
    img = np.zeros((h + base + 2 * pad, w + 2 * pad, 4), np.uint8)

    def bgr(rgb):
        return (int(rgb[2] * 255), int(rgb[1] * 255), int(rgb[0] * 255))

    outlined_text(img, text, (pad, pad + h), fs, bgr(colour), thick, outline=ring, outline_colour=bgr(outline),
                  font=font)
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV always encodes a small BGRA image
        raise ValueError("cannot encode the label image")
    return buf.tobytes(), img.shape[1] / img.shape[0]
