"""The exporter worker in a real run (separate processes over a loopback zenoh session):
its files equal the offline export of the run's poses.jsonl, its TRC/CSV grow as readable
prefixes, and a run killed mid-way leaves only .partial files.

Until the pose stage exists, a test-only source (``tests.replay_poses:ReplayPoses``)
publishes the simulator's ground-truth joints as the pose stage would.
"""
import json
import os
import signal
import time

import numpy as np
import pytest
import yaml

from app.messages import JOINTS
from tests.conftest import smartroom, start_smartroom
from tests.test_export import groundtruth_records, parse_trc

pytestmark = pytest.mark.integration
FPS = 25.0


@pytest.fixture(scope="session")
def gt_poses(tmp_path_factory):
    """meeting3, 4 s at 25 fps (3 people, one entering late), a forearm dropped for a while."""
    recs = groundtruth_records("meeting3", 4.0, FPS)
    for r in recs:
        for p in r["poses"]:
            if p["track"] == 2 and 30 <= r["frame"] < 45:
                p["active"]["l_wrist"] = False
    path = tmp_path_factory.mktemp("gt") / "poses.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in recs))
    return path, recs


def _layout(tmp_path, poses, rate):
    layout = {"room": "smartroom", "bus": {"listen": ["tcp/127.0.0.1:0"]},
              "workers": [{"name": "pose", "kind": "tests.replay_poses:ReplayPoses",
                           "params": {"file": str(poses), "rate": rate}},
                          {"name": "recorder", "kind": "recorder"},
                          {"name": "exporter", "kind": "exporter"}]}
    path = tmp_path / "layout.yaml"
    path.write_text(yaml.safe_dump(layout))
    return path


def test_live_export_equals_the_offline_export(tiny_recording, gt_poses, tmp_path):
    poses, recs = gt_poses
    out = tmp_path / "out"
    r = smartroom("run", "--recording", tiny_recording, "--layout", _layout(tmp_path, poses, 100.0),
                  "--headless", "--out", out, timeout=180)
    assert r.returncode == 0, r.stderr[-3000:]
    live = out / "export"
    names = sorted(p.name for p in live.iterdir())
    tracks = sorted({p["track"] for rec in recs for p in rec["poses"]})
    assert names == sorted([f"track{k}.bvh" for k in tracks] + [f"track{k}.trc" for k in tracks]
                           + ["poses.c3d", "poses.csv"]), names
    # every frame went through the bus to the recorder and the exporter
    written = [json.loads(ln) for ln in (out / "poses.jsonl").read_text().splitlines()]
    assert [w["frame"] for w in written] == [r["frame"] for r in recs]
    offline = tmp_path / "offline"
    r = smartroom("export", out, "--out", offline)
    assert r.returncode == 0, r.stderr
    for name in names:
        assert (live / name).read_bytes() == (offline / name).read_bytes(), name


def _children(pid):
    kids = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as fh:
                    if int(fh.read().rsplit(")", 1)[1].split()[1]) == pid:
                        kids.append(int(d))
            except (OSError, ValueError, IndexError):
                pass
    return kids


