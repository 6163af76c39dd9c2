"""Video files given as live cameras (a test rig, a looped demo on a kiosk): read at the
camera's rate, not as fast as the decoder goes."""
import time

import pytest

from app.sources import _CameraThread
from tests.synthetic import write_tiny_recording


@pytest.mark.parametrize("playlist", [False, True], ids=["video file", "ffconcat playlist"])
def test_a_file_given_as_a_camera_is_read_at_the_camera_rate(tmp_path, playlist):
    """A playlist (ffconcat, the way to loop a clip for days) does not say its length, and was
    read flat out: one core decoding for nothing."""
    rec = write_tiny_recording(tmp_path / "r", frames=60)
    video = rec / "videos" / "cam0.avi"
    source = video
    if playlist:
        source = video.parent / "loop.ffconcat"   # names relative to the playlist (ffmpeg's safe mode)
        source.write_text("ffconcat version 1.0\n" + f"file {video.name}\n" * 20)
    cam = _CameraThread("cam0", str(source), 160, 120, fps=20.0)
    cam.start()
    try:
        t0 = time.process_time(), time.monotonic()
        time.sleep(1.5)
        cpu = time.process_time() - t0[0]
        assert cam.paced
        assert cam.take() is not None
        # 30 frames of 160x120 at 20 fps cost a few ms; flat out the thread decodes all second long
        assert cpu < 0.5, cpu
    finally:
        cam.stopped.set()
        cam.join(timeout=5)
