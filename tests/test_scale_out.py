"""Scale-out (issue 26): the pose stage spread over workers (``share: [k, n]``) and
threads (``threads``) gives the results one pose worker gives, byte for byte, through
real worker processes on a real zenoh bus, on a recording of three people."""
import json
from pathlib import Path

import pytest
import yaml

from tests.conftest import ROOT, simulated, smartroom

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def meeting(tmp_path_factory):
    return simulated(tmp_path_factory, "meeting3", 2.0)


def _layout(tmp_path: Path, name: str, pose_workers: list[dict]) -> Path:
    layout = yaml.safe_load((ROOT / "deploy/layouts/local.yaml").read_text())
    workers = [w for w in layout["workers"] if w["kind"] not in ("pose", "viewer")]
    at = [w["kind"] for w in workers].index("recorder")
    base = next(w for w in layout["workers"] if w["kind"] == "pose")["params"]
    workers[at:at] = [{"name": w["name"], "kind": "pose", "params": {**base, **w["params"]}} for w in pose_workers]
    layout["workers"] = workers
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(layout))
    return path


def test_sharded_and_threaded_pose_layouts_give_the_single_worker_s_results(meeting, tmp_path):
    layouts = {
        "single": [{"name": "pose", "params": {}}],
        "shards": [{"name": "pose_a", "params": {"share": [0, 2]}}, {"name": "pose_b", "params": {"share": [1, 2]}}],
        "threads": [{"name": "pose", "params": {"threads": 3}}],
    }
    files = {}
    for name, workers in layouts.items():
        out = tmp_path / name
        r = smartroom("run", "--recording", meeting, "--layout", _layout(tmp_path, name, workers), "--headless",
                      "--no-pace", "--out", out, timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]
        stats = json.loads((out / "stats.json").read_text())
        assert stats["complete"] is True
        files[name] = {f: (out / f).read_bytes() for f in ("tracks.jsonl", "poses.jsonl")}
    records = [json.loads(line) for line in files["single"]["poses.jsonl"].decode().splitlines()]
    assert len(records) == 50
    assert max(len(rec["poses"]) for rec in records) >= 2            # more than one person to share
    for name in ("shards", "threads"):
        assert files[name]["tracks.jsonl"] == files["single"]["tracks.jsonl"], name
        assert files[name]["poses.jsonl"] == files["single"]["poses.jsonl"], name
