"""Text on the PNGs (calibrate check, simulate --preview, the viewer's labels): the dark
outline is around the letters, not a ghost of them drawn further apart."""
import cv2
import numpy as np
import pytest

from app.drawing import outlined_text
from tests.conftest import smartroom
from tests.synthetic import write_tiny_recording


def _ghost(img, outline: int) -> int:
    """Dark pixels (the outline) farther than ``outline`` + 1.5 px from every light pixel
    (the letters, on a mid-grey ground): none when the outline is around them."""
    light = np.all(img[..., :3] >= 160, axis=-1)   # the letters, their anti-aliased edge included
    dark = np.all(img[..., :3] <= 30, axis=-1)
    assert light.sum() > 50 and dark.sum() > 50
    dist = cv2.distanceTransform((~light).astype(np.uint8), cv2.DIST_L2, 3)
    return int((dark & (dist > outline + 1.5)).sum())


@pytest.mark.parametrize("scale, thickness", [(0.6, 1), (1.35, 3)])
def test_the_outline_is_around_the_letters(scale, thickness):
    img = np.full((80, 520, 3), 100, np.uint8)
    outlined_text(img, "cam0  frame 100  size 1920x1080", (6, 50), scale, (255, 255, 255), thickness,
                  outline=thickness + 1)
    assert _ghost(img, thickness + 1) == 0


def test_the_old_way_was_ghosted():
    """The same text twice, thick and dark then thin and light: OpenCV spaces the thick
    letters further apart, and this test tells it apart."""
    old = np.full((80, 520, 3), 100, np.uint8)
    for colour, thickness in (((0, 0, 0), 3), ((255, 255, 255), 1)):
        cv2.putText(old, "cam0  frame 100  size 1920x1080", (6, 50), cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, thickness,
                    cv2.LINE_AA)
    assert _ghost(old, 2) > 20


def test_the_preview_mosaic_labels_are_clean():
    from app.simulation.preview import mosaic
    tiles = [np.full((240, 320, 3), 110, np.uint8) for _ in range(4)]
    out = mosaic(tiles, [f"cam{k}  frame 100" for k in range(4)])
    assert _ghost(out, 2) == 0


def test_the_viewer_labels_are_clean():
    from app.viewer import three
    png, _ = three.text_image("#3", (1.0, 1.0, 1.0))
    rgba = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    a = rgba[..., 3:4] / 255.0
    over_grey = (100 * (1 - a) + rgba[..., :3] * a).astype(np.uint8)
    assert _ghost(over_grey, 3) == 0


@pytest.mark.integration
def test_calibrate_check_of_four_hd_cameras_is_big_enough_to_judge(tmp_path):
    rec = write_tiny_recording(tmp_path / "hd", frames=2, n_cameras=4, width=1920, height=1080)
    r = smartroom("calibrate", "check", "--recording", rec, "--out", tmp_path / "check")
    assert r.returncode == 0, r.stderr
    sheet = cv2.imread(str(tmp_path / "check" / "check.png"))
    assert sheet.shape == (1440, 2560, 3)        # each camera at 1280x720 (720x408 for all four before)
    one = cv2.imread(str(tmp_path / "check" / "check-cam0.png"))
    assert one.shape == (1080, 1920, 3) and _ghost(one[:300, :900], 4) == 0
