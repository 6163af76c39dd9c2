"""``smartroom calibrate``: make, import, check and fit camera calibrations.

- ``check FILE`` / ``check --recording DIR [--out DIR]``: validate and summarise; with a
  recording, compare each camera with its video (size, fps), draw the room box, world axes
  and floor grid on a frame of every camera (``check-<cam>.png`` and ``check.png``, a
  contact sheet), and print per-camera figures. Every problem is listed (one line each,
  naming the file and the camera), then the exit code is 1 if there was any.
- ``intrinsics --images GLOB | --video FILE --board SPEC``: K and distortion from views of
  a chessboard or ChArUco board (``cv2.calibrateCamera``), RMS reprojection error.
- ``extrinsics --intrinsics FILE... (--floor CAM=IMAGE... --board SPEC | --points FILE)``:
  each camera's pose from a board on the floor (the world: origin at the board, z up) or
  from known 3D points; ``--moved CAM=GLOB`` adds views of the board elsewhere for a joint
  refinement of all cameras.
- ``import FILE... [--format F] [--recording DIR] --out calibration.yaml``: from OpenCV,
  Qualisys QTM, Pose2Sim/Anipose/FreeMoCap/Caliscope TOML, EasyMocap, Vicon, HumanEva-I;
  with ``--recording`` the fps is the videos'.
- ``export FILE --format opencv|toml --out PATH``.
- ``fit --recording DIR [--rescale|--crop [bottom|top|centre]] [--turn DEG]``: fit the
  intrinsics to the videos, turn, rescale or crop chosen per camera from the sizes
  (:mod:`calibration.fitting`) unless given, one line per camera saying what and why.
- ``import-opencv CAM=FILE... --out FILE --fps F --room=...``: the first importer, kept.

Room bounds (``--room=xmin,ymin,zmin,xmax,ymax,zmax``, negative values fine) are estimated
from the cameras' common view of the floor when not given, and always printed.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

from calibration.room import ROOM_PATTERN

#: accept ``--room -3,-1.5,0,3,2,2.5``: argparse takes a leading ``-`` for an option unless
#: the string looks like a negative number to the parser that reads it
_NEGATIVE = re.compile(r"^-\d+$|^-\d*\.\d+$|" + ROOM_PATTERN.pattern)


def _room_option(p) -> None:
    p._negative_number_matcher = _NEGATIVE  # the leaf parser reads the values (Python 3.11+)
    p.add_argument("--room", metavar="X0,Y0,Z0,X1,Y1,Z1",
                   help="analysed volume in metres (negative values fine); estimated from the cameras when omitted")


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    c = sub.add_parser("check", help="validate a calibration; with --recording, draw it on the videos")
    c.add_argument("file", nargs="?", help="calibration.yaml or a recording folder")
    c.add_argument("--recording", help="recording folder: compare the calibration with its videos and draw it")
    c.add_argument("--out", help="folder for the check images (default: the recording folder's check/)")
    c.add_argument("--frame", type=int, default=0, help="frame drawn on (default 0)")
    c.add_argument("--grid", type=float, default=0.5, help="floor grid step in metres (default 0.5)")

    i = sub.add_parser("intrinsics", help="K and distortion of one camera from board images or a video")
    src = i.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", help="glob of board images, quoted: 'cam0/*.png'")
    src.add_argument("--video", help="a video of the board (frames sampled)")
    i.add_argument("--board", required=True, help="chessboard:9x6:0.025 or charuco:7x5:0.04:0.03[:DICT_4X4_50]")
    i.add_argument("--every", type=int, default=0, help="with --video: use every N-th frame (default: ~60 spread frames)")
    i.add_argument("--max-frames", type=int, default=60, help="with --video: frames sampled when --every is not given")
    i.add_argument("--name", default="cam0", help="camera name (default cam0)")
    i.add_argument("--fix-k3", action="store_true", help="keep k3 = 0 (few or central views)")
    i.add_argument("--out", help="OpenCV YAML file to write (camera_matrix, distortion_coefficients, size)")

    e = sub.add_parser("extrinsics", help="camera poses from a board on the floor or known 3D points")
    e.add_argument("--intrinsics", nargs="+", required=True, metavar="FILE",
                   help="calibration.yaml, or CAM=FILE OpenCV files from 'calibrate intrinsics'")
    e.add_argument("--board", help="the board (as for intrinsics)")
    e.add_argument("--floor", nargs="+", metavar="CAM=IMAGE", default=[],
                   help="each camera's image of the board lying on the floor (defines the world)")
    e.add_argument("--moved", nargs="+", metavar="CAM=GLOB", default=[],
                   help="images of the board elsewhere, the k-th file of every camera taken at once: joint refinement")
    e.add_argument("--points", help="YAML: world: {NAME: [x,y,z]}, pixels: {CAM: {NAME: [u,v]}} (instead of a board)")
    e.add_argument("--out", required=True, help="calibration.yaml to write")
    e.add_argument("--fps", type=float, default=25.0, help="frame rate of the recordings (default 25)")
    _room_option(e)

    m = sub.add_parser("import", help="calibration.yaml from another tool's calibration")
    m.add_argument("files", nargs="+", metavar="FILE", help="the file(s); CAM=FILE names a one-camera file's camera")
    m.add_argument("--format", help="opencv, toml, qualisys, easymocap, vicon, humaneva (guessed when omitted)")
    m.add_argument("--out", required=True, help="calibration.yaml to write")
    m.add_argument("--fps", type=float, help="frame rate (default: the videos' with --recording, else the file's, "
                                              "else 25)")
    m.add_argument("--recording", metavar="DIR",
                   help="the recording folder the calibration is for: its videos give the fps, its camera names "
                        "are compared with the imported ones")
    m.add_argument("--units", default="auto", help="length unit of translations: m, cm, mm or auto (default)")
    m.add_argument("--size", metavar="WxH", help="image size, for formats that do not carry it")
    m.add_argument("--binning", type=int, default=1, help="Qualisys: sensor binning factor (default 1)")
    m.add_argument("--view-rotation", choices=("apply", "ignore"), default="apply",
                   help="Qualisys: apply each camera's viewrotation (default) or keep the sensor's orientation")
    m.add_argument("--rename", nargs="+", default=[], metavar="OLD=NEW", help="rename cameras (to match videos/NEW.mp4)")
    _room_option(m)

    x = sub.add_parser("export", help="write a calibration.yaml in another format")
    x.add_argument("file", help="calibration.yaml or a recording folder")
    x.add_argument("--format", required=True, choices=("opencv", "toml"))
    x.add_argument("--out", required=True, help="toml: the file; opencv: a folder (one <cam>.yml per camera)")

    f = sub.add_parser("fit", help="fit the intrinsics to the recording's video sizes (turn, rescale or crop, "
                                   "chosen per camera from the sizes unless given)")
    f.add_argument("--recording", required=True)
    how = f.add_mutually_exclusive_group()
    how.add_argument("--rescale", action="store_true", help="the videos are the calibrated images scaled (all cameras)")
    how.add_argument("--crop", nargs="?", const="auto", choices=("bottom", "top", "centre", "right", "left", "auto"),
                     metavar="WHERE",
                     help="the videos are a window of the calibrated images, or the images padded (all cameras); "
                          "WHERE the rows that differ are: bottom (or right; codec padding, the principal point "
                          "stays), centre, top (or left); without WHERE, read from a band of one colour in the "
                          "video or assumed, and said")
    f.add_argument("--turn", type=int, metavar="DEG",
                   help="the videos are the images turned clockwise: 90 or 270 for the cameras whose videos are "
                        "portrait where the calibration is landscape, or the reverse (default: the turn that stands "
                        "the room upright); 180 for every camera")
    f.add_argument("--anchor", choices=("topleft", "centre"),
                   help="with --crop, the older spelling: topleft = --crop bottom, centre = --crop centre")
    f.add_argument("--out", help="calibration to write (default: the recording's, the old one kept as .orig)")

    o = sub.add_parser("import-opencv", help="build calibration.yaml from OpenCV FileStorage files")
    o.add_argument("cameras", nargs="+", metavar="CAM=FILE", help="camera name and its OpenCV .yml/.xml file")
    o.add_argument("--out", required=True, help="calibration.yaml to write")
    o.add_argument("--fps", type=float, required=True, help="frame rate of the cameras")
    o.add_argument("--room", required=True, help="analysed volume: xmin,ymin,zmin,xmax,ymax,zmax in metres")
    o._negative_number_matcher = _NEGATIVE


# -- helpers ----------------------------------------------------------------------------

def _size(text):
    from app.simulation.command import parse_size

    return parse_size(text) if text else None


def _pairs(items, what):
    from app.errors import InputError

    out = []
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name or not value:
            raise InputError(f"{what} {item!r}: expected CAM=VALUE")
        out.append((name, value))
    return out


def _room(text, cameras):
    """The room from ``--room`` or estimated; printed either way."""
    from calibration.room import estimate_room, format_room, parse_room

    if text:
        lo, hi = parse_room(text)
        print(f"room (given): {format_room(lo, hi)}")
    else:
        lo, hi = estimate_room(cameras)
        print(f"room (estimated from the floor area that {min(2, len(cameras))} or more cameras see): "
              f"{format_room(lo, hi)}")
    return lo, hi


def _save(cameras, fps, lo, hi, out):
    from calibration import Calibration, load_calibration, save_calibration

    calib = Calibration(float(fps), lo, hi, tuple(cameras), str(out))
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    save_calibration(calib, out)
    return load_calibration(out)  # what was written is valid


def _summary(calib) -> None:
    import numpy as np

    room = " .. ".join("[" + ", ".join(f"{v:g}" for v in np.round(c, 4)) + "]" for c in (calib.room_min, calib.room_max))
    print(f"{calib.path}: {len(calib.cameras)} cameras at {calib.fps:g} fps, room {room} m")
    for c in calib.cameras:
        hfov = 2 * math.degrees(math.atan(c.width / (2 * c.K[0, 0])))
        print(f"  {c.name}: {c.width}x{c.height}, hfov {hfov:.0f} deg, centre "
              f"[{', '.join(f'{v:.2f}' for v in c.centre)}], distortion {'yes' if c.has_distortion else 'none'}")


# -- actions ----------------------------------------------------------------------------

def _check(args) -> int:
    from app.errors import InputError
    from calibration.validate import check_calibration

    if args.recording:
        return _check_recording(args)
    if not args.file:
        raise InputError("calibrate check: give a calibration.yaml (or a recording folder), or --recording DIR")
    checked = check_calibration(args.file)
    _usable_summary(checked)
    return _problems(checked.problems)


def _usable_summary(checked) -> None:
    """The summary of what of a calibration is usable, and how much of it that is."""
    if checked.calibration is not None:
        _summary(checked.calibration)
        if len(checked.cameras) < len(checked.names):
            print(f"  ({len(checked.cameras)} of the {len(checked.names)} cameras usable; the problems follow)")


def _problems(problems, hints=()) -> int:
    """Print every problem (one line each) and the fixes; 1 if there was any."""
    for p in problems:
        print(f"problem: {p}")
    if not problems:
        print("no problems found")
        return 0
    for h in hints:
        print(h)
    print(f"{len(problems)} problem{'s' if len(problems) > 1 else ''} found")
    return 1


def _draw(cam, info, root, frame):
    """A frame of the camera's source (None when it cannot be read)."""
    from app.recording import RecordingError, find_source, open_source

    try:
        src = open_source(root, *find_source(root, cam.name), cam.name)
    except RecordingError:
        return None
    try:
        return src.read(min(max(frame, 0), max(info.count - 1, 0)))
    finally:
        src.close()


