"""Intrinsics and extrinsics recovered from board images rendered with known cameras."""
import cv2
import numpy as np
import pytest

from calibration import Camera, load_calibration
from calibration.boards import detect, floor_points, parse_board, render_view
from calibration.extrinsics import refine_jointly, solve_pose
from calibration.intrinsics import calibrate_intrinsics
from tests.conftest import smartroom

DIST = (-0.12, 0.03, 0.0008, -0.0005, 0.0)


def board_views(board, n=12, seed=1, size=(640, 480), hfov=65):
    """Views of the board from around it, the board landing in different parts of the image."""
    rng = np.random.default_rng(seed)
    pts = floor_points(board)
    centre, extent = pts.mean(axis=0), np.ptp(pts, axis=0).max()
    views = []
    for i in range(n):
        az, el = 2 * np.pi * i / n + rng.uniform(0, 0.3), np.radians(rng.uniform(40, 65))
        pos = centre + extent * rng.uniform(1.3, 1.8) * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el),
                                                                  np.sin(el)])
        aim = Camera.look_at("c", pos, centre, *size, hfov)
        off = rng.uniform(-0.25, 0.25, 2) * extent * np.array([1.0, 0.75])
        cam = Camera.look_at("c", pos, centre + off[0] * aim.R[0] + off[1] * aim.R[1], *size, hfov, dist=DIST)
        views.append((f"view{i:02d}.png", render_view(board, cam)))
    return cam, views


@pytest.fixture(scope="module", params=["chessboard:9x6:0.025", "charuco:7x5:0.04:0.03"])
def rendered(request):
    """(board, the true camera, its views), rendered once per module."""
    board = parse_board(request.param)
    return (board, *board_views(board))


def test_intrinsics_recovered_within_one_percent(rendered):
    board, truth, views = rendered
    r = calibrate_intrinsics(views, board)
    assert r.views_used >= 6 and r.rms < 0.3 and r.warning is None
    for i in (0, 1):
        assert abs(r.K[i, i] / truth.K[i, i] - 1) < 0.01, (r.K, truth.K)
    assert np.abs(r.K[:2, 2] - truth.K[:2, 2]).max() < 8.0  # the least determined: ~1 % of the width
    # the lens: pixels where the views put the board undistort to the same rays
    fitted = Camera("c", r.width, r.height, r.K, r.dist)
    corner = np.array([[120.0, 90.0], [520.0, 390.0], [320.0, 240.0]])
    a, b = fitted.undistort_points(corner), truth.undistort_points(corner)
    # relative to the centre's ray: a principal point shift turns all rays alike
    assert np.abs((a - a[-1]) - (b - b[-1])).max() * truth.K[0, 0] < 2.0


