"""A pose estimator saved mid-clip (app.pose.snapshot) and restored carries on exactly
as if it had never stopped: what a restarted pose worker relies on."""

import numpy as np
import pytest

from app.pose.estimator import PoseEstimator, PoseSettings
from app.pose.offline import simulated_clip
from app.pose.snapshot import SnapshotError, estimator_state, restore_estimator
from tests.conftest import through_npz


@pytest.fixture(scope="module")
def clip():
    frames, cal = simulated_clip("gesture1", range(0, 16), 0.04)
    return frames, cal


def _settings(cal, **kw):
    return PoseSettings(voxel_size=0.04, density=1, room_lo=tuple(cal.room_min), room_hi=tuple(cal.room_max), **kw)


def _step(est, fr):
    return est.update(fr.centres, fr.surface, fr.ids, fr.positions)


@pytest.mark.parametrize("method", ["shbm", "apf", "shbm+ddm", "behaviour"])
def test_a_restored_estimator_carries_on_bit_for_bit(clip, method):
    frames, cal = clip
    kw = dict(particles=100, layers=3) if method == "apf" else {}
    if method == "behaviour":   # cut after the behaviour tracker took over (frame 5)
        kw = dict(behaviour_start=5, behaviour_particles=100)
    whole = PoseEstimator(_settings(cal, method=method, **kw))
    first = PoseEstimator(_settings(cal, method=method, **kw))
    cut = {"shbm+ddm": 11, "behaviour": 8}.get(method, 6)     # DDM: after its lock-on (lock_frames 10)
    for fr in frames[:cut]:
        _step(whole, fr), _step(first, fr)
    arrays = through_npz(estimator_state(first))
    del first
    again = restore_estimator(_settings(cal, method=method, **kw), arrays)
    assert set(again.people) == set(whole.people) and again.people
    if method == "behaviour":
        assert all(p.tracker is not None for p in again.people.values())
    for fr in frames[cut:]:
        a, b = _step(whole, fr), _step(again, fr)
        assert a.keys() == b.keys() and a
        for tid in a:
            assert np.array_equal(a[tid][0], b[tid][0]), (fr.frame, tid)
            assert np.array_equal(a[tid][1], b[tid][1])


def test_a_snapshot_that_does_not_fit_is_refused(clip):
    frames, cal = clip
    est = PoseEstimator(_settings(cal))
    for fr in frames[:3]:
        _step(est, fr)
    arrays = through_npz(estimator_state(est))
    with pytest.raises(SnapshotError, match="other pose settings"):
        restore_estimator(_settings(cal, gamma=40), arrays)
    tid = next(iter(est.people))
    broken = dict(arrays)
    broken[f"p{tid}.set0"] = broken[f"p{tid}.set0"][:, :5]
    with pytest.raises(SnapshotError, match="particle set"):
        restore_estimator(_settings(cal), broken)
    nan = dict(arrays)
    nan[f"p{tid}.state"] = np.full_like(arrays[f"p{tid}.state"], np.nan)
    with pytest.raises(SnapshotError, match="finite"):
        restore_estimator(_settings(cal), nan)
    for meta in (np.array("{"), np.array('{"format": "other"}'), np.array(b"\x00\x01")):
        with pytest.raises(SnapshotError):
            restore_estimator(_settings(cal), {**arrays, "meta": meta})
    with pytest.raises(SnapshotError):
        restore_estimator(_settings(cal), {k: v for k, v in arrays.items() if k != "meta"})


def test_a_restored_estimator_carries_on_the_limb_proportions_fit(clip):
    """Cut while the proportions are being weighed (frames 5-12): the restored estimator
    ends the fit as the undisturbed one does and poses the same from then on."""
    frames, cal = clip
    kw = dict(proportions="fit", proportion_frames=8)
    whole = PoseEstimator(_settings(cal, **kw))
    first = PoseEstimator(_settings(cal, **kw))
    for fr in frames[:8]:
        _step(whole, fr), _step(first, fr)
    assert all(0 < p.fit.seen < p.fit.frames for p in first.people.values())
    again = restore_estimator(_settings(cal, **kw), through_npz(estimator_state(first)))
    for fr in frames[8:]:
        a, b = _step(whole, fr), _step(again, fr)
        assert a.keys() == b.keys() and a
        for tid in a:
            assert np.array_equal(a[tid][0], b[tid][0]), (fr.frame, tid)
    for tid, p in whole.people.items():
        assert p.fit.done and again.people[tid].proportions == p.proportions
