"""Hung workers (issue 25): the watchdog's verdicts (pure, a fake clock), and real runs in
which a stage is stopped with SIGSTOP (its process and liveliness still there, its loop
standing still): the launcher kills and restarts it within ``watchdog_s`` + 2 s, says
"hung" in stats.json, and the run completes with every frame (offline) or delivers
again (live)."""
import os
import signal
import time

import pytest

from app.messages import Heartbeat
from app.watchdog import Watchdog
from tests.conftest import start_smartroom
from tests.runs import (STAGES, any_pid, assert_counts_add_up, stats_of, voxel_frames, wait_for, worker_pid,
                        write_layout, running)
from tests.synthetic import write_tiny_recording


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def beat(name="pose", pid=10, loop_age=0.0, pending=0, busy=""):
    return Heartbeat(frame=-1, stamp=0.0, worker=name, pid=pid, loop_age=float(loop_age), pending=pending, busy=busy)


def test_a_process_without_heartbeats_is_hung_after_watchdog_s():
    clock = Clock()
    dog = Watchdog(10.0, clock=clock)
    dog.started("pose", 10)
    clock.t += 59.0
    assert dog.hung("pose") is None                      # still starting (imports): given a minute
    clock.t += 2.0
    assert "no heartbeat in the 61 s since it started" in dog.hung("pose")
    assert dog.beat(beat(loop_age=0.1))
    clock.t += 9.9
    assert dog.hung("pose") is None
    clock.t += 0.2
    assert "no heartbeat for 10 s" in dog.hung("pose")   # SIGSTOP: the whole process stands still
    dog.stopped("pose")
    assert dog.hung("pose") is None                       # gone: nothing to watch


def test_a_loop_standing_still_with_input_waiting_is_hung_unless_busy():
    clock = Clock()
    dog = Watchdog(10.0, clock=clock)
    dog.started("pose", 10)
    dog.beat(beat(loop_age=11.0, pending=0))
    assert dog.hung("pose") is None                       # idle: nothing waits for it
    dog.beat(beat(loop_age=11.0, pending=3, busy="compiling"))
    assert dog.hung("pose") is None                       # a first run's kernels
    dog.beat(beat(loop_age=11.0, pending=3, busy="setup"))
    assert dog.hung("pose") is None
    dog.beat(beat(loop_age=9.0, pending=3))
    assert dog.hung("pose") is None
    clock.t += 1.5                                        # its last heartbeat said 9 s, 1.5 s ago
    assert "not turned for 10 s with 3 messages waiting" in dog.hung("pose")


def test_heartbeats_of_another_process_do_not_count():
    clock = Clock()
    dog = Watchdog(10.0, clock=clock)
    dog.started("pose", 10)
    assert not dog.beat(beat(pid=11))                     # an earlier incarnation, or a forger
    assert not dog.beat(beat(name="stranger", pid=10))
    clock.t += 60.5
    assert dog.hung("pose") is not None
    dog.started("pose", 12)                               # restarted: a fresh start
    assert dog.hung("pose") is None


def _stop(out, name, settle: float, stopped: list) -> float:
    """SIGSTOP worker ``name`` once it handles frames (its pid appended to ``stopped``); the
    seconds until the launcher has killed it."""
    pid = wait_for(lambda: worker_pid(out, name), timeout=60)
    assert pid, f"{name} never reported"
    time.sleep(settle)
    os.kill(pid, signal.SIGSTOP)
    stopped.append(pid)
    t0 = time.monotonic()
    assert wait_for(lambda: not running(pid), timeout=15, period=0.1), "the stopped worker was never killed"
    return time.monotonic() - t0


def _resume(stopped: list) -> None:
    for pid in stopped:   # a worker the test stopped and the launcher did not kill
        try:
            os.kill(pid, signal.SIGCONT)
        except ProcessLookupError:
            pass


@pytest.mark.integration
def test_a_stage_stopped_offline_is_restarted_and_the_run_completes(tmp_path):
    """SIGSTOP of the reconstruction on a recording: killed within watchdog_s + 2 s, restarted
    (reason "hung"), and the run completes with every frame once."""
    rec = write_tiny_recording(tmp_path / "rec", frames=250)
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml", restarts={"watchdog_s": 4})
    proc = start_smartroom("run", "--recording", rec, "--headless", "--layout", layout, "--out", out)
    stopped = []
    try:
        killed_after = _stop(out, "reconstruction", 0.5, stopped)
        _, err = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
        _resume(stopped)
    print("killed after", round(killed_after, 2), "s")
    assert killed_after <= 4 + 2
    assert "reconstruction is hung" in err
    assert proc.returncode == 0, err
    s = stats_of(out)
    assert s["complete"] is True, s.get("reasons")
    failures = s["restarts"]["reconstruction"]["failures"]
    assert [f.get("reason") for f in failures] == ["hung"] and failures[0]["exit"] == -9
    assert s["stages"]["reconstruction"]["restarts"] == 1
    assert_counts_add_up(s, 250)
    assert [f for f, _ in voxel_frames(out / "voxels.bin")] == list(range(250))
    for name in (*STAGES, "recorder"):
        assert s["stages"][name]["frames_out"] == 250, (name, s["stages"][name])


