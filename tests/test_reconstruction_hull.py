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
             ("edge", {"tolerance": 0, "footprint": 0.34}), ("tight", TIGHT), ("cells", CELLS),
             ("cells_g", {**CELLS, "ghost_share": 0.2}))}


#: the tight hull of issue 8: k = 0, footprint test, learnt occluders below 1 m
TIGHT = {"tolerance": 0, "footprint": 0.34, "occlusion": "learnt", "occlusion_top": 1.0}
#: occlusion learnt per 8 cm cell and camera (app/reconstruction/occlusion_cells.py)
CELLS = {"tolerance": 0, "footprint": 0.34, "occlusion": "cells", "occlusion_top": 1.0}


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


def test_cell_occlusion_hull(hulls):
    """Occlusion learnt per voxel cell and camera gives back much of what k = 0 with the
    edge test loses at far less volume than k = 1, nobody in pieces."""
    k1, edge, cells = hulls["k1"], hulls["edge"], hulls["cells"]
    assert cells["recall"] > edge["recall"] + 0.03
    assert cells["volume_ratio"] < 0.7 * k1["volume_ratio"]
    assert cells["largest_share_min"] >= 0.9 and cells["frames_in_pieces"] == 0.0
    # dropping the components no camera needs (ghosts) removes volume, not body
    g, tight = hulls["cells_g"], hulls["tight"]
    assert g["volume_ratio"] < cells["volume_ratio"] and g["recall"] >= cells["recall"] - 0.002
    # and it keeps as much of the body as the per-pixel tight hull at less volume
    # (measured here: tight 0.949 / 3.88x, cells 0.953 / 3.64x, cells + ghost filter 0.953 / 3.28x)
    assert g["recall"] >= tight["recall"] - 0.002 and g["volume_ratio"] < 0.9 * tight["volume_ratio"]


def test_cell_occlusion_selection_is_exact(clip):
    """The cells variant keeps exactly: every voxel of the k = 0 carving (same
    footprint test), plus voxels of the k = 1 carving whose one dissenting camera is
    learnt occluded at the voxel's cell, in components attached to the k = 0 voxels; nothing before any learning (frame 0 is the
    k = 0 hull); its misses are the per-voxel count of :mod:`.consensus`; the
    hierarchical and flat carvings agree and learn the same model."""
    from app.components import label_voxels
    from app.reconstruction.consensus import count_misses

    sim, frames = clip
    size = frames[0][1]["cam0"].shape[::-1]
    kw = dict(mask_sizes={c: size for c in sim.cameras}, colouring="none", footprint=0.34)
    cells = Reconstructor(sim.calibration, VOXEL, misses=True, **kw, **{k: v for k, v in CELLS.items()
                                                                         if k != "footprint"})
    flat = Reconstructor(sim.calibration, VOXEL, method="flat", **kw, **{k: v for k, v in CELLS.items()
                                                                          if k != "footprint"})
    k0 = Reconstructor(sim.calibration, VOXEL, tolerance=0, **kw)
    k1 = Reconstructor(sim.calibration, VOXEL, tolerance=1, misses=True, **kw)
    occ = cells.cell_occluders
    cell = occ.cell
    grew = 0
    for n, (i, masks, _) in enumerate(frames[:30]):
        before = occ.occluded.copy()
        got, _, _, _ = cells.reconstruct(masks)
        assert np.array_equal(got, flat.carve(masks)), i
        ref0 = k0.carve(masks)
        ref1, _, _, _ = k1.reconstruct(masks)
        m1 = k1.misses
        dissent = np.zeros(len(ref1), dtype=np.int64)
        pix = k1.table.pixels(ref1)
        for c, name in enumerate(k1.names):
            from app.reconstruction.footprint import accept_map
            acc = accept_map(masks[name].view(np.uint8), 0.34).reshape(-1)
            bg = (pix[:, c] >= 0) & (acc[np.maximum(pix[:, c], 0)] == 0)
            dissent[bg] = c
        cidx = ref1.astype(np.int64) // cell
        cd = occ.cell_dims
        key = ((cidx[:, 0] * cd[1] + cidx[:, 1]) * cd[2] + cidx[:, 2]) * len(k1.names) + dissent
        low = ref1[:, 2] < cells._k_top
        fg = (pix >= 0).sum(axis=1) - m1
        extra = (m1 == 1) & low & (fg >= occ.support) & (before[key] == 1)
        expected, em = ref1[(m1 == 0) | extra], m1[(m1 == 0) | extra]
        labels, count = label_voxels(expected, k1.grid.dims)       # added voxels only where attached
        expected = expected[np.isin(labels, labels[em == 0])]
        assert np.array_equal(got, expected), i
        assert np.isin(ref0.view("u2,u2,u2"), got.view("u2,u2,u2")).all()
        if n == 0:
            assert np.array_equal(got, ref0)
        assert np.array_equal(cells.misses, count_misses(got, cells.layout, cells.table.lut, cells._votes))
        grew += int(extra.sum())
    assert grew > 0 and occ.occluded.any()
    assert np.array_equal(occ.occluded, flat.cell_occluders.occluded)


