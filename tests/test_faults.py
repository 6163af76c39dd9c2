"""A room that runs for days (issue 9): crashes, kills, a fuzzed bus, a dead launcher,
bad input, a full disk and a damaged video, with real worker processes over a real
loopback zenoh session. Each test checks what is left: the result files, the counts
in ``stats.json`` and the exit code."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from app.results import iter_voxels
from tests.conftest import simulated, smartroom, start_smartroom
from tests.synthetic import write_tiny_recording

pytestmark = pytest.mark.integration

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


def assert_counts_add_up(s, expected):
    for name in STAGES:
        st = s["stages"][name]
        assert st["frames_in"] + st["frames_missing"] == expected, (name, st)
        assert st["frames_out"] + st["frames_dropped"] == st["frames_in"], (name, st)


def voxel_frames(path):
    return [(m.frame, tuple(m.cameras)) for m in iter_voxels(path)]


@pytest.fixture(scope="module")
def recording_20s(tmp_path_factory):
    """2 cameras, 160x120, 500 frames (20 s) at 25 fps."""
    return write_tiny_recording(tmp_path_factory.mktemp("rec") / "r20", frames=500)


def test_every_worker_kind_killed_or_terminated_mid_run(recording_20s, tmp_path):
    """kill -9 and SIGTERM of each kind: each is back within seconds, the run completes,
    voxels.bin holds every frame (none lost in a killed worker's inbox), counts add up."""
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml")
    proc = start_smartroom("run", "--recording", recording_20s, "--headless", "--layout", layout, "--out", out)
    back_after = {}
    plan = [("grabber", signal.SIGKILL), ("segmentation", signal.SIGTERM), ("reconstruction", signal.SIGKILL),
            ("recorder", signal.SIGTERM), ("grabber", signal.SIGTERM), ("segmentation", signal.SIGKILL),
            ("reconstruction", signal.SIGTERM), ("recorder", signal.SIGKILL)]
    try:
        for name, sig in plan:
            pid = wait_for(lambda: worker_pid(out, name), timeout=30)
            assert pid, f"{name} never reported"
            time.sleep(0.6)
            os.kill(pid, sig)
            t0 = time.monotonic()
            assert wait_for(lambda: worker_pid(out, name, not_pid=pid), timeout=15), f"{name} not restarted"
            back_after[(name, sig.name)] = round(time.monotonic() - t0, 2)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    (tmp_path / "launcher.err").write_text(err or "")   # the workers' logs, to read after a failure
    print("back after (s):", back_after)
    assert proc.returncode == 0, err
    s = stats_of(out)
    assert s["complete"] is True, s.get("reasons")
    assert s["stages"]["grabber"]["frames_out"] == 500          # the grabber carried on where it was
    assert_counts_add_up(s, 500)
    for name in (*STAGES, "recorder"):
        assert s["stages"][name]["restarts"] == 2, name
    frames = [f for f, _ in voxel_frames(out / "voxels.bin")]
    # nothing lost: what was in flight to a killed worker was sent to it again when it was back
    assert frames == list(range(500))
    for name in (*STAGES, "recorder"):
        assert s["stages"][name]["frames_out"] == 500, (name, s["stages"][name])
    assert not list(out.glob("*.partial"))


def test_a_stage_crashing_ten_times_keeps_being_restarted(long_recording, tmp_path):
    out = tmp_path / "out"
    crash_at = list(range(8, 200, 20))   # ten crashes, one second apart
    layout = write_layout(tmp_path / "layout.yaml", restarts={"window_s": 2, "storm": 4},
                          extra_workers=[{"name": "crashy", "kind": "tests.fault_stages:CrashyStage",
                                          "params": {"crash_at": crash_at}}])
    r = smartroom("run", "--recording", long_recording, "--headless", "--layout", layout, "--out", out, timeout=180)
    assert r.returncode == 0, r.stderr
    s = stats_of(out)
    assert s["complete"] is True and s["stages"]["crashy"]["restarts"] == 10
    assert r.stderr.count("worker crashy died (crashed)") == 10
    assert_counts_add_up(s, 250)
    assert s["stages"]["reconstruction"]["frames_out"] == 250    # the others never noticed


def test_a_restart_storm_is_stopped_and_reported(long_recording, tmp_path):
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml", restarts={"window_s": 60, "storm": 3},
                          extra_workers=[{"name": "crashy", "kind": "tests.fault_stages:CrashyStage",
                                          "params": {"crash_on_start": True}}])
    r = smartroom("run", "--recording", long_recording, "--headless", "--layout", layout, "--out", out, timeout=120)
    assert r.returncode == 1, r.stderr
    assert "restart storm stopped" in r.stderr and "Traceback" not in r.stderr
    s = stats_of(out)
    assert s["complete"] is False and any("storm" in x for x in s["reasons"])


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
        hub = yaml.safe_load((out / "layout.yaml").read_text())["bus"]["listen"]
        session = open_session(BusConfig(listen=["tcp/127.0.0.1:0"], connect=hub))
        keys = Keys("faults")
        targets = [keys.frame("cam0"), keys.frame("cam1"), keys.frame("junk1"), keys.mask("cam0"), keys.mask("cam1"),
                   keys.voxels(), keys.stage("blobs"), keys.tracks(), keys.poses(), keys.eos("grabber"),
                   keys.eos("segmentation"),
                   keys.stats("segmentation"), keys.ack("segmentation")]
        rng = np.random.default_rng(0)
        good = (out / "layout.yaml").read_bytes()
        pubs = {k: session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK) for k in targets}
        time.sleep(1.0)   # gossip links this session to every worker directly
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


