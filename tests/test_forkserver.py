"""The fork server (app.forkserver): a process forked from it is its launcher's child with
the command line, environment and working directory asked for, and its exit and signals
are what a fresh process's would be. Whole runs with forked workers are every other
integration test; ``test_faults`` compares one with fresh processes, byte for byte."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from app.forkserver import ForkServer
from tests.conftest import ROOT, smartroom


def _env():
    return dict(os.environ, PYTHONUNBUFFERED="1", SMARTROOM_LAUNCHER_PID=str(os.getpid()))


@pytest.fixture
def server():
    s = ForkServer()
    yield s
    s.close()


FORKED = """
import os, sys
from app.forkserver import ForkServer
server = ForkServer()
worker = server.start(sys.argv[1:], dict(os.environ, SMARTROOM_LAUNCHER_PID=str(os.getpid())), os.getcwd())
rc = worker.wait(60)
server.close()
sys.exit(rc)
"""


def test_a_forked_command_exits_as_a_fresh_process_does(tmp_path):
    """A worker on a layout that is not there: the same exit code and one-line error
    (the forked process writes on its launcher's standard error)."""
    argv = ["worker", "pose", "--layout", str(tmp_path / "missing.yaml")]
    fresh = smartroom(*argv)
    forked = subprocess.run([sys.executable, "-c", FORKED, *argv], capture_output=True, text=True, timeout=120,
                            cwd=ROOT)
    assert forked.returncode == fresh.returncode != 0
    assert forked.stderr == fresh.stderr
    assert fresh.stderr.count("\n") == 1 and "missing.yaml: layout file not found" in fresh.stderr


def test_a_forked_process_is_the_launchers_child_with_its_own_command_line(server, tmp_path):
    argv = ["simulate", "--scene", "walk1", "--seconds", "60", "--out", str(tmp_path / "sim")]
    proc = server.start(argv, _env(), str(tmp_path))
    try:
        stat = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        assert int(stat[1]) == os.getpid()                      # adopted: this process waits for it
        assert int(stat[3]) == proc.pid                         # a session of its own (sid)
        # the worker names itself just after the fork (the pid comes back before): a moment later
        deadline = time.monotonic() + 5.0
        while True:
            cmdline = Path(f"/proc/{proc.pid}/cmdline").read_bytes().split(b"\0")
            if cmdline[1:3] == [b"-m", b"app.cli"] or time.monotonic() > deadline:
                break
            time.sleep(0.01)
        assert cmdline[1:5] == [b"-m", b"app.cli", b"simulate", b"--scene"]
        assert os.readlink(f"/proc/{proc.pid}/cwd") == str(tmp_path)
        time.sleep(0.5)
        assert proc.poll() is None
    finally:
        proc.send_signal(signal.SIGTERM)
    assert proc.wait(10) == -signal.SIGTERM
