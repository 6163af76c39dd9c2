"""A finished run, replayed in the viewer's page: no bus, no recomputation.

The results folder's files (``tracks.jsonl``, ``poses.jsonl``, ``voxels.bin`` when the
recorder kept it, the recording's calibration for the room and the cameras) become one
group of objects per frame (voxels, skeletons, trails) under ``ROOT/replay/f<frame>``,
one ellipsoid with its id label per track, optionally one camera's recorded frame per
frame in a corner of the view, and a three.js animation clip that shows
each frame's group at its time and moves each track's ellipsoid. meshcat's page plays
the clip itself: its Animations panel has play, pause, reset and a time slider; the
controls added here are a frame slider and one-frame steps back and forward. Pure: files
in, meshcat commands out (:mod:`app.viewer.three`); ``smartroom view`` sends them.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.errors import InputError
from app.files import read_jsonl, read_yaml
from app.messages import JOINTS
from app.viewer import three
from app.viewer.geometry import ellipsoid_rings, point_size, rgb_floats, subsample, track_colour, translation
from app.viewer.scene import CAMERA, FOV_DEG, LABEL_HEIGHT, ROOT, Scene, skeleton_object

__all__ = ["RunData", "load_run", "replay_commands", "frame_path", "REPLAY"]

REPLAY = f"{ROOT}/replay"
TRACKS = f"{ROOT}/replay_tracks"
IMAGES = f"{CAMERA}/smartroom_images"     # the recording's frames, in a corner of the view


def frame_path(frame: int) -> str:
    return f"{REPLAY}/{frame_name(frame)}"


def frame_name(frame: int) -> str:
    return f"f{frame:06d}"


@dataclass
class RunData:
    """What a results folder holds, by frame."""

    folder: Path
    fps: float
    calibration: object = None
    tracks: dict = field(default_factory=dict)     # frame -> (ids (N,), positions (N, 3))
    poses: dict = field(default_factory=dict)      # frame -> (tracks (N,), joints (N, 15, 3), active (N, 15))
    voxels: dict = field(default_factory=dict)     # frame -> (centres (n, 3), colours (n, 3) uint8, size)
    grid: tuple | None = None                      # (origin, dims, voxel_size) of the first voxel frame
    images: dict = field(default_factory=dict)     # frame -> JPEG of the chosen camera (``images=CAM``)
    image_aspect: float = 4 / 3

    @property
    def frames(self) -> list[int]:
        return sorted(set(self.tracks) | set(self.poses) | set(self.voxels))


def _calibration(folder: Path, run: dict):
    from calibration import load_calibration
    for path in ([Path(run["recording"]) / "calibration.yaml"] if run.get("recording") else []) + \
            ([Path(run["calibration"])] if run.get("calibration") else []):
        if path.is_file():
            return load_calibration(path)
    return None


def load_run(results, voxels: bool = True, max_points: int = 8000, allow_empty: bool = False,
             images: str | None = None, image_width: int = 320, span: tuple | None = None) -> RunData:
    """Read a results folder (``max_points``: voxels kept per frame, surface first;
    ``images``: a camera whose recorded frames are shown too, ``image_width`` pixels wide;
    ``span``: only frames ``first..last`` (inclusive; the page holds every frame it plays,
    so a long run is best replayed a part at a time)."""
    lo, hi = span if span is not None else (-1, float("inf"))
    folder = Path(results)
    if not folder.is_dir():
        raise InputError(f"{folder}: results folder not found")
    layout = folder / "layout.yaml"
    run = {}
    if layout.is_file():
        data = read_yaml(layout, "layout") or {}
        run = (data.get("run") or {}) if isinstance(data, dict) else {}
    fps = run.get("fps")
    if not isinstance(fps, (int, float)) or fps <= 0:
        stats = folder / "stats.json"
        fps = json.loads(stats.read_text()).get("recording_fps") if stats.is_file() else None
    fps = float(fps) if isinstance(fps, (int, float)) and fps > 0 else 25.0
    out = RunData(folder, fps, _calibration(folder, run))
    if (folder / "tracks.jsonl").is_file():
        for n, rec in enumerate(read_jsonl(folder / "tracks.jsonl"), 1):
            try:
                ids = np.array([int(t["id"]) for t in rec["tracks"]], np.int64)
                pos = np.array([t["position"] for t in rec["tracks"]], float).reshape(-1, 3)
                if lo <= int(rec["frame"]) <= hi:
                    out.tracks[int(rec["frame"])] = (ids, pos)
            except (KeyError, TypeError, ValueError):
                raise InputError(f"{folder / 'tracks.jsonl'}: line {n} is not a tracks record") from None
    if (folder / "poses.jsonl").is_file():
        for n, rec in enumerate(read_jsonl(folder / "poses.jsonl"), 1):
            try:
                poses = rec["poses"]
                ids = np.array([int(p["track"]) for p in poses], np.int64)
                joints = np.array([[p["joints"][j] for j in JOINTS] for p in poses], float).reshape(-1, 15, 3)
                active = np.array([[bool((p.get("active") or {}).get(j, True)) for j in JOINTS] for p in poses],
                                  bool).reshape(-1, 15)
                if lo <= int(rec["frame"]) <= hi:
                    out.poses[int(rec["frame"])] = (ids, joints, active)
            except (KeyError, TypeError, ValueError):
                raise InputError(f"{folder / 'poses.jsonl'}: line {n} is not a poses record") from None
    if voxels and (folder / "voxels.bin").is_file():
        from app.results import iter_voxels
        for msg in iter_voxels(folder / "voxels.bin"):
            if not lo <= msg.frame <= hi:
                continue
            if out.grid is None:
                out.grid = (list(msg.origin), list(msg.dims), float(msg.voxel_size))
            n = 0 if msg.indices is None else len(msg.indices)
            if n == 0:
                out.voxels[int(msg.frame)] = (np.zeros((0, 3)), None, float(msg.voxel_size), 0)
                continue
            centres = msg.centres()
            cols = np.asarray(msg.colours) if msg.colours is not None and len(msg.colours) == n else None
            surface = msg.surface if msg.surface is not None and len(msg.surface) == n else None
            keep = subsample(n, max_points, surface)
            if keep is not None:
                centres = centres[keep]
                cols = cols[keep] if cols is not None else None
            out.voxels[int(msg.frame)] = (centres, cols, float(msg.voxel_size), n)
    if images:
        _load_images(out, run, images, image_width)
    if not out.frames and not allow_empty:
        raise InputError(f"{folder}: nothing to replay (no tracks.jsonl, poses.jsonl or voxels.bin)")
    return out


def _load_images(out: RunData, run: dict, camera: str, width: int) -> None:
    """The recording's frames of ``camera`` for the run's frames, scaled and JPEG-encoded."""
    import cv2

    from app.recording import Recording
    if not run.get("recording"):
        raise InputError(f"{out.folder / 'layout.yaml'}: the run names no recording, so no frames to show")
    rec = Recording(run["recording"])
    if camera not in rec.cameras:
        raise InputError(f"--images {camera}: the recording has cameras {', '.join(rec.cameras)}")
    frames = out.frames
    if not frames:
        return
    for i, views in rec.frames([camera], start=frames[0], stop=frames[-1] + 1):
        img = views.get(camera)
        if img is None:
            continue
        h, w = img.shape[:2]
        small = cv2.resize(img, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)
        ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 75])
        if ok:
            out.images[i] = buf.tobytes()
            out.image_aspect = w / h


def _room(data: RunData):
    """Room bounds: the calibration's, else the voxel grid's, else around what was captured."""
    if data.calibration is not None:
        return data.calibration.room_min, data.calibration.room_max, data.calibration.cameras
    if data.grid is not None:
        origin, dims, size = data.grid
        lo = np.asarray(origin, float)
        return lo, lo + np.asarray(dims, float) * size, ()
    pts = [p for _, p in data.tracks.values()] + [j.reshape(-1, 3) for _, j, _ in data.poses.values()]
    pts = np.concatenate(pts) if pts else np.zeros((1, 3))
    lo, hi = pts.min(axis=0) - 0.5, pts.max(axis=0) + 0.5
    lo[2], hi[2] = 0.0, max(hi[2], 2.0)
    return lo, hi, ()


def replay_commands(data: RunData, trail: int = 25, ellipsoid=(0.3, 0.3, 0.9), start: int | None = None,
                    paused: bool = False, frustum_depth: float = 0.4) -> tuple[Scene, list[dict]]:
    """The scene and every command that draws and animates the run (see module docstring).
    ``start``: the frame shown first; ``paused``: do not play at once."""
    lo, hi, cameras = _room(data)
    scene = Scene(lo, hi, cameras, frustum_depth=frustum_depth, ellipsoid=ellipsoid, trail=trail)
    cmds = scene.setup()
    frames = data.frames
    if not frames:
        return scene, cmds + scene.status(f"replay {data.folder.resolve().name} | nothing recorded")
    first, last = frames[0], frames[-1]
    fps = data.fps
    anim = []
    history: dict[int, list] = {}
    seen_tracks: dict[int, list] = {}
    for f in frames:
        g = frame_path(f)
        drawn = False
        if f in data.voxels:
            centres, cols, size, total = data.voxels[f]
            if len(centres):
                if cols is None:
                    cols = (rgb_floats(None, len(centres)) * 255).round().astype(np.uint8)
                cmds.append(three.set_object(f"{g}/voxels", three.points(
                    centres, cols, size=point_size(size, total, len(centres)))))
                drawn = True
        if f in data.poses:
            ids, joints, active = data.poses[f]
            for tid, jk, ak in zip(ids, joints, active):
                cmds.append(three.set_object(f"{g}/poses/{int(tid)}", skeleton_object(jk, ak, int(tid))))
                drawn = True
        if f in data.tracks:
            ids, positions = data.tracks[f]
            for tid, p in zip(ids, positions):
                tid = int(tid)
                seen_tracks.setdefault(tid, []).append((f, p))
                h = history.setdefault(tid, [])
                h.append(p)
                del h[:-max(trail, 1)]
                if trail and len(h) >= 2:
                    cmds.append(three.set_object(f"{g}/trails/{tid}", three.line_strip(np.array(h), track_colour(tid))))
                    drawn = True
        if drawn:
            shown = f == (first if start is None else start)
            cmds.append(three.set_property(g, "visible", bool(shown)))
            i = f - first
            times, values = ([0, i, i + 1], [False, True, False]) if i > 0 else ([0, 1], [True, False])
            if f == last:
                times, values = times[:-1], values[:-1]
            anim.append(three.track(frame_name(f), "visible", "boolean", times, values))
    rings = ellipsoid_rings(scene.semi_axes)
    for tid, seen in sorted(seen_tracks.items()):
        path = f"{TRACKS}/t{tid}"
        colour = track_colour(tid)
        cmds.append(three.set_object(f"{path}/body", three.line_segments(rings, colour=colour, opacity=0.85)))
        png, aspect = three.text_image(f"#{tid}", colour)
        cmds.append(three.set_object(f"{path}/label", three.sprite(
            png, LABEL_HEIGHT * 1.2, aspect, [0.0, 0.0, scene.semi_axes[2] + 0.15])))
        t0 = seen[0][1]
        cmds.append(three.set_transform(path, translation(t0)))
        frames_seen = [f for f, _ in seen]
        anim.append(three.track(f"t{tid}", "position", "vector3", [f - first for f in frames_seen],
                                [[float(v) for v in p] for _, p in seen]))
        vis_t, vis_v = [], []
        present = set(frames_seen)
        for f in frames:   # visible exactly on the frames the track was reported
            on = f in present
            if not vis_v or vis_v[-1] != on:
                vis_t.append(f - first)
                vis_v.append(on)
        if vis_t[0] != 0:
            vis_t, vis_v = [0] + vis_t, [False] + vis_v
        anim.append(three.track(f"t{tid}", "visible", "boolean", vis_t, vis_v))
    name = data.folder.resolve().name
    cmds += scene.status(f"replay {name} | frames {first}-{last} | {fps:g} fps", (1.0, 1.0, 1.0))
    more = []
    if data.images:
        image_cmds, image_anim = _images(data, first, last, first if start is None else start, scene.aspect)
        cmds += image_cmds
        more.append((IMAGES, image_anim))
    cmds.append(three.set_animation(ROOT, anim, fps, play=True, more=more))
    cmds += _controls(first, last, fps, first if start is None else start, paused or start is not None)
    return scene, cmds


def _images(data: RunData, first: int, last: int, start: int, aspect: float):
    """The camera's frames at the bottom left of the view (children of meshcat's camera,
    like the status line), one shown at a time by the animation."""
    height = 0.42                                  # of the 1.53 units the view is high, one unit ahead
    top = np.tan(np.radians(FOV_DEG) / 2.0)
    width = height * data.image_aspect
    at = [-top * aspect + 0.03 + width / 2, -top + 0.03 + height / 2, -1.0]
    cmds, anim = [], []
    for f, jpeg in sorted(data.images.items()):
        path = f"{IMAGES}/{image_name(f)}"
        # an object without an image first: the group exists at once (an image loads later),
        # so the animation finds it by name
        cmds.append(three.set_object(f"{path}/anchor", three.line_segments(np.zeros((0, 2, 3)))))
        cmds.append(three.set_object(f"{path}/image", three.sprite(jpeg, height, data.image_aspect, at, 19,
                                                                   attenuate=True, mime="image/jpeg")))
        cmds.append(three.set_property(path, "visible", f == start))
        i = f - first
        times, values = ([0, i, i + 1], [False, True, False]) if i > 0 else ([0, 1], [True, False])
        if f == last:
            times, values = times[:-1], values[:-1]
        anim.append(three.track(image_name(f), "visible", "boolean", times, values))
    return cmds, anim


def image_name(frame: int) -> str:
    return f"i{frame:06d}"


def _controls(first: int, last: int, fps: float, start: int, paused: bool) -> list[dict]:
    """A frame slider and one-frame steps (JavaScript run by the page: ``viewer`` is
    meshcat's page object, ``viewer.animator`` its animation player)."""
    go = ("const go = (f) => { const a = viewer.animator; if (a.playing) a.pause(); "
          f"f = Math.max({first}, Math.min({last}, Math.round(f))); const t = (f - {first}) / {fps}; "
          "a.display_progress(t); a.seek(t); return f; };")
    now = f"Math.round(viewer.animator.time * {fps}) + {first}"
    # the frame slider follows the animation while it plays; the panel opens
    follow = ("const c = viewer.gui.__controllers.find((c) => c.property === 'frame'); "
              "const a = viewer.animator; const shown = a.display_progress.bind(a); "
              f"a.display_progress = (t) => {{ shown(t); if (c) {{ c.object.frame = Math.round(t * {fps}) + {first}; "
              "c.updateDisplay(); } }; viewer.gui.open();")
    init = f"go({start});" if paused else ""
    return [
        three.set_control("frame", f"(() => {{ {go} {follow} {init} return (v) => go(v); }})()", start, first, last, 1),
        three.set_control("step back", f"(() => {{ {go} return () => go({now} - 1); }})()"),
        three.set_control("step forward", f"(() => {{ {go} return () => go({now} + 1); }})()"),
    ]