def _check_recording(args) -> int:
    import cv2

    from app.recording_check import check_recording
    from calibration.fitting import fit_camera
    from calibration.overlay import contact_sheet, draw_calibration, floor_coverage
    from calibration.transform import rescaled

    fc = check_recording(args.recording)
    calib = fc.calibration.calibration  # the usable part of it
    _usable_summary(fc.calibration)
    drawable = [c for c in calib.cameras if c.name in fc.sources] if calib is not None else []
    if drawable:
        out = Path(args.out) if args.out else fc.path / "check"
        out.mkdir(parents=True, exist_ok=True)
        sheet = []
        print(f"{'camera':<10} {'calibration':>12} {'video':>12} {'size':>6} {'fps':>12} {'height m':>9} "
              f"{'floor seen':>10}")
        for cam in drawable:
            info = fc.sources[cam.name]
            img = _draw(cam, info, fc.path, args.frame)
            size_ok = tuple(info.size) == (cam.width, cam.height)
            fps_txt = f"{info.fps:g}" if info.fps > 0 else "(images)"
            fps_ok = info.fps <= 0 or abs(info.fps - calib.fps) <= 0.01 * calib.fps
            drawn_cam, how = cam, ""
            if not size_ok:  # drawn as fit would fit it
                fitted = fit_camera(cam, *info.size, frames=(lambda: [img]) if img is not None else None)
                drawn_cam, how = ((fitted.camera, " MISMATCH (drawn as fit would fit it)") if fitted.decided
                                  else (rescaled(cam, *info.size), " MISMATCH (drawn rescaled)"))
            lines = [f"calib {cam.width}x{cam.height} video {info.size[0]}x{info.size[1]}" + how,
                     f"fps calib {calib.fps:g} video {fps_txt}" + ("" if fps_ok else " MISMATCH"),
                     f"centre height {cam.centre[2]:.2f} m"]
            drawn = draw_calibration(drawn_cam, img, calib.room_min, calib.room_max, args.grid, lines)
            cv2.imwrite(str(out / f"check-{cam.name}.png"), drawn)
            sheet.append(drawn)
            cover = floor_coverage(cam, calib.room_min, calib.room_max)
            print(f"{cam.name:<10} {f'{cam.width}x{cam.height}':>12} {f'{info.size[0]}x{info.size[1]}':>12} "
                  f"{'ok' if size_ok else 'WRONG':>6} {fps_txt + ('' if fps_ok else ' WRONG'):>12} "
                  f"{cam.centre[2]:>9.2f} {100 * cover:>9.0f}%")
        cv2.imwrite(str(out / "check.png"), contact_sheet(sheet))
        print(f"drawn on frame {args.frame}: {out / 'check.png'} and check-<camera>.png (room box yellow, floor grid "
              f"{args.grid:g} m, axes x red y green z blue, 1 m)")
    hints = []
    if fc.sizes_wrong:
        hints.append(f"fix the sizes: smartroom calibrate fit --recording {fc.path} (chooses turn, rescale or crop "
                     f"for {', '.join(fc.sizes_wrong)} from the sizes and says why)")
    rates = sorted({round(i.fps, 3) for i in fc.sources.values() if i.kind == "video" and i.fps > 0})
    if calib is not None and len(rates) == 1 and abs(rates[0] - calib.fps) > 0.01 * calib.fps:
        hints.append(f"fix the frame rate: set fps: {rates[0]:g} in {calib.path}")
    return _problems(fc.problems, hints)


