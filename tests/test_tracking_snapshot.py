"""A multi-tracker saved mid-scene (app.tracking.snapshot) and restored carries on exactly
as if it had never stopped: what a restarted tracking worker relies on."""
import json

import numpy as np
import pytest

from app.tracking.blobs import ComponentAnalysis
from app.tracking.classifier import load_tree
from app.tracking.scene import OccupancyIndex, SceneFrame
from app.tracking.snapshot import SnapshotError, restore_tracker, tracker_state
from app.tracking.tracker import MultiTracker, TrackerParams
from tests.conftest import through_npz
from tests.test_tracking import DIMS, VS, crossing

PARAMS = {"ss_colour": {}, "ss_raw": {}, "pf_colour": {"particles": 60}, "naive": {}}


def _as_scenes(frames, tree) -> list:
    """Voxel frames of tests/test_tracking.py as the tracker's scenes (CCA and person test)."""
    cca = ComponentAnalysis(DIMS, (0, 0, 0), VS, tree)
    out = []
    for v in frames:
        labels, feats, person = cca(v.indices)
        out.append(SceneFrame(v.frame, v.t, v.indices, v.colours, v.surface, labels, feats, person, (0, 0, 0), VS,
                              OccupancyIndex(DIMS)))   # a scene's column index lives in its OccupancyIndex
    return out


@pytest.fixture(scope="module")
def scenes():
    """The crossing of tests/test_tracking.py (two people merge into one blob), as scenes."""
    frames, _ = crossing(n=60)
    tree = load_tree()
    return _as_scenes(frames, tree), tree


@pytest.mark.parametrize("filt", sorted(PARAMS))
def test_a_restored_tracker_carries_on_bit_for_bit(scenes, filt):
    frames, tree = scenes
    params = TrackerParams(filter=filt, **PARAMS[filt])
    whole, first = MultiTracker(params, tree), MultiTracker(params, tree)
    cut = 30                     # tracks confirmed, the two people about to merge
    for sc in frames[:cut]:
        whole.update(sc), first.update(sc)
    assert len(first.tracks) == 2
    arrays = through_npz(tracker_state(first, DIMS))
    size = sum(a.nbytes for a in arrays.values())
    assert size < 40_000, size   # sparse histograms: a few kB per track
    del first
    again = restore_tracker(TrackerParams(filter=filt, **PARAMS[filt]), tree, arrays, DIMS)
    if filt != "naive":          # every attribute of a target is restored (none forgotten)
        for a, b in zip(whole.tracks, again.tracks):
            assert set(vars(a.target) if hasattr(a.target, "__dict__") else ()) == set(vars(b.target))
    for sc in frames[cut:]:
        ids_a, pos_a = whole.update(sc)
        ids_b, pos_b = again.update(sc)
        assert np.array_equal(ids_a, ids_b) and np.array_equal(pos_a, pos_b), sc.frame
    assert whole.next_id == again.next_id


def test_a_snapshot_that_does_not_fit_is_refused(scenes):
    frames, tree = scenes
    t = MultiTracker(TrackerParams(), tree)
    for sc in frames[:12]:
        t.update(sc)
    good = through_npz(tracker_state(t, DIMS))
    restore_tracker(TrackerParams(), tree, good, DIMS)   # fits

    def bad(**change):
        a = dict(good)
        a.update(change)
        return a

    meta = json.loads(str(good["meta"][()]))
    cases = {
        "other filter": (TrackerParams(filter="pf_colour"), good, DIMS),
        "other parameters": (TrackerParams(samples=300), good, DIMS),
        "other grid": (TrackerParams(), good, (10, 10, 10)),
        "no meta": (TrackerParams(), {k: v for k, v in good.items() if k != "meta"}, DIMS),
        "garbage meta": (TrackerParams(), bad(meta=np.array("{not json")), DIMS),
        "other format": (TrackerParams(), bad(meta=np.array(json.dumps(meta | {"format": "x/1"}))), DIMS),
        "samples outside the grid": (TrackerParams(), bad(**{"t0.samples": good["t0.samples"] + 1000}), DIMS),
        "NaN position": (TrackerParams(), bad(**{"t0.x": np.full(3, np.nan)}), DIMS),
        "weights of another length": (TrackerParams(), bad(**{"t0.weights": good["t0.weights"][:-1]}), DIMS),
        "histogram bin out of range": (TrackerParams(), bad(**{"t0.ref_bins": good["t0.ref_bins"] + 10 ** 6}), DIMS),
        "pickled object": (TrackerParams(), bad(**{"t0.x": np.array([object()] * 3, dtype=object)}), DIMS),
        "bad random state": (TrackerParams(), bad(meta=np.array(json.dumps(meta | {"rng": {"state": 1}}))), DIMS),
        "missing track": (TrackerParams(), bad(meta=np.array(json.dumps(meta | {"tracks": meta["tracks"] * 2}))),
                          DIMS),
    }
    for name, (params, arrays, dims) in cases.items():
        with pytest.raises(SnapshotError):
            restore_tracker(params, tree, arrays, dims)
            pytest.fail(name)


