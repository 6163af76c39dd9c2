"""The pose stage over a real loopback zenoh session: a test source publishes a
simulated clip's voxels and true tracks (two people of meeting3), the pose worker
publishes poses, the recorder writes poses.jsonl; every person is posed every frame,
each against their own ground truth."""
import numpy as np
import pytest

from app.messages import JOINTS
from app.pose.offline import simulated_clip
from tests.pose_source import run_clip

FRAMES = range(0, 24)


def _write_clip(path, clip, cal, voxel_size):
    origin = np.asarray(cal.room_min, float)
    dims = np.ceil((np.asarray(cal.room_max) - origin) / voxel_size - 1e-9).astype(np.int64)
    idx = [np.floor((fr.centres - origin) / voxel_size).astype(np.int16) for fr in clip]
    np.savez(path, voxel_size=voxel_size, origin=origin, dims=dims, frames=np.array([fr.frame for fr in clip]),
             offsets=np.cumsum([0] + [len(i) for i in idx]), indices=np.concatenate(idx),
             track_offsets=np.cumsum([0] + [len(fr.ids) for fr in clip]),
             ids=np.concatenate([np.array(fr.ids) + 10 for fr in clip]),      # track ids are not person ids
             positions=np.concatenate([fr.positions for fr in clip]))


@pytest.mark.integration
def test_pose_worker_poses_every_tracked_person(tiny_recording, tmp_path):
    clip, cal = simulated_clip("meeting3", FRAMES, 0.03, zenithal=False)
    assert all(len(fr.ids) >= 2 for fr in clip)
    _write_clip(tmp_path / "clip.npz", clip, cal, 0.03)
    records = run_clip(tmp_path / "clip.npz", tmp_path, tiny_recording,
                       [{"name": "pose", "params": {"method": "shbm", "density": 1.5}}])
    assert len(records) >= len(FRAMES) // 2         # a stage that falls behind poses the newest frame
    by_frame = {fr.frame: fr for fr in clip}
    errors = []
    for rec in records:
        fr = by_frame[rec["frame"]]
        assert {p["track"] for p in rec["poses"]} == {i + 10 for i in fr.ids}   # everyone, every frame
        for p in rec["poses"]:
            est = np.array([p["joints"][n] for n in JOINTS])
            truth = fr.truth[p["track"] - 10]
            errors.append(np.linalg.norm(est - truth, axis=1))
    E = np.array(errors)[2 * len(clip[0].ids):]      # after the first frames (lock-on)
    mmta = float((E <= 0.1).mean())
    print(f"pose worker, meeting3 2 people at 3 cm: MMTA {mmta:.3f}, MPJPE {1e3 * E.mean():.0f} mm")
    assert mmta >= 0.8
