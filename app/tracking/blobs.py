"""Connected components of one frame and their features (thesis §4.2.3, Eq. 4.1, Table 4.1).

:func:`component_features` takes the occupied voxels and their component labels (from
:class:`app.components.Labeller`, 26-connectivity over the occupied list) and returns
one row per component, in the order of :data:`FEATURES`:

- weight ``|C| s^3 rho`` in kg, with rho = 1.1 g/cm^3;
- z-centroid, top (highest voxel centre), height (top - lowest) in metres;
- bounding box: the larger and the smaller of the x and y extents (m);
- and, for the trackers, the centroid x, y (m) and the voxel count.

Extents are measured between voxel centres plus one voxel, so a single voxel is ``s`` wide.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from app.components import Labeller

__all__ = ["FEATURES", "CLASSIFIER_FEATURES", "component_features", "features_from_sums", "ComponentAnalysis", "DENSITY_KG_M3"]

FEATURES = ("weight", "z_centroid", "top", "height", "extent_major", "extent_minor", "x", "y", "voxels")
#: Table 4.1: what the person / no-person classifier sees
CLASSIFIER_FEATURES = FEATURES[:6]
DENSITY_KG_M3 = 1100.0   # rho = 1.1 g/cm^3


@njit(cache=True, nogil=True)
def _accumulate(idx, labels, k, out_min, out_max, out_sum, counts):
    for a in range(idx.shape[0]):
        c = labels[a]
        counts[c] += 1
        for d in range(3):
            v = idx[a, d]
            out_sum[c, d] += v
            if v < out_min[c, d]:
                out_min[c, d] = v
            if v > out_max[c, d]:
                out_max[c, d] = v


def component_features(indices: np.ndarray, labels: np.ndarray, count: int, origin, voxel_size: float) -> np.ndarray:
    """Features (count, len(FEATURES)) float32 of the components (Table 4.1 + centroid)."""
    idx = np.asarray(indices).reshape(-1, 3)
    k = int(count)
    mins = np.full((k, 3), np.iinfo(np.int64).max, dtype=np.int64)
    maxs = np.full((k, 3), -1, dtype=np.int64)
    sums = np.zeros((k, 3), dtype=np.float64)
    counts = np.zeros(k, dtype=np.int64)
    if k:
        _accumulate(idx, np.asarray(labels), k, mins, maxs, sums, counts)
    return features_from_sums(mins, maxs, sums, counts, origin, voxel_size)


def features_from_sums(mins, maxs, sums, counts, origin, voxel_size: float) -> np.ndarray:
    """Features (K, len(FEATURES)) float32 from per-component index bounds ``mins`` /
    ``maxs`` (K, 3), index sums (K, 3) and voxel counts (K,)."""
    k = len(counts)
    s = float(voxel_size)
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    n = np.maximum(counts, 1)[:, None]
    centroid = o + (sums / n + 0.5) * s
    ext = (maxs - mins + 1) * s
    out = np.empty((k, len(FEATURES)), dtype=np.float32)
    out[:, 0] = counts * s ** 3 * DENSITY_KG_M3
    out[:, 1] = centroid[:, 2]
    out[:, 2] = o[2] + (maxs[:, 2] + 0.5) * s
    out[:, 3] = (maxs[:, 2] - mins[:, 2]) * s
    out[:, 4] = np.maximum(ext[:, 0], ext[:, 1])
    out[:, 5] = np.minimum(ext[:, 0], ext[:, 1])
    out[:, 6] = centroid[:, 0]
    out[:, 7] = centroid[:, 1]
    out[:, 8] = counts
    return out


class ComponentAnalysis:
    """CCA + features + person test of one grid (a worker keeps one: the labeller's index
    grid is reused between frames). ``classifier``: a :class:`~app.tracking.classifier.DecisionTree`
    or None (every component a person)."""

    def __init__(self, dims, origin, voxel_size: float, classifier=None, connectivity: int = 26):
        self.labeller = Labeller(dims, connectivity)
        self.origin = np.asarray(origin, dtype=np.float64)
        self.voxel_size = float(voxel_size)
        self.classifier = classifier

    def __call__(self, indices: np.ndarray):
        """``(labels (N,) int32, features (K, F) float32, person (K,) uint8)``."""
        labels, k = self.labeller(indices)
        runs = self.labeller.runs
        if runs is not None:   # the same sums over runs (integers: exact in any order)
            from app.tracking.columns import run_sums

            start, z0, z1, col, run_label = runs
            mins = np.full((k, 3), np.iinfo(np.int64).max, dtype=np.int64)
            maxs = np.full((k, 3), -1, dtype=np.int64)
            sums = np.zeros((k, 3), dtype=np.float64)
            counts = np.zeros(k, dtype=np.int64)
            run_sums(np.arange(len(z0)), z0, z1, col, self.labeller.dims[1], run_label, k, mins, maxs, sums, counts)
            feats = features_from_sums(mins, maxs, sums, counts, self.origin, self.voxel_size)
        else:
            feats = component_features(indices, labels, k, self.origin, self.voxel_size)
        if self.classifier is None:
            person = np.ones(k, dtype=np.uint8)
        else:
            person = self.classifier.predict(feats[:, :len(CLASSIFIER_FEATURES)]).astype(np.uint8)
        return labels.astype(np.int32), feats, person