def test_exclusive_pixels_match_brute_force(clip):
    """Per component and camera, the foreground pixels its voxel centres project to and
    those no other component projects to (app/reconstruction/ghosts.py), against sets
    built from the projection table, on a k = 0 hull of the clip."""
    from app.components import label_voxels
    from app.reconstruction.carving import FG_VOTE
    from app.reconstruction.ghosts import exclusive_pixels

    sim, frames = clip
    size = frames[0][1]["cam0"].shape[::-1]
    r = Reconstructor(sim.calibration, VOXEL, mask_sizes={c: size for c in sim.cameras}, colouring="none",
                      tolerance=0, footprint=0.34)
    i, masks, _ = frames[-1]
    idx = r.carve(masks)
    labels, count = label_voxels(idx, r.grid.dims)
    assert count >= 3
    n_cams = len(r.names)
    total = np.zeros((count, n_cams), dtype=np.int64)
    excl = np.zeros_like(total)
    owner = np.full(r.table.mask_total + 1, -1, dtype=np.int32)
    stamp = owner.copy()
    exclusive_pixels(idx, labels, np.int64(count), np.int64(r.layout.levels), r.layout.brick_dims_arr, r.table.lut,
                     r._votes, owner, stamp, total, excl)
    assert (owner == -1).all() and (stamp == -1).all()
    pix = r.table.pixels(idx)
    for c in range(n_cams):
        q = pix[:, c] + int(r.table.mask_offset[c])
        fg = (pix[:, c] >= 0) & (r._votes[np.maximum(q, 0)] == FG_VOTE)
        sets = [set(q[fg & (labels == lab)].tolist()) for lab in range(count)]
        for lab in range(count):
            others = set().union(*(sets[o] for o in range(count) if o != lab))
            assert total[lab, c] == len(sets[lab]) and excl[lab, c] == len(sets[lab] - others), (c, lab)


def test_one_miss_bound_is_the_best_selection_and_far_below_the_learnt_ones(clip, hulls):
    """The per-frame oracle of ``smartroom bench reconstruction --hull-bounds``: it keeps
    exactly the k = 0 voxels plus the body among the voxels one camera misses, in
    components that hold body; so its recall is k = 1's (same edge test) and its volume
    at most k = 0's plus that body. On the MOG2 masks of this clip it is far tighter
    than the best learnt selection (cells + ghost filter) at more recall: the margin
    issue 8's target would need a rule to find (measured here: bound 0.980 / 1.90x
    against cells + ghost filter 0.953 / 3.28x)."""
    from app.benchmarks.reconstruction import one_miss_bound

    sim, frames = clip
    size = frames[0][1]["cam0"].shape[::-1]
    r = Reconstructor(sim.calibration, VOXEL, mask_sizes={c: size for c in sim.cameras}, colouring="none",
                      min_top=0.25, tolerance=1, footprint=0.34)
    total = {}
    for n, (i, masks, body) in enumerate(frames):
        carved = r.carve(masks)
        if n < len(frames) - SCORED:
            continue
        truth = true_occupancy(body, r.grid.origin, VOXEL, r.grid.dims)
        counts = one_miss_bound(r, carved, truth)
        misses = r.misses_of(carved)
        # by hand: the agreed voxels, the one-miss body, and the k = 1 hull's own counts
        dims = np.asarray(r.grid.dims, dtype=np.int64)
        flat_c = (carved[:, 0].astype(np.int64) * dims[1] + carved[:, 1]) * dims[2] + carved[:, 2]
        flat_t = (truth[:, 0] * dims[1] + truth[:, 1]) * dims[2] + truth[:, 2]
        is_body = np.isin(flat_c, flat_t)
        assert counts["k1"] == len(carved) and counts["k1_body"] == is_body.sum()
        assert counts["k0"] == (misses == 0).sum() and counts["k0_body"] == ((misses == 0) & is_body).sum()
        assert counts["bound_body"] == counts["k1_body"] - ((misses > 1) & is_body).sum()
        assert counts["bound"] <= counts["k0"] + ((misses == 1) & is_body).sum()
        assert set(misses.tolist()) <= {0, 1}     # a k = 1 hull: no voxel missed by two cameras
        total = {k: total.get(k, 0) + v for k, v in counts.items()}
    body = total["true"]
    bound_recall, bound_volume = total["bound_body"] / body, total["bound"] / body
    assert bound_recall == total["k1_body"] / body
    g = hulls["cells_g"]
    print(f"bound {bound_recall:.3f} / {bound_volume:.2f}x, cells+g {g['recall']:.3f} / {g['volume_ratio']:.2f}x")
    assert bound_recall > g["recall"] + 0.01 and bound_volume < 0.75 * g["volume_ratio"]
