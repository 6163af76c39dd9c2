"""Segmentation and reconstruction on the simulated room, against its ground truth:
true silhouettes, true body volume and clothing colours."""
import cv2
import numpy as np
import pytest

from app.evaluation.reconstruction import score_frame
from app.reconstruction import Reconstructor
from app.segmentation import CameraSegmenter, SegmentationParams, working_size
from app.simulation.occupancy import true_occupancy
from app.simulation.simulator import Simulator

FRAMES = range(0, 40, 4)   # the models learn from every frame; the checks use these


@pytest.fixture(scope="module")
def meeting():
    """meeting3 through the segmentation core at half size: frames, masks, labels."""
    sim = Simulator("meeting3", seed=0, seconds=4)
    segs = {c: CameraSegmenter(SegmentationParams(scale=2), sim.background(c)) for c in sim.cameras}
    out = []
    for i in range(max(FRAMES) + 1):
        images, labels, _ = sim.render(i)
        masks = {c: segs[c].apply(images[c]) for c in sim.cameras}
        if i in FRAMES:
            out.append((i, images, labels, masks, {c: segs[c].small for c in sim.cameras}))
    return sim, out


def _truth_mask(labels, size):
    return cv2.resize((labels >= 0).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)


def test_masks_match_the_true_silhouettes(meeting):
    sim, frames = meeting
    for cam in sim.cameras:
        ious, missed = [], []
        for _, images, labels, masks, _ in frames:
            m = masks[cam]
            t = _truth_mask(labels[cam], m.shape[::-1])
            ious.append((m & t).sum() / max(1, (m | t).sum()))
            missed.append((t & ~m).sum() / max(1, t.sum()))
        # half-size masks: people's outlines and contact shadows at their feet cost IoU
        assert np.mean(ious) > 0.7, (cam, np.mean(ious))
        assert np.mean(missed) < 0.08, (cam, np.mean(missed))


def _reconstructor(sim, frames, **kw):
    masks0, small0 = frames[0][3], frames[0][4]
    return Reconstructor(sim.calibration, 0.04, mask_sizes={c: m.shape[::-1] for c, m in masks0.items()},
                         colour_sizes={c: im.shape[1::-1] for c, im in small0.items()}, **kw)


def test_voxels_cover_the_true_bodies_without_floor_shadows(meeting):
    sim, frames = meeting
    rec = _reconstructor(sim, frames, colouring="none", min_top=0.25)
    for i, _, _, masks, _ in frames:
        idx = rec.carve(masks)
        truth = true_occupancy(sim.body_record(i), rec.grid.origin, 0.04, rec.grid.dims)
        s = score_frame(i, idx, truth, rec.grid.dims, 0.04)
        assert s.recall > 0.9, s
        assert s.floor_blob <= 20, s


def test_a_dropped_camera_still_yields_the_bodies(meeting):
    sim, frames = meeting
    rec = _reconstructor(sim, frames, colouring="none", min_top=0.25)
    i, _, _, masks, _ = frames[-1]
    truth = true_occupancy(sim.body_record(i), rec.grid.origin, 0.04, rec.grid.dims)
    full = score_frame(i, rec.carve(masks), truth, rec.grid.dims, 0.04)
    dropped = dict(masks, cam2=None)
    less = score_frame(i, rec.carve(dropped), truth, rec.grid.dims, 0.04)
    assert less.recall > 0.9 and less.voxels >= full.voxels * 0.8


def _chroma(c):
    c = np.asarray(c, dtype=float).reshape(-1, 3) + 1.0
    return c / c.sum(axis=1, keepdims=True)


def test_visibility_colouring_gives_the_shirt_its_colour():
    """walk1: the chest's surface voxels take the shirt's colour as the cameras see it
    (chromaticity, since shading changes brightness per view). That visibility keeps
    the colour seen through the body out is shown with a two-coloured body in
    test_reconstruction.py, where the simulator's one-coloured shirts cannot."""
    sim = Simulator("walk1", seed=0, seconds=2)
    i = 30
    images, labels, gt = sim.render(i, noise=False)
    person = gt["people"][0]
    j = person["joints"]
    lo = max(j["l_hip"][2], j["r_hip"][2]) + 0.12
    hi = min(j["l_shoulder"][2], j["r_shoulder"][2]) - 0.08
    size = working_size(640, 480, 2)
    masks = {c: cv2.resize((labels[c] >= 0).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
             for c in sim.cameras}
    small = {c: cv2.resize(images[c], size, interpolation=cv2.INTER_AREA) for c in sim.cameras}
    # the shirt as the cameras see it: pixels of the person between chest heights
    seen = []
    for cam in sim.calibration.cameras:
        band = np.array([[x, y, z] for z in np.linspace(lo, hi, 5)
                         for x, y in np.asarray(person["centroid"][:2]) + 0.02 * np.random.default_rng(0).normal(size=(20, 2))])
        uv = np.round(cam.project(band)).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
        uv = uv[ok]
        own = labels[cam.name][uv[:, 1], uv[:, 0]] == person["id"]
        seen.append(images[cam.name][uv[own, 1], uv[own, 0], ::-1])
    shirt = np.median(_chroma(np.concatenate(seen)), axis=0)
    rec = Reconstructor(sim.calibration, 0.03, mask_sizes={c: size for c in sim.cameras},
                        colour_sizes={c: size for c in sim.cameras}, colouring="visibility", tolerance=0)
    idx, colours, surface, _ = rec.reconstruct(masks, small)
    centres = rec.grid.centres(idx)
    chest = surface & (centres[:, 2] > lo) & (centres[:, 2] < hi)
    chest &= np.linalg.norm(centres[:, :2] - np.asarray(person["centroid"][:2]), axis=1) < 0.25
    assert chest.sum() > 50
    error = np.linalg.norm(_chroma(colours[chest]) - shirt, axis=1)
    assert np.median(error) < 0.03, np.median(error)
