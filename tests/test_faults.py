"""Bad input and a hostile or busy machine (issue 9): a fuzzed bus, damaged videos, a full
disk, bad layouts and output folders, live cameras that never open or stop, and results
that do not depend on machine load; real worker processes over a real zenoh hub. Each
test checks what is left: the result files, the counts in ``stats.json`` and the exit code."""
import json
import os
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from app.results import iter_voxels
from tests.conftest import simulated, smartroom, start_smartroom
from tests.runs import STAGES, write_layout, stats_of, wait_for, worker_pid, voxel_frames, hog
from tests.synthetic import write_tiny_recording

pytestmark = pytest.mark.integration


def _fuzz_payloads(rng, good: bytes):
    """Random, truncated, wrong-version, overflowing and out-of-window variants."""
    from app.messages import EndOfStream, Frame, Mask, Voxels, encode
    out = [rng.bytes(int(rng.integers(0, 200))), good[: int(rng.integers(0, len(good)))],
           good[:3] + bytes([9]) + good[4:]]
    huge = encode(Voxels(frame=1, voxel_size=0.08, dims=[60000, 60000, 60000], indices=np.zeros((0, 3), np.int16),
                         colours=np.zeros(0, np.uint8), surface=np.zeros(0, bool)))
    out.append(huge)
    m = np.zeros((15, 20), bool)
    out.append(encode(Mask.pack(m, frame=10 ** 9, camera="cam0", cameras=["cam0"])))      # far future
    out.append(encode(Mask.pack(m, frame=10 ** 6, camera="cam0", cameras=["cam0"], epoch=2 ** 40)))  # forged epoch
    out.append(encode(Frame(frame=5, camera="nobody", cameras=["nobody"], image=np.zeros((4, 4, 3), np.uint8))))
    out.append(encode(EndOfStream(frame=0, worker="grabber", frames=1, fps=25.0)))        # forged end of stream
    return out


def test_fuzzing_every_key_crashes_nothing_and_ends_nothing(long_recording, tmp_path):
    import zenoh

    from app.bus import BusConfig, Keys, open_session
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml")
    proc = start_smartroom("run", "--recording", long_recording, "--headless", "--layout", layout, "--out", out)
    sent = 0
    try:
        assert wait_for(lambda: worker_pid(out, "reconstruction"), timeout=60)
        # connected as the room's workers are (the hub drops what an outsider publishes in the
        # room, tests/test_bus_private.py): the fuzz reaches the workers' own checks
        inside = yaml.safe_load((out / "layout.yaml").read_text())["bus"]["connect"]
        session = open_session(BusConfig(listen=[], connect=inside), mode="client")
        keys = Keys("faults")
        targets = [keys.frame("cam0"), keys.frame("cam1"), keys.frame("junk1"), keys.mask("cam0"), keys.mask("cam1"),
                   keys.voxels(), keys.stage("blobs"), keys.tracks(), keys.poses(), keys.eos("grabber"),
                   keys.eos("segmentation"),
                   keys.stats("segmentation"), keys.ack("segmentation")]
        rng = np.random.default_rng(0)
        good = (out / "layout.yaml").read_bytes()
        pubs = {k: session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK) for k in targets}
        time.sleep(1.0)   # the hub routes this session's messages to every worker
        t_end = time.monotonic() + 4.0
        while time.monotonic() < t_end:
            for k in targets:
                for payload in _fuzz_payloads(rng, good):
                    pubs[k].put(payload)
                    sent += 1
            time.sleep(0.02)
        session.close()
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert sent > 2000
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    s = stats_of(out)
    assert s["complete"] is True
    for name in STAGES:
        assert s["stages"][name]["restarts"] == 0, name
    assert s["stages"]["reconstruction"]["frames_out"] == 250       # nothing ended early or was lost
    seg, rec = s["workers"]["segmentation"], s["workers"]["reconstruction"]
    per_key = sent // len(targets)
    # every message that reached a stage was counted, under its key and reason (a few may
    # have been pushed out of a full inbox instead, which counts them as dropped items)
    for w, key in ((seg, "frame/cam0"), (seg, "frame/junk1"), (rec, "mask/cam1")):
        counted = sum(n for k, n in w["rejected"].items() if k.startswith(key))
        assert counted + w["items_dropped"] >= per_key, (key, counted, w["items_dropped"], per_key)
    assert any("end of stream from a running worker" in k or "eos/grabber" in k for k in seg["rejected"])


