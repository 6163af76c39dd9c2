"""Worker logs: ``RESULTS/logs/<name>.log`` per worker (rotated, bounded), a crash's
traceback there and one line on the terminal."""
import subprocess
import sys

import pytest

from tests.conftest import ROOT, smartroom
from tests.runs import write_layout
from workers.base import LOG_BACKUPS, LOG_BYTES

pytestmark = pytest.mark.integration


def test_every_worker_logs_to_its_file_and_a_crash_is_one_line_on_the_terminal(tiny_recording, tmp_path):
    out = tmp_path / "out"
    crashy = {"name": "crashy", "kind": "tests.fault_stages:CrashyStage", "params": {"crash_at": [5], "raises": True}}
    layout = write_layout(tmp_path / "layout.yaml", extra_workers=[crashy], recorder_voxels=False)
    r = smartroom("run", "--recording", tiny_recording, "--headless", "--no-pace", "--layout", layout, "--out", out,
                  timeout=180)
    assert r.returncode == 0, r.stderr
    logs = out / "logs"
    assert sorted(p.name for p in logs.glob("*.log")) == sorted(
        f"{n}.log" for n in ("grabber", "segmentation", "reconstruction", "recorder", "crashy"))
    for path in logs.glob("*.log"):
        text = path.read_text()
        assert f"{path.stem}[" in text and " INFO " in text and "ready (" in text, (path.name, text[-500:])
    text = (logs / "crashy.log").read_text()
    # the crash: its warning, its traceback (indented under its line), the restarted incarnation
    assert "WARNING tests.fault_stages" not in text                        # named by the worker's logger
    assert "about to fail on frame 5" in text and "CRITICAL smartroom.crashy: crashed" in text
    crash = text[text.index("CRITICAL"):].splitlines()
    assert crash[1] == "  Traceback (most recent call last):"
    assert "  RuntimeError: a bug met on frame 5" in crash
    assert "restarted (incarnation 1)" in text
    # the terminal: one line for the crash, where its traceback is, and the launcher's restart
    assert "Traceback" not in r.stderr and "about to fail" in r.stderr
    line = [ln for ln in r.stderr.splitlines() if "crashed:" in ln]
    assert line == [f"smartroom: worker crashy crashed: RuntimeError: a bug met on frame 5 "
                    f"(traceback in {logs / 'crashy.log'})"], r.stderr


def test_a_log_file_rotates_and_stays_bounded(tmp_path):
    code = ("import logging, sys\nfrom workers.base import configure_logging\n"
            "configure_logging('w', logging.WARNING, sys.argv[1])\n"
            "log = logging.getLogger('smartroom.w')\n"
            "for i in range(70000): log.info('line %d %s', i, 'x' * 80)\n")
    subprocess.run([sys.executable, "-c", code, str(tmp_path)], check=True, cwd=ROOT)
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["w.log"] + [f"w.log.{k}" for k in range(1, LOG_BACKUPS + 1)]
    assert all((tmp_path / f).stat().st_size <= LOG_BYTES for f in files)
    assert "line 69999" in (tmp_path / "w.log").read_text().splitlines()[-1]