def test_intrinsics_command_from_images_and_video(rendered, tmp_path):
    board, truth, views = rendered
    if board.kind != "chessboard":
        pytest.skip("the command is tested once, with the chessboard")
    (tmp_path / "cam0").mkdir()
    video = cv2.VideoWriter(str(tmp_path / "board.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (640, 480))
    for name, img in views:
        cv2.imwrite(str(tmp_path / "cam0" / name), img)
        for _ in range(3):
            video.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    video.release()
    r = smartroom("calibrate", "intrinsics", "--images", str(tmp_path / "cam0" / "*.png"),
                  "--board", "chessboard:9x6:0.025", "--out", tmp_path / "cam0.yml")
    assert r.returncode == 0, r.stderr
    assert "RMS reprojection error" in r.stdout and "warning" not in r.stdout
    fs = cv2.FileStorage(str(tmp_path / "cam0.yml"), cv2.FILE_STORAGE_READ)
    K = fs.getNode("camera_matrix").mat()
    assert abs(K[0, 0] / truth.K[0, 0] - 1) < 0.01
    r = smartroom("calibrate", "intrinsics", "--video", tmp_path / "board.avi", "--every", 3,
                  "--board", "chessboard:9x6:0.025")
    assert r.returncode == 0, r.stderr
    fx = float(r.stdout.split("fx ")[1].split()[0])
    assert abs(fx / truth.K[0, 0] - 1) < 0.01
    # a wrong board is said plainly
    r = smartroom("calibrate", "intrinsics", "--images", str(tmp_path / "cam0" / "*.png"),
                  "--board", "chessboard:12x9:0.025")
    assert r.returncode == 2 and "the board was found in 0 of 12 views" in r.stderr


def room_cameras(board, size=(1280, 960)):
    centre = floor_points(board).mean(axis=0)
    return [Camera.look_at(f"cam{i}", centre + np.array([2.2 * np.cos(a), 2.2 * np.sin(a), 2.2]), centre, *size, 70,
                           dist=(-0.08, 0.01, 0.0005, -0.0003, 0.0))
            for i, a in enumerate(np.radians([0, 100, 200, 290]))]


def pose_error(got, truth):
    mm = np.linalg.norm(got.centre - truth.centre) * 1000
    deg = np.degrees(np.arccos(np.clip((np.trace(got.R @ truth.R.T) - 1) / 2, -1, 1)))
    return mm, deg


@pytest.mark.parametrize("spec", ["chessboard:9x6:0.12", "charuco:7x5:0.16:0.12"])
def test_extrinsics_from_a_board_on_the_floor(spec):
    board = parse_board(spec)
    for truth in room_cameras(board):
        d = detect(board, render_view(board, truth))
        guess = Camera(truth.name, truth.width, truth.height, truth.K, truth.dist)
        r = solve_pose(guess, floor_points(board, d.ids), d.pixels)
        mm, deg = pose_error(r.camera, truth)
        assert mm < 5.0 and deg < 0.2 and r.rms < 0.5, (truth.name, mm, deg, r.rms)


def test_joint_refinement_with_the_board_moved(tmp_path):
    """Floor view plus two raised, tilted placements seen by all cameras: poses stay within
    5 mm / 0.2 degrees and every camera's RMS stays small; the command line does the same."""
    board = parse_board("charuco:7x5:0.16:0.12")
    cams = room_cameras(board)
    placements = [(cv2.Rodrigues(np.array([np.pi + 0.25, 0.1, 0.3]))[0], np.array([0.2, 0.3, 0.6])),
                  (cv2.Rodrigues(np.array([np.pi - 0.2, -0.15, -0.4]))[0], np.array([-0.2, -0.2, 0.9]))]
    floor, moved, obs = [], [], []
    for ci, c in enumerate(cams):
        img = render_view(board, c)
        cv2.imwrite(str(tmp_path / f"{c.name}-floor.png"), img)
        floor.append(f"{c.name}={tmp_path / f'{c.name}-floor.png'}")
        d = detect(board, img)
        obs.append((ci, 0, d.ids, d.pixels))
        for k, pose in enumerate(placements, start=1):
            img = render_view(board, c, pose)
            cv2.imwrite(str(tmp_path / f"{c.name}-moved{k}.png"), img)
            d = detect(board, img)
            if d is not None:
                obs.append((ci, k, d.ids, d.pixels))
        moved.append(f"{c.name}={tmp_path / (c.name + '-moved*.png')}")
    assert len(obs) > len(cams) + 4
    first = [solve_pose(Camera(c.name, c.width, c.height, c.K, c.dist), floor_points(board, o[2]), o[3]).camera
             for c, o in zip(cams, [o for o in obs if o[1] == 0])]
    for r, truth in zip(refine_jointly(first, obs, floor_points(board)), cams):
        mm, deg = pose_error(r.camera, truth)
        assert mm < 5.0 and deg < 0.2 and r.rms < 0.5, (truth.name, mm, deg, r.rms)
    # the command line: intrinsics from a calibration.yaml, floor + moved images
    from calibration import Calibration, save_calibration
    save_calibration(Calibration(25.0, np.zeros(3), np.ones(3), tuple(
        Camera(c.name, c.width, c.height, c.K, c.dist) for c in cams)), tmp_path / "intrinsics.yaml")
    r = smartroom("calibrate", "extrinsics", "--intrinsics", tmp_path / "intrinsics.yaml", "--board",
                  "charuco:7x5:0.16:0.12", "--floor", *floor, "--moved", *moved, "--out", tmp_path / "calibration.yaml",
                  "--fps", 60)
    assert r.returncode == 0, r.stderr
    assert "joint refinement over 3 board placements" in r.stdout and "room (estimated" in r.stdout
    calib = load_calibration(tmp_path / "calibration.yaml")
    assert calib.fps == 60
    for got, truth in zip(calib.cameras, cams):
        mm, deg = pose_error(got, truth)
        assert mm < 5.0 and deg < 0.2, (got.name, mm, deg)
    assert calib.room_min[2] == 0 and np.all(calib.room_max[:2] > 0.5) and np.all(calib.room_min[:2] < 0)


def test_extrinsics_from_known_points(tmp_path):
    import yaml

    truth = room_cameras(parse_board("chessboard:9x6:0.12"), size=(640, 480))[:2]
    world = {f"p{i}": p for i, p in enumerate(np.random.default_rng(4).uniform([-1, -1, 0], [1.5, 1.2, 1.5], (12, 3)))}
    pixels = {c.name: {n: c.project(p[None])[0].tolist() for n, p in world.items()} for c in truth}
    (tmp_path / "points.yaml").write_text(yaml.safe_dump({"world": {n: p.tolist() for n, p in world.items()},
                                                          "pixels": pixels}))
    files = []
    for c in truth:
        from calibration.formats import write_opencv
        write_opencv(Camera(c.name, c.width, c.height, c.K, c.dist), tmp_path / f"{c.name}.yml")
        files.append(f"{c.name}={tmp_path / (c.name + '.yml')}")
    r = smartroom("calibrate", "extrinsics", "--intrinsics", *files, "--points", tmp_path / "points.yaml",
                  "--out", tmp_path / "c.yaml", "--room", "-2,-2,0,2,2,2.2")
    assert r.returncode == 0, r.stderr
    for got, t in zip(load_calibration(tmp_path / "c.yaml").cameras, truth):
        mm, deg = pose_error(got, t)
        assert mm < 1.0 and deg < 0.01
