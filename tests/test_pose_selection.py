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


def test_a_pose_shard_finds_the_owners_of_its_people_s_voxels_alone():
    """A pose shard posing some of the frame's tracks (issue 26) looks only at the voxels
    and silhouette pixels within reach of its people, and finds for them the owners the
    full split of the frame among every track gives: same voxels per posed person, to the
    bit, on voxels at the edge of the reach too."""
    from app.messages import Voxels
    from app.pose.estimator import assign_voxels
    from app.pose.selection import within_reach

    rng = np.random.default_rng(3)
    vs, origin, dims = 0.02, [-0.5, -0.5, 0.0], [200, 200, 100]
    idx = rng.integers(0, 100, size=(20000, 3)).astype(np.uint16) * np.array([2, 2, 1], np.uint16)
    vox = Voxels(frame=0, stamp=0.0, t=0.0, voxel_size=vs, origin=origin, dims=dims, cameras=["a"], indices=idx)
    centres = vox.centres()
    tracks = rng.uniform(0.0, 3.5, size=(6, 3))
    tracks[4, :2] = tracks[3, :2] + 0.3            # two people close: their reaches overlap
    reach = 0.9
    tracks[5, 0] = centres[7, 0] + reach           # a voxel right at the edge of a reach
    tracks[5, 1] = centres[7, 1]
    full = assign_voxels(centres, tracks, reach)
    for wanted in ([0], [3], [3, 4], [5], [1, 2, 5], []):
        take = within_reach(vox, tracks, reach, wanted)
        mine = np.isin(full, wanted)
        assert not (mine & ~take).any()            # every voxel a posed person owns is looked at
        assert np.array_equal(vox.centres(take), centres[take])
        part = assign_voxels(centres[take], tracks, reach, wanted)
        for k in wanted:
            assert np.array_equal(centres[take][part == k], centres[full == k])
        if wanted:   # on every voxel: those out of every posed person's reach are nobody's
            alone = assign_voxels(centres, tracks, reach, wanted)
            dx, dy = centres[:, None, 0] - tracks[None, wanted, 0], centres[:, None, 1] - tracks[None, wanted, 1]
            far = np.sqrt(dx * dx + dy * dy).min(axis=1) > reach
            assert far.any() and (alone[far] == -1).all() and np.array_equal(alone[~far], full[~far])
