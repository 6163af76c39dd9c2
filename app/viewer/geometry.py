"""Geometry of what the viewer draws, as plain numpy: the room box and floor grid,
camera frustums, limb segments of a pose and the solid skeleton built on them (bones and
joints as small meshes), voxel subsampling, colours and the default view. World coordinates are metres, z up (CONTRACT: floor at z = 0)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.messages import JOINTS

__all__ = [
    "LIMBS", "LIMB_INDEX", "box_edges", "floor_grid", "frustum_corners", "frustum_segments",
    "limb_segments", "skeleton_mesh", "subsample", "point_size", "rgb_floats", "track_colour", "ViewCamera",
    "default_view", "translation", "ellipsoid_rings",
]

#: Limbs of the 15-joint body (CONTRACT §1 names), each drawn as one segment.
LIMBS = (
    ("pelvis", "neck"), ("neck", "head"),
    ("neck", "l_shoulder"), ("l_shoulder", "l_elbow"), ("l_elbow", "l_wrist"),
    ("neck", "r_shoulder"), ("r_shoulder", "r_elbow"), ("r_elbow", "r_wrist"),
    ("pelvis", "l_hip"), ("l_hip", "l_knee"), ("l_knee", "l_ankle"),
    ("pelvis", "r_hip"), ("r_hip", "r_knee"), ("r_knee", "r_ankle"),
)
#: :data:`LIMBS` as (14, 2) indices into :data:`app.messages.JOINTS`.
LIMB_INDEX = np.array([[JOINTS.index(a), JOINTS.index(b)] for a, b in LIMBS], dtype=np.intp)

#: Colours of tracks (by id), RGB in [0, 1]: distinct hues, none grey, none the voxels' neutral.
PALETTE = np.array([
    [1.00, 0.35, 0.20], [0.20, 0.80, 1.00], [1.00, 0.85, 0.10], [0.75, 0.35, 1.00],
    [0.25, 1.00, 0.45], [1.00, 0.40, 0.75], [0.10, 0.55, 1.00], [0.65, 1.00, 0.15],
])


def translation(p) -> np.ndarray:
    """4x4 homogeneous translation."""
    m = np.eye(4)
    m[:3, 3] = np.asarray(p, dtype=np.float64).reshape(3)
    return m


def box_edges(lo, hi) -> np.ndarray:
    """The 12 edges of an axis-aligned box as (12, 2, 3) segment end points."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)])
    pairs = [(i, i | (1 << k)) for i in range(8) for k in range(3) if not (i >> k) & 1]
    return corners[np.array(pairs)]


