"""`smartroom bench`: the profile report of a short run, and the bus benchmark."""
import json

import cv2
import pytest

from tests.conftest import smartroom

pytestmark = pytest.mark.integration


def test_pipeline_profile_report(tiny_recording, tmp_path, spine_layout):
    out = tmp_path / "bench"
    r = smartroom("bench", "--recording", tiny_recording, "--frames", 40, "--out", out, "--layout", spine_layout,
                  timeout=180)
    assert r.returncode == 0, r.stderr
    prof = json.loads((out / "profile.json").read_text())
    unpaced, paced = prof["modes"]["unpaced"], prof["modes"]["paced"]
    assert 0.6 <= paced["rtf"] <= 1.05   # paced at the recording's fps (loose: test machines are noisy)
    assert unpaced["rtf"] > paced["rtf"]  # unpaced measures capacity
    for mode in (unpaced, paced):
        seg = mode["stages"]["segmentation"]
        assert seg["frames_out"] + seg["frames_dropped"] + seg["frames_missing"] == 40
        assert len(seg["per_frame"]) == seg["frames_out"]
        assert seg["latency_ms"]["p95"] >= seg["latency_ms"]["p50"] > 0
        assert mode["rtf_over_time"]
        # CPU per frame handled, summed per stage over its workers (issue 26)
        rec = mode["by_stage"]["reconstruction"]
        assert rec["workers"] == ["reconstruction"] and rec["cpu_ms_per_frame"] > 0
        assert rec["cpu_ms_per_frame"] == mode["stages"]["reconstruction"]["cpu_ms_per_frame"]
    img = cv2.imread(str(out / "profile.png"))
    assert img is not None and img.shape[0] > 300 and img.shape[1] > 600
    assert "unpaced: RTF" in r.stdout and "paced: RTF" in r.stdout
    assert "cpu ms/frame (summed)" in r.stdout


def test_stage_figures_sum_the_cpu_of_a_stage_s_workers():
    """``smartroom bench`` per stage: three pose shards' CPU per frame add up (how well
    the stage scales out is that sum against one worker's), two reconstruction workers
    taking the frames in turn share the stage's frames; the slowest shard's process time
    is the stage's."""
    from app.benchmarks.pipeline import by_stage

    def worker(stage, order, cpu, p50, frames=100):
        return {"stage": stage, "order": order, "cpu_ms_per_frame": cpu, "process_ms": {"p50": p50, "p95": p50},
                "frames_in": frames, "frames_out": frames}

    stages = {"reconstruction_0": worker("reconstruction", 2, 30.0, 30.0, 50),   # frames taken in turn
              "reconstruction_1": worker("reconstruction", 2, 34.0, 33.0, 50),
              "pose_0": worker("pose", 5, 10.0, 12.0), "pose_1": worker("pose", 5, 11.5, 14.0),
              "pose_2": worker("pose", 5, 9.0, 11.0), "tracking": worker("tracking", 4, 7.0, 7.5)}
    out = by_stage(stages, frames=100)
    assert list(out) == ["reconstruction", "tracking", "pose"]
    assert out["pose"]["workers"] == ["pose_0", "pose_1", "pose_2"]
    assert out["pose"]["cpu_ms_per_frame"] == 30.5 and out["pose"]["process_ms_p50"] == 14.0
    # two workers of 50 frames each at 30 and 34 ms a frame: 32 ms a frame of the stage's 100, not 64
    assert out["reconstruction"]["cpu_ms_per_frame"] == 32.0 and out["reconstruction"]["process_ms_p50"] == 33.0


def test_sweep_tabulates_rtf_per_value(tiny_recording, tmp_path, spine_layout):
    out = tmp_path / "sweep"
    r = smartroom("bench", "--recording", tiny_recording, "--frames", 20, "--modes", "unpaced", "--out", out,
                  "--sweep", "segmentation.history=50,200", "--layout", spine_layout, timeout=180)
    assert r.returncode == 0, r.stderr
    table = r.stdout[r.stdout.index("value"):].splitlines()
    assert table[1].startswith("segmentation.history=50") and table[2].startswith("segmentation.history=200")
    assert float(table[1].split()[1]) > 0 and float(table[2].split()[1]) > 0


def test_bus_benchmark_between_two_processes(tmp_path):
    r = smartroom("bench", "bus", "--frames", 40, "--out", tmp_path, timeout=180)
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "bench_bus.json").read_text())["bus"]
    for mode in res:
        assert mode["latency_frames"] == 40 and mode["throughput_frames"] == mode["throughput_sent"]
        assert 0 < mode["latency_ms_p50"] < 50


def test_no_pose_seeds_is_a_clear_error(tmp_path):
    r = smartroom("bench", "pose", "--pose-seeds", 0, "--out", tmp_path / "b", timeout=60)
    assert r.returncode != 0 and "--pose-seeds 0: must be at least 1" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "b").exists()
