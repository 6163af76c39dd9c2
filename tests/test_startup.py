"""Start-up is reported apart from the run's speed: the real-time factor counts from the
first frame delivered, without the time the pipeline waited for kernels to compile, and
the monitor says the pipeline is starting (not "behind", not which stage is the
bottleneck) while a stage compiles."""
import json
import time

import numpy as np
import pytest

from app.compiles import CompileClock, union_seconds
from app.messages import Stats
from app.monitor import PipelineView
from app.report import summary_table
from app.stats import StageLedger, summarise
from tests.conftest import smartroom
from tests.runs import write_layout


def test_a_stage_rate_counts_from_its_first_output_without_compiles():
    t = [100.0]
    led = StageLedger(clock=lambda: t[0])
    t[0] = 130.0                                  # 30 s of start-up (tables, background, kernels)
    for f in range(100):
        led.received(f, 100.0 + f / 25)
        led.emitted(f, 100.0 + f / 25)
        t[0] += 0.04
    fig = led.figures(final=True)
    assert fig["fps"] == pytest.approx(25.0, rel=0.02) and fig["first_emit"] == 130.0
    # a compile of 20 s on frame 50 of the deepest stage's 100: left out of the rate, reported apart
    deep = {"frames_in": 100, "frames_out": 100, "first_emit": 130.0, "last_emit": 153.96, "fps": 4.1,
            "compile_spans": [[101.0, 125.0], [140.0, 160.0]], "compile_s": 44.0, "setup_s": 8.5}
    s = summarise({"grabber": {"stage": "grabber", "order": 0, "figures": {"frames_out": 100, "fps": 25.0}},
                   "pose": {"stage": "pose", "order": 5, "figures": deep}}, 25.0, 100, started=100.0)
    assert s["fps"] == pytest.approx(99 / (23.96 - 13.96), rel=1e-3) and s["rtf"] == pytest.approx(s["fps"] / 25, 1e-3)
    assert s["startup"] == {"s": 30.0, "setup_s": {"pose": 8.5}, "compile_s": 44.0, "compile_after_first_frame_s": 13.96}
    assert s["rtf_with_startup"] == pytest.approx(100 / 53.96 / 25, rel=1e-3)
    text = summary_table(s)
    assert "start-up: 30.0 s to the first frame delivered (set-up up to 8.5 s, kernels compiled 44.0 s" in text
    assert union_seconds([[0, 2], [1, 3], [5, 6]], 0.5, 5.5) == pytest.approx(3.0)


def test_the_compile_clock_hears_numba_compile():
    import numba
    clock = CompileClock(on_start=lambda: said.append(1)).install()
    said = []

    @numba.njit(cache=False)
    def inner(x):
        return x * 2.0

    @numba.njit(cache=False)
    def outer(a):
        return inner(a.sum())
    outer(np.ones(np.random.randint(3, 9)))
    fig = clock.figures()
    assert fig["compile_s"] > 0 and len(fig["compile_spans"]) == 1 and not fig["compiling"]
    assert said == [1]                            # once: the callee's compile is inside the caller's


def _stats(worker, order, fps_out, **fig):
    return Stats(worker=worker, stage=worker, figures={"order": order, "fps_in": fps_out, "fps_out": fps_out,
                                                       "frames_out": 50, "busy": 0.5, **fig})


def test_the_monitor_says_starting_while_a_stage_compiles():
    now = [1000.0]
    view = PipelineView(25.0, clock=lambda: now[0])
    view.update(_stats("grabber", 0, 25.0))
    view.update(_stats("tracking", 4, 0.0, compiling=True, compile_spans=[[995.0, 1000.0]]))
    assert view.rtf() is None and view.line().startswith("rtf=- verdict=waiting")
    assert "bottleneck" not in view.line()
    view.update(_stats("tracking", 4, 0.5, compiling=False, compile_spans=[[995.0, 1000.0]]))
    now[0] = 1001.0                               # its rates are still of the compile's window
    assert view.rtf() is None
    now[0] = 1003.0
    view.update(_stats("tracking", 4, 24.0, compile_spans=[[995.0, 1000.0]]))
    assert view.rtf() == pytest.approx(24 / 25)


@pytest.mark.integration
def test_a_compile_mid_run_is_not_the_runs_speed(long_recording, tmp_path):
    """A paced run (RTF 1) whose stage compiles for 3 s on frame 10: stats.json's RTF stays
    about 1, the compile is reported apart, and the monitor never calls it 'behind'."""
    out = tmp_path / "out"
    stage = {"name": "compiling", "kind": "tests.fault_stages:CompilingStage", "params": {"at": 10, "compile_s": 3.0}}
    monitor = {"name": "monitor", "kind": "monitor", "params": {"line_period": 0.25}}
    layout = write_layout(tmp_path / "layout.yaml", extra_workers=[stage, monitor], recorder_voxels=False)
    t0 = time.monotonic()
    r = smartroom("run", "--recording", long_recording, "--frames", 100, "--headless", "--layout", layout,
                  "--out", out, timeout=180)
    assert r.returncode == 0, r.stderr
    s = json.loads((out / "stats.json").read_text())
    assert s["final_stage"] == "compiling"
    assert s["startup"]["compile_after_first_frame_s"] == pytest.approx(3.0, abs=0.3)
    # paced at the recording's rate, the compile not counted: counted, 100 frames at 25 fps
    # and 3 s of compile would read 4 / 7 = 0.57; a machine busy with the other test process
    # has read 0.79 (0.85 before: it failed two full runs in four on 2026-11-27)
    assert 0.72 <= s["rtf"] <= 1.1, s["rtf"]
    assert s["rtf_with_startup"] < s["rtf"] and 0 < s["startup"]["s"] < time.monotonic() - t0
    heads = [ln for ln in r.stdout.splitlines() if ln.startswith("monitor: rtf=")]
    assert any("starting=compiling" in ln for ln in heads), heads   # it said what was going on
    compiling = [i for i, ln in enumerate(heads) if "starting=compiling" in ln]
    during = heads[compiling[0]:compiling[-1] + 2]              # the compile, and the line after it
    assert all("verdict=waiting" in ln and "bottleneck" not in ln for ln in during), "\n".join(heads)
    # after it, the run's own rate, not the compile's (4 / 7 = 0.57 if it were counted): some
    # line at the bound stats.json's RTF is held to (on a machine loaded by the other test
    # process a paced run may fall behind after the compile, which the monitor then says,
    # rightly: one full run on 2026-11-27 read 0.82, 0.68, 0.74, 0.93 there, never real-time)
    after = [float(ln.split("rtf=")[1].split()[0]) for ln in heads[compiling[-1] + 1:]
             if not ln.startswith("monitor: rtf=-")]
    assert after and max(after) >= 0.72, "\n".join(heads)
