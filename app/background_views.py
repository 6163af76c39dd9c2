"""Backgrounds estimated from a recording, checked against what the other cameras see of
the room (issue 22: a person who stands still from the first frame of a recording that
has no empty-room images).

:func:`app.segmentation.estimate_background_robust` takes, per pixel, the median of the
frames where nobody differs from it. A person who stays at one place for most of the
recording is that median: each camera's estimate shows them as part of the room, the
masks never show them and no track ever starts. One camera alone cannot tell them from
the room. Several can: the room's walls, floor and ceiling (the calibration's room box)
are where every camera's ray ends when nothing stands in its way, and a point of them
is seen by the other cameras too. Where one camera's estimate shows something that the
others, which agree among themselves, do not see at the wall or floor point behind it,
something stands in front of that point; where its estimate agrees with them, the ray
crossed free space (shape from silhouette on these "suspect" pixels, §3.2's carving).

The room's content found so (everything in front of the box that the robust median
kept: still people, furniture, and the space just above the furniture, which every
camera sees against it) is looked at above ``furniture`` height, on the suspect pixels
that nothing low explains (a table top that the other cameras see too is explained,
:func:`explained_low`). A 3D component there that rises to ``min_top``, has the
footprint of one or two people, stands away from the walls (a doorway's far side is no
wall of the box) and that no camera sees through (where two cameras' cones cross, no one
stands) is taken for a person standing still, with the content under it. In the
cameras whose background was estimated, the pixels of that column that differ from the
other cameras' view of the room behind them, and that nothing low explains, are painted
with that view: the estimate shows the room there, and the person becomes foreground
again. Furniture is left as it was (it belongs to the background), and so is every
camera that has an empty-room image.

Not found: a person still against a wall, one crouching or seated below ``min_top``
from the first frame, and one whom fewer than two cameras see against a wall or floor
point the others agree on (a rig of three cameras in a cluttered room).

Where the room's box is not the room's walls (a calibration whose box is only the
capture volume), the other cameras' samples of a wall point disagree among themselves
on any textured wall, and nothing is painted: the check fails safe.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numba import njit

from app.components import label_voxels
from app.reconstruction.grid import VoxelGrid

__all__ = ["ViewCheck", "StillPerson", "box_exits", "room_box_points", "explained_low", "other_views", "still_people",
           "repaint_backgrounds"]


@dataclass(frozen=True)
class ViewCheck:
    """Parameters of the check (grey levels on 0-255, metres)."""

    width: int = 320              # the check works on images this wide (shrunk by an integer factor)
    agree: float = 24.0           # other cameras agree when within this of their median (max over channels)
    differ: float = 40.0          # a camera's estimate differs from them by more than this: suspect
    voxel: float = 0.06           # carving grid
    furniture: float = 1.1        # the room's furniture stays below this height (tables, benches, cabinets)
    min_top: float = 1.3          # a still person's component above ``furniture`` rises to this at least
    max_footprint: float = 1.4    # and spans at most this in x and y (two people close together, at most)
    min_voxels: int = 20          # of the component above ``furniture``
    wall_gap: float = 0.35        # a component centred nearer a wall than this is the wall's
    seen_through: float = 0.8     # a component that one camera sees through on this share of it is no one
    low: tuple = tuple(round(0.05 * i, 2) for i in range(21))   # heights (0-1 m) of what a pixel may show low


@dataclass
class StillPerson:
    """A component taken for a person standing still (room coordinates, metres)."""

    centre: tuple
    top: float
    points: np.ndarray = field(repr=False)   # the centres (N, 3) of its column's voxels


def _shrink_factor(width: int, target: int) -> int:
    return max(1, int(round(width / float(target))))


def box_exits(camera, room_min, room_max, pixels):
    """Where the rays of ``pixels`` (N, 2, full-size coordinates) leave the room box:
    ``(points (N, 3), ok (N,))``; ``ok`` is false everywhere for a camera outside the box
    (its rays' far ends are not the room's walls)."""
    lo, hi = np.asarray(room_min, float), np.asarray(room_max, float)
    centre = camera.centre
    d = camera.pixel_rays(np.asarray(pixels, np.float64).reshape(-1, 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 1e-12, (hi - centre) / d, np.where(d < -1e-12, (lo - centre) / d, np.inf)).min(axis=1)
    inside = not (np.any(centre < lo - 0.05) or np.any(centre > hi + 0.05))
    return centre + d * np.where(np.isfinite(t), t, 0.0)[:, None], np.isfinite(t) & (t > 0) & inside


def room_box_points(camera, room_min, room_max, factor: int):
    """:func:`box_exits` of every pixel centre of the image shrunk by ``factor``:
    ``(points (h, w, 3), ok (h, w))``."""
    w, h = camera.width // factor, camera.height // factor
    ys, xs = np.mgrid[0:h, 0:w]
    pts, ok = box_exits(camera, room_min, room_max,
                        np.stack([(xs.ravel() + 0.5) * factor - 0.5, (ys.ravel() + 0.5) * factor - 0.5], axis=1))
    return pts.reshape(h, w, 3), ok.reshape(h, w)


def _pixels(camera, pts, factor: int, shape):
    """``(x, y, seen)``: the pixels (int64, of an image of ``shape`` shrunk by ``factor``)
    where ``pts`` (N, 3) project, and which of them are in front of the camera and on the
    image (``x`` and ``y`` only for those)."""
    uv, z = camera.project(pts, return_depth=True)
    h, w = shape[:2]
    with np.errstate(invalid="ignore"):
        x = np.floor((uv[:, 0] + 0.5) / factor)
        y = np.floor((uv[:, 1] + 0.5) / factor)
        seen = (z > 1e-6) & (x >= 0) & (x < w) & (y >= 0) & (y < h)
    return x[seen].astype(np.int64), y[seen].astype(np.int64), seen


def _sample(camera, image, factor: int, pts):
    """Colours (N, 3) float32 of ``image`` (shrunk by ``factor``) at the projections of
    ``pts`` (N, 3); NaN where the point is behind the camera or off the image."""
    x, y, seen = _pixels(camera, pts, factor, image.shape)
    out = np.full((len(pts), 3), np.nan, np.float32)
    out[seen] = image[y, x]
    return out


def other_views(index: int, cameras, images, factors, pts, agree: float):
    """The room at ``pts`` (N, 3) as the cameras other than ``index`` see it:
    ``(colour (N, 3), inliers (N,))``: the median of the samples within ``agree`` of
    their median, and how many there were (0: nobody sees the point)."""
    rows = [_sample(cam, images[k], factors[k], pts) for k, cam in enumerate(cameras) if k != index]
    if not rows:
        return np.full((len(pts), 3), np.nan, np.float32), np.zeros(len(pts), np.int64)
    samples = np.ascontiguousarray(np.stack(rows), dtype=np.float32)
    colour = np.empty((samples.shape[1], 3), np.float32)
    inliers = np.empty(samples.shape[1], np.int64)
    _agreeing_median(samples, np.float32(agree), colour, inliers)
    return colour, inliers


@njit(cache=True, nogil=True)
def _median3(vals, n, out, c):
    """``out[c]``: the median (mean of the middle two for an even count) of ``vals[:n]``
    (sorted in place: a handful of cameras)."""
    for a in range(1, n):
        x = vals[a]
        b = a - 1
        while b >= 0 and vals[b] > x:
            vals[b + 1] = vals[b]
            b -= 1
        vals[b + 1] = x
    out[c] = vals[n // 2] if n % 2 else 0.5 * (vals[n // 2 - 1] + vals[n // 2])


@njit(cache=True, nogil=True)
def _agreeing_median(samples, agree, colour, inliers):
    """Per point of ``samples`` (cameras, N, 3; NaN: not seen): the per-channel median of
    the samples within ``agree`` (max over channels) of the per-channel median of all,
    and how many those were (NaN and 0 where no camera sees the point)."""
    m, n, _ = samples.shape
    vals = np.empty(m, np.float32)
    med = np.empty(3, np.float32)
    keep = np.empty(m, np.bool_)
    for i in range(n):
        for c in range(3):
            k = 0
            for j in range(m):
                if samples[j, i, 0] == samples[j, i, 0]:
                    vals[k] = samples[j, i, c]
                    k += 1
            if k == 0:
                break
            _median3(vals, k, med, c)
        if k == 0:
            colour[i, 0] = colour[i, 1] = colour[i, 2] = np.nan
            inliers[i] = 0
            continue
        count = 0
        for j in range(m):
            keep[j] = False
            if samples[j, i, 0] == samples[j, i, 0]:
                d = 0.0
                for c in range(3):
                    d = max(d, abs(samples[j, i, c] - med[c]))
                if d <= agree:
                    keep[j] = True
                    count += 1
        inliers[i] = count
        for c in range(3):
            k = 0
            for j in range(m):
                if keep[j]:
                    vals[k] = samples[j, i, c]
                    k += 1
            if k:
                _median3(vals, k, colour[i], c)
            else:
                colour[i, c] = np.nan


def explained_low(k, cameras, images, factors, ends, own, check):
    """Which pixels of camera ``k`` (their rays ending at ``ends`` on the room box, their
    colours ``own``) show something low that the other cameras see too: a point of the
    ray at one of ``check.low`` heights whose colour two other cameras agree on with this
    one (a table top, where the others see the floor under the table behind it; a chair's
    back, a vertical face that a ray crosses between two heights 0.05 m apart: the
    heights are that close so that one of them falls on it). Every
    such pixel's cone crosses the space above the furniture: without this, the cones of
    a table's pixels meet above the table as if someone stood there."""
    centre = cameras[k].centre
    d = ends - centre
    out = np.zeros(len(ends), bool)
    for height in check.low:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (height - centre[2]) / d[:, 2]
        on = (t > 0) & (t < 1)
        if not on.any():
            continue
        colour, inliers = other_views(k, cameras, images, factors, centre + d[on] * t[on, None], check.agree)
        agree = (inliers >= 2) & (np.abs(own[on] - np.nan_to_num(colour)).max(axis=1) <= check.agree)
        out[np.flatnonzero(on)[agree]] = True
    return out