def _running(pid) -> bool:
    """Alive and not a zombie (an orphan that exited waits for init to reap it)."""
    try:
        state = Path(f"/proc/{pid}/status").read_text().split("State:")[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def test_ctrl_c_while_a_stage_still_loads_ends_the_run(long_recording, tmp_path):
    """Ctrl-C in the first seconds: the grabber ends its stream before a slow stage has
    loaded; that stage takes the launcher's repeated end of stream (its own went by before
    it listened), so the run ends complete instead of waiting 15 s and giving up."""
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml", extra_workers=[
        {"name": "heavy", "kind": "tests.fault_stages:SlowSetupStage", "params": {"setup_s": 6.0}}])
    proc = start_smartroom("run", "--recording", long_recording, "--headless", "--layout", layout, "--out", out)
    try:
        assert wait_for(lambda: worker_pid(out, "grabber") or _any_pid(out, "grabber"), timeout=60)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    s = stats_of(out)
    assert s["complete"] is True and s["stopped_by_user"] is True, s.get("reasons")
    assert s["workers"]["heavy"]["ended"] is True


def test_killing_the_launcher_leaves_no_worker_alive(long_recording, tmp_path):
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml")
    proc = start_smartroom("run", "--recording", long_recording, "--headless", "--layout", layout, "--out", out)
    try:
        pids = wait_for(lambda: [worker_pid(out, n) for n in (*STAGES, "recorder")]
                        if all(worker_pid(out, n) for n in STAGES) else None, timeout=60)
        assert pids
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(5)
        time.sleep(2.0)
        alive = [pid for pid in filter(None, pids) if _running(pid)]
        assert not alive, "workers outlived their launcher by 2 s"
    finally:
        for pid in filter(None, pids or []):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


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


def _hog(n=2):
    code = "import time\nt=time.time()\nwhile time.time()-t<120: pass"
    return [subprocess.Popen([sys.executable, "-c", code]) for _ in range(n)]


def test_results_do_not_depend_on_machine_load(tmp_path):
    """Two runs of one recording, one beside a CPU hog, give identical voxels (issue 8)."""
    rec = write_tiny_recording(tmp_path / "rec", frames=120, n_cameras=3)
    layout = write_layout(tmp_path / "layout.yaml")
    runs = []
    for name, loaded in (("idle", False), ("loaded", True)):
        hogs = _hog() if loaded else []
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
    r = smartroom("run", "--live", "cam0=/nonexistent/cam0.mp4", "--live", "cam1=/nonexistent/cam1.mp4",
                  "--calibration", Path(long_recording) / "calibration.yaml", "--headless", "--layout", layout,
                  "--set", "grabber.open_timeout=2", "--out", out, timeout=60)
    assert time.monotonic() - t0 < 30
    assert r.returncode == 2, r.stderr
    line = [x for x in r.stderr.splitlines() if x.startswith("smartroom: error:")]
    assert len(line) == 1 and "no live camera delivered an image" in line[0] and "cam1" in line[0]