def test_a_damaged_video_is_an_error_naming_file_and_frame(tmp_path):
    rec = write_tiny_recording(tmp_path / "rec", frames=125)
    video = rec / "videos" / "cam1.avi"
    with open(video, "r+b") as fh:
        fh.truncate(int(os.path.getsize(video) * 0.4))
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml")
    r = smartroom("run", "--recording", rec, "--headless", "--no-pace", "--layout", layout, "--out", out, timeout=120)
    assert r.returncode == 2, r.stderr
    line = [x for x in r.stderr.splitlines() if x.startswith("smartroom: error:")]
    assert len(line) == 1 and "videos/cam1.avi: frame" in line[0] and "cannot be decoded" in line[0]
    assert "Traceback" not in r.stderr
    s = stats_of(out)
    assert s["complete"] is False and "cannot be decoded" in s["reasons"][0]
    frames = [m.frame for m in iter_voxels(next(out.glob("voxels.bin*")))]
    assert frames == list(range(len(frames))) and len(frames) >= 40   # valid up to where it stopped

    # on request, the damaged stretch is skipped: those frames have one camera, fewer
    # than min_views, so they are dropped and counted, never published (the default layout:
    # the stages after reconstruction are not waited for on frames it gave up)
    out2 = tmp_path / "out2"
    r = smartroom("run", "--recording", rec, "--headless", "--no-pace", "--out", out2,
                  "--set", "grabber.skip_bad_frames=true", "--set", "recorder.voxels=true", timeout=180)
    assert r.returncode == 0, r.stderr
    s = stats_of(out2)
    lost = s["workers"]["grabber"]["views_lost"]["cam1"]
    assert lost >= 60
    rec_w = s["workers"]["reconstruction"]
    assert rec_w["frames_too_few_views"] == lost
    published = voxel_frames(out2 / "voxels.bin")
    assert len(published) == 125 - lost and all(cams == ("cam0", "cam1") for _, cams in published)


