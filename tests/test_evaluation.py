"""Reconstruction scores on hand-made voxel sets."""
import numpy as np

from app.evaluation.reconstruction import score_frame, summarise_scores


def _box(x0, x1, y0, y1, z0, z1):
    g = np.mgrid[x0:x1, y0:y1, z0:z1].reshape(3, -1).T
    return g


def test_recall_precision_spurious_and_floor_blob():
    dims = (100, 100, 60)
    truth = _box(40, 50, 40, 50, 0, 40)                     # a 20 x 20 x 80 cm body at 2 cm
    hull = _box(39, 51, 39, 51, 0, 42)                      # the visual hull: a little larger
    shadow = _box(60, 66, 40, 46, 0, 1)                     # 36 voxels on the floor, 20 cm away
    skirt = _box(51, 58, 40, 50, 0, 1)                      # hull excess on the floor, joined to the body
    speck = np.array([[10, 10, 30]])                        # noise in the air: a (tiny) ghost
    rec = np.concatenate([hull, shadow, speck, skirt])
    s = score_frame(0, rec, truth, dims, 0.02)
    assert s.recall == 1.0
    assert abs(s.precision - truth.shape[0] / len(np.unique(rec, axis=0))) < 1e-9
    assert s.spurious == 36 + 1 + 3 * 10 and s.floor_blob == 36  # the skirt beyond 10 cm is spurious, not detached
    assert s.ghost == 1
    s2 = score_frame(1, truth[::2], truth, dims, 0.02)
    assert abs(s2.recall - 0.5) < 1e-9 and s2.precision == 1.0 and s2.floor_blob == 0
    summary = summarise_scores([s, s2])
    assert summary["frames_with_floor_blob_over_20"] == 0.5 and not summary["shadow_target_met"]
    assert abs(summary["recall"] - 0.75) < 1e-9
