"""Background segmentation against known silhouettes."""
import numpy as np

from app.recording import Recording
from app.segmentation import CameraSegmenter, SegmentationParams, estimate_background
from tests.synthetic import write_tiny_recording


def _box_mask(i, frames, width, height, scale):
    m = np.zeros((height, width), bool)
    x = int((i / max(1, frames - 1)) * (width - width // 4))
    m[height // 3:height - 9, x:x + width // 6 + 1] = True
    return m[::scale, ::scale]


def _iou(a, b):
    return (a & b).sum() / max(1, (a | b).sum())


def _mean_iou(rec, background, scale=1, frames=60):
    ious = []
    for cam in rec.cameras:
        seg = CameraSegmenter(SegmentationParams(scale=scale), background(cam))
        for i, images in rec.frames([cam]):
            mask = seg.apply(images[cam])
            if i >= 5:
                truth = _box_mask(i, frames, 160, 120, scale)
                ious.append(_iou(mask, truth[:mask.shape[0], :mask.shape[1]]))
    return float(np.mean(ious))


def test_masks_match_the_moving_box_with_a_background_image(tmp_path):
    rec = Recording(write_tiny_recording(tmp_path / "r", frames=60))
    assert _mean_iou(rec, rec.background) > 0.9
    assert _mean_iou(rec, rec.background, scale=2) > 0.8


def test_median_background_when_the_recording_has_none(tmp_path):
    rec = Recording(write_tiny_recording(tmp_path / "r", frames=60, background=False))
    assert rec.background("cam0") is None
    est = estimate_background(rec.sample("cam0", 25))
    truth = Recording(write_tiny_recording(tmp_path / "t", frames=2)).background("cam0")
    assert np.mean(np.abs(est.astype(int) - truth.astype(int)) > 20) < 0.02  # the moving box is gone
    assert _mean_iou(rec, lambda cam: estimate_background(rec.sample(cam, 25))) > 0.85
