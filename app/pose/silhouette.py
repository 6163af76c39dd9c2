"""A silhouette term for the pose likelihood: how much of each camera's silhouette of a
person the model's projection covers.

The voxels the pose stage fits (:mod:`app.pose.selection`, the consensus hull) are the
intersection of every camera's silhouette cone, so one camera's thin or broken mask
carves a limb for all of them: on walk1 the swinging forearms and shins are half gone
from the consensus voxels while each camera's mask still holds 96-98 % of the person
(docs/benchmarks.md, "Segmentation"), and the pose folds the arms
into the trunk. Each camera's silhouette still shows the limb. This term scores the
model against the silhouettes themselves, in the direction the voxel scores cannot:
per camera, the share of the person's silhouette pixels that the model's projection
covers, ``rho_Sil = mean_c |S_c ∩ proj_c(model)| / |S_c|``, entering the log-likelihood
as ``-(1 - rho_Sil)^2 / (2 sigma_Sil^2)`` (the form of the coverage term of
:mod:`app.pose.coverage`). Only coverage is scored, never the model outside a
silhouette: a limb a camera sees behind furniture is missing from that camera's
silhouette and must not be pushed away (the voxel scores already keep the model inside
the data), and the phantoms of the hull cost nothing here (their pixels are other
people's, or this person's already covered). This is the coverage half of the
bidirectional silhouette likelihoods of model-based trackers (e.g. Sigal et al.'s
HumanEva baseline); the thesis poses on voxels only (Ch. 6), so ``silhouette = 0``
is its likelihood.

Which silhouette pixels are whose: a foreground pixel belongs to the one track whose
vertical axis its viewing ray passes within ``reach`` of (horizontally, over the
ray's stretch between the floor and ``top``); pixels near two tracks, or none, belong to
nobody (people overlapping in a view are scored in the other views). The rays are
fixed per camera and silhouette size (:class:`CameraRays`, cached).

The model's projection: the surface points of the fleshed model (a look-up table of
:func:`app.pose.likelihood.kernel_lut` built for the term on a lattice of
``silhouette_density`` voxel sizes, about one reduced silhouette pixel) projected with
the pinhole model into the reduced silhouettes, which are first remapped once a frame to
undistorted views (the lens model of §2.2.2 per point cost 3x more); a pixel counts
once per particle (a stamp grid with a token per particle, never cleared).

Each person's silhouette in each camera is first coarsened to the model points'
lattice at the person's depth (:func:`coarsening`, ``PoseSettings.silhouette_fit``): a
point then covers about one pixel whether the camera is near or far, fine or coarse,
and ``rho_Sil`` of the true pose is about the same on every rig (on the project's own
rooms, 3-5 m from 640-pixel cameras, it was; on a random scene's near cameras it was 0.2).

Figures (docs/benchmarks.md, "Pose", and docs/history/pose-likelihood.md, "Session 8"): replays of the pipeline's
voxels over 30 pose seeds, walk1 at 2 cm MMTA 0.878 -> 0.930, meeting3 at 4 cm 0.825 ->
0.861, gesture1 0.953 -> 0.968; the default pipeline on meeting3 stays real time.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from app.pose.model import DOF_AXIS, DOF_SEGMENT, SEG_PARENT, fk_segments, posed_tracks

__all__ = ["CameraRays", "SilhouetteView", "PersonSilhouettes", "silhouette_coverage", "coarsening", "warm_up"]


class CameraRays:
    """One camera's reduced silhouettes without lens distortion: the remap from a
    silhouette of ``width`` x ``height`` to the undistorted pinhole view of the same size
    (``K`` scaled to it), and per pixel of that view the horizontal stretch (x0, y0, x1, y1)
    of its viewing ray between heights 0 and ``top`` (``valid``: it has one). The
    scorer then projects with the pinhole model alone (:func:`_coverage`)."""

    def __init__(self, camera, width: int, height: int, top: float = 2.2, far: float = 30.0):
        import cv2
        sx, sy = camera.width / width, camera.height / height
        K = np.asarray(camera.K, dtype=np.float64)
        k = np.array([[K[0, 0] / sx, K[0, 1] / sx, (K[0, 2] + 0.5) / sx - 0.5],
                      [0.0, K[1, 1] / sy, (K[1, 2] + 0.5) / sy - 0.5], [0.0, 0.0, 1.0]])
        # for each pixel of the undistorted reduced view, where it lies in the full-size image
        mx, my = cv2.initUndistortRectifyMap(K, np.asarray(camera.dist, np.float64), None, k, (width, height),
                                             cv2.CV_32FC1)
        self.map = ((mx + 0.5) / sx - 0.5).astype(np.float32), ((my + 0.5) / sy - 0.5).astype(np.float32)
        self.intrinsics = np.array([k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2]])
        self.R = np.ascontiguousarray(camera.R, dtype=np.float64)
        self.t = np.asarray(camera.t, dtype=np.float64).ravel()
        iu, iv = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        yn = (iv - k[1, 2]) / k[1, 1]
        xn = (iu - k[0, 2] - k[0, 1] * yn) / k[0, 0]
        d = np.stack([xn, yn, np.ones_like(xn)], axis=-1).reshape(-1, 3) @ self.R   # R^T [x y 1]
        c = -self.R.T @ self.t
        dz = d[:, 2]
        flat = np.abs(dz) < 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (0.0 - c[2]) / dz, (top - c[2]) / dz
        lo = np.where(flat, 0.0, np.minimum(t0, t1))
        hi = np.where(flat, far if 0 <= c[2] <= top else -1.0, np.maximum(t0, t1))
        lo, hi = np.maximum(lo, 0.0), np.minimum(hi, far)
        self.valid = (hi > lo).reshape(height, width)
        a = c[None, :2] + lo[:, None] * d[:, :2]
        b = c[None, :2] + hi[:, None] * d[:, :2]
        self.segments = np.concatenate([a, b], axis=1).reshape(height, width, 4)

    def undistort(self, mask: np.ndarray) -> np.ndarray:
        """The reduced silhouette in the undistorted pinhole view (nearest pixel; outside: background)."""
        import cv2
        return cv2.remap(mask.astype(np.uint8), self.map[0], self.map[1], cv2.INTER_NEAREST,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


_RAYS: dict = {}


def _rays(camera, width: int, height: int) -> CameraRays:
    key = (camera.name, width, height, np.asarray(camera.K).tobytes(), np.asarray(camera.dist).tobytes(),
           np.asarray(camera.R).tobytes(), np.asarray(camera.t).tobytes())
    if key not in _RAYS:
        if len(_RAYS) > 64:
            _RAYS.clear()
        _RAYS[key] = CameraRays(camera, width, height)
    return _RAYS[key]


@njit(cache=True, nogil=True)
def _pixel_owners(segments, rows, cols, points, reach, pick, owner):
    """Per pixel ``(rows, cols)`` the track ``points (T, 3)`` whose ``reach`` its ray's
    segment passes, when exactly one does, else -1: the horizontal distance of each point
    to the segment (``CameraRays.segments``: to the point's projection on the segment's
    line, clamped to its ends), one pixel at a time, without the (n, T) temporaries of the numpy it
    replaced (a frame's silhouettes at 2 cm cost every pose worker 7 ms: issue 26). A
    pixel whose ray passes no ``pick``ed track is -1 without looking at the others (a
    pose shard's people: only they can own it)."""
    everyone = True
    for k in range(pick.shape[0]):
        everyone = everyone and pick[k]
    for i in range(rows.shape[0]):
        ax, ay = segments[rows[i], cols[i], 0], segments[rows[i], cols[i], 1]
        bx, by = segments[rows[i], cols[i], 2] - ax, segments[rows[i], cols[i], 3] - ay
        den = max(bx * bx + by * by, 1e-12)
        if not everyone:
            near = False
            for k in range(points.shape[0]):
                if pick[k]:
                    px, py = points[k, 0] - ax, points[k, 1] - ay
                    u = min(max((px * bx + py * by) / den, 0.0), 1.0)
                    if np.hypot(px - u * bx, py - u * by) < reach:
                        near = True
                        break
            if not near:
                owner[i] = -1
                continue
        n, first = 0, -1
        for k in range(points.shape[0]):
            px, py = points[k, 0] - ax, points[k, 1] - ay
            u = min(max((px * bx + py * by) / den, 0.0), 1.0)
            if np.hypot(px - u * bx, py - u * by) < reach:
                n += 1
                if first < 0:
                    first = k
        owner[i] = first if n == 1 else -1


class PersonSilhouettes:
    """One person's silhouette pixels in every camera of a frame, for the scorer:
    ``grids (C, H, W)`` uint8 (undistorted views, padded to the largest camera),
    ``counts (C,)`` (0: the camera is not scored), the views' pinhole intrinsics ``(C, 5)``
    (fx, skew, cx, fy, cy) and the cameras' ``R (C, 3, 3)``, ``t (C, 3)``."""

    def __init__(self, grids, counts, intrinsics, R, t):
        self.grids, self.counts, self.intrinsics, self.R, self.t = grids, counts, intrinsics, R, t


class SilhouetteView:
    """A frame's silhouettes (``masks``, one boolean (h, w) per camera) and the cameras
    (``cameras``: calibration cameras, same order); :meth:`people` splits them by track."""

    def __init__(self, masks: list, cameras: list, reach: float = 0.6, min_pixels: int = 20):
        self.rays = [_rays(c, m.shape[1], m.shape[0]) for c, m in zip(cameras, masks)]
        self._sent = masks
        self._masks = None
        self.reach = float(reach)
        self.min_pixels = int(min_pixels)

    @property
    def masks(self) -> list:
        """The silhouettes in the undistorted pinhole views, made when first asked for (a
        pose shard none of whose people is in the frame never asks: issue 26)."""
        if self._masks is None:
            self._masks = [r.undistort(np.asarray(m, bool)) for r, m in zip(self.rays, self._sent)]
        return self._masks

    def people(self, positions: np.ndarray, spacing: float = 0.0, wanted=None) -> list:
        """Per track (``positions (T, 3)``) its :class:`PersonSilhouettes` (``wanted``: the
        indices of the tracks asked for, None for all; the others' are None). ``spacing`` (m,
        0 = off): the model points' lattice spacing; each person's silhouette in a camera
        is coarsened (a coarse pixel is the person's when any of its pixels is) by the
        whole factor that makes a pixel at the person's depth about that wide
        (:func:`coarsening`), so that ``rho_Sil`` of a body in its true pose does not depend
        on how near the camera stands or how fine it is."""
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        T, C = len(positions), len(self.masks)
        pick = posed_tracks(T, wanted)
        H = max((m.shape[0] for m in self.masks), default=1)
        W = max((m.shape[1] for m in self.masks), default=1)
        grids = np.zeros((T, C, H, W), np.uint8)
        counts = np.zeros((T, C))
        intr = np.tile(np.array([r.intrinsics for r in self.rays]).reshape(1, C, 5), (T, 1, 1))
        for c, (mask, rays) in enumerate(zip(self.masks, self.rays)):
            rows, cols = np.nonzero(mask & rays.valid)
            if not len(rows) or not T:
                continue
            owner = np.empty(len(rows), np.int64)   # the one track whose reach the pixel's ray passes, or -1
            _pixel_owners(rays.segments, rows, cols, positions, self.reach, pick, owner)
            for k in np.flatnonzero(pick):
                mine = owner == k
                n = int(mine.sum())
                if n < self.min_pixels:
                    continue
                f = coarsening(rays, positions[k], spacing) if spacing > 0 else 1
                if f > 1:
                    r, q = rows[mine] // f, cols[mine] // f
                    grids[k, c, r, q] = 1
                    counts[k, c] = int(np.count_nonzero(grids[k, c, :r.max() + 1, :q.max() + 1]))
                    fx, sk, cx, fy, cy = intr[k, c]
                    intr[k, c] = (fx / f, sk / f, (cx + 0.5) / f - 0.5, fy / f, (cy + 0.5) / f - 0.5)
                else:
                    grids[k, c, rows[mine], cols[mine]] = 1
                    counts[k, c] = n
        R = np.array([r.R for r in self.rays]).reshape(C, 3, 3)
        t = np.array([r.t for r in self.rays]).reshape(C, 3)
        return [PersonSilhouettes(grids[k], counts[k], intr[k], R, t) if pick[k] else None for k in range(T)]


def coarsening(rays: CameraRays, position, spacing: float, body_z: float = 0.9) -> int:
    """The whole factor by which a camera's silhouette pixels are merged for a person at
    ``position`` (its depth taken at ``body_z`` m, mid-body) so that a merged pixel is about
    ``spacing`` m wide there: ``max(1, round(spacing f / depth))`` with ``f`` the view's
    focal length in pixels. The model's points lie on a lattice of ``spacing``; on pixels
    finer than that they hit one pixel in ``(spacing / pixel)^2`` and ``rho_Sil`` of the true
    pose falls with the pixel size: 0.2 on a 3-camera rig 1.9 m from a person (4 cm voxels,
    8 cm lattice, 2.8 pixels apart), where the term then preferred a seated person
    kneeling 0.25 m too low (random scene 4, a tuning seed)."""
    p = np.array([position[0], position[1], body_z], dtype=np.float64)
    depth = float(rays.R[2] @ p + rays.t[2])
    if depth <= 1e-3:
        return 1
    return max(1, int(round(spacing * float(rays.intrinsics[0]) / depth)))


def silhouette_coverage(states, height, lut, active, person: PersonSilhouettes, stamp, token: int) -> np.ndarray:
    """``rho_Sil (P,)`` of every state: the mean over the scored cameras of the share of
    the person's silhouette pixels covered by the projected surface points of the
    ``active`` parts. ``stamp``: an int64 grid of ``person.grids``' shape kept by the
    caller with ``token`` growing by ``len(states)`` a call (no clearing)."""
    out = np.empty(len(states))
    _coverage(np.ascontiguousarray(states, dtype=np.float64), float(height), lut.lx, lut.ly, lut.lz,
              lut.part_start, lut.part_segment, lut.part_surface, np.asarray(active, np.bool_), person.intrinsics,
              person.R, person.t, person.grids, stamp, int(token), person.counts, SEG_PARENT, lut.seg_offset,
              DOF_SEGMENT, DOF_AXIS, out)
    return out


@njit(cache=True, nogil=True)
def _coverage(states, height, lx, ly, lz, part_start, part_segment, part_surface, active, intr, cam_R, cam_t,
              grids, stamp, token0, counts, seg_parent, seg_offset, dof_segment, dof_axis, out):
    """Per state: forward kinematics, then per active part and scored camera the part's
    surface points straight into the camera (the segment's and the camera's rotations
    composed once), pinhole projection, and each silhouette pixel hit counted once."""
    S = seg_parent.shape[0]
    R = np.zeros((S, 3, 3))
    O = np.zeros((S, 3))
    C = intr.shape[0]
    H, W = grids.shape[1], grids.shape[2]
    cov = np.zeros(C)
    A = np.empty((3, 3))
    b = np.empty(3)
    most = 0
    for q in range(part_start.shape[0] - 1):
        most = max(most, part_surface[q])
    pix = np.empty(most, np.int64)
    flat = grids.reshape(C, H * W)
    flat_stamp = stamp.reshape(C, H * W)
    n_cams = 0
    for c in range(C):
        if counts[c] > 0:
            n_cams += 1
    for k in range(states.shape[0]):
        token = token0 + k
        fk_segments(states[k], height, seg_parent, seg_offset, dof_segment, dof_axis, R, O, None)
        for c in range(C):
            cov[c] = 0.0
        for q in range(part_start.shape[0] - 1):
            if not active[q]:
                continue
            s = part_segment[q]
            m0 = part_start[q]
            m1 = m0 + part_surface[q]
            for c in range(C):
                if counts[c] <= 0:
                    continue
                for i in range(3):
                    b[i] = cam_t[c, i]
                    for j in range(3):
                        A[i, j] = cam_R[c, i, 0] * R[s, 0, j] + cam_R[c, i, 1] * R[s, 1, j] + cam_R[c, i, 2] * R[s, 2, j]
                        b[i] += cam_R[c, i, j] * O[s, j]
                fx, sk, cx, fy, cy = intr[c, 0], intr[c, 1], intr[c, 2], intr[c, 3], intr[c, 4]
                a00, a01, a02, b0 = A[0, 0], A[0, 1], A[0, 2], b[0]
                a10, a11, a12, b1 = A[1, 0], A[1, 1], A[1, 2], b[1]
                a20, a21, a22, b2 = A[2, 0], A[2, 1], A[2, 2], b[2]
                # branch-free projection into a pixel index (-1: not in the view), vectorised
                for m in range(m0, m1):
                    z = a20 * lx[m] + a21 * ly[m] + a22 * lz[m] + b2
                    inv = 1.0 / max(z, 1e-6)
                    x = (a00 * lx[m] + a01 * ly[m] + a02 * lz[m] + b0) * inv
                    y = (a10 * lx[m] + a11 * ly[m] + a12 * lz[m] + b1) * inv
                    fu = fx * x + sk * y + cx + 0.5
                    fv = fy * y + cy + 0.5
                    ok = (z > 1e-6) & (fu >= 0.0) & (fv >= 0.0) & (fu < W) & (fv < H)
                    pix[m - m0] = np.int64(fv) * W + np.int64(fu) if ok else -1
                for i in range(m1 - m0):
                    f = pix[i]
                    if f >= 0 and flat[c, f] != 0 and flat_stamp[c, f] != token:
                        flat_stamp[c, f] = token
                        cov[c] += 1.0
        total = 0.0
        for c in range(C):
            if counts[c] > 0:
                total += cov[c] / counts[c]
        out[k] = total / n_cams if n_cams else 1.0


def warm_up() -> None:
    """Compile the kernel (or load it from numba's cache) before the first frame: one
    particle against one empty camera."""
    from app.pose.flesh import PARTS, build_flesh
    from app.pose.likelihood import kernel_lut
    from app.pose.model import neutral_state

    person = PersonSilhouettes(np.zeros((1, 2, 2), np.uint8), np.zeros(1), np.zeros((1, 5)), np.zeros((1, 3, 3)),
                               np.zeros((1, 3)))
    silhouette_coverage(neutral_state(1.75)[None], 1.75, kernel_lut(build_flesh(1.75, 0.08, 1.0)),
                        np.ones(len(PARTS), bool), person, np.zeros((1, 2, 2), np.int64), 1)
    _pixel_owners(np.zeros((1, 1, 4)), np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros((1, 3)), 1.0,
                  np.ones(1, np.bool_), np.empty(1, np.int64))
