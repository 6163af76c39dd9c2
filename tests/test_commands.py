"""The smaller verbs as a user runs them: record, calibrate, simulate --list."""
import cv2
import numpy as np
import pytest

from app.recording import Recording
from tests.conftest import smartroom


def test_record_from_a_recording_and_from_live_cameras(tiny_recording, tmp_path):
    r = smartroom("record", "--recording", tiny_recording, "--frames", 10, "--out", tmp_path / "copy")
    assert r.returncode == 0, r.stderr
    rec = Recording(tmp_path / "copy")
    assert rec.frame_count == 10 and rec.cameras == ["cam0", "cam1"]
    live = [f"cam0={tiny_recording / 'videos' / 'cam0.avi'}", f"cam1={tiny_recording / 'videos' / 'cam1.avi'}"]
    r = smartroom("record", "--live", live[0], "--live", live[1], "--calibration", tiny_recording / "calibration.yaml",
                  "--frames", 8, "--out", tmp_path / "live", "--codec", "MJPG")
    assert r.returncode == 0, r.stderr
    rec = Recording(tmp_path / "live")
    assert rec.frame_count == 8
    i, images = next(iter(rec.frames()))
    assert images["cam0"].shape == (120, 160, 3)
    r = smartroom("record", "--recording", tiny_recording, "--out", tmp_path / "copy")
    assert r.returncode == 2 and "already exists" in r.stderr


def test_calibrate_check_and_import_opencv(tiny_recording, tmp_path):
    r = smartroom("calibrate", "check", tiny_recording)
    assert r.returncode == 0 and "2 cameras at 25 fps" in r.stdout and "distortion yes" in r.stdout
    calib = Recording(tiny_recording).calibration
    files = []
    for cam in calib.cameras:
        path = tmp_path / f"{cam.name}.yml"
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        fs.write("camera_matrix", cam.K)
        fs.write("distortion_coefficients", cam.dist.reshape(1, 5))
        fs.write("rvec", cv2.Rodrigues(cam.R)[0])
        fs.write("tvec", cam.t.reshape(3, 1))
        fs.write("image_width", cam.width)
        fs.write("image_height", cam.height)
        fs.release()
        files.append(f"{cam.name}={path}")
    out = tmp_path / "calibration.yaml"
    r = smartroom("calibrate", "import-opencv", *files, "--out", out, "--fps", 25, "--room", "0,0,0,4,4,2.5")
    assert r.returncode == 0, r.stderr
    from calibration import load_calibration
    back = load_calibration(out)
    pts = np.random.default_rng(0).uniform([0.5, 0.5, 0], [3.5, 3.5, 2], (50, 3))
    for a, b in zip(calib.cameras, back.cameras):
        np.testing.assert_allclose(a.project(pts), b.project(pts), atol=1e-6)


@pytest.mark.parametrize("args, message", [
    (("simulate", "--scene", "nope", "--out", "x"), "nope"),
    (("calibrate", "check", "/nonexistent/calibration.yaml"), "file not found"),
    (("run", "--set", "segmentation.histroy=3", "--recording", "/nonexistent"), "unknown parameter 'histroy'"),
])
def test_bad_input_is_one_line(args, message):
    r = smartroom(*args)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("smartroom: error:")]
    assert len(lines) == 1 and message in lines[0] and "Traceback" not in r.stderr


def test_simulate_lists_the_scenes():
    r = smartroom("simulate", "--list")
    assert r.returncode == 0
    for scene in ("walk1", "gesture1", "meeting3", "crowd6", "occluded1"):
        assert scene in r.stdout
