"""Particle filter tracking (thesis §4.3.2, Eq. 4.8-4.13), one filter per target.

A particle is a body instance: an ellipsoid of axes ``(s_x, s_y, z)`` centred at the
particle's centroid ``x^j`` (the state). Each frame: systematic resampling, Gaussian
propagation (no dynamical model, as in the thesis), weighting by

- ``p_raw`` (Eq. 4.9): occupied voxels in the ellipsoid over its volume in voxels;
- ``p_colour`` (Eq. 4.10): Bhattacharyya coefficient between the target's reference
  YCbCr histogram (21 bins per channel) and that of the coloured (surface) voxels in the
  ellipsoid; combined as ``lambda p_raw + (1 - lambda) p_colour`` (Eq. 4.8, lambda = 0.8);
- blocking (Eq. 4.12-4.13): times ``1 - exp(-k ||x^j_xy - x~^l_xy||^2)`` for every other
  target's last estimate, ``k = 1 / s_x^2``. The extracted Eq. 4.12 writes phi of the two
  targets' estimates, which does not depend on the particle and would not block
  anything; Fig. 4.6 and the text penalise particles falling in another target's
  exclusion zone, which is what is implemented.

The estimate is the weighted mean of the particles; the reference histogram adapts as
``H_t = 0.9 H_{t-1} + 0.1 H(estimate)`` (Eq. 4.11).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from app.tracking import columns
from app.tracking.scene import SceneFrame, histogram

__all__ = ["ParticleTarget", "ellipsoid_voxels"]


@njit(cache=True, nogil=True)
def _likelihoods(particles, centres, bins, sx, sy, voxel_volume, ref, use_colour, raw, col):
    """Eq. 4.9 and 4.10 for every particle over the local voxels."""
    scratch = np.zeros(ref.shape[0], dtype=np.float64)
    touched = np.empty(centres.shape[0], dtype=np.int64)
    for j in range(particles.shape[0]):
        cx, cy, cz = particles[j, 0], particles[j, 1], particles[j, 2]
        sz = max(cz, 0.05)
        inside = 0
        nt = 0
        ncol = 0
        for a in range(centres.shape[0]):
            dx = (centres[a, 0] - cx) / sx
            dy = (centres[a, 1] - cy) / sy
            dz = (centres[a, 2] - cz) / sz
            if dx * dx + dy * dy + dz * dz <= 1.0:
                inside += 1
                if use_colour:
                    b = bins[a]
                    if b >= 0:
                        if scratch[b] == 0.0:
                            touched[nt] = b
                            nt += 1
                        scratch[b] += 1.0
                        ncol += 1
        volume = 4.0 / 3.0 * np.pi * sx * sy * sz / voxel_volume
        raw[j] = min(1.0, inside / volume)
        if use_colour:
            s = 0.0
            for i in range(nt):
                b = touched[i]
                s += np.sqrt(ref[b] * scratch[b] / ncol)
                scratch[b] = 0.0
            col[j] = s


def ellipsoid_voxels(scene: SceneFrame, x, sx: float, exclude_xy=None) -> np.ndarray:
    """List positions of the voxels in the body ellipsoid at ``x`` (axes sx, sx, z),
    without those nearer (xy) to one of ``exclude_xy`` than to ``x``."""
    excl = np.zeros((0, 2)) if exclude_xy is None or not len(exclude_xy) else \
        np.ascontiguousarray(np.asarray(exclude_xy, dtype=np.float64)[:, :2])
    o = scene.origin
    return columns.ellipsoid_voxels(scene.col_start, scene.indices, scene.dims[0], scene.dims[1], o[0], o[1], o[2],
                                    scene.voxel_size, np.asarray(x, dtype=np.float64), float(sx), excl)


def blocking(points_xy: np.ndarray, others_xy: np.ndarray, k: float) -> np.ndarray:
    """Eq. 4.13's exclusion factor of each point against every other target (product)."""
    w = np.ones(len(points_xy))
    for o in others_xy:
        w *= 1.0 - np.exp(-k * ((points_xy - o[:2]) ** 2).sum(axis=1))
    return w


def systematic_resample(weights: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``n`` replicas, each parent drawn in proportion to its weight."""
    c = np.cumsum(weights)
    c /= c[-1]
    u = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(c, u), len(weights) - 1)


class ParticleTarget:
    """One target of the particle filter tracker."""

    name = "pf"

    def __init__(self, position, scene: SceneFrame, rng: np.random.Generator, params, colour: bool = True):
        self.p = params
        self.rng = rng
        self.colour = colour and scene.has_colour
        self.x = np.asarray(position, dtype=np.float64).copy()
        n = int(params.particles)
        self.particles = self.x + rng.normal(0.0, 1.0, (n, 3)) * params.pf_sigma
        self.weights = np.full(n, 1.0 / n)
        self.reference = None
        if self.colour:
            self.reference = histogram(scene.bins[_coloured(scene, ellipsoid_voxels(scene, self.x, params.sx))])

    @classmethod
    def step_all(cls, targets: list["ParticleTarget"], scene: SceneFrame) -> None:
        estimates = np.array([t.x for t in targets]) if targets else np.zeros((0, 3))
        for i, t in enumerate(targets):
            t.step(scene, np.delete(estimates, i, axis=0), estimates)

    def step(self, scene: SceneFrame, others: np.ndarray, all_estimates: np.ndarray) -> None:
        p, rng = self.p, self.rng
        n = len(self.particles)
        parents = systematic_resample(self.weights, n, rng)
        parts = self.particles[parents] + rng.normal(0.0, 1.0, (n, 3)) * p.pf_sigma
        parts[:, 2] = np.clip(parts[:, 2], p.z_min, p.z_max)
        reach = p.sx + 3 * float(np.max(p.pf_sigma)) + float(np.abs(parts[:, :2] - self.x[:2]).max())
        local = scene.near_xy(self.x, reach)
        raw = np.zeros(n)
        col = np.zeros(n)
        use_colour = self.colour and self.reference is not None
        ref = self.reference if use_colour else np.zeros(1)
        _likelihoods(parts, scene.centres_at(local), scene.bins[local], p.sx, p.sx, scene.voxel_size ** 3,
                     ref, use_colour, raw, col)
        like = p.lam * raw + (1 - p.lam) * col if use_colour else raw          # Eq. 4.8
        w = like * blocking(parts[:, :2], others, 1.0 / p.sx ** 2)            # Eq. 4.12-4.13
        total = w.sum()
        self.particles = parts
        if total <= 1e-12:
            self.weights = np.full(n, 1.0 / n)
            return                                                             # nothing seen: keep x
        self.weights = w / total
        self.x = self.weights @ parts
        if use_colour:                                                         # Eq. 4.11
            h = histogram(scene.bins[_coloured(scene, ellipsoid_voxels(scene, self.x, p.sx, others))])
            if h is not None:
                self.reference = p.adapt * self.reference + (1 - p.adapt) * h


def _coloured(scene: SceneFrame, sel: np.ndarray) -> np.ndarray:
    return sel[scene.bins[sel] >= 0]

