"""The ghost test of new tracks (app/tracking/ghosts.py): a visual hull carved from the
silhouettes of two people in two and in three cameras holds, besides the two bodies,
blobs where one person's viewing cone crosses the other's; judged against the people
known (as the tracker asks), those are ghosts and each person is not."""
import cv2
import numpy as np
import pytest

from app.tracking.blobs import ComponentAnalysis
from app.tracking.ghosts import GhostTest
from calibration.camera import Camera

VOXEL = 0.05
ROOM = (5.0, 5.0, 2.0)
PEOPLE = ((1.5, 2.5), (3.5, 2.5))   # xy of two 1.7 m tall, 0.5 m wide columns


def _body_points(xy, step=0.02):
    r = np.arange(-0.25, 0.25 + 1e-9, step)
    gx, gy, gz = np.meshgrid(r, r, np.arange(0.0, 1.7, step), indexing="ij")
    keep = gx ** 2 + gy ** 2 <= 0.25 ** 2
    return np.stack([gx[keep] + xy[0], gy[keep] + xy[1], gz[keep]], axis=1)


def _silhouette(cam):
    """The camera's silhouette of the two people (uint8, full size)."""
    body = np.concatenate([_body_points(p) for p in PEOPLE])
    mask = np.zeros((cam.height, cam.width), np.uint8)
    uv = np.round(cam.project(body)).astype(int)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    mask[uv[ok, 1], uv[ok, 0]] = 1
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))


def _hull(cameras):
    """Voxel centres inside every camera's silhouette of the two people, and their labels."""
    dims = tuple(int(round(d / VOXEL)) for d in ROOM)
    idx = np.stack(np.meshgrid(*[np.arange(d) for d in dims], indexing="ij"), axis=-1).reshape(-1, 3)
    centres = (idx + 0.5) * VOXEL
    keep = np.ones(len(idx), dtype=bool)
    for cam in cameras:
        mask = _silhouette(cam)
        uv = cam.project(centres)
        inside = np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width - 0.5) & \
            (uv[:, 1] >= 0) & (uv[:, 1] < cam.height - 0.5)
        hit = np.zeros(len(idx), dtype=bool)
        uvi = np.round(uv[inside]).astype(int)
        hit[np.nonzero(inside)[0]] = mask[uvi[:, 1], uvi[:, 0]] > 0
        keep &= hit
    idx = idx[keep].astype(np.int64)
    labels, feats, _ = ComponentAnalysis(dims, (0.0, 0.0, 0.0), VOXEL)(idx)
    return (idx + 0.5) * VOXEL, labels, feats


def _cameras(n):
    spots = [(-0.5, -0.5, 2.5), (5.5, -0.5, 2.5), (2.5, 5.8, 2.5)][:n]
    return [Camera.look_at(f"c{k}", p, (2.5, 2.5, 0.9), 320, 240, hfov_deg=80.0) for k, p in enumerate(spots)]


@pytest.mark.parametrize("n_cameras", [2, 3])
def test_ghosts_where_cones_cross_and_people_not(n_cameras):
    cameras = _cameras(n_cameras)
    centres, labels, feats = _hull(cameras)
    test = GhostTest(cameras)
    comps = [c for c in range(len(feats)) if (labels == c).sum() >= 20]
    near = {c: min(np.hypot(*(centres[labels == c, :2].mean(axis=0) - np.asarray(p))) for p in PEOPLE)
            for c in comps}
    body = [c for c in comps if near[c] < 0.2]
    assert len(body) == 2
    # each person against the other (the one known): not a ghost
    people = [test(centres[labels == a], centres[labels == b]) for a, b in (body, body[::-1])]
    assert people == [False, False]
    # every other blob against the two people: a ghost
    known = np.isin(labels, body)
    ghosts = [test(centres[labels == c], centres[known]) for c in comps if c not in body]
    if n_cameras == 2:
        assert len(ghosts) >= 1        # two cameras, two people: their cones cross
    assert all(ghosts), ghosts


def test_a_camera_that_sees_the_room_through_a_blob_is_no_witness_of_it():
    """The tracker's hull keeps voxels one camera misses: carved from two of three
    cameras, the ghosts where the two cones cross lie where the third camera sees the
    room, yet their cells there are no person's. Without silhouettes the third camera is
    the ghost's witness; with them (reduced 4x, as the reconstruction sends them) it is
    not, and it stays each person's witness though their silhouette is thinned by a
    reduced pixel."""
    from app.segmentation import reduce_mask

    cameras = _cameras(3)
    centres, labels, feats = _hull(cameras[:2])
    comps = [c for c in range(len(feats)) if (labels == c).sum() >= 20]
    near = {c: min(np.hypot(*(centres[labels == c, :2].mean(axis=0) - np.asarray(p))) for p in PEOPLE)
            for c in comps}
    body = [c for c in comps if near[c] < 0.2]
    ghosts = [c for c in comps if c not in body]
    assert len(body) == 2 and ghosts
    test = GhostTest(cameras, min_cameras=1)   # one witness is enough: the third camera decides
    masks = {cam.name: reduce_mask(_silhouette(cam).astype(bool), 4) for cam in cameras}
    seen = test.seen_cells(masks)
    thin = test.seen_cells({n: cv2.erode(m.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
                            for n, m in masks.items()})
    known = np.isin(labels, body)
    counts = test.counts(centres[known])
    for c in ghosts:
        mine = centres[labels == c]
        assert test.own_shares(mine, counts)[2] > 0.5                 # cells of its own ...
        assert test.own_shares(mine, counts, None, seen)[2] < test.min_own   # ... where the camera sees the room
        assert test.verdict(mine, counts) is False and test.verdict(mine, counts, None, seen) is True
    for a, b in (body, body[::-1]):
        mine, other = centres[labels == a], test.counts(centres[labels == b])
        for cells in (seen, thin):
            assert test.own_shares(mine, other, None, cells)[2] > 0.5
            assert test.verdict(mine, other, None, cells) is False
    assert test.seen_cells(None) is None and test.seen_cells({"elsewhere": masks["c0"]}) is None


def test_a_person_alone_or_unseen_is_never_a_ghost():
    cameras = _cameras(3)
    body = _body_points(PEOPLE[0], step=0.05)
    test = GhostTest(cameras)
    assert test(body, np.zeros((0, 3))) is False
    assert test(body + (20.0, 0.0, 0.0), body) is False    # out of every view: nothing to judge


def test_the_cells_kernel_projects_as_the_camera_does():
    """The ghost test's one-pass projection (issue 26) gives the cells that
    ``Camera.project`` gives, lens distortion, points behind the camera and points
    outside the image included."""
    K = np.array([[520.0, 0.3, 330.0], [0.0, 515.0, 242.0], [0.0, 0.0, 1.0]])
    a = np.deg2rad(25)
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]) @ \
        np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)
    cam = Camera("c", 640, 480, K, np.array([-0.21, 0.08, 0.001, -0.002, 0.01]), R, -R @ np.array([2.5, -1.0, 2.2]))
    pts = np.random.default_rng(3).uniform((-3, -6, -1), (8, 8, 4), (50000, 3))
    test = GhostTest([cam])
    cells, (h, w) = test._cells(cam, pts)
    uv = cam.project(pts) / test.cell
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    assert 1000 < ok.sum() < len(pts) - 1000 and np.isnan(uv).any()   # some in, some out, some behind
    uv = uv[ok].astype(np.int64)
    assert np.array_equal(cells, uv[:, 1] * w + uv[:, 0])