def test_a_killed_run_leaves_only_partial_files_and_readable_prefixes(tiny_recording, gt_poses, tmp_path):
    poses, recs = gt_poses
    out = tmp_path / "out"
    proc = start_smartroom("run", "--recording", tiny_recording, "--layout", _layout(tmp_path, poses, 10.0),
                           "--headless", "--out", out)
    folder = out / "export"
    prefix = folder / "track1.trc.partial"
    try:
        deadline = time.monotonic() + 90
        rows = 0
        while time.monotonic() < deadline and proc.poll() is None:
            if prefix.is_file():
                lines = prefix.read_text().split("\n")
                rows = len([ln for ln in lines[6:-1] if ln])   # complete lines only
                if rows >= 10:
                    break
            time.sleep(0.2)
        assert rows >= 10 and proc.poll() is None, "no growing TRC prefix while the run goes on"
        # SIGKILL the whole run: the launcher and every worker it started
        pids = [proc.pid] + _children(proc.pid)
        for pid in pids:
            os.kill(pid, signal.SIGKILL)
        proc.wait(10)
        for pid in pids[1:]:
            for _ in range(50):
                try:
                    with open(f"/proc/{pid}/stat") as fh:
                        if fh.read().split(")")[-1].split()[0] == "Z":
                            break
                except OSError:
                    break
                time.sleep(0.1)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        proc.stdout.close()
        proc.stderr.close()
    files = sorted(p.name for p in folder.iterdir())
    assert files and all(".partial" in name for name in files), files
    assert not (out / "poses.jsonl").exists()
    # what was written so far is a readable TRC: a header and whole rows of the true joints
    head, markers, frames, times, xyz = parse_trc(prefix)
    assert markers == list(JOINTS) and int(head["NumFrames"]) <= len(frames)
    truth = {r["frame"]: p for r in recs for p in r["poses"] if p["track"] == 1}
    world = xyz / 1000.0 @ np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
    for f, w in zip(frames, world):
        expect = np.array([truth[f]["joints"][j] for j in JOINTS])
        assert np.abs(w - expect).max() < 1e-3
    csv_lines = (folder / "poses.csv.partial").read_text().split("\n")
    assert csv_lines[0].startswith("frame,t,track,pelvis_x") and len(csv_lines) > 10


def _worker_pid(launcher_pid, name):
    for pid in _children(launcher_pid):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as fh:
                args = fh.read().split(b"\0")
        except OSError:
            continue
        if b"worker" in args and name.encode() in args:
            return pid
    return None


def test_a_restarted_exporter_carries_on_from_its_journal(tiny_recording, gt_poses, tmp_path):
    """kill -9 of the exporter alone: the launcher restarts it, it reads its journal back,
    and the run still ends with complete files holding the frames from before the crash.
    (This test source does not wait for acknowledgements, so frames sent while the exporter
    restarts are missing from its files; the grabber of a real pipeline waits for it.)"""
    poses, recs = gt_poses
    out = tmp_path / "out"
    proc = start_smartroom("run", "--recording", tiny_recording, "--layout", _layout(tmp_path, poses, 10.0),
                           "--headless", "--out", out)
    prefix = out / "export" / "track2.trc.partial"   # track 2 is there from frame 0
    try:
        deadline = time.monotonic() + 90
        before = None
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                _, _, frames, _, _ = parse_trc(prefix)
            except (OSError, AssertionError, ValueError, IndexError):   # not there yet, or a row half-written
                frames = []
            if len(frames) >= 15:
                pid = _worker_pid(proc.pid, "exporter")
                if pid:
                    os.kill(pid, signal.SIGKILL)
                    before = frames
                    break
            time.sleep(0.1)
        assert before is not None, "the exporter was not killed mid-run"
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == 0, err[-3000:]
    folder = out / "export"
    assert not [p for p in folder.iterdir() if ".partial" in p.name]
    head, markers, frames, _, xyz = parse_trc(folder / "track2.trc")
    assert set(before) <= set(frames)                     # what the first incarnation had, kept
    assert frames[-1] == recs[-1]["frame"]                # and the restarted one carried on to the end
    truth = {r["frame"]: p for r in recs for p in r["poses"] if p["track"] == 2}
    world = xyz / 1000.0 @ np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
    for f, w in zip(frames, world):
        ok = np.isfinite(w).all(axis=1)   # a dropped wrist, or frames sent while the exporter restarted
        if ok.any():
            assert np.abs(w[ok] - np.array([truth[f]["joints"][j] for j in JOINTS])[ok]).max() < 1e-3
    assert np.isfinite(world).all(axis=(1, 2)).sum() >= 0.7 * len(frames)
    stats = json.loads((out / "stats.json").read_text())
    assert stats["workers"]["exporter"]["restarts"] >= 1