def _intrinsics(args) -> int:
    import numpy as np

    from calibration import Camera
    from calibration.boards import parse_board
    from calibration.formats import write_opencv
    from calibration.intrinsics import calibrate_intrinsics, frames_from_video, images_from_glob

    board = parse_board(args.board)
    if args.images:
        views, source = images_from_glob(args.images), args.images
    else:
        views, source = frames_from_video(args.video, args.every, args.max_frames), args.video
    r = calibrate_intrinsics(views, board, fix_k3=args.fix_k3, source=source)
    K = r.K
    print(f"{args.name}: {r.width}x{r.height}, board found in {r.views_used} of {r.views_total} views")
    print(f"  fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f} px; "
          f"dist {' '.join(f'{v:.5f}' for v in r.dist)}")
    print(f"  RMS reprojection error {r.rms:.3f} px (worst view {max(r.per_view_rms):.3f} px)")
    if r.warning:
        print(f"  warning: {r.warning}")
    if args.out:
        write_opencv(Camera(args.name, r.width, r.height, K, r.dist, np.eye(3), np.zeros(3)), args.out)
        print(f"wrote {args.out}")
    return 0


def _load_intrinsics(items):
    from calibration import load_calibration
    from calibration.formats import read_opencv

    if len(items) == 1 and "=" not in items[0]:
        return list(load_calibration(items[0]).cameras)
    cams = []
    for name, path in _pairs(items, "--intrinsics"):
        cams += read_opencv(path, name=name, units="m", pose=False).cameras
    return cams


