import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.synthetic import write_tiny_recording

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="session")
def tiny_recording(tmp_path_factory):
    """2 cameras, 160x120, 60 frames at 25 fps, with background images."""
    return write_tiny_recording(tmp_path_factory.mktemp("rec") / "tiny", frames=60)


@pytest.fixture(scope="session")
def long_recording(tmp_path_factory):
    """2 cameras, 160x120, 250 frames (10 s) at 25 fps."""
    return write_tiny_recording(tmp_path_factory.mktemp("rec") / "long", frames=250)


def smartroom(*args, timeout=120, env=None, **kw):
    """Run the CLI as a separate process, as a user would (``env``: its environment, this
    process's by default)."""
    env = dict(os.environ if env is None else env, PYTHONUNBUFFERED="1")
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env=env, **kw)


def simulated(tmp_path_factory, scene: str, seconds: float, size: str = "320x240"):
    """A recording of ``seconds`` of a simulated ``scene`` (made by ``smartroom simulate``)."""
    out = tmp_path_factory.mktemp("sim") / scene
    r = smartroom("simulate", "--scene", scene, "--seconds", seconds, "--size", size, "--out", out, timeout=300)
    assert r.returncode == 0, r.stderr
    return out


def through_npz(arrays: dict) -> dict:
    """``arrays`` saved with ``numpy.savez`` and loaded back (no pickles), as a state file is."""
    import io

    import numpy as np
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    buf.seek(0)
    with np.load(buf, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def start_smartroom(*args, **kw):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "app.cli", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env, **kw)


SPINE_LAYOUT = """room: smartroom
bus: {listen: [tcp/127.0.0.1:0]}
workers:
  - {name: grabber, kind: grabber}
  - {name: segmentation, kind: segmentation}
  - {name: reconstruction, kind: reconstruction, params: {voxel_size: 0.04}}
  - {name: recorder, kind: recorder}
  - {name: monitor, kind: monitor}
"""


@pytest.fixture(scope="session")
def spine_layout(tmp_path_factory):
    """The spine alone (grabber, segmentation, reconstruction, recorder, monitor): tests of
    the process machinery that need not carry tracking and pose."""
    path = tmp_path_factory.mktemp("layouts") / "spine.yaml"
    path.write_text(SPINE_LAYOUT)
    return path
