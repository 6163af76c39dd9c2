"""The column / run index of a frame (app.tracking.columns) answers the trackers'
neighbourhood queries exactly as brute force over the voxel centres and a dense
occupancy grid do, on sorted and shuffled voxel lists."""
import numpy as np
import pytest

from app.components import label_voxels
from app.tracking import columns
from app.tracking.particle import ellipsoid_voxels
from app.tracking.scene import OccupancyIndex, SceneFrame

DIMS = (30, 24, 40)
ORIGIN = (-0.3, 0.2, 0.0)
S = 0.05


def _scene(shuffle: bool, seed: int = 0):
    rng = np.random.default_rng(seed)
    dense = rng.random(DIMS) < 0.06
    dense[:, :, 30:] = False
    idx = np.argwhere(dense)
    n = len(idx)
    colours = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    surface = rng.random(n) < 0.5
    labels, k = label_voxels(idx, DIMS)   # component labels: a z run lies in one component
    if shuffle:
        order = rng.permutation(n)
        idx, colours, surface, labels = idx[order], colours[order], surface[order], labels[order]
    feats = np.zeros((k, 9))
    scene = SceneFrame(0, 0.0, idx.astype(np.uint16), colours, surface, labels, feats, np.ones(k, bool), ORIGIN, S,
                       OccupancyIndex(DIMS))
    return scene, rng


@pytest.mark.parametrize("shuffle", [False, True])
def test_queries_match_brute_force(shuffle):
    scene, rng = _scene(shuffle)
    centres = np.asarray(ORIGIN) + (scene.indices.astype(np.int64) + 0.5) * S
    assert np.array_equal(scene.centres, centres)
    grid = np.full(DIMS, -1, np.int64)
    grid[tuple(scene.indices.T)] = np.arange(scene.n)
    for _ in range(20):
        x = np.array([rng.uniform(-0.3, 1.2), rng.uniform(0.2, 1.4), rng.uniform(0.2, 1.2)])
        r = rng.uniform(0.05, 0.5)
        near = scene.near_xy(x, r)
        ref = np.nonzero(((centres[:, :2] - x[:2]) ** 2).sum(axis=1) <= r * r)[0]
        assert np.array_equal(near, ref)
        # support and host label (the smallest of the most frequent)
        k, host = columns.disc_support(scene.col_run, scene.run_z0, scene.run_z1, scene.run_label, DIMS[0], DIMS[1],
                                       ORIGIN[0], ORIGIN[1], S, x[0], x[1], r, np.zeros(scene.components, np.int64))
        assert k == len(ref) and host == (np.bincount(scene.labels[ref]).argmax() if len(ref) else -1)
        # ellipsoid without the voxels nearer to another target
        other = x[:2] + rng.normal(0, 0.2, (2, 2))
        got = ellipsoid_voxels(scene, x, r, other)
        d = centres - x
        inside = (d[:, 0] ** 2 + d[:, 1] ** 2) / r ** 2 + (d[:, 2] / max(x[2], 0.05)) ** 2 <= 1.0
        own = (d[:, :2] ** 2).sum(axis=1)
        mine = own <= ((centres[:, None, :2] - other[None]) ** 2).sum(axis=2).min(axis=1)
        assert np.array_equal(got, np.nonzero(inside & mine & (own <= r * r))[0])
    # the 5x5x5 neighbourhood of Eq. 4.20-4.21 against the dense grid
    samples = scene.indices[rng.choice(scene.n, 50, replace=False)].astype(np.int64)
    ref_hist = rng.random(21 ** 3)
    raw, col = np.zeros(50), np.zeros(50)
    columns.neighbourhood(samples, scene.col_run, scene.run_start, scene.run_z0, scene.run_z1, DIMS[0], DIMS[1],
                          scene.bins, ref_hist, 0.5, True, 2, raw, col)
    for a, (i, j, k) in enumerate(samples):
        block = grid[max(i - 2, 0):i + 3, max(j - 2, 0):j + 3, max(k - 2, 0):k + 3]
        at = block[block >= 0]
        b = scene.bins[at]
        b = b[b >= 0]
        assert raw[a] == 1.0 - abs(2.0 * len(at) / 125 - 1.0)
        assert col[a] == ((ref_hist[b] >= 0.5).sum() / len(b) if len(b) else 0.0)
