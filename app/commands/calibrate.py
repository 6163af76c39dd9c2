"""``smartroom calibrate``: check a calibration and import other formats.

- ``smartroom calibrate check FILE``: validate and summarise (cameras, centres, fields of view).
- ``smartroom calibrate import-opencv --out FILE --fps F --room X0,Y0,Z0,X1,Y1,Z1 CAM=FILE.yml ...``:
  build ``calibration.yaml`` from OpenCV FileStorage files holding ``camera_matrix``,
  ``distortion_coefficients``, ``rvec`` (or ``R``), ``tvec`` and ``image_width/height``.
"""
from __future__ import annotations

import math


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    c = sub.add_parser("check", help="validate a calibration.yaml and summarise it")
    c.add_argument("file", help="calibration.yaml or a recording folder")
    i = sub.add_parser("import-opencv", help="build calibration.yaml from OpenCV FileStorage files")
    i.add_argument("cameras", nargs="+", metavar="CAM=FILE", help="camera name and its OpenCV .yml/.xml file")
    i.add_argument("--out", required=True, help="calibration.yaml to write")
    i.add_argument("--fps", type=float, required=True, help="frame rate of the cameras")
    i.add_argument("--room", required=True, help="analysed volume: xmin,ymin,zmin,xmax,ymax,zmax in metres")


def _check(args) -> int:
    from calibration import load_calibration

    calib = load_calibration(args.file)
    print(f"{calib.path}: {len(calib.cameras)} cameras at {calib.fps:g} fps, room "
          f"{calib.room_min.tolist()} .. {calib.room_max.tolist()} m")
    for c in calib.cameras:
        hfov = 2 * math.degrees(math.atan(c.width / (2 * c.K[0, 0])))
        print(f"  {c.name}: {c.width}x{c.height}, hfov {hfov:.0f} deg, centre "
              f"[{', '.join(f'{v:.2f}' for v in c.centre)}], distortion {'yes' if c.has_distortion else 'none'}")
    return 0


def _import_opencv(args) -> int:
    import cv2
    import numpy as np

    from app.errors import InputError
    from calibration import Calibration, Camera, save_calibration

    try:
        room = [float(v) for v in args.room.split(",")]
    except ValueError:
        room = []
    if len(room) != 6:
        raise InputError("--room must be xmin,ymin,zmin,xmax,ymax,zmax")
    cams = []
    for item in args.cameras:
        if "=" not in item:
            raise InputError(f"{item}: expected CAM=FILE")
        name, path = item.split("=", 1)
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
        if not fs.isOpened():
            raise InputError(f"{path}: cannot be opened as an OpenCV FileStorage file")

        def mat(key, _fs=fs):
            node = _fs.getNode(key)
            return None if node.empty() else node.mat()

        K, dist = mat("camera_matrix"), mat("distortion_coefficients")
        R, rvec, tvec = mat("R"), mat("rvec"), mat("tvec")
        width, height = fs.getNode("image_width").real(), fs.getNode("image_height").real()
        if K is None or tvec is None or (R is None and rvec is None) or not width or not height:
            raise InputError(f"{path}: needs camera_matrix, tvec, R or rvec, image_width and image_height")
        if R is None:
            R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3))
        cams.append(Camera(name=name, width=int(width), height=int(height), K=K,
                           dist=np.zeros(5) if dist is None else dist.ravel()[:5], R=R, t=np.ravel(tvec)))
    calib = Calibration(args.fps, np.array(room[:3]), np.array(room[3:]), tuple(cams), args.out)
    save_calibration(calib, args.out)
    from calibration import load_calibration
    load_calibration(args.out)  # validate what was written
    print(f"smartroom: wrote {args.out} with {len(cams)} cameras")
    return 0


def main(args) -> int:
    return {"check": _check, "import-opencv": _import_opencv}[args.action](args)
