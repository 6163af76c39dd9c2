"""When a worker takes its upstream's end of stream as true (workers/base.py): the end
counts once its sender has left the bus around the time it was heard; the launcher's
repeats of it, heard long after, neither confirm a forged end nor undo a true one."""
import json

import pytest
import yaml

from app.config import parse_layout
from app.messages import EndOfStream
from tests.conftest import smartroom
from tests.slow_stage import SlowStage
from tests.synthetic import write_tiny_recording

EOS = EndOfStream(frame=199, worker="segmentation", frames=200, fps=25.0)


def _stage(tmp_path) -> SlowStage:
    layout = parse_layout({"workers": [{"name": "grabber", "kind": "grabber"},
                                       {"name": "segmentation", "kind": "segmentation"},
                                       {"name": "slow", "kind": "tests.slow_stage:SlowStage"}]})
    layout.run.out = str(tmp_path)
    w = SlowStage(layout.worker("slow"), layout)
    w._wait_for = set(w.upstream())
    assert w._wait_for == {"segmentation"}
    w.alive.add("segmentation")
    return w


def _leaves(w: SlowStage, t: float) -> None:
    w.alive.discard("segmentation")      # its liveliness token went away (as _on_liveliness does)
    w._died["segmentation"] = t


def test_an_end_heard_as_its_sender_left_stays_true_however_late_the_stage_looks(tmp_path):
    """The stage was busy with its last frames for 25 s after segmentation ended; the
    launcher said the end again every second meanwhile. (The run used to wait for good.)"""
    w = _stage(tmp_path)
    w._heard_end(EOS, 100.0)
    _leaves(w, 100.2)
    for t in range(101, 126):            # the launcher's repeats
        w._heard_end(EOS, float(t))
    assert w._upstream_ended("segmentation", 125.5)
    assert w._source_eos.frames == 200


def test_a_forged_end_is_not_made_true_by_a_crash_long_after(tmp_path):
    w = _stage(tmp_path)
    w._heard_end(EOS, 100.0)             # forged: segmentation runs on
    _leaves(w, 160.0)                     # it crashed a minute later (no repeats: it did not end)
    assert not w._upstream_ended("segmentation", 165.0)
    w._heard_end(EOS, 175.0)             # a forger again, well after the crash
    assert not w._upstream_ended("segmentation", 176.0)


def test_a_stage_started_after_its_upstream_left_takes_the_launcher_s_repeat(tmp_path):
    w = _stage(tmp_path)
    _leaves(w, 50.0)
    w._eos_since = 80.0                   # this incarnation listened for ends from 80 s on
    w._heard_end(EOS, 81.0)
    assert w._upstream_ended("segmentation", 81.5)


@pytest.mark.integration
def test_a_stage_busy_for_long_after_its_upstream_ended_still_ends_the_run(tmp_path):
    """Real processes: a stage still busy 14 s after segmentation ended (two frames of two
    cameras at 3.5 s a mask) takes segmentation's end once it is done, and the run
    completes. It used to wait for good, and the launcher stopped it after 60 s without
    progress, incomplete (CI's statures3 run ended so now and then under load)."""
    rec = write_tiny_recording(tmp_path / "rec", frames=3)
    layout = yaml.safe_load(open("deploy/layouts/local.yaml"))
    layout["workers"].insert(2, {"name": "slow", "kind": "tests.slow_stage:SlowStage", "params": {"delay_ms": 3500.0}})
    (tmp_path / "slow.yaml").write_text(yaml.safe_dump(layout))
    r = smartroom("run", "--recording", rec, "--headless", "--layout", tmp_path / "slow.yaml", "--out", tmp_path / "o",
                  timeout=150)
    assert r.returncode == 0, r.stderr
    stats = json.loads((tmp_path / "o" / "stats.json").read_text())
    assert stats["complete"] is True
    assert stats["workers"]["slow"]["frames_out"] == 3 and stats["workers"]["slow"]["frames_missing"] == 0
