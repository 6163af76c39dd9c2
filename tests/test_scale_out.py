"""Scale-out (issue 26): the pose stage spread over workers by person (``share: [k, n]``)
and threads (``threads``), and the reconstruction over workers by frame (``share: [k,
n]``), give the results of one worker each, byte for byte, through real worker processes
on a real zenoh bus, on a recording of three people; a reconstruction worker killed in
the middle loses nothing."""
import json
import os
from pathlib import Path

import pytest
import yaml

from app.results import iter_voxels
from tests.conftest import ROOT, simulated, smartroom

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def meeting(tmp_path_factory):
    return simulated(tmp_path_factory, "meeting3", 2.0)


def _layout(tmp_path: Path, name: str, pose_workers: list[dict], reconstruction: list[dict] | None = None) -> Path:
    layout = yaml.safe_load((ROOT / "deploy/layouts/local.yaml").read_text())
    workers = [w for w in layout["workers"] if w["kind"] not in ("pose", "viewer")]
    at = [w["kind"] for w in workers].index("recorder")
    base = next(w for w in layout["workers"] if w["kind"] == "pose")["params"]
    workers[at:at] = [{"name": w["name"], "kind": "pose", "params": {**base, **w["params"]}} for w in pose_workers]
    if reconstruction:
        at = [w["kind"] for w in workers].index("reconstruction")
        base = workers[at]["params"]
        workers[at:at + 1] = [{"name": w["name"], "kind": "reconstruction", "params": {**base, **w["params"]}}
                              for w in reconstruction]
        workers[0]["params"] = {"window": 4}   # frames in flight: both reconstruction workers busy
    layout["workers"] = workers
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(layout))
    return path


def test_sharded_and_threaded_layouts_give_the_single_worker_s_results(meeting, tmp_path):
    one_pose = [{"name": "pose", "params": {}}]
    runs = {
        "single": (one_pose, None, {}),
        "pose_shares": ([{"name": "pose_a", "params": {"share": [0, 2]}},
                         {"name": "pose_b", "params": {"share": [1, 2]}}], None, {}),
        "threads": ([{"name": "pose", "params": {"threads": 3}}], None, {}),
        # two reconstruction workers taking the frames in turn; rec_b is killed (SIGKILL)
        # after it has reconstructed frame 21, its output of that frame lost on the way
        "frame_shares": (one_pose, [{"name": "rec_a", "params": {"share": [0, 2]}},
                                    {"name": "rec_b", "params": {"share": [1, 2]}}],
                         {"SMARTROOM_LOSE_OUTPUT": "rec_b:21"}),
    }
    files, stats = {}, {}
    for name, (pose, rec, env) in runs.items():
        out = tmp_path / name
        r = smartroom("run", "--recording", meeting, "--layout", _layout(tmp_path, name, pose, rec), "--headless",
                      "--no-pace", "--set", "recorder.voxels=true", "--out", out, timeout=300,
                      env=dict(os.environ, **env))
        assert r.returncode == 0, r.stderr[-2000:]
        stats[name] = json.loads((out / "stats.json").read_text())
        assert stats[name]["complete"] is True
        files[name] = {f: (out / f).read_bytes() for f in ("tracks.jsonl", "poses.jsonl")}
        files[name]["voxels"] = [(m.frame, m.indices.tobytes()) for m in iter_voxels(out / "voxels.bin")]
    records = [json.loads(line) for line in files["single"]["poses.jsonl"].decode().splitlines()]
    assert len(records) == 50
    assert max(len(rec["poses"]) for rec in records) >= 2            # more than one person to share
    for name in runs:
        assert files[name] == files["single"], name
    # the frames were shared, and the killed worker was restarted and caught up
    s = stats["frame_shares"]
    assert s["restarts"]["rec_b"]["count"] == 1
    assert [s["stages"][w]["frames_out"] for w in ("rec_a", "rec_b")] == [25, 25]
    assert all(st["frames_missing"] == 0 for st in s["stages"].values())
    assert [f for f, _ in files["frame_shares"]["voxels"]] == list(range(50))   # in order, each once