def _extrinsics(args) -> int:
    import glob

    import cv2

    from app.errors import InputError
    from calibration.boards import detect, floor_points, parse_board
    from calibration.extrinsics import refine_jointly, solve_pose
    from calibration.files import read_points

    cams = {c.name: c for c in _load_intrinsics(args.intrinsics)}
    results = {}
    if args.points:
        world, pixels = read_points(args.points)
        for name, seen in pixels.items():
            if name not in cams:
                raise InputError(f"{args.points}: pixels: unknown camera {name} (have {', '.join(cams)})")
            names = [n for n in seen if n in world]
            results[name] = solve_pose(cams[name], [world[n] for n in names], [seen[n] for n in names],
                                       f"{args.points}: camera {name}")
    else:
        if not args.board or not args.floor:
            raise InputError("extrinsics: give --board and --floor CAM=IMAGE for each camera, or --points FILE")
        board = parse_board(args.board)
        observations = []
        order = []
        for name, path in _pairs(args.floor, "--floor"):
            if name not in cams:
                raise InputError(f"--floor {name}: unknown camera (have {', '.join(cams)})")
            img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise InputError(f"{path}: cannot be read as an image")
            d = detect(board, img)
            if d is None:
                raise InputError(f"{path}: the board {args.board} is not found")
            results[name] = solve_pose(cams[name], floor_points(board, d.ids), d.pixels, f"{path}")
            order.append(name)
            observations.append((len(order) - 1, 0, d.ids, d.pixels))
        if args.moved:
            for name, pattern in _pairs(args.moved, "--moved"):
                if name not in results:
                    raise InputError(f"--moved {name}: the camera has no --floor image")
                for k, path in enumerate(sorted(glob.glob(pattern)), start=1):
                    img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
                    d = detect(board, img) if img is not None else None
                    if d is not None:
                        observations.append((order.index(name), k, d.ids, d.pixels))
            before = {n: results[n].rms for n in order}
            refined = refine_jointly([results[n].camera for n in order], observations, floor_points(board))
            for n, r in zip(order, refined):
                results[n] = r
            print("joint refinement over "
                  f"{len({v for _, v, _, _ in observations})} board placements: RMS "
                  + ", ".join(f"{n} {before[n]:.3f} -> {results[n].rms:.3f} px" for n in order))
    missing = [n for n in cams if n not in results]
    if missing:
        print(f"warning: no pose for {', '.join(missing)} (left out of {args.out})")
    for n, r in results.items():
        c = r.camera
        print(f"  {n}: centre [{', '.join(f'{v:.3f}' for v in c.centre)}] m, RMS {r.rms:.3f} px over {r.points} points"
              + ("  (above 1 px: check the points)" if r.rms > 1.0 else ""))
    out_cams = [results[n].camera for n in cams if n in results]
    lo, hi = _room(args.room, out_cams)
    calib = _save(out_cams, args.fps, lo, hi, args.out)
    print(f"wrote {calib.path} with {len(out_cams)} cameras")
    return 0


