"""Background segmentation against known silhouettes."""
import numpy as np
import pytest

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


@pytest.mark.parametrize("background", [True, False])
def test_a_frame_taken_without_learning_leaves_the_model_as_it_was(tmp_path, background):
    """``apply(..., learn=False)`` (a frame sent again after a restart, which the model
    took already) gives a mask and changes nothing: the masks after it are those of a
    model that never saw it, to the pixel (bootstrap without a background image too;
    the dark-shadow and exposure steps on)."""
    rec = Recording(write_tiny_recording(tmp_path / "r", frames=40, background=background))
    images = [im["cam0"] for _, im in rec.frames(["cam0"])]
    params = SegmentationParams(scale=2, exposure=50)
    a, b = (CameraSegmenter(params, rec.background("cam0")) for _ in range(2))
    for i, image in enumerate(images):
        if i in (12, 30):
            extra = b.apply(images[i - 3], learn=False)
            assert not background or _iou(extra, _box_mask(i - 3, 40, 160, 120, 2)[:extra.shape[0], :extra.shape[1]]) > 0.5
        assert np.array_equal(a.apply(image), b.apply(image)), i


# -- the masks against the simulator's true silhouettes (issue 8) -------------------------

def test_fill_holes_fills_small_enclosed_holes_only():
    from app.segmentation import fill_holes

    m = np.zeros((40, 60), np.uint8)
    m[5:35, 5:30] = 1
    m[10:13, 10:13] = 0          # a stripe of clothing: 9 pixels, enclosed
    m[15:30, 10:25] = 0          # the gap between an arm and the body: 225 pixels, enclosed
    m[20:35, 40:60] = 1
    m[25:28, 55:60] = 0          # open to the image's border
    out = fill_holes(m.copy(), 50)
    assert out[10:13, 10:13].all()
    assert not out[15:30, 10:25].any() and not out[25:28, 55:60].any()
    assert out.sum() == m.sum() + 9


@pytest.fixture(scope="module")
def meeting_clip(tmp_path_factory):
    """0.8 s of the simulated meeting3 (people, furniture, soft floor and contact
    shadows) at 640x480 and 10 fps, and its true silhouettes at half size (the mask
    scale matched to 2 cm voxels)."""
    from app.benchmarks.segmentation import truth_frames
    from app.simulation.simulator import render_recording

    path = render_recording("meeting3", tmp_path_factory.mktemp("masks") / "meeting3", seconds=0.8, fps=10)
    return path, truth_frames(path, 8, (2,))[2]


def test_masks_against_true_silhouettes(meeting_clip):
    """Pixel recall and precision of the masks against the true silhouettes, every
    camera: the default (dark floor shadows, filled holes) keeps as much of the people
    as MOG2 alone and leaves fewer of their shadows."""
    from app.benchmarks.segmentation import MASK_VARIANTS, score_masks

    path, truth = meeting_clip
    scores = {name: score_masks(path, truth, 2, params, warmup=2) for name, params in MASK_VARIANTS}
    before, now = scores["before"], scores["default"]
    assert now["recall"] >= 0.95 and now["camera_recall_min"] >= 0.93, now
    assert now["precision"] >= 0.8, now
    # measured: recall 0.970 -> 0.971, precision 0.821 -> 0.841, shadows 9.9 -> 6.8 % of the person
    assert now["recall"] >= before["recall"] - 0.005, (before, now)
    assert now["precision"] >= before["precision"] + 0.01, (before, now)
    assert now["false_shadow"] < 0.85 * before["false_shadow"], (before, now)


@pytest.mark.parametrize("segmentation, size, scale", [
    ([{"scale": 4}], (640, 480), 4),                                   # the colour follows the mask
    ([{"scale": 4, "colour_scale": 2}], (640, 480), 2),
    ([{"scale": 4, "colour_scale": 0}], (640, 480), 4),                # no colour sent
    ([{"scale": 4, "cameras": ["c0"]}, {"scale": 2, "cameras": ["c1"]}], (640, 480), 2),
    ([{"scale": 4}], (642, 480), 2),                                   # every camera's size divides too
    ([{"scale": 3}], (640, 480), 1),
    ([], (640, 480), 1),                                               # nobody reduces: full size
])
def test_frames_travel_as_small_as_every_segmentation_worker_allows(segmentation, size, scale):
    from types import SimpleNamespace

    from app.config import parse_layout
    from workers.segmentation import frame_scale

    layout = parse_layout({"room": "r", "workers": [
        {"name": "grabber", "kind": "grabber"},
        *({"name": f"seg{i}", "kind": "segmentation", "params": p} for i, p in enumerate(segmentation))]})
    cameras = [SimpleNamespace(name=c, width=size[0], height=size[1]) for c in ("c0", "c1")]
    assert frame_scale(layout, SimpleNamespace(cameras=cameras)) == scale


def test_a_flickering_light_is_not_foreground():
    """Mains flicker and auto exposure scale the whole frame (issue 22): with a flicker
    of up to 11 % (five times the built-in scenes'), MOG2 alone calls the bright floor
    foreground on the frames brighter than the empty-room image (false foreground 0.65
    of the people's pixels here; 0.22 with ``exposure``); matching each frame's brightness to
    the background first (``exposure``: over its running mean) leaves the people and
    drops that floor."""
    import cv2

    from app.segmentation import exposure_gain
    from app.simulation.simulator import Simulator

    sim = Simulator("meeting3", seed=0, seconds=2)
    sim.flicker = 5.0
    cams = sim.cameras[:2]
    empty = {c: sim.background(c) for c in cams}
    segs = {(c, e): CameraSegmenter(SegmentationParams(scale=4, exposure=e), empty[c])
            for c in cams for e in (0, 50)}
    found = {e: [0, 0, 0] for e in (0, 50)}   # person pixels in the mask, false foreground, person pixels
    gains = []
    for i in range(30):
        images, labels, _ = sim.render(i)
        for c in cams:
            gains.append(exposure_gain(images[c], empty[c]) / sim.gain(i, sim.cameras.index(c)))
            for e in (0, 50):
                m = segs[(c, e)].apply(images[c])
                t = cv2.resize((labels[c] >= 0).astype(np.uint8), m.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
                found[e][0] += int((m & t).sum())
                found[e][1] += int((m & ~t).sum())
                found[e][2] += int(t.sum())
    assert np.abs(np.asarray(gains) - 1.0).max() < 0.01          # the gain is the flicker's, people or not
    recall = {e: found[e][0] / found[e][2] for e in found}
    false = {e: found[e][1] / found[e][2] for e in found}
    assert false[50] < 0.5 * false[0], false
    assert recall[50] > recall[0] - 0.01, recall
