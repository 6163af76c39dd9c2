"""The viewer's scene: what the room, the cameras and each frame's voxels, tracks and
poses look like, as meshcat commands (:mod:`app.viewer.three`). Pure: arrays in,
command dicts out; the viewer worker sends them.

Everything lives under :data:`ROOT`, translated so that the point the default view
looks at is meshcat's origin: meshcat's orbit controls turn around the scene origin,
so the room turns around its own centre. A frame's voxels, tracks and skeletons are one
group (:data:`LIVE`) that the next frame replaces whole; the scene remembers each
track's trail.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from app.messages import JOINTS
from app.viewer import three
from app.viewer.geometry import (box_edges, default_view, ellipsoid_rings, floor_grid, frustum_segments, point_size,
                                 rgb_floats, skeleton_mesh, subsample, track_colour, translation)

__all__ = ["Scene", "skeleton_object", "ROOT", "LIVE", "STATUS", "BACKGROUND", "ROOM_COLOUR", "FRUSTUM_COLOUR", "INACTIVE_COLOUR",
           "KEYPOINT_COLOUR"]

ROOT = "/meshcat/smartroom"
LIVE = f"{ROOT}/live"           # the frame on show (voxels, tracks, skeletons): one group, replaced whole
#: The status line (RTF) is a child of meshcat's camera: it stays at the top of the view.
STATUS = "/Cameras/default/rotated/<object>/smartroom_status"
CAMERA = "/Cameras/default/rotated/<object>"
FOV_DEG = 75.0                 # meshcat's default camera

BACKGROUND = (0.09, 0.10, 0.12)
FLOOR_COLOUR = (0.17, 0.18, 0.21)
GRID_COLOUR = (0.30, 0.32, 0.36)
ROOM_COLOUR = (0.62, 0.66, 0.72)
FRUSTUM_COLOUR = (1.00, 1.00, 1.00)
INACTIVE_COLOUR = (0.45, 0.45, 0.45)
MARKER_COLOUR = (1.0, 0.3, 0.9)    # marker mode's triangulated markers (magenta), over the skeletons
KEYPOINT_COLOUR = (1.0, 0.85, 0.1)  # the keypoint cue's triangulated joints (yellow), over the skeletons
LABEL_HEIGHT = 0.045           # labels keep their size on screen: ~3 % of the view's height


class Scene:
    """Commands that draw the room once and then each frame's results.

    ``room_min``/``room_max``: the analysed volume (None: unknown until the first voxel
    grid says it); ``cameras``: :class:`calibration.Camera` objects; ``ellipsoid``: the
    semi-axes (m) of a person around the track's centroid; ``trail``: positions kept per
    track; ``max_points``: voxels drawn at most per frame.
    """

    def __init__(self, room_min=None, room_max=None, cameras=(), *, frustum_depth: float = 0.4,
                 ellipsoid=(0.3, 0.3, 0.9), trail: int = 25, max_points: int = 30000, aspect: float = 4 / 3):
        self.room_min = None if room_min is None else np.asarray(room_min, float)
        self.room_max = None if room_max is None else np.asarray(room_max, float)
        self.cameras = tuple(cameras)
        self.frustum_depth = float(frustum_depth)
        self.semi_axes = np.asarray(ellipsoid, float).reshape(3)
        self._rings = ellipsoid_rings(self.semi_axes)
        self.trail = max(0, int(trail))
        self.max_points = int(max_points)
        self.aspect = aspect
        self.view = None
        self.origin = np.zeros(3)          # world point at meshcat's origin (the view's target)
        self.shown_tracks: set[int] = set()
        self.shown_poses: set[int] = set()
        self.trails: dict[int, deque] = {}
        self._trail_frames: dict[int, int] = {}   # the frame each trail's newest point is of
        self.voxels_shown = 0

    @property
    def has_room(self) -> bool:
        return self.room_min is not None and self.room_max is not None

    # -- once ---------------------------------------------------------------------------
    def setup(self) -> list[dict]:
        """The look of the page, the room, the cameras and the default view."""
        bg = [float(c) for c in BACKGROUND]
        cmds = [three.set_property("/Background", "top_color", bg),
                three.set_property("/Background", "bottom_color", bg),
                three.set_property("/Grid", "visible", False),    # meshcat's 20 m grid: the room has its own
                three.set_property("/Axes", "visible", False)]    # meshcat's axes sit at the view target
        if self.has_room:
            cmds += self.room()
        return cmds

    def room(self) -> list[dict]:
        """Room box, floor, world axes, camera frustums with their names, and the view."""
        lo, hi = self.room_min, self.room_max
        fit = [box_edges(lo, hi).reshape(-1, 3)] + [c.centre.reshape(1, 3) for c in self.cameras]
        self.view = default_view(np.concatenate(fit), FOV_DEG, self.aspect)
        self.origin = np.asarray(self.view.target, float)
        eye = self.view.eye - self.view.target
        cmds = [three.set_transform(ROOT, translation(-self.origin)),
                three.set_transform("/Cameras/default", np.eye(4)),
                # the camera's frame is meshcat's "rotated" one (y up): world (x, y, z) -> (x, z, -y)
                three.set_property(CAMERA, "position", [float(eye[0]), float(eye[2]), float(-eye[1])])]
        floor = np.array([[lo[0], lo[1], lo[2]], [hi[0], lo[1], lo[2]], [hi[0], hi[1], lo[2]], [lo[0], hi[1], lo[2]]])
        floor[:, 2] -= 0.002   # just under the grid and the box
        cmds.append(three.set_object(f"{ROOT}/room/floor", three.triangles(floor, [[0, 1, 2], [0, 2, 3]], FLOOR_COLOUR)))
        grid = floor_grid(lo, hi, 1.0 if (hi - lo)[:2].max() > 3 else 0.5)
        if len(grid):
            cmds.append(three.set_object(f"{ROOT}/room/grid", three.line_segments(grid, colour=GRID_COLOUR)))
        cmds.append(three.set_object(f"{ROOT}/room/box", three.line_segments(box_edges(lo, hi), colour=ROOM_COLOUR)))
        axes = np.array([[[0, 0, 0], [0.4, 0, 0]], [[0, 0, 0], [0, 0.4, 0]], [[0, 0, 0], [0, 0, 0.4]]], float)
        cmds.append(three.set_object(f"{ROOT}/room/axes", three.line_segments(
            axes, colours=np.eye(3, dtype=np.float32))))
        for cam in self.cameras:
            path = f"{ROOT}/cameras/{_safe(cam.name)}"
            cmds.append(three.set_object(f"{path}/frustum", three.line_segments(
                frustum_segments(cam, self.frustum_depth), colour=FRUSTUM_COLOUR)))
            png, aspect = three.text_image(cam.name, FRUSTUM_COLOUR)
            cmds.append(three.set_object(f"{path}/label", three.sprite(
                png, LABEL_HEIGHT, aspect, cam.centre + [0.0, 0.0, 0.15])))
        return cmds

    def room_from_grid(self, origin, dims, voxel_size) -> list[dict]:
        """Without a calibration, the voxel grid's bounds are the room (first grid only)."""
        if self.has_room or voxel_size <= 0 or not np.all(np.asarray(dims) > 0):
            return []
        self.room_min = np.asarray(origin, float)
        self.room_max = self.room_min + np.asarray(dims, float) * float(voxel_size)
        return self.room()

    # -- every frame ------------------------------------------------------------------
    def frame(self, frame: int, voxels=None, tracks=None, poses=None, epoch: int = 0, keypoints=None,
              markers=None) -> list[dict]:
        """One frame on show: its voxels, tracks and skeletons as one group object at
        :data:`LIVE`, which replaces the frame shown before in one step (the page never
        shows parts of two frames). ``voxels``: ``(centres, colours, voxel_size, surface)``;
        ``tracks``: ``(ids, positions)``; ``poses``: ``(tracks, joints, active)``;
        ``keypoints``: ``[(track, points (K, 3))]``, the keypoint cue's joints triangulated;
        ``markers``: (K, 3), marker mode's markers triangulated from the cameras; None: the
        frame has no such part (nothing of it is drawn). The group's ``userData`` says
        which frame it is and which parts it has."""
        children, parts = [], []
        if voxels is not None:
            parts.append("voxels")
            obj = self._voxels(*voxels)
            if obj is not None:
                children.append(obj)
        else:
            self.voxels_shown = 0
        if tracks is not None:
            parts.append("tracks")
            children += self._tracks(frame, *tracks)
        self.shown_tracks = set(int(i) for i in np.asarray(tracks[0]).reshape(-1)) if tracks is not None else set()
        for tid in set(self.trails) - self.shown_tracks:   # a track that is gone loses its trail
            del self.trails[tid]
        if poses is not None:
            parts.append("poses")
            children += self._skeletons(*poses)
        self.shown_poses = set(int(t) for t in np.asarray(poses[0]).reshape(-1)) if poses is not None else set()
        if keypoints is not None:
            parts.append("keypoints")
            children += [three.named(three.points(np.asarray(pts, float).reshape(-1, 3), colour=KEYPOINT_COLOUR,
                                                  size=0.05, on_top=True, render_order=6,
                                                  user_data={"track": int(tid)}), f"keypoints {int(tid)}")
                         for tid, pts in keypoints if len(pts)]
        if markers is not None:
            parts.append("markers")
            pts = np.asarray(markers, float).reshape(-1, 3)
            if len(pts):
                children.append(three.named(three.points(pts, colour=MARKER_COLOUR, size=0.04, on_top=True,
                                                         render_order=6, user_data={"markers": len(pts)}), "markers"))
        info = {"frame": int(frame), "epoch": int(epoch), "parts": parts}
        return [three.set_object(LIVE, three.group(children, "frame", user_data=info))]

    def _voxels(self, centres, colours=None, voxel_size: float = 0.02, surface=None) -> dict | None:
        """The occupied voxels as points in their own colours (neutral when uncoloured),
        at most ``max_points`` of them (surface first)."""
        centres = np.asarray(centres, float).reshape(-1, 3)
        n = len(centres)
        if n == 0:
            self.voxels_shown = 0
            return None
        cols = np.asarray(colours) if colours is not None else None
        if cols is None or cols.shape != (n, 3):
            cols = (rgb_floats(None, n) * 255).round().astype(np.uint8)
        keep = subsample(n, self.max_points, surface)
        if keep is not None:
            centres, cols = centres[keep], cols[keep]
        self.voxels_shown = len(centres)
        size = point_size(voxel_size, n, len(centres))
        return three.named(three.points(centres, cols, size=size, user_data={"total": n}), "voxels")

    def _tracks(self, frame: int, ids, positions) -> list[dict]:
        """Per track an ellipsoid with its id label at its centroid, and its trail."""
        ids = [int(i) for i in np.asarray(ids).reshape(-1)]
        positions = np.asarray(positions, float).reshape(-1, 3)
        out = []
        for tid, p in zip(ids, positions):
            colour = track_colour(tid)
            body = three.line_segments(self._rings, colour=colour, opacity=0.85)
            png, aspect = three.text_image(f"#{tid}", colour)
            label = three.sprite(png, LABEL_HEIGHT * 1.2, aspect, [0.0, 0.0, self.semi_axes[2] + 0.15])
            out.append(three.group([three.named(body, "body"), three.named(label, "label")], f"track {tid}",
                                   matrix=translation(p), user_data={"track": tid}))
            if self.trail:
                trail = self.trails.setdefault(tid, deque(maxlen=self.trail))
                if self._trail_frames.get(tid) != frame:   # a frame drawn again adds nothing
                    trail.append(p.copy())
                    self._trail_frames[tid] = frame
                if len(trail) >= 2:
                    out.append(three.named(three.line_strip(np.array(trail), colour), f"trail {tid}"))
        return out

    def _skeletons(self, tracks, joints, active=None) -> list[dict]:
        """One solid skeleton per pose (:func:`skeleton_mesh`: bones and joints in the
        track's colour, what the model lost grey and thinner), drawn over the voxels."""
        tracks = [int(t) for t in np.asarray(tracks).reshape(-1)]
        # a frame without people (every run's first) has no poses: (0, 15, 3) and (0, 15)
        joints = np.asarray(joints, float).reshape(len(tracks), len(JOINTS), 3)
        act = None if active is None or np.size(active) != joints.shape[0] * joints.shape[1] else \
            np.asarray(active, bool).reshape(joints.shape[:2])
        return [skeleton_object(joints[k], act[k] if act is not None else None, tid) for k, tid in enumerate(tracks)]

    def status(self, text: str, colour=(1.0, 1.0, 1.0), info: dict | None = None) -> list[dict]:
        """A line of text at the top of the view (the camera's child, one metre ahead);
        ``info``: what it says as data (``userData`` on the page)."""
        png, aspect = three.text_image(text, colour)
        height = 0.055
        top = np.tan(np.radians(FOV_DEG) / 2.0)
        return [three.set_object(STATUS, three.sprite(png, height, aspect, [0.0, top - height, -1.0], 20,
                                                      attenuate=True, user_data={"text": text, **(info or {})}))]


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(name)) or "camera"


def skeleton_object(joints, active, track: int, name: str | None = None) -> dict:
    """One person's skeleton (:func:`app.viewer.geometry.skeleton_mesh`) in the track's
    colour, drawn over everything (seen through the voxels around it)."""
    verts, faces, cols = skeleton_mesh(joints, active, track_colour(track), INACTIVE_COLOUR)
    obj = three.triangles(verts, faces, colours=cols.astype(np.float32), on_top=True, render_order=5,
                          user_data={"track": int(track)})
    return three.named(obj, name or f"skeleton {int(track)}")