def _import_fps(args, file_fps) -> float:
    """The recording's frame rate: ``--fps``, else the videos' (``--recording``), else the
    file's, else 25; every choice printed."""
    from app.errors import InputError
    from app.recording_check import recording_fps

    if args.recording:
        try:
            fps, videos = recording_fps(args.recording)
        except InputError:
            if args.fps:
                print(f"note: fps {args.fps:g} given; the videos of {args.recording} were not compared")
                return args.fps
            raise
        shown = ", ".join(videos)
        if args.fps:
            if abs(args.fps - fps) > 0.01 * fps:
                print(f"note: --fps {args.fps:g} given, but the videos of {args.recording} are {fps:g} fps "
                      f"({shown}): a run on them stops on the mismatch")
            return args.fps
        print(f"fps {fps:g} from the videos of {args.recording} ({shown})"
              + (f"; the file says {file_fps:g}" if file_fps and abs(file_fps - fps) > 0.01 * fps else ""))
        return fps
    if args.fps:
        return args.fps
    if file_fps:
        return file_fps
    print("note: fps 25 assumed (the file has none): give --fps, or --recording DIR to take the videos'; "
          "`smartroom calibrate check --recording` compares")
    return 25.0


def _import(args) -> int:
    from app.errors import InputError
    from calibration import Camera
    from calibration.formats import read_cameras

    fmt, got = read_cameras(args.files, args.format, units=args.units, size=_size(args.size),
                            binning=args.binning, view_rotation=args.view_rotation)
    renames = dict(_pairs(args.rename, "--rename"))
    cams = []
    for c in got.cameras:
        name = renames.pop(c.name, c.name)
        cams.append(Camera(name, c.width, c.height, c.K, c.dist, c.R, c.t))
    if renames:
        raise InputError(f"--rename: no camera {', '.join(renames)} in {args.files[0]}")
    for note in got.notes:
        print(f"note: {note}")
    fps = _import_fps(args, got.fps)
    if args.recording:
        _compare_names(cams, args.recording)
    lo, hi = _room(args.room, cams)
    calib = _save(cams, fps, lo, hi, args.out)
    print(f"imported {len(cams)} cameras from {', '.join(args.files)} ({fmt}) into {calib.path}")
    _summary(calib)
    return 0


