"""A recording of a room that is never empty (the still2 scene: no background/
images, one person standing still for seconds): the background is estimated with the
people left out, and both people are reconstructed against their true body volume."""
import numpy as np
import pytest

from app.recording import Recording
from app.reconstruction import Reconstructor
from app.segmentation import CameraSegmenter, SegmentationParams, estimate_background_robust
from app.simulation.occupancy import load_bodies, true_occupancy
from app.simulation.simulator import Simulator, render_recording

FPS = 10


@pytest.fixture(scope="module")
def still(tmp_path_factory):
    return render_recording("still2", tmp_path_factory.mktemp("still") / "still2", fps=FPS, width=320, height=240)


def test_still_person_is_reconstructed_without_an_empty_room_image(still):
    rec = Recording(still)
    assert all(rec.background(cam) is None for cam in rec.cameras)   # the room is never empty
    sim = Simulator("still2", fps=FPS, width=320, height=240)
    backgrounds = {}
    for cam in rec.cameras:
        bg, uncertain = estimate_background_robust(rec.sample(cam, 25))
        assert uncertain < 0.1, (cam, uncertain)
        # what people left in it: pixels far from the true empty room
        wrong = np.mean(np.abs(bg.astype(int) - sim.background(cam, noise=False).astype(int)).max(axis=2) > 30)
        assert wrong < 0.02, (cam, wrong)
        backgrounds[cam] = bg
    segs = {c: CameraSegmenter(SegmentationParams(scale=2), backgrounds[c]) for c in rec.cameras}
    recon = Reconstructor(rec.calibration, 0.04, mask_sizes={c: (160, 120) for c in rec.cameras}, colouring="none",
                          min_top=0.25)
    bodies = load_bodies(still)
    still_recall, other_recall = [], []
    for i, images in rec.frames():
        idx = recon.carve({c: segs[c].apply(images[c]) for c in rec.cameras})
        if i % 5:
            continue
        truth, who = true_occupancy(bodies[i], recon.grid.origin, 0.04, recon.grid.dims, with_person=True)
        got = recon.grid.dense(idx)[truth[:, 0], truth[:, 1], truth[:, 2]]
        for pid in np.unique(who):
            r = got[who == pid].mean()
            (still_recall if pid == 1 else other_recall).append((i, r))
    # person 1 stands still for the first 4 s, then walks; person 2 walks all along
    during = [r for i, r in still_recall if i < 4 * FPS]
    assert len(during) >= 6 and min(during) > 0.85, still_recall
    assert np.mean([r for _, r in still_recall]) > 0.9, still_recall
    assert np.mean([r for _, r in other_recall]) > 0.9, other_recall