@pytest.fixture
def small_disk(tmp_path):
    """A 200 KB file system (tmpfs), or the test is skipped where none can be mounted."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("cannot mount a small tmpfs here")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_result_files_end_on_a_whole_record_when_the_disk_fills(small_disk):
    """tracks.jsonl / poses.jsonl lines, voxels.bin records and state files written until
    the disk is full: every file ends with its last complete record (a write the disk
    took only part of used to leave a cut-off line), and no empty .partial is left."""
    from app.files import write_json
    from app.messages import Voxels
    from app.results import VoxelWriter
    from workers.recorder import JsonLinesWriter

    rng = np.random.default_rng(1)
    lines = JsonLinesWriter(small_disk / "poses.jsonl")
    voxels = VoxelWriter(small_disk / "voxels.bin")
    written = {"lines": 0, "voxels": 0}
    with pytest.raises(OSError):
        for frame in range(100000):
            n = int(rng.integers(1, 400))   # records of every size, so one straddles the end of the disk
            if lines.write(frame, {"frame": frame, "t": frame / 25, "poses": [[0.123456] * 15] * n}):
                written["lines"] += 1
            idx = rng.integers(0, 100, (n, 3)).astype(np.uint16)
            voxels.write(Voxels(frame=frame, voxel_size=0.04, origin=[0, 0, 0], dims=[100, 100, 100], cameras=["c"],
                                indices=idx, colours=np.zeros((n, 3), np.uint8), surface=np.ones(n, bool)))
            written["voxels"] += 1
    kept = [json.loads(ln)["frame"] for ln in (small_disk / "poses.jsonl.partial").read_bytes().splitlines()]
    assert kept == list(range(written["lines"])) and kept
    assert (small_disk / "poses.jsonl.partial").read_bytes().endswith(b"\n")
    frames = [m.frame for m in iter_voxels(small_disk / "voxels.bin.partial")]
    assert frames == list(range(written["voxels"]))
    with pytest.raises(OSError):
        write_json(small_disk / "state.json", {"x": "y" * 1_000_000})
    assert not (small_disk / "state.json").exists() and not (small_disk / "state.json.partial").exists()


def test_a_full_disk_ends_the_run_with_valid_files_and_honest_stats(long_recording, tmp_path):
    mnt = tmp_path / "small"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("cannot mount a small tmpfs here")
    try:
        out = mnt / "out"
        layout = write_layout(tmp_path / "layout.yaml", reconstruction={"voxel_size": 0.04})
        r = smartroom("run", "--recording", long_recording, "--headless", "--no-pace", "--layout", layout,
                      "--out", out, timeout=120)
        assert r.returncode == 2, r.stderr
        assert "disk full" in r.stderr and "Traceback" not in r.stderr
        s = stats_of(out)
        assert s["complete"] is False and any("disk full" in x for x in s["reasons"])
        frames = [m.frame for m in iter_voxels(out / "voxels.bin.partial")]   # every record complete
        assert frames == list(range(len(frames))) and frames
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_results_do_not_depend_on_machine_load(tmp_path):
    """Two runs of one recording, one beside a CPU hog, give identical voxels (issue 8)."""
    rec = write_tiny_recording(tmp_path / "rec", frames=120, n_cameras=3)
    layout = write_layout(tmp_path / "layout.yaml")
    runs = []
    for name, loaded in (("idle", False), ("loaded", True)):
        hogs = hog() if loaded else []
        try:
            r = smartroom("run", "--recording", rec, "--headless", "--no-pace", "--layout", layout,
                          "--out", tmp_path / name, timeout=180)
        finally:
            for h in hogs:
                h.kill()
        assert r.returncode == 0, r.stderr
        runs.append([(m.frame, tuple(m.cameras), m.indices.tobytes(), m.colours.tobytes())
                     for m in iter_voxels(tmp_path / name / "voxels.bin")])
    assert len(runs[0]) == 120 and all(len(f[1]) == 3 for f in runs[0])
    assert runs[0] == runs[1]


def test_frame_zero_is_complete_when_a_camera_starts_slowly(long_recording, tmp_path):
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml")
    doc = yaml.safe_load(Path(layout).read_text())
    doc["workers"][1] = {"name": "seg0", "kind": "segmentation", "params": {"cameras": ["cam0"]}}
    doc["workers"].insert(2, {"name": "seg1", "kind": "tests.fault_stages:SlowStartSegmentation",
                              "params": {"cameras": ["cam1"], "first_delay_s": 2.0}})
    Path(layout).write_text(yaml.safe_dump(doc))
    r = smartroom("run", "--recording", long_recording, "--headless", "--layout", layout, "--frames", 40,
                  "--out", out, timeout=120)
    assert r.returncode == 0, r.stderr
    frames = voxel_frames(out / "voxels.bin")
    assert frames[0] == (0, ("cam0", "cam1"))
    assert len(frames) == 40 and all(cams == ("cam0", "cam1") for _, cams in frames)


BAD_LAYOUTS = {
    "run key": ({"run": {"recordingg": "x"}}, "run: unknown key 'recordingg'"),
    "kind not a worker": ({"workers+": [{"name": "w", "kind": "app.errors:InputError"}]}, "is not a worker"),
    "no source": ({"workers": [{"name": "r", "kind": "recorder"}]}, "no source"),
    "window": ({"grabber": {"window": 0}}, "parameter window = 0 is outside"),
    "history": ({"segmentation": {"history": -3}}, "parameter history = -3 is outside"),
    "scale": ({"segmentation": {"scale": 99}}, "parameter scale = 99 is outside"),
    "close_px": ({"segmentation": {"close_px": 500}}, "parameter close_px = 500 is outside"),
    "wait_ms": ({"reconstruction": {"wait_ms": 0}}, "parameter wait_ms = 0.0 is outside"),
    "tolerance": ({"reconstruction": {"tolerance": -1}}, "parameter tolerance = -1 is outside"),
    "restarts": ({"restarts": {"storm": 0}}, "restarts: storm = 0 is outside"),
}


@pytest.mark.parametrize("case", sorted(BAD_LAYOUTS))
def test_bad_layouts_are_one_line_errors(case, long_recording, tmp_path):
    change, message = BAD_LAYOUTS[case]
    doc = yaml.safe_load(Path(write_layout(tmp_path / "base.yaml")).read_text())
    for key, value in change.items():
        if key in ("run", "restarts", "workers"):
            doc[key] = value
        elif key == "workers+":
            doc["workers"] += value
        else:
            next(w for w in doc["workers"] if w["name"] == key).setdefault("params", {}).update(value)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc))
    r = smartroom("run", "--recording", long_recording, "--headless", "--layout", path, "--out", tmp_path / "o")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], r.stderr


def test_bad_output_folders_are_one_line_errors(long_recording, tmp_path):
    ro = tmp_path / "readonly"
    ro.mkdir()
    ro.chmod(0o500)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    done = tmp_path / "done"
    done.mkdir()
    (done / "stats.json").write_text("{}")
    for out, message in ((blocker / "out", "cannot write there"), (done, "already holds the results of a run")):
        r = smartroom("run", "--recording", long_recording, "--headless", "--out", out)
        assert r.returncode == 2
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], r.stderr
    assert (done / "stats.json").read_text() == "{}"


def test_eval_refuses_results_of_another_recording(long_recording, tmp_path):
    other = write_tiny_recording(tmp_path / "other", frames=30, n_cameras=3)
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml")
    r = smartroom("run", "--recording", long_recording, "--headless", "--no-pace", "--frames", 20,
                  "--layout", layout, "--out", out, timeout=120)
    assert r.returncode == 0, r.stderr
    r = smartroom("eval", "--recording", other, "--results", out)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "these results were made from" in lines[0], r.stderr


def test_a_live_camera_that_never_opens_is_a_clear_error(long_recording, tmp_path):
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml", recorder_voxels=False)
    t0 = time.monotonic()
    r = smartroom("run", "--live", "cam0=/nonexistent/cam0.mp4", "--live", "cam1=7",
                  "--calibration", Path(long_recording) / "calibration.yaml", "--headless", "--layout", layout,
                  "--set", "grabber.open_timeout=2", "--out", out, timeout=60)
    assert time.monotonic() - t0 < 30
    assert r.returncode == 2, r.stderr
    line = [x for x in r.stderr.splitlines() if x.startswith("smartroom: error:")]
    assert len(line) == 1 and "no live camera delivered an image" in line[0] and "cam1" in line[0]
    # and nothing else but the line that said what runs: no OpenCV warnings repeated at each
    # retry, no workers' SIGTERM warnings, no table of zeros, no "RTF 0.00"
    assert r.stdout == "", r.stdout
    assert [x for x in r.stderr.splitlines() if x != line[0]] == [
        f"smartroom: 4 workers here on cam0=/nonexistent/cam0.mp4, cam1=7; results in {out.resolve()}"], r.stderr
    log = (out / "logs" / "grabber.log").read_text()          # what happened is in the grabber's log
    assert "camera cam1 (7) cannot be opened" in log


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    return simulated(tmp_path_factory, "walk1", 2)


def test_tracks_and_poses_do_not_depend_on_machine_load(walk, tmp_path):
    """The whole default pipeline (to tracking and pose) on one recording, once beside two
    CPU hogs, and once with every worker a fresh process instead of forked from the
    launcher's fork server (``SMARTROOM_SPAWN=exec``, app.forkserver): the same
    tracks.jsonl and poses.jsonl, byte for byte."""
    files = []
    for name, loaded, spawn in (("idle", False, "fork"), ("loaded", True, "fork"), ("exec", False, "exec")):
        hogs = hog() if loaded else []
        try:
            r = smartroom("run", "--recording", walk, "--headless", "--no-pace", "--out", tmp_path / name,
                          timeout=300, env=dict(os.environ, SMARTROOM_SPAWN=spawn))
        finally:
            for h in hogs:
                h.kill()
        assert r.returncode == 0, r.stderr
        assert "fork server" not in r.stderr
        files.append([(tmp_path / name / f).read_bytes() for f in ("tracks.jsonl", "poses.jsonl")])
    assert files[0] == files[1] == files[2]
    tracks = [json.loads(line) for line in files[0][0].decode().splitlines()]
    assert len(tracks) == 50 and sum(len(t["tracks"]) for t in tracks) >= 40   # somebody was tracked


def test_live_cameras_that_all_stop_end_the_stream_with_a_reason(tmp_path):
    """Both live cameras stop delivering: the stream ends, the files are completed, and the
    run says why it is not complete (exit 1)."""
    a = write_tiny_recording(tmp_path / "a", frames=20)
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml")
    r = smartroom("run", "--live", f"cam0={a / 'videos' / 'cam0.avi'}", "--live", f"cam1={a / 'videos' / 'cam1.avi'}",
                  "--calibration", a / "calibration.yaml", "--headless", "--layout", layout,
                  "--set", "grabber.lost_timeout=1.5", "--out", out, timeout=90)
    assert r.returncode == 1, r.stderr
    s = stats_of(out)
    assert s["complete"] is False and any("every live camera stopped delivering" in x for x in s["reasons"])
    assert (out / "voxels.bin").is_file() and not list(out.glob("*.partial"))
    # live stages may drop frames; every frame is accounted for: received or counted missing,
    # put out or counted dropped (segmentation builds its models and kernels before it is
    # alive, so an idle or loaded machine writes all 20 here; 9 with four pipelines beside)
    for name, st in s["stages"].items():
        assert st["frames_in"] + st["frames_missing"] == st["frames_expected"], name
        assert st["frames_out"] + st["frames_dropped"] == st["frames_in"], name
    assert len(voxel_frames(out / "voxels.bin")) == s["stages"]["recorder"]["frames_out"] >= 5


def test_commands_started_in_the_same_second_get_their_own_results_folder(tmp_path, monkeypatch):
    """Two benches started together once shared runs/bench/<second> and one failed ("cannot
    write there") when the other removed its write probe; a default folder is now made anew."""
    import argparse
    import time

    from app.commands.options import resolve_out
    monkeypatch.setattr(time, "strftime", lambda fmt: "20261123-145852")
    args = argparse.Namespace(out=None)
    first = resolve_out(args, prefix=str(tmp_path / "runs"))
    second = resolve_out(args, prefix=str(tmp_path / "runs"))
    assert first != second and first.is_dir() and second.is_dir()
    assert second.name == "20261123-145852-2"
