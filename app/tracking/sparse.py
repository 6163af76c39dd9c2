"""Sparse Sampling tracking (thesis §4.3.3, Eq. 4.14-4.21, Fig. 4.8), one filter per target.

Samples are voxel positions ``y^i`` (never two in one voxel) meant to lie on the target's
surface; the centroid is their weighted mean (Eq. 4.18). Each frame:

1. discrete resampling: replicas of each sample in proportion to its weight;
2. propagation with discrete noise (a random offset of up to ``ss_step`` voxels per
   axis); a replica landing on a voxel that already holds a sample searches the 26
   adjacent voxels, from a random one onwards, for a free one, and is dismissed if there
   is none (Fig. 4.8(b));
3. pseudo-likelihood (Eq. 4.19): ``lambda p_raw + (1 - lambda) p_colour`` on the
   neighbourhood ``C(y, q=26, r=2)`` (the 5x5x5 voxels around the sample, looked up in
   the frame's column index, :func:`app.tracking.columns.neighbourhood`):
   ``p_raw = 1 - |2 |O| / |C| - 1|`` (Eq. 4.20, highest on a surface) and ``p_colour`` the
   share of the coloured voxels of the neighbourhood whose bin in the target's reference
   histogram is at least ``gamma``, the threshold that keeps the bins holding 80 % of
   the histogram (Eq. 4.21);
4. intra-target removal: a sample farther (xy) than ``delta = 1.5 s_x`` from the last
   estimate gets weight 0; inter-target blocking as in the particle filter (Eq. 4.12-4.13);
5. estimate: ``x~ = sum w^i y^i`` (Eq. 4.18).

``colour=False`` is SS-raw (lambda = 1). A target whose samples all die is re-seeded on
the surface voxels within ``delta`` of its last estimate.

Beyond the thesis, so that colour decides who is who in a merged blob (Fig. 4.12; each
selectable, off is the thesis): the reference histogram is not adapted (Eq. 4.11) while
another target is within ``colour_freeze`` (the blob's colours are both people's), and
the blocking by a differently dressed target (Bhattacharyya < ``duplicate_similarity``)
is lifted in proportion to the sample's colour score (``colour_unblock``): a track may
follow its own colours past the other target instead of being held on its side.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from app.tracking.columns import neighbourhood
from app.tracking.particle import blocking, ellipsoid_voxels, systematic_resample
from app.tracking.scene import SceneFrame, coverage_threshold, histogram

__all__ = ["SparseTarget"]

_NEIGHBOURS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                        if (i, j, k) != (0, 0, 0)], dtype=np.int64)


@njit(cache=True, nogil=True)
def _untaken(samples, fresh, taken):
    """Which of ``fresh`` lie on no voxel of ``samples`` (``taken``: a zeroed scratch
    grid, left zeroed)."""
    for a in range(samples.shape[0]):
        taken[samples[a, 0], samples[a, 1], samples[a, 2]] = 1
    out = np.empty(fresh.shape[0], dtype=np.bool_)
    for a in range(fresh.shape[0]):
        out[a] = taken[fresh[a, 0], fresh[a, 1], fresh[a, 2]] == 0
    for a in range(samples.shape[0]):
        taken[samples[a, 0], samples[a, 1], samples[a, 2]] = 0
    return out


@njit(cache=True, nogil=True)
def _propagate(parents, offsets, starts, neighbours, taken, out):
    """Place replicas ``parents + offsets`` on free voxels (Fig. 4.8); returns how many."""
    nx, ny, nz = taken.shape
    m = 0
    for a in range(parents.shape[0]):
        x = parents[a, 0] + offsets[a, 0]
        y = parents[a, 1] + offsets[a, 1]
        z = parents[a, 2] + offsets[a, 2]
        placed = False
        for t in range(27):
            if t == 0:
                qx, qy, qz = x, y, z
            else:
                o = (starts[a] + t - 1) % 26
                qx, qy, qz = x + neighbours[o, 0], y + neighbours[o, 1], z + neighbours[o, 2]
            if qx < 0 or qy < 0 or qz < 0 or qx >= nx or qy >= ny or qz >= nz:
                continue
            if taken[qx, qy, qz] == 0:
                taken[qx, qy, qz] = 1
                out[m, 0], out[m, 1], out[m, 2] = qx, qy, qz
                m += 1
                placed = True
                break
        if not placed:
            continue
    for a in range(m):   # wipe the scratch grid
        taken[out[a, 0], out[a, 1], out[a, 2]] = 0
    return m


class SparseTarget:
    """One target of the Sparse Sampling tracker."""

    name = "ss"

    def __init__(self, position, scene: SceneFrame, rng: np.random.Generator, params, colour: bool = True):
        self.p = params
        self.rng = rng
        self.colour = colour and scene.has_colour
        self.x = np.asarray(position, dtype=np.float64).copy()
        self.samples = np.zeros((0, 3), dtype=np.int64)
        self.weights = np.zeros(0)
        self.reference = None
        self.efficiency = 0.0
        if self.colour:
            sel = ellipsoid_voxels(scene, self.x, params.sx)
            self.reference = histogram(scene.bins[sel[scene.bins[sel] >= 0]])
        self._seed(scene)

    def _seed(self, scene: SceneFrame) -> None:
        """Samples on random surface voxels within delta of the estimate (all voxels if
        the surface is not flagged)."""
        p = self.p
        near = scene.near_xy(self.x, p.alpha * p.sx)
        surf = near[scene.surface[near]] if scene.surface.any() else near
        n = min(int(p.samples), len(surf))
        pick = self.rng.choice(surf, n, replace=False) if n else surf[:0]
        self.samples = scene.indices[pick].astype(np.int64)
        self.weights = np.full(n, 1.0 / n) if n else np.zeros(0)

    def _fresh(self, scene: SceneFrame, k: int) -> np.ndarray:
        """``k`` random surface voxels within delta of the estimate (beyond the thesis:
        ``ss_reseed``, the share of samples drawn afresh each frame, keeps the sampling
        set spread over the whole surface so that the mean of Eq. 4.18 cannot drift with
        the cloud; 0 is the thesis's filter)."""
        if k <= 0:
            return np.zeros((0, 3), dtype=np.int64)
        p = self.p
        near = scene.near_xy(self.x, p.alpha * p.sx)
        surf = near[scene.surface[near]] if scene.surface.any() else near
        if len(surf) == 0:
            return np.zeros((0, 3), dtype=np.int64)
        pick = self.rng.choice(surf, min(k, len(surf)), replace=False)
        return scene.indices[pick].astype(np.int64)

    @classmethod
    def step_all(cls, targets: list["SparseTarget"], scene: SceneFrame) -> None:
        estimates = np.array([t.x for t in targets]) if targets else np.zeros((0, 3))
        for i, t in enumerate(targets):
            distinct = np.array([t.distinct_from(o) for j, o in enumerate(targets) if j != i], dtype=bool)
            t.step(scene, np.delete(estimates, i, axis=0), distinct)

    def distinct_from(self, other: "SparseTarget") -> bool:
        """Whether colour tells this target from ``other``: both have a reference
        histogram and they are less alike (Bhattacharyya) than ``duplicate_similarity``."""
        a, b = self.reference, getattr(other, "reference", None)
        if not self.colour or a is None or b is None or self.p.duplicate_similarity <= 0:
            return False
        return bool(np.sqrt(a * b).sum() < self.p.duplicate_similarity)

    def step(self, scene: SceneFrame, others: np.ndarray, distinct: np.ndarray | None = None) -> None:
        p, rng = self.p, self.rng
        if len(self.samples) == 0:
            self._seed(scene)
            if len(self.samples) == 0:
                self.efficiency = 0.0
                return
        n = int(p.samples)
        fresh = self._fresh(scene, int(round(p.ss_reseed * n)))
        parents = self.samples[systematic_resample(self.weights, n - len(fresh), rng)]
        step = max(1, int(round(p.ss_step / scene.voxel_size)))
        offsets = rng.integers(-step, step + 1, (n, 3))
        starts = rng.integers(0, 26, n)
        placed = np.empty((n, 3), dtype=np.int64)
        taken = _scratch(scene.dims)
        m = _propagate(parents, offsets, starts, _NEIGHBOURS, taken, placed)
        samples = placed[:m]
        if len(fresh):   # fresh samples on voxels no replica took
            samples = np.concatenate([samples, fresh[_untaken(samples, fresh, taken)]])
            m = len(samples)
        raw = np.zeros(m)
        col = np.zeros(m)
        use_colour = self.colour and self.reference is not None
        ref = self.reference if use_colour else np.zeros(1)
        gamma = coverage_threshold(self.reference, p.coverage) if use_colour else 0.0
        neighbourhood(samples, scene.col_run, scene.run_start, scene.run_z0, scene.run_z1, scene.dims[0],
                      scene.dims[1], scene.bins, ref, gamma, use_colour, p.ss_radius, raw, col)   # Eq. 4.20-4.21
        w = p.lam * raw + (1 - p.lam) * col if use_colour else raw           # Eq. 4.19
        world = scene.origin + (samples + 0.5) * scene.voxel_size
        far = ((world[:, :2] - self.x[:2]) ** 2).sum(axis=1) > (p.alpha * p.sx) ** 2
        w[far] = 0.0                                                          # intra-target removal
        k = p.ss_blocking / p.sx ** 2
        lift = distinct if use_colour and p.colour_unblock and distinct is not None else np.zeros(len(others), bool)
        w *= blocking(world[:, :2], others[~lift], k)                        # Eq. 4.12-4.13
        for o in others[lift]:   # beyond the thesis: the target's own colours are not blocked by
            b = blocking(world[:, :2], o[None], k)   # a differently dressed target (colour_unblock)
            w *= b + (1 - b) * col
        total = w.sum()
        self.efficiency = float(total / n)
        if total <= 1e-9:
            self._seed(scene)
            return
        self.samples, self.weights = samples, w / total
        self.x = self.weights @ world                                         # Eq. 4.18
        near_other = len(others) and p.colour_freeze > 0 and \
            (((others[:, :2] - self.x[:2]) ** 2).sum(axis=1) < p.colour_freeze ** 2).any()
        if use_colour and not near_other:                                     # Eq. 4.11
            sel = ellipsoid_voxels(scene, self.x, p.sx, others)
            h = histogram(scene.bins[sel[scene.bins[sel] >= 0]])
            if h is not None:
                self.reference = p.adapt * self.reference + (1 - p.adapt) * h


_SCRATCH: dict = {}


def _scratch(shape) -> np.ndarray:
    """A zeroed uint8 grid of ``shape`` shared by the targets (wiped after each use)."""
    g = _SCRATCH.get(shape)
    if g is None:
        _SCRATCH.clear()
        g = _SCRATCH[shape] = np.zeros(shape, dtype=np.uint8)
    return g