@pytest.mark.integration
def test_a_stage_stuck_in_a_call_leaves_its_stacks_when_killed(tmp_path):
    """A stage stuck in a call that never returns (deaf to SIGTERM, its heartbeats going on)
    is killed as hung, and before the kill it writes every thread's stack to the
    launcher's stderr: the cause of a hang is left behind. The run still completes."""
    rec = write_tiny_recording(tmp_path / "rec", frames=100)
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml", restarts={"watchdog_s": 3}, extra_workers=[
        {"name": "stuck", "kind": "tests.fault_stages:StuckStage", "params": {"at": 10}}])
    proc = start_smartroom("run", "--recording", rec, "--headless", "--layout", layout, "--out", out)
    try:
        _, err = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "worker stuck is hung" in err, err
    stacks = err.split("worker stuck is hung", 1)[1]
    assert "most recent call first" in stacks and "stuck_for_good" in stacks, err
    assert proc.returncode == 0, err
    s = stats_of(out)
    assert s["complete"] is True, s.get("reasons")
    assert [f.get("reason") for f in s["restarts"]["stuck"]["failures"]] == ["hung"]
    assert s["stages"]["stuck"]["frames_out"] == 100


@pytest.mark.integration
def test_a_stage_stopped_live_is_restarted_and_delivers_again(tmp_path):
    """Live cameras: the segmentation stopped for good is killed and restarted, and frames
    flow to the end again (the stages after it jump to the newest frames)."""
    a = write_tiny_recording(tmp_path / "a", frames=600)
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml", restarts={"watchdog_s": 3})
    proc = start_smartroom("run", "--live", f"cam0={a / 'videos' / 'cam0.avi'}",
                           "--live", f"cam1={a / 'videos' / 'cam1.avi'}", "--calibration", a / "calibration.yaml",
                           "--headless", "--layout", layout, "--frames", 400, "--out", out)
    stopped = []
    try:
        killed_after = _stop(out, "segmentation", 1.0, stopped)
        assert wait_for(lambda: any_pid(out, "segmentation") not in (None, *stopped), timeout=30)
        _, err = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
        _resume(stopped)
    assert killed_after <= 3 + 2
    assert proc.returncode == 0, err
    s = stats_of(out)
    assert s["complete"] is True, s.get("reasons")
    assert s["restarts"]["segmentation"]["failures"][0]["reason"] == "hung"
    frames = [f for f, _ in voxel_frames(out / "voxels.bin")]
    assert frames == sorted(set(frames))
    # it delivers again after the restart: frames from the last seconds of the run are there
    assert frames[-1] >= 380, frames[-20:]


def test_a_silence_that_ends_without_a_restart_is_kept():
    clock = Clock()
    dog = Watchdog(30.0, clock=clock, wall=lambda: 5000.0)
    dog.started("tracking", 7)
    dog.beat(beat("tracking", 7))
    clock.t += 1.0
    dog.beat(beat("tracking", 7))
    assert dog.silences() == {}
    clock.t += 20.0                                       # SIGSTOP 20 s, then SIGCONT
    assert dog.hung("tracking") is None
    dog.beat(beat("tracking", 7, loop_age=20.0))
    assert dog.silences() == {"tracking": [{"until": 5000.0, "s": 20.0}]}


STALL_S = 100.0   # issue 25's probe: pose SIGSTOPped 100 s in a live run, then SIGCONT


@pytest.mark.integration
def test_a_live_stage_stalled_100_s_delivers_again_after_it_resumes(tmp_path):
    """Live cameras, a watchdog longer than the stall: the segmentation stopped for 100 s
    and then continued is not restarted; it and the stages after it jump to the newest
    frames (counting what they skipped) instead of refusing everything as outside their
    window, frames flow to the end of the run again, and stats.json keeps the silence."""
    fps = 25.0
    a = write_tiny_recording(tmp_path / "a", frames=int((STALL_S + 40) * fps))
    out = tmp_path / "out"
    layout = write_layout(tmp_path / "layout.yaml", restarts={"watchdog_s": STALL_S + 60})
    total = int((STALL_S + 25) * fps)
    proc = start_smartroom("run", "--live", f"cam0={a / 'videos' / 'cam0.avi'}",
                           "--live", f"cam1={a / 'videos' / 'cam1.avi'}", "--calibration", a / "calibration.yaml",
                           "--headless", "--layout", layout, "--frames", total, "--out", out)
    stopped = []
    try:
        pid = wait_for(lambda: worker_pid(out, "segmentation"), timeout=60)
        assert pid, "segmentation never reported"
        time.sleep(1.0)
        os.kill(pid, signal.SIGSTOP)
        stopped.append(pid)
        stopped_at = time.monotonic()
        time.sleep(STALL_S)
        _resume(stopped)
        resumed_at = time.monotonic()
        _, err = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
        _resume(stopped)
    assert resumed_at - stopped_at >= STALL_S
    assert proc.returncode == 0, err[-2000:]
    s = stats_of(out)
    assert s["complete"] is True, s.get("reasons")
    assert "segmentation" not in (s.get("restarts") or {})          # continued, not restarted
    assert any(g["s"] >= STALL_S - 5 for g in s["silences"]["segmentation"]), s.get("silences")
    frames = [f for f, _ in voxel_frames(out / "voxels.bin")]
    assert frames == sorted(set(frames))
    # the frames after the stall are there: it delivers again until the end of the run
    late = [f for f in frames if f >= total - 10 * fps]
    assert len(late) >= 5 * fps, (len(late), frames[-10:])
    assert s["workers"]["reconstruction"]["frames_skipped"] > 0 or s["workers"]["segmentation"]["frames_skipped"] > 0
