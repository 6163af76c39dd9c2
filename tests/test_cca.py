"""Connected components and their features (Table 4.1), and the Blobs message."""
import numpy as np
import pytest

from app.messages import Blobs, MessageError, Voxels, decode
from app.tracking.blobs import FEATURES, ComponentAnalysis, component_features
from tests.payloads import older_payload


def _box(i0, j0, k0, ni, nj, nk):
    ii, jj, kk = np.meshgrid(np.arange(i0, i0 + ni), np.arange(j0, j0 + nj), np.arange(k0, k0 + nk), indexing="ij")
    return np.stack([ii, jj, kk], -1).reshape(-1, 3)


def test_features_of_two_boxes():
    """A 10x5x40 box at 2 cm and a diagonal neighbour pair: exact Table 4.1 figures."""
    s = 0.02
    a = _box(10, 20, 0, 10, 5, 40)
    b = np.array([[50, 50, 5], [51, 51, 6]])              # 26-connected only
    idx = np.concatenate([a, b]).astype(np.uint16)
    labels, feats, person = ComponentAnalysis((100, 100, 100), (0.0, 0.0, 0.0), s)(idx)
    assert feats.shape == (2, len(FEATURES)) and person.tolist() == [1, 1]
    f = dict(zip(FEATURES, feats[0]))
    assert f["voxels"] == 2000
    assert f["weight"] == pytest.approx(2000 * s ** 3 * 1100.0, rel=1e-5)   # |C| s^3 rho, kg
    assert f["top"] == pytest.approx(39.5 * s, abs=1e-6)
    assert f["height"] == pytest.approx(39 * s, abs=1e-6)
    assert f["z_centroid"] == pytest.approx(20 * s, abs=1e-6)
    assert f["extent_major"] == pytest.approx(10 * s) and f["extent_minor"] == pytest.approx(5 * s)
    assert f["x"] == pytest.approx(15 * s) and f["y"] == pytest.approx(22.5 * s)
    assert feats[1, FEATURES.index("voxels")] == 2
    assert set(labels[:2000]) == {0} and set(labels[2000:]) == {1}
    # 6-connectivity splits the diagonal pair
    _, f6, _ = ComponentAnalysis((100, 100, 100), (0.0, 0.0, 0.0), s, connectivity=6)(idx)
    assert len(f6) == 3


def test_empty_frame():
    labels, feats, person = ComponentAnalysis((8, 8, 8), (0, 0, 0), 0.1)(np.zeros((0, 3), np.uint16))
    assert labels.shape == (0,) and feats.shape == (0, len(FEATURES)) and person.shape == (0,)


def _blobs():
    idx = _box(1, 1, 0, 3, 3, 6).astype(np.uint16)
    labels, feats, person = ComponentAnalysis((10, 10, 10), (0, 0, 0), 0.1)(idx)
    return Blobs(frame=3, t=0.12, voxel_size=0.1, origin=[0.0, 0.0, 0.0], dims=[10, 10, 10], cameras=["cam0"],
                 indices=idx, colours=np.zeros((len(idx), 3), np.uint8), surface=np.ones(len(idx), bool),
                 labels=labels, features=feats, person=person)


def test_blobs_round_trip_and_validate():
    msg = decode(_blobs().to_bytes())
    msg.validate()
    assert isinstance(msg, Blobs) and msg.frame == 3 and msg.features.shape == (1, len(FEATURES))
    assert np.allclose(msg.centres().mean(axis=0), [0.25, 0.25, 0.3])


def test_blobs_carry_the_voxels_silhouettes_and_older_blobs_decode_without():
    """The CCA worker passes the voxels' silhouettes on (the tracker's ghost test): they
    round-trip, a Blobs of the build before (six arrays) decodes with none, and sizes
    that do not match the bytes are refused."""
    masks = [np.eye(5, 12, dtype=bool)]
    msg = _blobs()
    msg.silhouette_sizes, msg.silhouettes = Voxels(cameras=["cam0"]).with_silhouettes(masks).silhouette_sizes, \
        Voxels(cameras=["cam0"]).with_silhouettes(masks).silhouettes
    back = decode(msg.to_bytes())
    back.validate()
    np.testing.assert_array_equal(back.silhouette_masks()[0], masks[0])
    old = decode(older_payload(_blobs(), "silhouette_sizes"))
    old.validate()
    assert old.silhouette_masks() == [] and np.array_equal(old.labels, msg.labels)
    msg.silhouette_sizes = [[12, 6]]
    with pytest.raises(MessageError, match="silhouettes hold"):
        decode(msg.to_bytes()).validate()


@pytest.mark.parametrize("field,value", [
    ("labels", np.full(54, 5, np.int32)),                     # label beyond the component count
    ("indices", np.full((54, 3), 20, np.uint16)),             # outside the grid
    ("features", np.zeros((1, 3), np.float32)),               # wrong feature count
    ("person", np.zeros(2, np.uint8)),                        # one verdict per component
])
def test_blobs_validate_rejects_inconsistent_messages(field, value):
    msg = _blobs()
    setattr(msg, field, value)
    with pytest.raises(MessageError):
        decode(msg.to_bytes()).validate()


def test_component_features_match_a_dense_reference():
    """Random blobs: features against scipy's dense labelling (26-connectivity)."""
    from scipy import ndimage

    rng = np.random.default_rng(1)
    grid = rng.random((30, 30, 20)) < 0.25
    dense, n = ndimage.label(grid, structure=np.ones((3, 3, 3)))
    idx = np.argwhere(grid)
    labels, feats, _ = ComponentAnalysis(grid.shape, (0, 0, 0), 0.05)(idx.astype(np.uint16))
    assert len(feats) == n
    ref = dense[idx[:, 0], idx[:, 1], idx[:, 2]]
    for c in range(n):
        mine = idx[labels == c]
        assert len(set(ref[labels == c])) == 1
        assert feats[c, FEATURES.index("top")] == pytest.approx((mine[:, 2].max() + 0.5) * 0.05, abs=1e-6)
    ref_feats = component_features(idx, labels, n, (0, 0, 0), 0.05)
    assert np.array_equal(ref_feats, feats)