def floor_grid(lo, hi, step: float = 1.0) -> np.ndarray:
    """Lines of a grid on the floor (z = lo[2]) inside the room, every ``step`` metres,
    the room's own border excluded (the box draws it): (k, 2, 3)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    z = lo[2]
    segs = []
    for x in np.arange(lo[0] + step, hi[0] - 1e-6, step):
        segs.append([[x, lo[1], z], [x, hi[1], z]])
    for y in np.arange(lo[1] + step, hi[1] - 1e-6, step):
        segs.append([[lo[0], y, z], [hi[0], y, z]])
    return np.array(segs, dtype=np.float64).reshape(-1, 2, 3)


def frustum_corners(camera, depth: float) -> tuple[np.ndarray, np.ndarray]:
    """The camera centre and the world points (4, 3) seen at the image corners at
    ``depth`` metres along the optical axis (top-left, top-right, bottom-right,
    bottom-left; the lens distortion is ignored)."""
    w, h = camera.width, camera.height
    pix = np.array([[-0.5, -0.5, 1.0], [w - 0.5, -0.5, 1.0], [w - 0.5, h - 0.5, 1.0], [-0.5, h - 0.5, 1.0]])
    rays = pix @ np.linalg.inv(camera.K).T            # normalised coordinates, z = 1
    return camera.centre, camera.centre + depth * rays @ camera.R   # R^T x for each row x


def frustum_segments(camera, depth: float = 0.4) -> np.ndarray:
    """A camera's frustum as (10, 2, 3) segments: four edges from the centre, the image
    rectangle at ``depth`` and a small triangle on the top edge (the image's up)."""
    c, q = frustum_corners(camera, depth)
    segs = [[c, q[i]] for i in range(4)] + [[q[i], q[(i + 1) % 4]] for i in range(4)]
    top_mid = 0.5 * (q[0] + q[1])
    up = top_mid - 0.5 * (q[2] + q[3])
    apex = top_mid + 0.25 * up
    half = 0.2 * (q[1] - q[0])
    segs += [[top_mid - half, apex], [apex, top_mid + half]]
    return np.array(segs, dtype=np.float64)


def ellipsoid_rings(semi_axes, latitudes=(-0.55, 0.0, 0.55), meridians: int = 4, points: int = 48) -> np.ndarray:
    """An ellipsoid centred on the origin drawn as a cage of rings, (k, 2, 3) segments:
    horizontal rings at the given heights (fractions of the vertical semi-axis) and
    ``meridians`` vertical half-planes' rings. Light enough that the voxels inside keep
    their own colours."""
    a = np.asarray(semi_axes, float).reshape(3)
    t = np.linspace(0.0, 2.0 * np.pi, points + 1)
    rings = []
    for h in latitudes:
        r = np.sqrt(max(0.0, 1.0 - h * h))
        rings.append(np.stack([r * np.cos(t), r * np.sin(t), np.full_like(t, h)], axis=1))
    for k in range(meridians // 2 if meridians > 1 else meridians):
        phi = np.pi * k / max(1, meridians // 2)
        rings.append(np.stack([np.cos(phi) * np.sin(t), np.sin(phi) * np.sin(t), np.cos(t)], axis=1))
    segs = [np.stack([ring[:-1], ring[1:]], axis=1) for ring in rings]
    return np.concatenate(segs) * a


def limb_segments(joints, active=None) -> tuple[np.ndarray, np.ndarray]:
    """Segments (14, 2, 3) of one pose's limbs and whether each limb is active (both of
    its joints active; all active when ``active`` is None)."""
    j = np.asarray(joints, dtype=np.float64).reshape(len(JOINTS), 3)
    segs = j[LIMB_INDEX]
    if active is None or np.size(active) != len(JOINTS):
        return segs, np.ones(len(LIMBS), dtype=bool)
    a = np.asarray(active, dtype=bool).reshape(len(JOINTS))
    return segs, a[LIMB_INDEX].all(axis=1)


def _prism(a: np.ndarray, b: np.ndarray, radius: float, sides: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed-sided prism of ``sides`` faces around the segment a-b: vertices (2 sides, 3)
    and triangles (2 sides, 3) indexing them."""
    axis = b - a
    length = np.linalg.norm(axis)
    d = axis / length if length > 1e-9 else np.array([0.0, 0.0, 1.0])
    ref = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(d, ref)
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    t = 2.0 * np.pi * np.arange(sides) / sides
    ring = radius * (np.cos(t)[:, None] * u + np.sin(t)[:, None] * v)
    verts = np.concatenate([a + ring, b + ring])
    k = np.arange(sides)
    k1 = (k + 1) % sides
    faces = np.concatenate([np.stack([k, k1, sides + k], 1), np.stack([k1, sides + k1, sides + k], 1)])
    return verts, faces


_OCTAHEDRON = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
_OCTAHEDRON_FACES = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])


def skeleton_mesh(joints, active, colour, inactive_colour, bone_radius: float = 0.022,
                  joint_radius: float = 0.035, sides: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pose as a solid skeleton: each limb of :data:`LIMBS` a bone (a thin prism)
    between its joints, each joint a small octahedron. A limb the model lost (either joint
    inactive) is grey and half as thick, an inactive joint grey: what was lost is seen as
    lost. Lines would be one pixel wide whatever the distance (WebGL draws no thicker
    lines), leaving only the joints visible. Returns vertices (V, 3), triangles (T, 3) and
    per-vertex colours (V, 3) in [0, 1]."""
    j = np.asarray(joints, dtype=np.float64).reshape(len(JOINTS), 3)
    segs, limb_on = limb_segments(j, active)
    joint_on = np.ones(len(JOINTS), bool) if active is None or np.size(active) != len(JOINTS) else \
        np.asarray(active, bool).reshape(len(JOINTS))
    colour = np.asarray(colour, float).reshape(3)
    grey = np.asarray(inactive_colour, float).reshape(3)
    verts, faces, cols = [], [], []
    n = 0
    for (a, b), on in zip(segs, limb_on):
        v, f = _prism(a, b, bone_radius if on else 0.5 * bone_radius, sides)
        verts.append(v)
        faces.append(f + n)
        cols.append(np.tile(colour if on else grey, (len(v), 1)))
        n += len(v)
    for p, on in zip(j, joint_on):
        verts.append(p + joint_radius * _OCTAHEDRON)
        faces.append(_OCTAHEDRON_FACES + n)
        cols.append(np.tile(colour if on else grey, (len(_OCTAHEDRON), 1)))
        n += len(_OCTAHEDRON)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(cols)


def subsample(n: int, max_points: int, surface=None) -> np.ndarray | None:
    """Indices of at most ``max_points`` of ``n`` voxels to display (None: all of them).

    Surface voxels (``surface`` flags, thesis's V^S) are what a viewer sees of a solid,
    so they are kept first; what is still too many is thinned with an even stride, the
    same voxels from frame to frame (no flicker from random picks).
    """
    if max_points <= 0 or n <= max_points:
        return None
    idx = np.arange(n)
    if surface is not None and np.size(surface) == n:
        s = np.flatnonzero(np.asarray(surface, dtype=bool))
        if 0 < s.size:
            idx = s
            if idx.size <= max_points:
                return idx
    keep = np.linspace(0, idx.size - 1, max_points).round().astype(np.intp)
    return idx[np.unique(keep)]


def point_size(voxel_size: float, total: int, shown: int) -> float:
    """Display size of one voxel point (metres): the voxel's edge, grown by the cube root
    of the thinning ratio so that a subsampled solid still looks solid (at most 2.5x)."""
    if shown <= 0:
        return float(voxel_size)
    return float(voxel_size) * float(np.clip((total / shown) ** (1.0 / 3.0), 1.0, 2.5))


def rgb_floats(colours, n: int, neutral=(0.78, 0.80, 0.85)) -> np.ndarray:
    """RGB colours (n, 3) in [0, 1] from uint8 colours, or the neutral colour for all
    when there are none (or they do not fit)."""
    c = np.asarray(colours) if colours is not None else np.zeros((0, 3), np.uint8)
    if c.ndim != 2 or c.shape != (n, 3):
        return np.tile(np.asarray(neutral, dtype=np.float32), (n, 1))
    if c.dtype == np.uint8:
        return c.astype(np.float32) / 255.0
    return np.clip(c.astype(np.float32), 0.0, 1.0)


def track_colour(track_id: int) -> np.ndarray:
    """The colour (RGB in [0, 1]) of a track, fixed by its id."""
    return PALETTE[int(track_id) % len(PALETTE)]


@dataclass(frozen=True)
class ViewCamera:
    """A perspective view: eye, target, z up and a vertical field of view (three.js's
    PerspectiveCamera, which meshcat's default camera is)."""

    eye: np.ndarray
    target: np.ndarray
    fov_deg: float = 75.0

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit right, up and forward vectors of the view."""
        f = np.asarray(self.target, float) - np.asarray(self.eye, float)
        f /= np.linalg.norm(f)
        r = np.cross(f, [0.0, 0.0, 1.0])
        r /= np.linalg.norm(r)
        return r, np.cross(r, f), f

    def project(self, points, width: int, height: int) -> np.ndarray:
        """Pixel coordinates (N, 2) of world points in a ``width`` x ``height`` image
        (x to the right, y down; points behind the eye get NaN)."""
        r, u, f = self.basis()
        d = np.asarray(points, float).reshape(-1, 3) - np.asarray(self.eye, float)
        z = d @ f
        t = np.tan(np.radians(self.fov_deg) / 2.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = (d @ r) / (z * t * width / height)
            y = (d @ u) / (z * t)
        px = np.stack([(x + 1.0) * width / 2.0, (1.0 - y) * height / 2.0], axis=1)
        px[z <= 1e-6] = np.nan
        return px


def default_view(points, fov_deg: float = 75.0, aspect: float = 4 / 3, azimuth_deg: float = -115.0,
                 elevation_deg: float = 38.0, fill: float = 0.92, target_height: float = 0.4) -> ViewCamera:
    """A view from above one side that shows every point (the room's corners, the
    cameras) within ``fill`` of the image, for a window of ``aspect`` or wider.

    The target is the centre of the points' floor footprint raised to ``target_height``
    of their height; the eye backs away along the (azimuth, elevation) direction until
    everything fits.
    """
    p = np.asarray(points, float).reshape(-1, 3)
    lo, hi = p.min(axis=0), p.max(axis=0)
    target = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2] + target_height * (hi[2] - lo[2])])
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    direction = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    w, h = 1000, max(1, int(round(1000 / aspect)))

    def fits(dist: float) -> bool:
        px = ViewCamera(target + dist * direction, target, fov_deg).project(p, w, h)
        if np.isnan(px).any():
            return False
        m = (1.0 - fill) / 2.0
        return bool((px[:, 0] >= m * w).all() and (px[:, 0] <= (1 - m) * w).all()
                    and (px[:, 1] >= m * h).all() and (px[:, 1] <= (1 - m) * h).all())

    near, far = 0.1, 10.0 * (np.linalg.norm(hi - lo) + 1.0)
    for _ in range(60):   # the smallest distance that fits (fitting is monotonic beyond the points)
        mid = 0.5 * (near + far)
        near, far = (near, mid) if fits(mid) else (mid, far)
    return ViewCamera(target + far * direction, target, fov_deg)