def test_the_tracking_and_pose_stages_survive_kills_too(recording_20s, tmp_path):
    """The default layout's later stages (cca, tracking, pose) and the monitor, killed and
    terminated mid-run: restarted, the run completes, every stage's counts add up."""
    out = tmp_path / "out"
    proc = start_smartroom("run", "--recording", recording_20s, "--headless", "--out", out)
    plan = [("cca", signal.SIGKILL), ("tracking", signal.SIGTERM), ("pose", signal.SIGKILL),
            ("monitor", signal.SIGKILL)]
    try:
        for name, sig in plan:
            pid = wait_for(lambda: worker_pid(out, name) or (name == "monitor" and _any_pid(out, name)), timeout=90)
            assert pid, f"{name} never reported"
            time.sleep(0.5)
            os.kill(pid, sig)
            assert wait_for(lambda: _any_pid(out, name) not in (None, pid), timeout=30), f"{name} not restarted"
        _, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    s = stats_of(out)
    assert s["complete"] is True, s.get("reasons")
    for name in ("cca", "tracking", "pose"):
        st = s["stages"][name]
        assert st["restarts"] == 1, name
        assert st["frames_in"] + st["frames_missing"] == 500, (name, st)
        assert st["frames_out"] + st["frames_dropped"] == st["frames_in"], (name, st)
        assert st["frames_out"] == 500, (name, st)   # what was in flight at a kill was sent again
    assert s["restarts"]["monitor"]["count"] == 1
    for name in ("tracks", "poses"):
        frames = [json.loads(line)["frame"] for line in open(out / f"{name}.jsonl")]
        assert frames == list(range(500)), name
    assert not list(out.glob("*.partial"))


def _any_pid(out, name):
    w = ((stats_of(out) or {}).get("workers") or {}).get(name)
    return w.get("pid") if w else None


def test_a_worker_restarted_after_its_upstream_ended_still_finishes(long_recording, tmp_path):
    """The end of stream went by while the recorder was down: the launcher says it again,
    so the restarted recorder completes its files instead of waiting for ever."""
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml")
    proc = start_smartroom("run", "--recording", long_recording, "--headless", "--no-pace", "--layout", layout,
                           "--out", out)
    try:
        pid = wait_for(lambda: worker_pid(out, "recorder"), timeout=60)
        wait_for(lambda: ((stats_of(out) or {}).get("stages", {}).get("grabber") or {}).get("final"), timeout=60)
        os.kill(pid, signal.SIGKILL)
        t0 = time.monotonic()
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert time.monotonic() - t0 < 20
    s = stats_of(out)
    assert s["complete"] is True and s["stages"]["recorder"]["restarts"] == 1
    assert (out / "voxels.bin").is_file()


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    return simulated(tmp_path_factory, "walk1", 2)


def test_tracks_and_poses_do_not_depend_on_machine_load(walk, tmp_path):
    """The whole default pipeline (to tracking and pose) twice on one recording, once beside
    two CPU hogs: the same tracks.jsonl and poses.jsonl, byte for byte."""
    files = []
    for name, loaded in (("idle", False), ("loaded", True)):
        hogs = _hog() if loaded else []
        try:
            r = smartroom("run", "--recording", walk, "--headless", "--no-pace", "--out", tmp_path / name,
                          timeout=300)
        finally:
            for h in hogs:
                h.kill()
        assert r.returncode == 0, r.stderr
        files.append([(tmp_path / name / f).read_bytes() for f in ("tracks.jsonl", "poses.jsonl")])
    assert files[0] == files[1]
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
    # alive, so an idle or loaded machine writes all 20 here)
    for name, st in s["stages"].items():
        assert st["frames_in"] + st["frames_missing"] == st["frames_expected"], name
        assert st["frames_out"] + st["frames_dropped"] == st["frames_in"], name
    assert len(voxel_frames(out / "voxels.bin")) == s["stages"]["recorder"]["frames_out"] >= 10


