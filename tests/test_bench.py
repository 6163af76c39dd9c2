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
    img = cv2.imread(str(out / "profile.png"))
    assert img is not None and img.shape[0] > 300 and img.shape[1] > 600
    assert "unpaced: RTF" in r.stdout and "paced: RTF" in r.stdout


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
