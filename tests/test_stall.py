"""A stalled offline run never hangs (workers/flow.py, rule 6): a remote stage that never
delivers, or never comes on the bus, ends the run with one line naming it and the frame,
exit 1, within ``stall_timeout_s`` + 5 s. Real worker processes over a real zenoh hub."""
import json
import threading
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import start_smartroom

pytestmark = pytest.mark.integration

STALL_S = 8.0
ENDS_WITHIN_S = STALL_S + 5.0


def _layout(path: Path, segmentation_kind: str, port: int = 0) -> Path:
    doc = {"room": "stall", "bus": {"listen": [f"tcp/127.0.0.1:{port}"]},
           "workers": [{"name": "grabber", "kind": "grabber",
                        "params": {"stall_timeout_s": STALL_S, "ready_timeout": 1.0}},
                       {"name": "segmentation", "kind": segmentation_kind, "host": "camera-pc"},
                       {"name": "reconstruction", "kind": "reconstruction", "params": {"voxel_size": 0.08}},
                       {"name": "recorder", "kind": "recorder"}]}
    path.write_text(yaml.safe_dump(doc))
    return path


class Lines:
    """A process's stderr read as it comes, each line with the time it arrived."""

    def __init__(self, stream):
        self.lines: list[tuple[float, str]] = []
        self._t = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._t.start()

    def _read(self, stream):
        for line in stream:
            self.lines.append((time.monotonic(), line.rstrip("\n")))

    def first(self, text: str) -> float | None:
        return next((t for t, line in self.lines if text in line), None)

    def text(self) -> str:
        self._t.join(5)
        return "\n".join(line for _, line in self.lines)


def _run(tmp_path, kind: str, remote: bool):
    """The run; with ``remote``, the camera host's segmentation is started first (as a
    camera PC booted before the processing PC: it waits for the hub), so that it is on
    the bus before the flow control starts counting, however long it takes to load."""
    from app.bus import free_port
    layout = _layout(tmp_path / "layout.yaml", kind, port=free_port() if remote else 0)
    out, recording = tmp_path / "out", _recording(tmp_path)
    worker = worker_err = None
    if remote:
        worker = start_smartroom("worker", "segmentation", "--layout", layout, "--recording", recording,
                                 "--out", out)
        worker_err = Lines(worker.stderr)
    proc = start_smartroom("run", "--recording", recording, "--headless", "--layout", layout,
                           "--out", out, "--no-pace")
    err = Lines(proc.stderr)
    try:
        proc.wait(timeout=120)
        ended = time.monotonic()
    finally:
        for p in (proc, worker):
            if p is not None and p.poll() is None:
                p.kill()
    if worker is not None:
        worker.wait(timeout=30)
    return proc.returncode, err, worker_err, ended, json.loads((out / "stats.json").read_text()), out


def _recording(tmp_path):
    from tests.synthetic import write_tiny_recording
    return write_tiny_recording(tmp_path / "rec", frames=20)


def test_a_remote_stage_that_never_delivers_ends_the_run_with_the_reason(tmp_path):
    rc, err, worker_err, ended, stats, out = _run(tmp_path, "tests.fault_stages:MuteSegmentation", remote=True)
    took_in = worker_err.first("mute: took frame 0 in")   # frames 0-1 went; frame 2 waits from here on
    assert took_in is not None, worker_err.text()
    assert rc == 1, err.text()
    print(f"ended {ended - took_in:.1f} s after frame 0 went in (stall_timeout_s {STALL_S:g})")
    assert ended - took_in <= ENDS_WITHIN_S, (ended - took_in, err.text())
    lines = [line for line in err.text().splitlines() if "stalled" in line and "incomplete" in line]
    assert lines and "frame 2" in lines[0] and "segmentation" in lines[0], err.text()
    assert stats["complete"] is False and any("stalled" in r for r in stats["reasons"])
    assert "Traceback" not in err.text()


def test_a_worker_that_never_comes_on_the_bus_ends_the_run_with_the_reason(tmp_path):
    rc, err, _, ended, stats, out = _run(tmp_path, "segmentation", remote=False)
    waits = err.first("to be on the bus")   # said after ready_timeout (1 s), while the others come up
    assert waits is not None, err.text()
    assert rc == 1, err.text()
    print(f"ended {ended - waits:.1f} s after the first wait was said (stall_timeout_s {STALL_S:g})")
    assert ended - waits <= ENDS_WITHIN_S, (ended - waits, err.text())
    reason = next(r for r in stats["reasons"] if "stalled" in r)
    assert "segmentation (host camera-pc)" in reason and "frame 0" in reason
    assert stats["complete"] is False and "Traceback" not in err.text()
