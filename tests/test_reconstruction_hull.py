"""Issue 8: how tight the hull is and whether people come out whole, against the
simulator's true body volume: k = 0, k = 1, learnt occluders (Guan et al. 2006), the
silhouette-edge (footprint) test and the tight hull (both, occluders kept low)."""
import numpy as np
import pytest

from app.evaluation.reconstruction import score_frame, summarise_scores
from app.reconstruction import Reconstructor
from app.segmentation import CameraSegmenter, SegmentationParams
from app.simulation.occupancy import true_occupancy
from app.simulation.simulator import Simulator

VOXEL = 0.04
STRIDE = 2          # every other frame of 8 s: people cover more of the room
SCORED = 25         # the last frames are scored, the occluders learn over all


@pytest.fixture(scope="module")
def clip():
    """meeting3, 5 cameras at 320x240 (masks at 160x120, the 4 cm matched size of a
    640x480 camera), MOG2 masks and the true voxels (with their person) per frame."""
    sim = Simulator("meeting3", seed=0, seconds=8, width=320, height=240, zenithal=True)
    segs = {c: CameraSegmenter(SegmentationParams(scale=2), sim.background(c)) for c in sim.cameras}
    frames = []
    for i in range(0, sim.frame_count(), STRIDE):
        images, _, _ = sim.render(i)
        frames.append((i, {c: segs[c].apply(images[c]) for c in sim.cameras}, sim.body_record(i)))
    return sim, frames


def _run(sim, frames, **options):
    size = frames[0][1]["cam0"].shape[::-1]
    rec = Reconstructor(sim.calibration, VOXEL, mask_sizes={c: size for c in sim.cameras}, colouring="none",
                        min_top=0.25, **options)
    scores = []
    for n, (i, masks, body) in enumerate(frames):
        idx = rec.carve(masks)
        if n >= len(frames) - SCORED:
            truth, who = true_occupancy(body, rec.grid.origin, VOXEL, rec.grid.dims, with_person=True)
            scores.append(score_frame(i, idx, truth, rec.grid.dims, VOXEL, truth_person=who))
    return rec, summarise_scores(scores)


@pytest.fixture(scope="module")
def hulls(clip):
    sim, frames = clip
    return {name: _run(sim, frames, **opts)[1] for name, opts in
            (("k0", {"tolerance": 0}), ("k1", {"tolerance": 1}), ("occ", {"tolerance": 0, "occlusion": "learnt"}),
             ("edge", {"tolerance": 0, "footprint": 0.34}), ("tight", TIGHT))}


#: the tight hull of issue 8: k = 0, footprint test, learnt occluders below 1 m
TIGHT = {"tolerance": 0, "footprint": 0.34, "occlusion": "learnt", "occlusion_top": 1.0}


def test_hull_volume_recall_and_pieces(hulls):
    k0, k1, occ = hulls["k0"], hulls["k1"], hulls["occ"]
    print({k: {m: v[m] for m in ("recall", "volume_ratio", "largest_share_min")} for k, v in hulls.items()})
    # k = 1 keeps the body at the price of a hull several times its volume (issue 8)
    assert k1["recall"] > 0.93 and k1["volume_ratio"] > 2.5 * 1.2
    # k = 0 is tight but loses what the furniture hides from one camera
    assert k0["volume_ratio"] < 0.6 * k1["volume_ratio"] and k0["recall"] < k1["recall"] - 0.05
    # learnt occluders give back a good part of it without k = 1's excess
    assert occ["recall"] > k0["recall"] + 0.03
    assert occ["volume_ratio"] < k1["volume_ratio"]
    for h in hulls.values():   # nobody in pieces in the scored frames (share of the largest nearby component)
        assert h["largest_share_min"] > 0.6