def test_after_a_gap_a_restored_tracker_finds_its_people_where_they_went():
    """Live, a restarted worker misses about a second: two people 1.8 m apart walked 1.2 m
    meanwhile. Restored from the snapshot, the tracker first looks for every person within
    the distance walked (relocate): both keep their ids; without it both got new ones."""
    frames, truth = crossing(n=60, gap=1.2)
    tree = load_tree()
    cca = ComponentAnalysis(DIMS, (0, 0, 0), VS, tree)

    def scene(v):
        labels, feats, person = cca(v.indices)
        return SceneFrame(v.frame, v.t, v.indices, v.colours, v.surface, labels, feats, person, (0, 0, 0), VS,
                          OccupancyIndex(DIMS))

    before = MultiTracker(TrackerParams(), tree)
    for v in frames[:11]:
        before.update(scene(v))
    arrays = through_npz(tracker_state(before, DIMS))
    assert sorted(t.id for t in before.tracks) == [1, 2]
    for relocate in (False, True):
        t = restore_tracker(TrackerParams(), tree, arrays, DIMS)
        first = scene(frames[34])
        if relocate:
            t.relocate(first, t.p.refine_radius + 1.5 * (frames[34].t - frames[10].t))
        t.update(first)
        for v in frames[35:46]:
            ids, pos = t.update(scene(v))
        true_ids, true_pos = truth[45]
        who = {int(i): int(true_ids[np.argmin(((true_pos[:, :2] - p[:2]) ** 2).sum(1))]) for i, p in zip(ids, pos)}
        if relocate:
            assert who == {1: 1, 2: 2}
        else:
            assert set(who) == {3, 4}    # what a wider search saves


def test_places_left_behind_and_where_tracks_stay_are_restored():
    """Saved after the person left the place they stood at (and while their track settles
    somewhere else), the restored tracker still refuses the ghost they left behind and
    carries on bit for bit; a snapshot of an earlier build (no such arrays) restores with
    no place left behind, one whose places have no frame count restores them at 0."""
    from tests.test_tracking import _stands_then_leaves

    frames, _ = _stands_then_leaves()
    tree = load_tree()
    scenes = _as_scenes(frames, tree)
    whole, first = MultiTracker(TrackerParams(), tree), MultiTracker(TrackerParams(), tree)
    cut = 105
    for sc in scenes[:cut]:
        whole.update(sc), first.update(sc)
    assert len(first.vacated) == 1
    arrays = through_npz(tracker_state(first, DIMS))
    again = restore_tracker(TrackerParams(), tree, arrays, DIMS)
    assert np.array_equal(again.vacated[0], first.vacated[0])
    assert [(t.settled, t.away) for t in again.tracks] == [(t.settled, t.away) for t in first.tracks]
    for sc in scenes[cut:]:
        ids_a, pos_a = whole.update(sc)
        ids_b, pos_b = again.update(sc)
        assert np.array_equal(ids_a, ids_b) and np.array_equal(pos_a, pos_b), sc.frame
        assert len(ids_b) <= 1, sc.frame   # the ghost never a track
    older = {k: v for k, v in arrays.items() if k != "vacated" and not k.endswith(".anchor")}
    assert not restore_tracker(TrackerParams(), tree, older, DIMS).vacated
    # the build before kept a place as (x, y) alone: it restores with no frames counted yet
    two = {**arrays, "vacated": arrays["vacated"][:, :2]}
    assert np.array_equal(restore_tracker(TrackerParams(), tree, two, DIMS).vacated[0],
                          np.r_[first.vacated[0][:2], 0.0])
