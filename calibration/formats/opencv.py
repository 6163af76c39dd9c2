"""OpenCV FileStorage files (YAML ``%YAML:1.0`` or XML), one camera per file, and
EasyMocap's ``intri.yml`` + ``extri.yml`` pair.

OpenCV convention (``cv::FileStorage`` as written by OpenCV's ``calibration.cpp`` sample
and by ``cv2.FileStorage.write``): ``camera_matrix`` (also accepted: ``K``,
``cameraMatrix``, ``M``), ``distortion_coefficients`` (``dist``, ``D``, ``distCoeffs``) in
OpenCV order ``k1 k2 p1 p2 [k3 ...]``, the pose as ``R`` (3x3) or ``rvec`` (Rodrigues;
also ``rotation``), and ``T`` / ``tvec`` / ``translation``, world-to-camera
(``x_cam = R x_world + t``), and ``image_width`` + ``image_height`` (or ``image_size``,
``width``/``height``). Only the first 5 distortion terms are kept; more non-zero terms
(the rational model) are refused.

EasyMocap convention (``easymocap/mytools/camera_utils.py`` ``read_camera`` /
``write_camera``): ``intri.yml`` holds ``names`` (a list) and per camera ``K_<name>``,
``dist_<name>`` (or ``D_<name>``), and optionally ``H_<name>``/``W_<name>`` (image
height/width); ``extri.yml`` holds ``names`` and per camera ``R_<name>`` (Rodrigues,
world to camera), ``Rot_<name>`` (the same as a matrix) and ``T_<name>`` in metres. Files
without ``H_``/``W_`` get the size from ``--size`` or, failing that, twice the principal
point (as Pose2Sim's converter does), and the import says so.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from calibration.formats.common import FormatError, Imported, fail, make_camera, metres_per_unit, numbers, rotation

__all__ = ["read_opencv", "read_easymocap", "write_opencv"]

_K = ("camera_matrix", "K", "cameraMatrix", "M", "intrinsic_matrix")
_DIST = ("distortion_coefficients", "dist", "D", "distCoeffs", "dist_coeffs")
_R = ("R", "rvec", "rotation", "rotation_matrix")
_T = ("T", "tvec", "translation", "t")


def _open(path) -> cv2.FileStorage:
    p = Path(path)
    if not p.is_file():
        raise FormatError(f"{p}: file not found")
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except cv2.error:
        fs = None
    if fs is None or not fs.isOpened():
        raise FormatError(f"{p}: cannot be read as an OpenCV FileStorage file (YAML starting %YAML:1.0, or XML)")
    return fs


def _node(fs, keys):
    for k in keys:
        node = fs.getNode(k)
        if not node.empty():
            return k, node
    return None, None


def _value(node):
    if node.isSeq():
        return [node.at(i).real() for i in range(node.size())]
    if node.isReal() or node.isInt():
        return node.real()
    m = node.mat()
    return m if m is not None else node.string()


def _dist(values, path, where) -> np.ndarray:
    d = numbers(values, None, path, where)
    if d.size > 5 and np.any(d[5:] != 0):
        raise fail(path, where, f"has {d.size} terms; only k1 k2 p1 p2 k3 are supported")
    if d.size < 4 and d.size != 0:
        raise fail(path, where, f"must list k1 k2 p1 p2 [k3], got {d.size} numbers")
    return d[:5] if d.size else np.zeros(5)


def read_opencv(path, name: str | None = None, units: str = "m", size=None, pose: bool = True) -> Imported:
    """One camera from an OpenCV FileStorage file; ``name`` defaults to the file's stem.
    With ``pose=False`` (intrinsics only) a missing pose is the identity."""
    p = Path(path)
    fs = _open(p)
    try:
        kname, knode = _node(fs, _K)
        if knode is None:
            raise fail(p, "", f"no camera matrix (looked for {', '.join(_K)})")
        K = numbers(_value(knode), 9, p, kname).reshape(3, 3)
        dname, dnode = _node(fs, _DIST)
        dist = _dist(_value(dnode), p, dname) if dnode is not None else np.zeros(5)
        rname, rnode = _node(fs, _R)
        tname, tnode = _node(fs, _T)
        if (rnode is None or tnode is None) and pose:
            raise fail(p, "", f"no pose (needs one of {', '.join(_R)} and one of {', '.join(_T)})")
        R = rotation(_value(rnode), p, rname) if rnode is not None else np.eye(3)
        t = numbers(_value(tnode), 3, p, tname) if tnode is not None else np.zeros(3)
        w = h = None
        for wk, hk in (("image_width", "image_height"), ("width", "height"), ("W", "H")):
            wn, hn = fs.getNode(wk), fs.getNode(hk)
            if not wn.empty() and not hn.empty():
                w, h = wn.real(), hn.real()
                break
        sn = fs.getNode("image_size")
        if w is None and not sn.empty():
            w, h = numbers(_value(sn), 2, p, "image_size")
    finally:
        fs.release()
    notes: list[str] = []
    if w is None:
        if size is None:
            raise fail(p, "", "no image size (image_width and image_height, or image_size); give --size WxH")
        w, h = size
    scale = metres_per_unit(units, [t], p, notes)
    cam = make_camera(p, 0, name or p.name.split(".")[0], int(round(w)), int(round(h)), K, dist, R, t * scale)
    return Imported([cam], None, notes)


def _names(fs, path) -> list[str]:
    node = fs.getNode("names")
    if node.empty() or not node.isSeq() or node.size() == 0:
        raise fail(path, "names", "is missing or empty (EasyMocap lists the cameras in names)")
    out = []
    for i in range(node.size()):
        v = node.at(i)
        s = v.string()
        out.append(s if s else str(int(v.real())))
    return out


def read_easymocap(intri, extri=None, units: str = "m", size=None) -> Imported:
    """EasyMocap ``intri.yml`` + ``extri.yml`` (``extri`` defaults to the sibling file)."""
    ip = Path(intri)
    if ip.is_dir():
        ip = ip / "intri.yml"
    ep = Path(extri) if extri else ip.with_name("extri.yml")
    fi, fe = _open(ip), _open(ep)
    notes: list[str] = []
    raw = []
    try:
        names = _names(fi, ip)
        ext_names = set(_names(fe, ep))
        for n in names:
            if n not in ext_names:
                raise fail(ep, "names", f"has no camera {n} (listed in {ip.name})")
            kn = fi.getNode(f"K_{n}")
            if kn.empty():
                raise fail(ip, f"K_{n}", "is missing")
            K = numbers(kn.mat(), 9, ip, f"K_{n}").reshape(3, 3)
            dn = fi.getNode(f"dist_{n}")
            dn = fi.getNode(f"D_{n}") if dn.empty() else dn
            dist = _dist(dn.mat(), ip, f"dist_{n}") if not dn.empty() else np.zeros(5)
            rn = fe.getNode(f"Rot_{n}")
            rn = fe.getNode(f"R_{n}") if rn.empty() else rn
            if rn.empty():
                raise fail(ep, f"R_{n}", "is missing")
            R = rotation(rn.mat(), ep, f"R_{n}")
            tn = fe.getNode(f"T_{n}")
            if tn.empty():
                raise fail(ep, f"T_{n}", "is missing")
            t = numbers(tn.mat(), 3, ep, f"T_{n}")
            wn, hn = fi.getNode(f"W_{n}"), fi.getNode(f"H_{n}")
            if not wn.empty() and not hn.empty() and wn.real() > 0:
                w, h = wn.real(), hn.real()
            elif size is not None:
                w, h = size
            else:
                w, h = round(2 * K[0, 2] + 1), round(2 * K[1, 2] + 1)
                notes.append(f"{ip.name}: camera {n} has no W_/H_: size {w}x{h} guessed from the principal "
                             "point (give --size WxH, or correct it with smartroom calibrate fit)")
            raw.append((n, w, h, K, dist, R, t))
    finally:
        fi.release()
        fe.release()
    scale = metres_per_unit(units, [r[6] for r in raw], ep, notes)
    cams = [make_camera(ip, i, n, int(round(w)), int(round(h)), K, d, R, t * scale)
            for i, (n, w, h, K, d, R, t) in enumerate(raw)]
    return Imported(cams, None, notes)


def write_opencv(camera, path) -> None:
    """One camera as an OpenCV FileStorage YAML/XML file (by the extension)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise FormatError(f"{path}: cannot be written")
    fs.write("image_width", int(camera.width))
    fs.write("image_height", int(camera.height))
    fs.write("camera_matrix", camera.K)
    fs.write("distortion_coefficients", camera.dist.reshape(1, 5))
    fs.write("R", camera.R)
    fs.write("rvec", cv2.Rodrigues(camera.R)[0])
    fs.write("tvec", camera.t.reshape(3, 1))
    fs.release()