def test_tight_hull_beats_k1_volume_and_occluders(hulls):
    """The footprint test gives back body that k = 0 loses at the silhouettes' edges;
    with occluders learnt below 1 m (the tight hull) the hull keeps more of the body
    than the occluders alone, at less volume, and stays well under k = 1's volume
    (measured here: k = 0 0.83 / 1.9x, edge 0.86 / 2.1x, occluders 0.935 / 4.2x,
    tight 0.949 / 3.9x, k = 1 0.974 / 6.5x)."""
    k0, k1, occ, edge, tight = (hulls[n] for n in ("k0", "k1", "occ", "edge", "tight"))
    assert edge["recall"] > k0["recall"] + 0.015 and edge["volume_ratio"] < 1.3 * k0["volume_ratio"]
    assert tight["recall"] > occ["recall"] + 0.005 and tight["volume_ratio"] < occ["volume_ratio"]
    assert tight["recall"] > 0.93 and tight["volume_ratio"] < 0.7 * k1["volume_ratio"]
    assert tight["largest_share_min"] >= 0.9 and tight["frames_in_pieces"] == 0.0


def test_occluder_masks_are_learnt_where_furniture_hides(clip):
    """The cameras learn occluders on a small part of the image only (the table and
    chairs), and the coarse-to-fine carving with them (and the footprint test, and
    the occluders' height limit) keeps exactly the voxels of the per-voxel test."""
    sim, frames = clip
    size = frames[0][1]["cam0"].shape[::-1]
    kw = dict(mask_sizes={c: size for c in sim.cameras}, colouring="none", **TIGHT)
    hier = Reconstructor(sim.calibration, VOXEL, method="hierarchical", **kw)
    flat = Reconstructor(sim.calibration, VOXEL, method="flat", **kw)
    for i, masks, _ in frames:
        a, b = hier.carve(masks), flat.carve(masks)
        assert np.array_equal(a, b), i
    share = hier.occluder_share()
    assert 0.0 < max(share.values()) < 0.2, share
    assert np.array_equal(hier.occluders.occluded, flat.occluders.occluded)


def test_fragmentation_measure():
    """The largest component near a person: whole body 1.0, a body cut in two halves 0.5."""
    dims = (40, 40, 60)
    body = np.array([(x, y, z) for x in range(10, 14) for y in range(10, 14) for z in range(0, 44)])
    other = body + [20, 20, 0]
    truth = np.concatenate([body, other])
    who = np.repeat([1, 2], len(body))
    whole = score_frame(0, truth, truth, dims, 0.04, truth_person=who)
    assert whole.largest_share == 1.0 and whole.volume_ratio == 1.0 and whole.recall == 1.0
    cut = truth[~((truth[:, 2] == 20) & (truth[:, 0] < 20))]     # person 1 cut at the waist
    s = score_frame(0, cut, truth, dims, 0.04, truth_person=who)
    assert s.largest_share == pytest.approx(23 / 43)
    fat = np.concatenate([truth, truth + [4, 0, 0]])               # twice the volume
    assert score_frame(0, fat, truth, dims, 0.04, truth_person=who).volume_ratio == pytest.approx(2.0)


def test_accept_map_and_ghost_filter():
    """The footprint test's accept map against a brute-force count of the 3x3 box
    (pixels past the border count as background), and the ghost filter drops only the
    components smaller than its bound, keeping the order of the voxels."""
    from app.reconstruction.footprint import GhostFilter, accept_map

    rng = np.random.default_rng(1)
    mask = (rng.random((23, 31)) < 0.3).astype(np.uint8)
    padded = np.pad(mask, 1)
    counts = sum(padded[dv: dv + 23, du: du + 31] for dv in range(3) for du in range(3))
    for fraction in (0.01, 0.34, 0.5, 1.0):
        need = int(np.ceil(fraction * 9 - 1e-9))
        expected = (mask == 1) | (counts >= need)
        assert np.array_equal(accept_map(mask, fraction).astype(bool), expected), fraction
    big = np.array([(x, y, z) for x in range(3) for y in range(3) for z in range(3)])   # 27 voxels
    small = np.array([(10, 10, 10), (10, 10, 11)])                                        # 2 voxels
    idx = np.concatenate([big, small, big + [20, 0, 0]]).astype(np.uint16)
    kept = GhostFilter((40, 20, 20), 5)(idx)
    assert np.array_equal(kept, np.concatenate([big, big + [20, 0, 0]]).astype(np.uint16))
    assert len(GhostFilter((40, 20, 20), 1)(idx)) == len(idx)
