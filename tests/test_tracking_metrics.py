"""CLEAR MOT and IDF1 of app.evaluation.tracking checked against the motmetrics package."""
import numpy as np
import pytest

from app.evaluation.tracking import score_tracking

mm = pytest.importorskip("motmetrics")


def _synthetic(seed=0, frames=120):
    """Three true people walking; a tracker with noise, misses, a false positive, an id swap."""
    rng = np.random.default_rng(seed)
    truth, results = {}, {}
    for f in range(frames):
        t = f / 25
        gpos = np.array([[1 + 0.02 * f, 1.0, 1.0], [3 - 0.02 * f, 1.2, 1.0], [2.5, 3 + 0.3 * np.sin(t), 0.9]])
        gid = np.array([1, 2, 3])
        if f > 100:
            gpos, gid = gpos[:2], gid[:2]       # person 3 leaves
        truth[f] = (gid, gpos)
        hpos = gpos + rng.normal(0, 0.08, gpos.shape)
        hid = np.array([10, 11, 12])[:len(gid)]
        if 85 <= f < 95:
            hid = hid[[2, 1, 0][:len(hid)]]      # two tracks swap (far apart)
        keep = rng.random(len(hid)) > 0.05       # misses
        hpos, hid = hpos[keep], hid[keep]
        if f % 17 == 0:                          # a false positive
            hpos = np.vstack([hpos, [[4.5, 3.5, 1.0]]])
            hid = np.append(hid, 99)
        if f % 31 == 5:                          # a far-off estimate (miss + false positive)
            hpos = hpos.copy()
            hpos[:1, 0] += 0.8
        if f in (70, 71):
            continue                             # no line for this frame: all misses
        results[f] = (hid, hpos)
    return truth, results


def _motmetrics(truth, results, gate=0.5):
    acc = mm.MOTAccumulator(auto_id=False)
    for f in sorted(truth):
        gid, gpos = truth[f]
        hid, hpos = results.get(f, (np.zeros(0, int), np.zeros((0, 3))))
        d = np.linalg.norm(gpos[:, None, :2] - hpos[None, :, :2], axis=2) if len(gid) and len(hid) else \
            np.zeros((len(gid), len(hid)))
        d = np.where(d <= gate, d, np.nan)
        acc.update(list(gid), list(hid), d, frameid=f)
    mh = mm.metrics.create()
    return mh.compute(acc, metrics=["mota", "motp", "num_misses", "num_false_positives", "num_switches", "idf1",
                                    "num_matches"], name="x")


@pytest.mark.parametrize("seed", [0, 1])
def test_clear_mot_and_idf1_agree_with_motmetrics(seed):
    truth, results = _synthetic(seed)
    s = score_tracking(truth, results)
    ref = _motmetrics(truth, results).iloc[0]
    assert s.misses == ref["num_misses"]
    assert s.false_positives == ref["num_false_positives"]
    assert s.mismatches == ref["num_switches"]
    assert s.matches - s.mismatches == ref["num_matches"]   # motmetrics counts switches apart
    assert s.mota == pytest.approx(ref["mota"], abs=1e-9)
    assert s.motp_mm == pytest.approx(1e3 * ref["motp"], rel=1e-9)
    assert s.idf1 == pytest.approx(ref["idf1"], abs=1e-9)
    assert s.mismatches >= 2 and s.misses > 6   # the swap and the empty frames were seen


def test_perfect_tracker_scores_one():
    truth, _ = _synthetic()
    s = score_tracking(truth, truth)
    assert s.mota == 1.0 and s.idf1 == 1.0 and s.motp_mm == 0.0
