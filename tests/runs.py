"""What the fault tests share (test_faults, test_restarts, test_stage_state): the spine's
layout, the run's stats, waits, worker pids, CPU hogs."""
import json
import subprocess
import sys
import time
from pathlib import Path

import yaml

from app.results import iter_voxels

STAGES = ("grabber", "segmentation", "reconstruction")


def write_layout(path, extra_workers=(), restarts=None, recorder_voxels=True, **params):
    """The spine (grabber, segmentation, reconstruction at 8 cm, recorder keeping voxels)."""
    workers = [{"name": "grabber", "kind": "grabber"},
               {"name": "segmentation", "kind": "segmentation", "params": params.get("segmentation", {})},
               {"name": "reconstruction", "kind": "reconstruction",
                "params": {"voxel_size": 0.08, **params.get("reconstruction", {})}},
               {"name": "recorder", "kind": "recorder", "params": {"voxels": recorder_voxels}},
               *extra_workers]
    doc = {"room": "faults", "bus": {"listen": ["tcp/127.0.0.1:0"]}, "workers": workers}
    if restarts:
        doc["restarts"] = restarts
    Path(path).write_text(yaml.safe_dump(doc))
    return path


def stats_of(out):
    try:
        return json.loads((Path(out) / "stats.json").read_text())
    except (OSError, ValueError):
        return None


def wait_for(cond, timeout=30.0, period=0.05):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = cond()
        if v:
            return v
        time.sleep(period)
    return None


def worker_pid(out, name, not_pid=None):
    s = stats_of(out)
    w = (s or {}).get("workers", {}).get(name)
    if w and w.get("pid") and w.get("pid") != not_pid and w.get("frames_in", 0) > 0:
        return w["pid"]
    return None


def any_pid(out, name):
    w = ((stats_of(out) or {}).get("workers") or {}).get(name)
    return w.get("pid") if w else None


def assert_counts_add_up(s, expected):
    for name in STAGES:
        st = s["stages"][name]
        assert st["frames_in"] + st["frames_missing"] == expected, (name, st)
        assert st["frames_out"] + st["frames_dropped"] == st["frames_in"], (name, st)


def voxel_frames(path):
    return [(m.frame, tuple(m.cameras)) for m in iter_voxels(path)]


def hog(n=2):
    code = "import time\nt=time.time()\nwhile time.time()-t<120: pass"
    return [subprocess.Popen([sys.executable, "-c", code]) for _ in range(n)]


def running(pid) -> bool:
    """Alive and not a zombie (an orphan that exited waits for init to reap it)."""
    try:
        state = Path(f"/proc/{pid}/status").read_text().split("State:")[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"
