"""The pose stage's voxel subset (app.pose.selection): the tolerant subset keeps the
one-miss voxels of the shins next to a track, not the phantom away from it or above the
floor band, and only where enough cameras still see them."""
import numpy as np
import pytest

from app.pose.selection import pose_subset


def _scene(vs=0.02):
    """A person at (1, 1): a consensus trunk (0.3-1.7 m), shin voxels below 0.2 m that one
    camera misses, a one-miss phantom on the floor 1 m away and one-miss fat beside the
    trunk at 1 m high."""
    g = np.arange(-0.06, 0.06, vs)
    trunk = np.array([(1 + x, 1 + y, z) for x in g for y in g for z in np.arange(0.3, 1.7, vs)])
    shins = np.array([(1 + x, 1 + y, z) for x in g[:3] for y in g[:3] for z in np.arange(0.01, 0.3, vs)])
    phantom = np.array([(2 + x, 1 + y, z) for x in g for y in g for z in np.arange(0.01, 0.2, vs)])
    fat = np.array([(1.2 + x, 1 + y, 1.0 + z) for x in g for y in g for z in g])
    centres = np.concatenate([trunk, shins, phantom, fat])
    misses = np.concatenate([np.zeros(len(trunk)), np.ones(len(shins) + len(phantom) + len(fat))]).astype(np.uint8)
    parts = np.repeat(np.arange(4), [len(trunk), len(shins), len(phantom), len(fat)])
    return centres, misses, parts


def test_tolerant_keeps_low_shins_near_the_track_only():
    centres, misses, parts = _scene()
    track = np.array([[1.0, 1.0, 0.9]])
    keep = pose_subset(misses, centres, track, mode="tolerant", cameras=5, low=0.2, near=0.6, views=3)
    assert keep[parts == 0].all()                              # the consensus
    shin = parts == 1
    assert keep[shin & (centres[:, 2] < 0.2)].all()            # the one-miss shins below 0.2 m
    assert not keep[shin & (centres[:, 2] >= 0.2)].any()
    assert not keep[parts == 2].any()                          # the floor phantom 1 m away
    assert not keep[parts == 3].any()                          # one-miss fat at the arms' height
    # consensus: the k = 0 subset only
    cons = pose_subset(misses, centres, track, mode="consensus")
    assert np.array_equal(cons, misses == 0)
    assert pose_subset(misses, centres, track, mode="all") is None


def test_tolerant_needs_enough_views_and_a_track():
    centres, misses, _ = _scene()
    track = np.array([[1.0, 1.0, 0.9]])
    three = pose_subset(misses, centres, track, mode="tolerant", cameras=3, views=3)
    assert np.array_equal(three, misses == 0)                  # one miss of 3 cameras: 2 views, too few
    four = pose_subset(misses, centres, track, mode="tolerant", cameras=4, views=3)
    assert four.sum() > (misses == 0).sum()
    none = pose_subset(misses, centres, np.zeros((0, 3)), mode="tolerant", cameras=5)
    assert np.array_equal(none, misses == 0)
    assert pose_subset(None, centres, track, mode="tolerant") is None   # voxels without misses: all
    with pytest.raises(ValueError):
        pose_subset(misses, centres, track, mode="k1")
