"""Connected components over voxel lists (union-find), checked against a dense labelling."""
import numpy as np
import pytest
from scipy import ndimage

from app.components import component_sizes, label_voxels


@pytest.mark.parametrize("connectivity, structure", [(6, 1), (18, 2), (26, 3)])
def test_matches_dense_labelling(connectivity, structure):
    rng = np.random.default_rng(4)
    dense = rng.random((30, 25, 20)) < 0.12
    idx = np.argwhere(dense)
    labels, n = label_voxels(idx, dense.shape, connectivity)
    ref, n_ref = ndimage.label(dense, ndimage.generate_binary_structure(3, structure))
    assert n == n_ref
    # same partition: a bijection between our labels and scipy's
    pairs = set(zip(labels.tolist(), ref[tuple(idx.T)].tolist()))
    assert len(pairs) == n
    assert sorted(component_sizes(labels, n)) == sorted(np.bincount(ref[dense])[1:] if n else [])


def test_two_blobs_and_empty():
    a = np.array([[0, 0, 0], [0, 0, 1], [5, 5, 5], [6, 6, 6]])
    labels, n = label_voxels(a, (10, 10, 10))
    assert n == 2 and labels[0] == labels[1] and labels[2] == labels[3] and labels[0] != labels[2]
    labels, n = label_voxels(np.zeros((0, 3), int), (4, 4, 4))
    assert n == 0 and labels.size == 0


@pytest.mark.parametrize("connectivity", [6, 18, 26])
def test_runs_match_the_union_find_on_random_voxel_sets(connectivity):
    """The run-based labelling gives the per-voxel union-find's labels exactly (same
    numbering by first appearance), on sorted lists, shuffled lists and lists holding a
    voxel twice."""
    from app.components import label_voxels_union_find

    rng = np.random.default_rng(connectivity)
    for density in (0.03, 0.15, 0.4):
        dense = rng.random((23, 17, 29)) < density
        idx = np.argwhere(dense).astype(np.uint16)           # sorted (x, y, z), as published
        for case in (idx, idx[rng.permutation(len(idx))]):
            labels, n = label_voxels(case, dense.shape, connectivity)
            ref, n_ref = label_voxels_union_find(case, dense.shape, connectivity)
            assert n == n_ref and np.array_equal(labels, ref)
    twice = np.concatenate([idx[:50], idx[:50]])
    labels, n = label_voxels(twice, dense.shape, connectivity)
    assert np.array_equal(labels[:50], labels[50:])
    assert n == len(np.unique(label_voxels_union_find(idx[:50], dense.shape, connectivity)[0]))