def test_a_restarted_live_grabber_carries_the_frame_numbers_on(tmp_path):
    """Live cameras: the grabber killed mid-run comes back in a new epoch with the next
    frame number, so the stages follow it at once and no result holds a frame twice."""
    a = write_tiny_recording(tmp_path / "a", frames=400)
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml")
    proc = start_smartroom("run", "--live", f"cam0={a / 'videos' / 'cam0.avi'}",
                           "--live", f"cam1={a / 'videos' / 'cam1.avi'}", "--calibration", a / "calibration.yaml",
                           "--headless", "--layout", layout, "--frames", 150, "--out", out)
    try:
        pid = wait_for(lambda: worker_pid(out, "grabber"), timeout=60)
        time.sleep(1.5)
        os.kill(pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    s = stats_of(out)
    assert s["complete"] is True and s["stages"]["grabber"]["restarts"] == 1
    assert s["stages"]["grabber"]["frames_out"] == 150
    frames = [f for f, _ in voxel_frames(out / "voxels.bin")]
    # numbered on from the restart (never twice, never past the 150 grabbed); the last frames
    # too may be given up by a live stage (a view late; counted)
    assert frames == sorted(set(frames)) and 140 <= frames[-1] <= 149
    # live stages may drop frames to keep up (counted); what was written is what the recorder says
    assert len(frames) == s["stages"]["recorder"]["frames_out"] >= 75


@pytest.fixture(scope="module")
def meeting(tmp_path_factory):
    """6 s of meeting3 (150 frames, 2-3 people, two of them walking)."""
    return simulated(tmp_path_factory, "meeting3", 6)


TRACKING_LAYOUT = """room: faults
bus: {listen: ["tcp/127.0.0.1:0"]}
workers:
  - {name: grabber, kind: grabber}
  - {name: segmentation, kind: segmentation}
  - {name: reconstruction, kind: reconstruction, params: {voxel_size: 0.04}}
  - {name: cca, kind: cca}
  - {name: tracking, kind: tracking}
  - {name: recorder, kind: recorder, params: {voxels: false}}
"""
POSE_WORKER = "  - {name: pose, kind: pose, params: {method: shbm, density: 1}}\n"


def _child_pid(parent: int, name: str) -> int | None:
    """The pid of the launcher's worker process ``name`` (its child ``... worker NAME``)."""
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmd = (d / "cmdline").read_bytes().split(b"\0")
        except (OSError, ValueError, IndexError):
            continue
        if ppid == parent and b"worker" in cmd and cmd[cmd.index(b"worker") + 1:][:1] == [name.encode()]:
            return int(d.name)
    return None


def _gone(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"   # a zombie
    except (OSError, IndexError):
        return True


def _snapshot_frame(out, name="tracking") -> int:
    try:
        with np.load(Path(out) / "state" / f"{name}.npz") as z:
            return int(json.loads(str(z["worker"][()]))["frame"])
    except (OSError, ValueError, KeyError):
        return -1


@pytest.fixture(scope="module")
def calm_meeting(meeting, tmp_path_factory):
    """(layout, results) of an undisturbed run of ``meeting`` with tracking and pose."""
    folder = tmp_path_factory.mktemp("calm")
    layout = folder / "layout.yaml"
    layout.write_text(TRACKING_LAYOUT + POSE_WORKER)
    r = smartroom("run", "--recording", meeting, "--headless", "--no-pace", "--layout", layout,
                  "--out", folder / "out", timeout=120)
    assert r.returncode == 0, r.stderr
    return layout, folder / "out"


def assert_results_as_undisturbed(out, calm):
    """tracks.jsonl and poses.jsonl of ``out`` are those of ``calm``, byte for byte."""
    for name in ("tracks.jsonl", "poses.jsonl"):
        want, got = ([json.loads(line) for line in open(d / name)] for d in (calm, out))
        assert got == want, (name, "frames that differ", [a["frame"] for a, b in zip(want, got) if a != b][:10],
                             "missing", sorted({a["frame"] for a in want} - {b["frame"] for b in got}))
        assert (out / name).read_bytes() == (calm / name).read_bytes(), name


def test_killed_tracking_and_pose_workers_carry_on_as_if_never_stopped(meeting, calm_meeting, tmp_path):
    """kill -9 of the tracking worker, then of the pose worker, mid-run: each restarted
    worker takes over its earlier incarnation's snapshot (tracker; pose filters) and
    catches up on the frames put out since (sent again by the stages before it), so
    tracks.jsonl and poses.jsonl are those of an undisturbed run, byte for byte (every
    identity kept, every pose the same)."""
    layout, calm = calm_meeting
    out = tmp_path / "killed"
    proc = start_smartroom("run", "--recording", meeting, "--headless", "--no-pace", "--layout", layout, "--out", out)
    try:
        for name, at in (("tracking", 40), ("pose", 80)):
            assert wait_for(lambda: _snapshot_frame(out, name) >= at, timeout=60, period=0.01), f"no {name} snapshot"
            time.sleep(0.007)   # not always right after a snapshot (and the frame put out just before it)
            os.kill(_child_pid(proc.pid, name), signal.SIGKILL)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    print("\n".join(line for line in err.splitlines() if "[tracking]" in line or "[pose]" in line))
    assert proc.returncode == 0, err
    s = stats_of(out)
    assert s["complete"] is True and s["stages"]["tracking"]["restarts"] == 1 and s["stages"]["pose"]["restarts"] == 1
    assert "tracker restored at frame" in err and "pose estimator restored at frame" in err, err[-2000:]
    assert_results_as_undisturbed(out, calm)
    tracks = [json.loads(line) for line in open(out / "tracks.jsonl")]
    assert len(tracks) == 150 and {t["id"] for f in tracks[75:] for t in f["tracks"]} >= {1, 2}


def test_a_damaged_tracker_snapshot_is_one_log_line_and_a_fresh_start(meeting, tmp_path):
    """The tracking worker is killed and its snapshot damaged before it is back: the next
    incarnation says so once and starts with an empty tracker; the run completes."""
    layout = tmp_path / "layout.yaml"
    layout.write_text(TRACKING_LAYOUT)
    out = tmp_path / "out"
    proc = start_smartroom("run", "--recording", meeting, "--headless", "--no-pace", "--frames", 100,
                           "--layout", layout, "--out", out)
    try:
        assert wait_for(lambda: _snapshot_frame(out) >= 30, timeout=60, period=0.01), "no tracker snapshot"
        pid = _child_pid(proc.pid, "tracking")
        os.kill(pid, signal.SIGKILL)
        # damaged once the process is gone (it is restarted after 0.25 s and reads it later)
        assert wait_for(lambda: _gone(pid), period=0.001)
        (out / "state" / "tracking.npz").write_bytes(b"PK\x03\x04 not a snapshot")
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    s = stats_of(out)
    assert s["complete"] is True and s["stages"]["tracking"]["restarts"] == 1
    lines = [line for line in err.splitlines() if "[tracking]" in line and "tracking.npz" in line]
    assert len(lines) == 1 and "not readable" in lines[0] and "Traceback" not in err, err[-2000:]
    assert "tracker restored" not in err
    assert [json.loads(line)["frame"] for line in open(out / "tracks.jsonl")] == list(range(100))


def test_a_frame_lost_on_its_way_to_the_bus_is_put_out_again(meeting, calm_meeting, tmp_path, monkeypatch):
    """A worker killed between ``put()`` and zenoh sending the message: its journal says
    the frame is out, the consumers never got it. The restarted worker puts its newest
    frame out again: the grabber sends frame 40 again in its earlier epoch, the tracking
    worker works frame 57 anew (its snapshot is of 56), the pose worker sends frame 84's
    poses kept with its snapshot (of 84 itself). Nothing is missing; the files are those
    of an undisturbed run."""
    layout, calm = calm_meeting
    out = tmp_path / "lost"
    monkeypatch.setenv("SMARTROOM_LOSE_OUTPUT", "grabber:40,tracking:57,pose:84")
    r = smartroom("run", "--recording", meeting, "--headless", "--no-pace", "--layout", layout, "--out", out,
                  timeout=180)
    err = r.stderr
    print("\n".join(line for line in err.splitlines() if "WARNING" in line))
    assert r.returncode == 0, err
    s = stats_of(out)
    assert s["complete"] is True and all(s["stages"][n]["restarts"] == 1 for n in ("grabber", "tracking", "pose"))
    assert ("[grabber] WARNING put out frame 40 again" in err and "put out frame 57 again" in err
            and "put out frame 84 again from the state arrays" in err), err[-3000:]
    for name in ("grabber", "segmentation", "reconstruction", "tracking", "pose", "recorder"):
        st = s["stages"][name]
        assert (st["frames_in"], st["frames_out"], st["frames_missing"], st["frames_dropped"]) == (150, 150, 0, 0), st
    assert_results_as_undisturbed(out, calm)


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