def _compare_names(cams, recording) -> None:
    """A note when imported cameras have no video in the recording (``--rename`` fixes it)."""
    from app.recording_check import folder_sources

    have = folder_sources(Path(recording))
    missing = [c.name for c in cams if c.name not in have]
    if missing and have:
        print(f"note: {', '.join(missing)} ha{'ve' if len(missing) > 1 else 's'} no video in {recording} "
              f"(it has {', '.join(have)}): name them with --rename OLD=NEW")


def _export(args) -> int:
    from calibration import load_calibration
    from calibration.formats import write_opencv, write_toml

    from app.errors import InputError

    calib = load_calibration(args.file)
    out = Path(args.out)
    try:   # the folder it goes into is made, as for any result (a toml file's, the opencv folder)
        if args.format == "toml":
            if out.is_dir():
                raise InputError(f"--out {out}: is a folder; give the .toml file to write")
            out.parent.mkdir(parents=True, exist_ok=True)
            write_toml(list(calib.cameras), out)
            print(f"wrote {out} ({len(calib.cameras)} cameras, aniposelib/Pose2Sim TOML, metres)")
        else:
            out.mkdir(parents=True, exist_ok=True)
            for c in calib.cameras:
                write_opencv(c, out / f"{c.name}.yml")
            print(f"wrote {len(calib.cameras)} OpenCV files into {out}/")
    except OSError as exc:
        raise InputError(f"--out {out}: cannot write there ({exc.strerror or type(exc).__name__})") from None
    return 0


def _fit(args) -> int:
    import shutil

    from app.errors import InputError
    from app.recording import Recording
    from calibration.fitting import PLACEMENTS, fit_camera

    if args.turn is not None and (args.turn % 90 or args.turn % 360 == 0):
        raise InputError(f"--turn {args.turn}: must be 90, 180 or 270")
    placement = PLACEMENTS[args.crop] if args.crop not in (None, "auto") else None
    if args.anchor:
        if placement and placement != PLACEMENTS[args.anchor]:
            raise InputError(f"--anchor {args.anchor} and --crop {args.crop} disagree: give one")
        placement = PLACEMENTS[args.anchor]
    mode = "rescale" if args.rescale else "crop" if args.crop else None
    rec = Recording(args.recording, check=False)
    calib = rec.calibration
    cams, undecided = [], []
    for c in calib.cameras:
        w, h = rec.sources[c.name].size
        fitted = fit_camera(c, w, h, mode, args.turn, placement, frames=lambda name=c.name: rec.sample(name, 5))
        print(fitted.said)
        if not fitted.decided:
            undecided.append(c.name)
        cams.append(fitted.camera)
    if undecided:
        raise InputError(f"{rec.path / 'calibration.yaml'}: not changed: the sizes do not say how the videos of "
                         f"{', '.join(undecided)} were made; give --rescale or --crop [bottom|top|centre]")
    out = Path(args.out) if args.out else rec.path / "calibration.yaml"
    if not args.out:
        if all(a is b for a, b in zip(cams, calib.cameras)):
            print(f"every camera fits its video: {out} unchanged")
            return 0
        shutil.copy2(rec.path / "calibration.yaml", rec.path / "calibration.yaml.orig")
        print(f"kept the old calibration as {rec.path / 'calibration.yaml.orig'}")
    saved = _save(cams, calib.fps, calib.room_min, calib.room_max, out)
    print(f"wrote {saved.path}")
    return 0


def _import_opencv(args) -> int:
    from calibration.formats import read_opencv
    from calibration.room import parse_room

    lo, hi = parse_room(args.room)
    cams = []
    for name, path in _pairs(args.cameras, "camera"):
        cams += read_opencv(path, name=name, units="m").cameras
    _save(cams, args.fps, lo, hi, args.out)
    print(f"smartroom: wrote {args.out} with {len(cams)} cameras")
    return 0


def main(args) -> int:
    return {"check": _check, "intrinsics": _intrinsics, "extrinsics": _extrinsics, "import": _import,
            "export": _export, "fit": _fit, "import-opencv": _import_opencv}[args.action](args)
