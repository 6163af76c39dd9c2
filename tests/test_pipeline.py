"""The spine end to end: real worker processes over a real loopback zenoh session."""
import json
import os
import signal
import time

import pytest
import yaml

from app.bus import BusConfig, Keys, open_session
from app.messages import Stats
from tests.conftest import smartroom, start_smartroom
from tests.synthetic import write_tiny_recording

pytestmark = pytest.mark.integration


def _stats(out):
    return json.loads((out / "stats.json").read_text())


def _stats_now(out):
    """stats.json while the run goes on ({} before the first write, or mid-replace)."""
    try:
        return _stats(out)
    except (OSError, ValueError):
        return {}


def test_run_passes_every_frame_through_separate_processes(tiny_recording, tmp_path):
    out = tmp_path / "out"
    r = smartroom("run", "--recording", tiny_recording, "--frames", 50, "--headless", "--out", out)
    assert r.returncode == 0, r.stderr
    s = _stats(out)
    assert s["complete"] is True
    assert {"grabber", "segmentation", "reconstruction"} <= set(s["stages"])
    for name, st in s["stages"].items():
        assert st["final"], name
        if name != "recorder":   # the recorder counts the frames of the results it writes
            assert st["frames_in"] + st["frames_missing"] == 50, (name, st)
        assert st["frames_out"] + st["frames_dropped"] == st["frames_in"], (name, st)
    for stage in ("grabber", "segmentation", "reconstruction"):  # offline nothing is dropped or lost
        assert s["stages"][stage]["frames_out"] == 50, s["stages"][stage]
    pids = {w["pid"] for w in s["workers"].values()}
    assert len(pids) == len(s["workers"]) >= 4 and os.getpid() not in pids  # and the monitor
    assert 0 < s["rtf"] <= 1.05  # paced at the recording's fps (speed is the benchmark's, not a test's)
    assert s["delivered_ratio"] == 1.0
    assert (out / "layout.yaml").is_file()
    assert not list(out.glob("*.partial"))
    assert "segmentation" in r.stdout and "RTF" in r.stdout  # the summary table
    # and what to do next, in the last line
    assert r.stderr.splitlines()[-1] == (f"smartroom: results in {out}; next: smartroom view {out} (replay in the "
                                         f"browser), smartroom export {out} (BVH, C3D, TRC, CSV for Blender, Mokka, "
                                         "OpenSim)"), r.stderr


def test_no_pace_runs_faster_than_real_time(tiny_recording, tmp_path, spine_layout):
    out = tmp_path / "out"
    r = smartroom("run", "--recording", tiny_recording, "--headless", "--no-pace", "--out", out,
                  "--layout", spine_layout)
    assert r.returncode == 0, r.stderr
    s = _stats(out)
    assert s["stages"]["grabber"]["frames_out"] == 60
    assert s["rtf"] > 1.0
    # nothing to replay or export (no tracks, poses nor voxels): nothing proposed
    assert r.stderr.splitlines()[-1] == f"smartroom: results in {out}"


def _one_line_error(r):
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.startswith("smartroom: error:")]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert "Traceback" not in r.stderr
    return lines[0]


def test_missing_recording_is_one_line_error(tmp_path):
    line = _one_line_error(smartroom("run", "--recording", tmp_path / "nothing", "--headless", "--out", tmp_path / "o"))
    assert "recording folder not found" in line


def test_video_of_wrong_size_is_one_line_error_naming_the_file(tmp_path):
    rec = write_tiny_recording(tmp_path / "rec", frames=10, width=96, height=72)
    calib = yaml.safe_load((rec / "calibration.yaml").read_text())
    calib["cameras"][1]["width"], calib["cameras"][1]["height"] = 160, 120  # the video is 96x72
    (rec / "calibration.yaml").write_text(yaml.safe_dump(calib))
    (rec / "background" / "cam1.png").unlink()
    r = smartroom("run", "--recording", rec, "--headless", "--out", tmp_path / "o")
    line = _one_line_error(r)
    assert "videos/cam1.avi: frame size 96x72 does not match calibration 160x120" in line


def test_malformed_messages_are_counted_and_skipped(long_recording, tmp_path, spine_layout):
    out = tmp_path / "out"
    proc = start_smartroom("run", "--recording", long_recording, "--frames", 100, "--headless", "--out", out,
                           "--layout", spine_layout)
    layout_file = out / "layout.yaml"
    for _ in range(200):
        if layout_file.is_file():
            break
        time.sleep(0.05)
    layout = yaml.safe_load(layout_file.read_text())
    session = open_session(BusConfig(connect=layout["bus"]["connect"]))
    keys = Keys(layout["room"])
    alive = set()
    sub = session.liveliness().declare_subscriber(keys.alive(), lambda s: alive.add(Keys.last(s.key_expr)),
                                                  history=True)
    try:
        for _ in range(1200):
            if {"segmentation", "reconstruction"} <= alive:
                break
            time.sleep(0.05)
        time.sleep(0.5)
        wrong_type = Stats(frame=5, worker="intruder").to_bytes()  # a valid message on the wrong key
        for payload in (b"", b"garbage", b"SRM\x01" + bytes(40), b"\xff" * 1000, wrong_type):
            session.put(keys.frame("cam0"), payload)
            session.put(keys.mask("cam1"), payload)
            time.sleep(0.05)
    finally:
        sub.undeclare()
        session.close()
    _, err = proc.communicate(timeout=90)
    assert proc.returncode == 0, err
    s = _stats(out)
    for stage in ("segmentation", "reconstruction"):
        assert s["workers"][stage]["bad_messages"] >= 4, stage
        assert s["stages"][stage]["frames_out"] >= 95, stage  # the stream went on