class _Views:
    """The cameras, their backgrounds shrunk for the check, the room's box and the
    carving grid (the cells wholly inside the room)."""

    def __init__(self, calibration, backgrounds, check):
        self.cams = [calibration.camera(c) for c in calibration.names]
        self.factors = [_shrink_factor(c.width, check.width) for c in self.cams]
        self.small = [cv2.resize(backgrounds[c.name], (c.width // f, c.height // f), interpolation=cv2.INTER_AREA)
                      .astype(np.float32) for c, f in zip(self.cams, self.factors)]
        self.lo = np.asarray(calibration.room_min, float)
        self.hi = np.asarray(calibration.room_max, float)
        self.box = [room_box_points(c, self.lo, self.hi, f) for c, f in zip(self.cams, self.factors)]
        dims = np.maximum(1, np.floor((self.hi - self.lo) / check.voxel).astype(int))
        self.grid = VoxelGrid(self.lo, check.voxel, tuple(dims))
        self.centres = self.grid.centres(np.argwhere(np.ones(self.grid.dims, bool)))

    def carve(self, check):
        """``(full, high, free)``: the room's content (bool grid: cells that two cameras
        or more see on pixels whose estimate differs from the other cameras' view of the
        room behind them (suspect), and at most one sees through to a room surface the
        others agree on); the cells with two votes or more from suspect pixels that
        nothing low explains (:func:`explained_low`), where people are looked for; and
        per camera its pixels that see such a surface (free)."""
        n = len(self.centres)
        votes, high, seen_free = np.zeros(n, np.int32), np.zeros(n, np.int32), np.zeros(n, np.int32)
        free = []
        for k, cam in enumerate(self.cams):
            pts, ok = self.box[k]
            h, w = ok.shape
            own = self.small[k].reshape(-1, 3)
            colour, inliers = other_views(k, self.cams, self.small, self.factors, pts.reshape(-1, 3), check.agree)
            defined = ok.ravel() & (inliers >= 2)
            diff = np.abs(own - np.nan_to_num(colour)).max(axis=1)
            suspect = defined & (diff > check.differ)
            unexplained = suspect.copy()
            unexplained[suspect] = ~explained_low(k, self.cams, self.small, self.factors, pts.reshape(-1, 3)[suspect],
                                                  own[suspect], check)
            consistent = (defined & (diff <= check.agree)).reshape(h, w)
            suspect, unexplained = suspect.reshape(h, w), unexplained.reshape(h, w)
            free.append(consistent)
            x, y, seen = _pixels(cam, self.centres, self.factors[k], ok.shape)
            votes[seen] += suspect[y, x]
            high[seen] += unexplained[y, x]
            seen_free[seen] += consistent[y, x]
        dims = self.grid.dims
        return ((votes >= 2) & (seen_free <= 1)).reshape(dims), (high >= 2).reshape(dims), free

    def seen_through(self, points, free) -> float:
        """The largest share, over the cameras that see most of ``points``, of those
        points on ``free`` pixels (where that camera sees a room surface the others agree
        on)."""
        worst = 0.0
        for k, cam in enumerate(self.cams):
            x, y, seen = _pixels(cam, points, self.factors[k], free[k].shape)
            if seen.mean() >= 0.5:
                worst = max(worst, float(free[k][y, x].mean()))
        return worst


def still_people(calibration, backgrounds: dict, check: ViewCheck = ViewCheck()) -> list[StillPerson]:
    """The people standing still that the ``backgrounds`` (camera -> BGR image, every
    camera of ``calibration``) show as part of the room (see the module docstring).

    Every other camera's view of a wall or floor point is taken as clear: the floor under
    a table is suspect (the others see the table top there), and so the furniture and
    the space just above it are content too. The person is looked for above the
    furniture, on the suspect pixels that nothing low explains."""
    views = _Views(calibration, backgrounds, check)
    grid = views.grid
    full, high, free = views.carve(check)
    heights = grid.origin[2] + (np.arange(grid.dims[2]) + 0.5) * grid.voxel_size
    above = full & high & (heights >= check.furniture)[None, None, :]
    idx = np.argwhere(above)
    if not len(idx):
        return []
    labels, n = label_voxels(idx, grid.dims)
    people = []
    for lab in range(n):
        mine = idx[labels == lab]
        if len(mine) < check.min_voxels:
            continue
        cells = grid.centres(mine)
        top = float(cells[:, 2].max() + grid.voxel_size / 2)
        (x0, y0), (x1, y1) = mine[:, :2].min(axis=0), mine[:, :2].max(axis=0)
        if top < check.min_top or max(x1 - x0 + 1, y1 - y0 + 1) * grid.voxel_size > check.max_footprint:
            continue
        centre = cells[:, :2].mean(axis=0)
        if min((centre - views.lo[:2]).min(), (views.hi[:2] - centre).min()) < check.wall_gap:
            continue   # against a wall: a doorway (whose far side is no wall of the box), a shelf
        if views.seen_through(cells, free) >= check.seen_through:
            continue   # a camera sees the room through it: where two cameras' cones cross, not a person
        # the person's column: the content under that part, down to the floor
        x0, y0 = max(0, x0 - 1), max(0, y0 - 1)
        pts = grid.centres(np.argwhere(full[x0:x1 + 2, y0:y1 + 2, :]) + np.array([x0, y0, 0]))
        people.append(StillPerson(tuple(round(float(c), 3) for c in pts.mean(axis=0)), round(top, 3), pts))
    return people


def _column_mask(cam, people, voxel: float) -> np.ndarray:
    """The pixels (uint8, 255) of ``cam`` where the columns of ``people`` appear: a disc
    per voxel of about its projected size."""
    mask = np.zeros((cam.height, cam.width), np.uint8)
    f = float(cam.K[0, 0])
    for sp in people:
        uv, z = cam.project(sp.points, return_depth=True)
        with np.errstate(invalid="ignore"):
            good = (z > 1e-6) & (np.abs(uv - [cam.width / 2, cam.height / 2]) < [cam.width, cam.height]).all(axis=1)
        for (u, v), d in zip(uv[good], z[good]):
            r = max(1, int(np.ceil(0.75 * voxel * f / d)))
            cv2.circle(mask, (int(round(u)), int(round(v))), r, 255, -1)
    return mask


def repaint_backgrounds(calibration, backgrounds: dict, estimated, check: ViewCheck = ViewCheck()):
    """``(backgrounds, people, painted)``: the ``backgrounds`` with the people standing
    still (:func:`still_people`) painted out of the cameras in ``estimated`` (those whose
    image was estimated from the recording; the others come back as they were), and the
    pixels painted per camera."""
    people = still_people(calibration, backgrounds, check)
    out, painted = dict(backgrounds), {}
    if not people:
        return out, people, painted
    cams = [calibration.camera(c) for c in calibration.names]
    ones = [1] * len(cams)
    lo, hi = np.asarray(calibration.room_min, float), np.asarray(calibration.room_max, float)
    columns = [_column_mask(cam, people, check.voxel) for cam in cams]
    # the other cameras' view of the room, less the people found: a wall or floor point
    # that a camera sees behind one of them is not seen by it (NaN), or the person's
    # colours, in every estimate that holds them, would be painted in as the room's
    views = [backgrounds[c.name].astype(np.float32) for c in cams]
    for view, mask in zip(views, columns):
        view[mask > 0] = np.nan
    for k, cam in enumerate(cams):
        if cam.name not in estimated:
            continue
        ys, xs = np.nonzero(columns[k])
        if not len(ys):
            continue
        pts, ok = box_exits(cam, lo, hi, np.stack([xs, ys], axis=1))
        colour, inliers = other_views(k, cams, views, ones, pts, check.agree)
        image = out[cam.name].copy()
        own = image[ys, xs].astype(np.float32)
        paint = ok & (inliers >= 1) & (np.abs(own - np.nan_to_num(colour)).max(axis=1) > check.agree)
        paint[paint] = ~explained_low(k, cams, views, ones, pts[paint], own[paint], check)
        image[ys[paint], xs[paint]] = np.clip(np.rint(colour[paint]), 0, 255).astype(np.uint8)
        out[cam.name] = image
        painted[cam.name] = int(paint.sum())
    return out, people, painted

