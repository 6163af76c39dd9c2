"""Several pose workers sharing a frame's tracks (issue 11: more people than one worker
carries is a layout matter): the result writers join their poses, one line a frame with
every person, and lose nothing when one worker is behind."""
import numpy as np
import pytest

from app.messages import JOINTS, Poses
from app.pose.offline import simulated_clip
from app.pose_shares import SharedPoses
from tests.pose_source import run_clip
from tests.test_pose_worker import _write_clip


def _poses(frame, worker, tracks):
    n = len(tracks)
    return Poses(frame=frame, stamp=float(frame), t=frame / 25, worker=worker,
                 tracks=np.array(tracks, np.int64), joints=np.full((n, len(JOINTS), 3), float(frame)),
                 active=np.ones((n, len(JOINTS)), bool))


def test_a_frame_goes_out_once_every_worker_has_sent_it_or_moved_past_it():
    shares = SharedPoses(["pose_a", "pose_b"])
    assert shares.add(_poses(0, "pose_a", [2])) == []
    out = shares.add(_poses(0, "pose_b", [1, 3]))
    assert [m.frame for m in out] == [0] and out[0].tracks.tolist() == [1, 2, 3]
    assert out[0].joints.shape == (3, len(JOINTS), 3)
    assert shares.add(_poses(1, "pose_a", [2])) == []
    assert shares.add(_poses(2, "pose_a", [2])) == []
    out = shares.add(_poses(2, "pose_b", [1]))          # pose_b gave frame 1 up
    assert [(m.frame, m.tracks.tolist()) for m in out] == [(1, [2]), (2, [1, 2])]
    assert shares.add(_poses(3, "pose_a", [])) == []
    assert [m.frame for m in shares.flush()] == [3]     # the end of the stream completes the rest
    assert shares.partial == 0


def test_one_pose_worker_passes_straight_through_and_a_silent_one_does_not_hold_everything():
    one = SharedPoses(["pose"])
    msg = _poses(5, "pose", [1])
    assert one.add(msg) == [msg]
    shares = SharedPoses(["pose_a", "pose_b"], max_pending=3)
    out = []
    for f in range(6):
        out += shares.add(_poses(f, "pose_a", [1]))
    assert [m.frame for m in out] == [0, 1, 2] and shares.partial == 3


@pytest.mark.integration
def test_two_pose_workers_share_the_tracks_and_the_recorder_writes_everyone(tiny_recording, tmp_path):
    frames = range(0, 16)
    clip, cal = simulated_clip("meeting3", frames, 0.03, zenithal=False)
    assert all(len(fr.ids) >= 2 for fr in clip)
    _write_clip(tmp_path / "clip.npz", clip, cal, 0.03)
    pose = {"method": "shbm", "density": 2.0}
    records = run_clip(tmp_path / "clip.npz", tmp_path, tiny_recording,
                       [{"name": "pose_a", "params": {**pose, "share": [0, 2]}},
                        {"name": "pose_b", "params": {**pose, "share": [1, 2]}}])
    assert len(records) == len({rec["frame"] for rec in records}) >= len(frames) // 2
    by_frame = {fr.frame: fr for fr in clip}
    errors = []
    for rec in records:
        fr = by_frame[rec["frame"]]
        assert sorted(p["track"] for p in rec["poses"]) == sorted(i + 10 for i in fr.ids)   # both workers' people
        for p in rec["poses"]:
            est = np.array([p["joints"][n] for n in JOINTS])
            errors.append(np.linalg.norm(est - fr.truth[p["track"] - 10], axis=1).mean())
    assert np.median(errors) < 0.12                      # each joined pose is its own person's
