"""The camera model against OpenCV (thesis §2.2.2)."""
import cv2
import numpy as np
import pytest

from calibration import Camera


def _camera(dist=(-0.12, 0.03, 0.001, -0.002, 0.004)):
    return Camera.look_at("cam0", [4.8, 3.8, 2.4], [2.5, 2.0, 0.9], 640, 480, hfov_deg=75, dist=dist)


def _points(n=500, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform([0.5, 0.5, 0.0], [4.5, 3.5, 2.0], (n, 3))


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), (-0.12, 0.03, 0.001, -0.002, 0.004)])
def test_projection_matches_opencv(dist):
    cam = _camera(dist)
    pts = _points()
    rvec, _ = cv2.Rodrigues(cam.R)
    ref, _ = cv2.projectPoints(pts, rvec, cam.t, cam.K, cam.dist)
    np.testing.assert_allclose(cam.project(pts), ref.reshape(-1, 2), atol=1e-6)


def test_undistort_inverts_distortion_like_opencv():
    cam = _camera()
    uv = cam.project(_points())
    ours = cam.undistort_points(uv)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist, criteria=(cv2.TERM_CRITERIA_COUNT, 20, 0)).reshape(-1, 2)
    np.testing.assert_allclose(ours, ref, atol=1e-6)
    pc = cam.to_camera(_points())
    np.testing.assert_allclose(ours, pc[:, :2] / pc[:, 2:], atol=1e-6)


def test_pixel_rays_pass_through_the_points():
    cam = _camera()
    pts = _points()
    rays = cam.pixel_rays(cam.project(pts))
    to_pts = pts - cam.centre
    to_pts /= np.linalg.norm(to_pts, axis=1, keepdims=True)
    np.testing.assert_allclose(rays, to_pts, atol=1e-6)


def test_centre_projects_nowhere_and_points_behind_are_nan():
    cam = _camera()
    assert np.allclose(cam.to_camera(cam.centre[None])[0], 0, atol=1e-9)
    behind = cam.centre + (cam.centre - np.array([2.5, 2.0, 0.9]))
    assert np.isnan(cam.project(behind[None])).all()
    assert not cam.sees(behind[None])[0]
    assert cam.sees(np.array([[2.5, 2.0, 0.9]]))[0]


def test_look_at_centres_the_target():
    cam = _camera((0, 0, 0, 0, 0))
    uv = cam.project(np.array([[2.5, 2.0, 0.9]]))[0]
    np.testing.assert_allclose(uv, [319.5, 239.5], atol=1e-6)
    assert np.isclose(np.linalg.det(cam.R), 1.0)


def test_scaled_camera_maps_pixel_centres():
    cam = _camera()
    half = cam.scaled(320, 240)
    pts = _points()
    np.testing.assert_allclose(half.project(pts), (cam.project(pts) + 0.5) * 0.5 - 0.5, atol=1e-9)