def test_crashed_worker_is_restarted_and_the_run_still_ends(long_recording, tmp_path, spine_layout):
    out = tmp_path / "out"
    proc = start_smartroom("run", "--recording", long_recording, "--headless", "--out", out,
                           "--layout", spine_layout)
    pid = None
    for _ in range(1200):   # until frames flow (start-up takes longer on a loaded machine)
        w = _stats_now(out).get("workers", {}).get("segmentation")
        if w and w["frames_out"] > 10:
            pid = w["pid"]
            break
        time.sleep(0.05)
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    _, err = proc.communicate(timeout=90)
    assert "worker segmentation died (killed by SIGKILL); restarting" in err
    assert proc.returncode == 0, err
    s = _stats(out)
    assert s["complete"] and s["stages"]["grabber"]["frames_out"] == 250
    assert s["workers"]["segmentation"]["pid"] != pid  # the final figures come from the new process


def test_ctrl_c_ends_the_stream_and_completes_files(long_recording, tmp_path, spine_layout):
    out = tmp_path / "out"
    proc = start_smartroom("run", "--recording", long_recording, "--headless", "--out", out,
                           "--layout", spine_layout)
    for _ in range(600):   # until frames flow (start-up takes longer on a loaded machine)
        if (_stats_now(out).get("workers", {}).get("grabber") or {}).get("frames_out", 0) > 0:
            break
        time.sleep(0.1)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    s = _stats(out)
    assert s["complete"]
    n = s["stages"]["grabber"]["frames_out"]
    assert 0 < n < 250
    seg = s["stages"]["segmentation"]
    assert seg["final"] and seg["frames_in"] + seg["frames_missing"] == n


def test_unknown_worker_name(tmp_path):
    line = _one_line_error(smartroom("worker", "nobody"))
    assert "no worker named 'nobody'" in line


def test_live_cameras_and_a_camera_that_stops(tmp_path, spine_layout):
    """Live sources are cv2.VideoCapture URLs (here: video files); cam1's ends early and the
    run goes on with cam0."""
    long_rec = write_tiny_recording(tmp_path / "a", frames=80)
    short_rec = write_tiny_recording(tmp_path / "b", frames=10)
    out = tmp_path / "out"
    r = smartroom("run", "--live", f"cam0={long_rec / 'videos' / 'cam0.avi'}",
                  "--live", f"cam1={short_rec / 'videos' / 'cam1.avi'}",
                  "--calibration", long_rec / "calibration.yaml", "--frames", 40, "--headless", "--out", out,
                  "--layout", spine_layout,
                  timeout=120)
    assert r.returncode == 0, r.stderr
    assert "camera cam1" in r.stderr and "stopped delivering frames" in r.stderr
    s = _stats(out)
    assert s["stages"]["grabber"]["frames_out"] == 40
    seg = s["workers"]["segmentation"]
    assert seg["items_in"] < 2 * 40  # cam1 missed most frames
    # with cam1 gone a frame has one camera, fewer than min_views 2: dropped and counted, never
    # published empty
    rec = s["workers"]["reconstruction"]
    assert rec["frames_too_few_views"] >= 10
    assert rec["frames_out"] + rec["frames_too_few_views"] == rec["frames_in"]


def test_worker_on_another_host_joins_the_run(long_recording, tmp_path):
    """A layout whose segmentation runs elsewhere: the launcher does not start it, and a
    `smartroom worker` started apart (as on the camera PC) joins the run over zenoh."""
    layout = yaml.safe_load(open("deploy/layouts/local.yaml"))
    for w in layout["workers"]:
        if w["name"] == "segmentation":
            w["host"] = "camera-pc"
    path = tmp_path / "two.yaml"
    path.write_text(yaml.safe_dump(layout))
    out = tmp_path / "out"
    proc = start_smartroom("run", "--recording", long_recording, "--frames", 50, "--headless", "--layout", path,
                           "--out", out)
    for _ in range(200):
        if (out / "layout.yaml").is_file():
            break
        time.sleep(0.05)
    remote = start_smartroom("worker", "segmentation", "--layout", out / "layout.yaml")
    try:
        _, err = proc.communicate(timeout=120)
        remote.communicate(timeout=30)
    finally:
        for p in (proc, remote):
            if p.poll() is None:
                p.kill()
    assert proc.returncode == 0, err
    assert remote.returncode == 0
    s = _stats(out)
    assert s["stages"]["segmentation"]["frames_out"] >= 48
    assert s["stages"]["reconstruction"]["frames_out"] >= 48
