"""``calibrate fit``'s rule (calibration.fitting): turn, rescale or crop chosen from the
sizes, the crop's placement from a padding band or the codec convention, checked by
projecting known points with the fitted camera and with the camera the video really has."""
import cv2
import numpy as np
import pytest

from calibration import Camera
from calibration.fitting import fit_camera, padding_placement
from calibration.transform import cropped, turned

#: points in the room, seen by the cameras below
POINTS = np.array([[2.0, 2.0, 1.7], [1.0, 3.0, 0.2], [3.0, 1.5, 1.0], [2.5, 2.5, 0.0]])


def _video_camera(width=1920, height=1080, roll=0.0):
    """The camera the video really has: upright (or rolled by ``roll`` degrees)."""
    c = Camera.look_at("cam0", [4.5, -1.0, 2.5], [2.0, 2.0, 1.0], width, height, 70, dist=(-0.1, 0.01, 0, 0, 0))
    if roll:
        a = np.radians(roll)
        z = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        c = Camera(c.name, width, height, c.K, c.dist, z @ c.R, z @ c.t)
    return c


def _error(fitted, truth):
    """Largest pixel distance between where the fitted and the true camera put the points."""
    assert truth.sees(POINTS).all()
    return float(np.abs(fitted.project(POINTS) - truth.project(POINTS)).max())


def test_rescale_for_a_proxy_of_the_same_aspect():
    truth = _video_camera(1280, 720)
    f = fit_camera(_video_camera(1920, 1080), 1280, 720)
    assert f.decided and f.said.startswith("cam0: rescaled 1920x1080 -> 1280x720") and "one factor" in f.said
    assert (f.camera.width, f.camera.height) == (1280, 720) and _error(f.camera, truth) < 1e-6
    # rounded sizes (854x480 of 1920x1080) are a rescale too, not a crop
    assert "rescaled" in fit_camera(_video_camera(1920, 1080), 854, 480).said


def test_crop_for_a_codec_padded_calibration_bottom_or_centre():
    """A 1080-row video under a 1088-row calibration: a crop. Padded at the bottom (the
    codecs' way) the principal point stays; cut from the middle it moves 4 px. The video
    cannot show which, so the bottom is assumed and said, and ``--crop centre`` overrides."""
    truth = _video_camera(1920, 1080)
    bottom = cropped(truth, 0, 0, 1920, 1088)   # the calibrated image: the video and 8 rows below it
    centred = cropped(truth, 0, -4, 1920, 1088)  # 4 rows above and 4 below
    f = fit_camera(bottom, 1920, 1080)
    assert f.said.startswith("cam0: cropped 1920x1088 -> 1920x1080 at offset (0, 0), principal point kept")
    assert "assumed at the bottom as codecs pad" in f.said and "--crop centre" in f.said
    assert f.camera.K[1, 2] == bottom.K[1, 2] and f.camera.K[1, 1] == bottom.K[1, 1]
    assert _error(f.camera, truth) < 1e-9
    assert abs(_error(fit_camera(centred, 1920, 1080).camera, truth) - 4) < 1e-6  # the assumption, when wrong
    f = fit_camera(centred, 1920, 1080, placement="centre")
    assert "offset (0, 4), principal point moved by (0, -4) px" in f.said and "centred as given" in f.said
    assert _error(f.camera, truth) < 1e-9
    # mode="crop" (--crop) takes the same placement rules; one pixel short (Pose2Sim's 1087) is a crop too
    assert _error(fit_camera(bottom, 1920, 1080, mode="crop").camera, truth) < 1e-9
    assert fit_camera(cropped(truth, 0, 0, 1920, 1079), 1920, 1080).said.startswith("cam0: padded 1920x1079")


@pytest.mark.parametrize("calibrated_turn, expected", [(90, 270), (270, 90)])
def test_turn_for_a_portrait_video_of_a_landscape_calibration(calibrated_turn, expected):
    """The calibration was made on the sensor's landscape images (the room lies on its
    side in them); the video is portrait and upright: the turn that stands the room
    upright is chosen, and the fitted camera projects like the video's."""
    truth = _video_camera(1080, 1920)
    calib = turned(truth, calibrated_turn)
    assert (calib.width, calib.height) == (1920, 1080)
    f = fit_camera(calib, 1080, 1920)
    assert f.said.startswith(f"cam0: turned {expected} degrees clockwise, 1920x1080 -> 1080x1920")
    assert "stands the room upright" in f.said and f"--turn {360 - expected}" in f.said
    assert _error(f.camera, truth) < 1e-6
    # told the other way, it turns the other way
    f = fit_camera(calib, 1080, 1920, turn=360 - expected)
    assert f"turned {360 - expected} degrees" in f.said and "--turn" in f.said and _error(f.camera, truth) > 100


def test_turn_direction_unknown_is_said():
    """An upright landscape calibration under a portrait video: neither turn stands the
    room upright, so 90 is assumed and the line says so."""
    f = fit_camera(_video_camera(1920, 1080), 1080, 1920)
    assert "turned 90 degrees" in f.said and "90 assumed, --turn 270 otherwise" in f.said


def test_rescale_then_crop_and_undecided_sizes():
    truth = _video_camera(960, 540)
    calib = cropped(truth.scaled(1920, 1080), 0, 0, 1920, 1088)  # a 960x540 proxy of a 1088-row image
    f = fit_camera(calib, 960, 540)
    assert f.said.startswith("cam0: rescaled 1920x1088 -> 960x544 (x0.5000), then cropped 960x544 -> 960x540")
    assert _error(f.camera, truth) < 1e-6
    f = fit_camera(_video_camera(640, 480), 1920, 1080)
    assert not f.decided and "--rescale or --crop" in f.said and f.camera.width == 640


def _textured(height, width, seed=0):
    noise = np.random.default_rng(seed).integers(0, 255, (height // 6, width // 6, 3), dtype=np.uint8)
    return cv2.resize(noise, (width, height), interpolation=cv2.INTER_LINEAR)


def _jpeg(img):
    return cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])[1], cv2.IMREAD_COLOR)


@pytest.mark.parametrize("top, placement", [(0, "end"), (4, "centre"), (8, "start")])
def test_a_padding_band_in_the_video_says_where_the_crop_lies(top, placement):
    """A 128-row video of a 120-row calibration with 8 black rows at the bottom, split, or
    at the top (through a lossy codec): the band is found and the principal point follows it."""
    frames = []
    for seed in range(3):
        img = np.zeros((128, 160, 3), np.uint8)
        img[top:top + 120] = _textured(120, 160, seed)
        frames.append(_jpeg(img))
    assert padding_placement(frames, 0, 8)[0] == placement
    truth = _video_camera(160, 128)
    calib = cropped(truth, 0, top, 160, 120)
    f = fit_camera(calib, 160, 128, frames=lambda: frames)
    assert "of one colour" in f.said and _error(f.camera, truth) < 1e-9, f.said
    # no band (the picture fills the frame) or a plain picture: not found, the convention said
    assert padding_placement([_jpeg(_textured(128, 160))], 0, 8)[0] is None
    assert padding_placement([np.full((128, 160, 3), 90, np.uint8)], 0, 8) == \
        (None, "the frames are too plain to show a padding band")
