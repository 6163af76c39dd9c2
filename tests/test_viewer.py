"""The meshcat viewer: its scene geometry, its commands, its server, and a real run
rendered by headless Chromium and checked pixel by pixel."""
import os
import re
import shutil
import signal
import subprocess
import threading
import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest
import umsgpack
import yaml

from app.bus import BusConfig, Keys, Publisher, decode_sample, open_session
from app.config import LayoutError, parse_layout
from app.messages import JOINTS, Poses, Stats, Tracks, Voxels
from app.viewer import three
from app.viewer.geometry import (LIMB_INDEX, LIMBS, ViewCamera, box_edges, default_view, ellipsoid_rings,
                                 floor_grid, frustum_corners, frustum_segments, limb_segments, point_size,
                                 rgb_floats, subsample, track_colour)
from app.viewer.scene import BACKGROUND, LIVE, ROOT, STATUS, Scene
from app.viewer.server import LatestWins, MeshcatServer, ServerError, page_url
from calibration import Camera
from tests.conftest import start_smartroom
from tests.synthetic import tiny_calibration, write_tiny_recording


# -- geometry ---------------------------------------------------------------------------

def test_box_edges_are_the_twelve_axis_aligned_edges():
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([5.0, 4.0, 2.5])
    e = box_edges(lo, hi)
    assert e.shape == (12, 2, 3)
    d = np.abs(e[:, 1] - e[:, 0])
    assert ((d > 0).sum(axis=1) == 1).all()                      # each along one axis
    assert sorted(np.round(d.sum(axis=1), 6)) == [2.5] * 4 + [4.0] * 4 + [5.0] * 4
    assert len({tuple(sorted(map(tuple, s))) for s in e}) == 12  # no edge twice
    assert ((e >= lo) & (e <= hi)).all()


def test_floor_grid_lies_inside_the_room_on_the_floor():
    g = floor_grid([0, 0, 0], [5, 4, 2.5], 1.0)
    assert g.shape == (4 + 3, 2, 3)
    assert (g[..., 2] == 0).all() and (g[..., 0] >= 0).all() and (g[..., 0] <= 5).all()


def _camera(dist=(0, 0, 0, 0, 0)):
    return Camera.look_at("cam0", [4.8, 3.8, 2.4], [2.5, 2.0, 0.9], 640, 480, hfov_deg=75, dist=dist)


def test_frustum_corners_project_to_the_image_corners_at_the_given_depth():
    cam = _camera()
    c, q = frustum_corners(cam, 0.4)
    np.testing.assert_allclose(c, cam.centre)
    np.testing.assert_allclose(cam.to_camera(q)[:, 2], 0.4)
    np.testing.assert_allclose(cam.project(q), [[-0.5, -0.5], [639.5, -0.5], [639.5, 479.5], [-0.5, 479.5]], atol=1e-6)
    segs = frustum_segments(cam, 0.4)
    assert segs.shape == (10, 2, 3)
    up = cam.to_camera(segs[-1, 0])   # the marker sits above the image's top edge (camera y down)
    assert cam.project(segs[-2, 1][None])[0, 1] < -0.5 and up[2] > 0


def test_limbs_join_all_fifteen_joints_in_one_tree():
    assert len(LIMBS) == 14 and LIMB_INDEX.shape == (14, 2)
    assert set(LIMB_INDEX.ravel()) == set(range(len(JOINTS)))
    parent = list(range(len(JOINTS)))

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i
    for a, b in LIMB_INDEX:
        ra, rb = root(a), root(b)
        assert ra != rb, "a limb closes a cycle"
        parent[ra] = rb


def test_limb_segments_grey_out_limbs_of_inactive_joints():
    joints = np.arange(45, dtype=float).reshape(15, 3)
    active = np.ones(15, bool)
    active[JOINTS.index("l_wrist")] = False
    segs, on = limb_segments(joints, active)
    assert segs.shape == (14, 2, 3)
    off = [LIMBS[i] for i in np.flatnonzero(~on)]
    assert off == [("l_elbow", "l_wrist")]
    i = LIMBS.index(("neck", "head"))
    np.testing.assert_array_equal(segs[i], joints[[JOINTS.index("neck"), JOINTS.index("head")]])
    assert limb_segments(joints)[1].all()


def test_subsample_keeps_surface_first_and_is_stable():
    assert subsample(100, 200) is None
    idx = subsample(10_000, 1000)
    assert len(idx) == 1000 and np.all(np.diff(idx) > 0)
    np.testing.assert_array_equal(idx, subsample(10_000, 1000))   # same voxels every frame
    surface = np.zeros(10_000, bool)
    surface[::20] = True                                         # 500 surface voxels: all of them
    np.testing.assert_array_equal(subsample(10_000, 1000, surface), np.flatnonzero(surface))
    surface[::4] = True                                          # 2500: thinned among the surface
    idx = subsample(10_000, 1000, surface)
    assert len(idx) == 1000 and surface[idx].all()
    assert point_size(0.02, 10_000, 10_000) == pytest.approx(0.02)
    assert point_size(0.02, 8000, 1000) == pytest.approx(0.04)
    assert point_size(0.02, 10**9, 1) == pytest.approx(0.05)     # capped


def test_colours_default_to_neutral():
    np.testing.assert_allclose(rgb_floats(np.array([[255, 0, 128]], np.uint8), 1), [[1.0, 0.0, 128 / 255]])
    neutral = rgb_floats(np.zeros((0, 3), np.uint8), 4)
    assert neutral.shape == (4, 3) and np.ptp(neutral, axis=0).max() == 0
    assert not np.allclose(track_colour(1), track_colour(2))


def test_ellipsoid_rings_lie_on_the_ellipsoid():
    a = np.array([0.3, 0.25, 0.9])
    r = ellipsoid_rings(a).reshape(-1, 3)
    np.testing.assert_allclose(((r / a) ** 2).sum(axis=1), 1.0, atol=1e-9)
    assert r[:, 2].max() == pytest.approx(0.9) and r[:, 0].max() == pytest.approx(0.3)


def test_view_projects_its_target_to_the_centre_and_fits_the_room():
    v = ViewCamera(np.array([0.0, -5.0, 2.0]), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(v.project([[0, 0, 1]], 800, 600), [[400, 300]])
    px = v.project([[0, 0, 1.5], [1, 0, 1]], 800, 600)
    assert px[0, 1] < 300 and px[1, 0] > 400                     # z up is up, +x is right from -y
    assert np.isnan(v.project([[0, -6, 2]], 800, 600)).all()     # behind the eye
    corners = box_edges([0, 0, 0], [5, 4, 2.5]).reshape(-1, 3)
    view = default_view(corners, aspect=4 / 3)
    px = view.project(corners, 800, 600)
    assert (px[:, 0] >= 0).all() and (px[:, 0] <= 800).all() and (px[:, 1] >= 0).all() and (px[:, 1] <= 600).all()
    span = px.max(axis=0) - px.min(axis=0)
    assert span[0] > 0.6 * 800 or span[1] > 0.6 * 600           # and fills the view
    assert view.eye[2] > 2.5                                     # from above


# -- commands and scene ---------------------------------------------------------------------

def test_point_cloud_sends_uint8_colours_normalised():
    obj = three.points(np.zeros((5, 3)), np.full((5, 3), 200, np.uint8), size=0.03)
    attrs = obj["geometries"][0]["data"]["attributes"]
    assert attrs["position"]["type"] == "Float32Array" and attrs["position"]["itemSize"] == 3
    assert len(attrs["position"]["array"].data) == 5 * 3 * 4
    assert attrs["color"]["type"] == "Uint8Array" and attrs["color"]["normalized"] is True
    assert obj["materials"][0]["vertexColors"] is True and obj["object"]["type"] == "Points"
    umsgpack.packb(three.set_object("/meshcat/x", obj))          # what the server receives


def test_text_label_is_a_png_sprite():
    png, aspect = three.text_image("cam0", (1.0, 0.5, 0.0))
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape[2] == 4 and aspect == pytest.approx(img.shape[1] / img.shape[0]) and aspect > 1.5
    assert (img[..., 3] == 0).any() and (img[..., 3] == 255).any()    # transparent around the letters
    s = three.sprite(png, 0.05, aspect, [1, 2, 3])
    assert s["object"]["type"] == "Sprite" and s["images"][0]["url"].startswith("data:image/png;base64,")
    assert s["materials"][0]["depthTest"] is False
    assert s["object"]["matrix"][12:15] == [1.0, 2.0, 3.0]            # column-major: translation last


def _kinds(cmds):
    return [(c["type"], c["path"]) for c in cmds]


def test_scene_draws_the_room_and_cameras_once():
    cal = tiny_calibration()
    cmds = Scene(cal.room_min, cal.room_max, cal.cameras).setup()
    paths = [p for _, p in _kinds(cmds)]
    for p in ("room/box", "room/floor", "cameras/cam0/frustum", "cameras/cam0/label", "cameras/cam1/label"):
        assert f"{ROOT}/{p}" in paths
    assert ("set_transform", ROOT) in _kinds(cmds) and ("set_property", "/Grid") in _kinds(cmds)
    assert not any(p.startswith(f"{ROOT}/room") for p in [p for _, p in _kinds(Scene().setup())])
    scene = Scene()
    assert scene.room_from_grid([0, 0, 0], [100, 80, 50], 0.05)
    np.testing.assert_allclose(scene.room_max, [5, 4, 2.5])
    assert scene.room_from_grid([0, 0, 0], [10, 10, 10], 0.05) == []   # only the first grid


def _frame_group(cmds):
    """The frame on show that ``cmds`` put on the page: its ``userData`` and its children by name."""
    (cmd,) = [c for c in cmds if c["path"] == LIVE]
    assert cmd["type"] == "set_object" and cmd["object"]["object"]["type"] == "Group"
    obj = cmd["object"]
    return obj["object"]["userData"], {c["name"]: c for c in obj["object"]["children"]}, obj


def _attribute(obj, child, name, dtype=np.float32, width=3):
    """A child's geometry attribute (by name) from a group command's geometries."""
    geometry = next(g for g in obj["geometries"] if g["uuid"] == child["geometry"])
    return np.frombuffer(geometry["data"]["attributes"][name]["array"].data, dtype).reshape(-1, width)


def test_scene_frame_is_one_group_with_tracks_trails_and_removal():
    scene = Scene(trail=3)
    info, kids, _ = _frame_group(scene.frame(0, tracks=([1, 2], [[1, 1, 0.9], [2, 2, 0.9]])))
    assert info == {"frame": 0, "epoch": 0, "parts": ["tracks"]} and {"track 1", "track 2"} <= set(kids)
    assert [c["name"] for c in kids["track 1"]["children"]] == ["body", "label"]
    assert kids["track 2"]["matrix"][12:15] == [2.0, 2.0, 0.9]           # at its centroid
    for k in range(5):
        cmds = scene.frame(1 + k, tracks=([1, 2], [[1 + k, 1, 0.9], [2, 2, 0.9]]))
    scene.frame(5, tracks=([1, 2], [[5, 1, 0.9], [2, 2, 0.9]]))          # the same frame again: no new point
    assert len(scene.trails[1]) == 3 and scene.trails[1][-1][0] == 5
    info, kids, obj = _frame_group(cmds)
    assert info["frame"] == 5 and len(_attribute(obj, kids["trail 1"], "position")) == 3
    info, kids, _ = _frame_group(scene.frame(6, tracks=([2], [[2, 2, 0.9]])))
    assert "track 1" not in kids and "trail 1" not in kids                # gone with the frame it left in
    assert 1 not in scene.trails and scene.shown_tracks == {2}


def test_scene_skeletons_are_bones_and_joints_with_lost_limbs_grey_and_thin():
    from app.viewer.geometry import skeleton_mesh
    scene = Scene()
    joints = np.random.default_rng(0).uniform(0, 2, (2, 15, 3))
    active = np.ones((2, 15), bool)
    active[0, JOINTS.index("r_knee")] = False
    info, kids, obj = _frame_group(scene.frame(3, poses=([4, 5], joints, active)))
    assert info["parts"] == ["poses"] and {"skeleton 4", "skeleton 5"} <= set(kids)
    skel = kids["skeleton 4"]
    assert skel["type"] == "Mesh" and skel["userData"] == {"track": 4}
    material = next(m for m in obj["materials"] if m["uuid"] == skel["material"])
    assert material["depthTest"] is False                                # seen through the voxels
    verts = _attribute(obj, skel, "position")
    cols = _attribute(obj, skel, "color")
    # one prism of 6 sides per limb (12 vertices), then one octahedron per joint (6 vertices)
    assert len(verts) == 14 * 12 + 15 * 6 and len(cols) == len(verts)
    grey = [i for i in range(14) if not np.allclose(cols[12 * i], track_colour(4))]
    assert [LIMBS[i] for i in grey] == [("r_hip", "r_knee"), ("r_knee", "r_ankle")]
    for i in range(14):                                                 # a bone's thickness around its limb
        a, b = joints[0][LIMB_INDEX[i]]
        ring = verts[12 * i:12 * i + 6] - a
        d = (b - a) / np.linalg.norm(b - a)
        radius = np.linalg.norm(ring - np.outer(ring @ d, d), axis=1)
        np.testing.assert_allclose(radius, 0.011 if i in grey else 0.022, rtol=1e-4)
    knee = 14 * 12 + 6 * JOINTS.index("r_knee")
    np.testing.assert_allclose(verts[knee:knee + 6].mean(axis=0), joints[0, JOINTS.index("r_knee")], atol=1e-6)
    assert not np.allclose(cols[knee], track_colour(4))                 # the lost joint is grey
    _, kids, _ = _frame_group(scene.frame(4, poses=([5], joints[1:], active[1:])))
    assert "skeleton 4" not in kids and "skeleton 5" in kids
    assert skeleton_mesh(joints[1], None, (1, 0, 0), (0.5, 0.5, 0.5))[2].max() == 1.0


def test_scene_draws_a_frame_without_people_after_one_with_people():
    """Every run's first frame has no poses (frame 0 of any scene): the pose worker sends
    empty arrays, which once crashed the viewer (a reshape of size 0)."""
    from app.messages import decode
    scene = Scene()
    joints = np.random.default_rng(0).uniform(0, 2, (1, 15, 3))
    _, kids, _ = _frame_group(scene.frame(0, poses=([7], joints, np.ones((1, 15), bool))))
    assert "skeleton 7" in kids
    empty = Poses(frame=1, stamp=1.0, tracks=np.zeros(0, np.int64), joints=np.zeros((0, 15, 3)),
                  active=np.zeros((0, 15), bool))
    empty = decode(empty.to_bytes())                             # as it comes off the bus
    info, kids, _ = _frame_group(scene.frame(1, poses=(empty.tracks, empty.joints, empty.active)))
    assert info["parts"] == ["poses"] and kids == {} and scene.shown_poses == set()


def test_scene_voxels_are_thinned_for_display():
    scene = Scene(max_points=1000)
    n = 5000
    _, kids, obj = _frame_group(scene.frame(0, voxels=(np.random.default_rng(1).uniform(0, 2, (n, 3)),
                                                       np.zeros((n, 3), np.uint8), 0.02, None)))
    assert len(_attribute(obj, kids["voxels"], "position")) == 1000 and scene.voxels_shown == 1000
    assert kids["voxels"]["userData"] == {"total": n}
    assert next(m for m in obj["materials"] if m["uuid"] == kids["voxels"]["material"])["size"] > 0.02
    _, kids, obj = _frame_group(scene.frame(1, voxels=(np.zeros((3, 3)), np.zeros((0, 3), np.uint8), 0.02, None)))
    assert len(_attribute(obj, kids["voxels"], "color", np.uint8)) == 3            # uncoloured voxels: neutral
    info, kids, _ = _frame_group(scene.frame(2, voxels=(np.zeros((0, 3)), None, 0.02, None)))
    assert kids == {} and info["parts"] == ["voxels"] and scene.voxels_shown == 0
    status = scene.status("RTF 1.00", info={"frame": 2})
    assert _kinds(status)[0] == ("set_object", STATUS)
    assert status[0]["object"]["object"]["userData"] == {"text": "RTF 1.00", "frame": 2}


def _viewer_layout(params):
    """A layout with a viewer (and the grabber every layout needs)."""
    return parse_layout({"workers": [{"name": "grabber", "kind": "grabber"},
                                     {"name": "viewer", "kind": "viewer", "params": params}]})


def test_viewer_parameters_are_validated_by_the_layout():
    layout = _viewer_layout({"bind": "0.0.0.0"})
    p = layout.worker("viewer").params
    assert p["bind"] == "0.0.0.0" and p["port"] == 0 and p["max_rate"] > 10 and p["max_points"] > 0
    with pytest.raises(LayoutError, match="unknown parameter 'host'"):
        _viewer_layout({"host": "0.0.0.0"})
    with pytest.raises(LayoutError, match="must be an integer"):
        _viewer_layout({"port": "x"})


class _FakeServer:
    def __init__(self, bind, port, latest_only=()):
        self.url, self.clients, self.sent, self.port = f"http://{bind}:7000/static/", 0, [], 7000

    def start(self):
        return self

    def send(self, cmd):
        self.sent.append(cmd)

    def close(self):
        self.closed = True


def _shown(sent):
    """``(userData, children by name)`` of every frame the viewer put on the page, in order."""
    return [_frame_group([c])[:2] for c in sent if c["path"] == LIVE]


def test_viewer_draws_the_newest_frame_at_most_max_rate(monkeypatch):
    import workers.viewer as viewer_module

    monkeypatch.setattr(viewer_module, "MeshcatServer", _FakeServer)
    clock = [100.0]
    monkeypatch.setattr(viewer_module.time, "monotonic", lambda: clock[0])
    layout = _viewer_layout({"max_rate": 10.0})
    v = viewer_module.Viewer(layout.worker("viewer"), layout)
    v.setup()
    sent = v.server.sent
    assert any(c["path"] == "/Background" for c in sent)        # the page's look, before any frame
    for i in range(50):                                          # 2 s of tracks at 25 fps
        v.handle("k", Tracks(frame=i, stamp=time.time(), ids=np.array([1]), positions=np.array([[i * 0.01, 0, 0.9]])))
        v.tick()
        clock[0] += 0.04
    shown = _shown(sent)
    assert 18 <= len(shown) <= 21                                # ~10 per second, not 25
    assert v.ledger.done.count == len(shown)                     # drawn frames are the stage's output
    last = shown[-1][0]["frame"]
    v.flush()                                                    # the end of the stream: the newest is drawn
    info, kids = _shown(sent)[-1]
    assert info["frame"] == 49 and kids["track 1"]["matrix"][12] == pytest.approx(0.49)
    assert last < 49 and v.shown_frame == 49
    assert sent[-1]["path"] == STATUS and sent[-1]["object"]["object"]["userData"]["ended"] is True
    v.close()
    assert v.server.closed


def test_viewer_shows_voxels_tracks_and_skeletons_of_one_frame(monkeypatch):
    """The stages deliver a frame's parts at their own pace (tracks 2 frames after the
    voxels, poses 5 after): every frame drawn has the three parts of that one frame."""
    import workers.viewer as viewer_module

    monkeypatch.setattr(viewer_module, "MeshcatServer", _FakeServer)
    clock = [100.0]
    monkeypatch.setattr(viewer_module.time, "monotonic", lambda: clock[0])
    layout = _viewer_layout({"max_rate": 25.0})
    v = viewer_module.Viewer(layout.worker("viewer"), layout)
    v.setup()
    parts = {f: dict(zip(("voxels", "tracks", "poses"), (m for _, m in _frame_messages(f, 1.0 + 0.05 * f))))
             for f in range(40)}
    for t in range(45):
        for kind, lag in (("voxels", 0), ("tracks", 2), ("poses", 5)):
            if 0 <= t - lag < 40:
                v.handle(kind, parts[t - lag][kind])
        clock[0] += 0.04
        v.tick()
    shown = _shown(v.server.sent)
    assert len(shown) > 25
    for info, kids in shown:
        f = info["frame"]
        if f >= 5:   # from the first frame every stage delivered on (before it, what had come)
            assert info["parts"] == ["voxels", "tracks", "poses"], info
            assert {"voxels", "track 1", "skeleton 1"} <= set(kids)
        if "track 1" in kids:                                    # whatever is drawn is of that frame
            assert kids["track 1"]["matrix"][12] == pytest.approx(1.0 + 0.05 * f)
    assert shown[-1][0]["frame"] == 39
    assert [i["frame"] for i, _ in shown] == sorted(i["frame"] for i, _ in shown)


def _through_the_loop(v, key, msg) -> bool:
    """``msg`` off the bus into viewer ``v`` as the worker loop hands it over (repeats
    skipped); whether it was handled."""
    from app.messages import decode
    msg = decode(msg.to_bytes())
    if v._repeated(key, msg):
        return False
    v._follow_epoch(msg)
    v.ledger.received(msg.frame, msg.stamp)
    v.handle(key, msg)
    return True


def _frame_messages(frame, x):
    now = time.time()
    joints = np.zeros((1, 15, 3)) + [x, 1.0, 1.0]
    return [("smartroom/voxels/reconstruction", Voxels(frame=frame, stamp=now, voxel_size=0.1, origin=[0, 0, 0],
                                                      dims=[50, 40, 25], indices=np.array([[int(x * 10), 10, 9]],
                                                                                          np.int32),
                                                      colours=np.zeros((0, 3), np.uint8), surface=np.zeros(0, bool))),
            ("smartroom/tracks/tracking", Tracks(frame=frame, stamp=now, ids=np.array([1]),
                                                 positions=np.array([[x, 1.0, 0.9]]))),
            ("smartroom/poses/pose", Poses(frame=frame, stamp=now, tracks=np.array([1]), joints=joints,
                                           active=np.ones((1, 15), bool)))]


def test_a_restarted_viewer_draws_every_frames_tracks_and_poses(monkeypatch, tmp_path):
    """After a restart the viewer draws whole frames again: tracks and poses of a frame
    whose voxels it drew once were skipped as repeats (452 of them in a run, and the view
    kept its first people; see also tests/test_repeats.py)."""
    import workers.viewer as viewer_module

    monkeypatch.setattr(viewer_module, "MeshcatServer", _FakeServer)
    clock = [100.0]
    monkeypatch.setattr(viewer_module.time, "monotonic", lambda: clock[0])
    layout = _viewer_layout({"max_rate": 50.0})
    layout.run.out = str(tmp_path)

    def incarnation(frames):
        v = viewer_module.Viewer(layout.worker("viewer"), layout)
        v._restore_state()
        v.setup()
        for f in frames:
            for key, msg in _frame_messages(f, 1.0 + 0.1 * f):
                assert _through_the_loop(v, key, msg), (v.incarnation, f, key)
            clock[0] += 0.04
            v.tick()
        v.flush()
        v._save_state()
        return v

    first = incarnation(range(0, 5))
    assert first.incarnation == 0
    v = incarnation(range(5, 12))                   # killed and started again: frames go on
    assert v.incarnation == 1 and v.repeats_skipped == 0
    info, kids = _shown(v.server.sent)[-1]
    assert info == {"frame": 11, "epoch": 0, "parts": ["voxels", "tracks", "poses"]}
    assert kids["track 1"]["matrix"][12] == pytest.approx(1.0 + 0.1 * 11)   # the newest frame's track
    assert "skeleton 1" in kids, "no skeleton drawn after the restart"


# -- the server -----------------------------------------------------------------------------

def _listening_address(port: int) -> str | None:
    """The IPv4 address a local TCP socket listens on at ``port`` (from /proc/net/tcp)."""
    with open("/proc/net/tcp") as fh:
        for line in fh.readlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            addr, p = local.split(":")
            if int(p, 16) == port and state == "0A":
                return ".".join(str(b) for b in reversed(bytes.fromhex(addr)))
    return None


class _Future:
    def __init__(self):
        self.callbacks, self.finished = [], False

    def done(self):
        return self.finished

    def add_done_callback(self, fn):
        self.callbacks.append(fn)

    def finish(self):
        self.finished = True
        for fn in self.callbacks:
            fn(self)


def test_a_slow_browser_gets_only_the_newest_voxels():
    written, futures = [], []

    def write(data):
        written.append(data)
        futures.append(_Future())
        return futures[-1]
    sender = LatestWins(write, latest_only=["/v"])
    sender.push("/v", b"v1")
    for k in range(2, 6):                      # the socket has not taken v1 yet
        sender.push("/v", b"v%d" % k)
        sender.push("/t", b"t%d" % k)          # everything else goes at once, in order
    assert written == [b"v1", b"t2", b"t3", b"t4", b"t5"]
    futures[0].finish()                        # v1 landed: only the newest waiting one follows
    assert written[-1] == b"v5" and written.count(b"v4") == 0
    futures[-1].finish()
    sender.push("/v", b"v6")
    assert written[-1] == b"v6"


@pytest.mark.skipif(not os.path.exists("/proc/net/tcp"), reason="reads listening sockets from /proc/net/tcp")
@pytest.mark.parametrize("bind", ["127.0.0.1", "0.0.0.0"])
def test_server_binds_where_asked_and_serves_the_page_itself(bind):
    server = MeshcatServer(bind, 0).start()
    try:
        assert 7000 <= server.port < 7100
        assert _listening_address(server.port) == bind
        page = urllib.request.urlopen(f"http://127.0.0.1:{server.port}/static/", timeout=10).read().decode()
        assert "MeshCat" in page and 'src="main.min.js"' in page    # three.js comes from this server
        js = urllib.request.urlopen(f"http://127.0.0.1:{server.port}/static/main.min.js", timeout=10).read()
        assert len(js) > 100_000
        server.send(three.set_object(f"{ROOT}/x", three.points(np.zeros((2, 3)))))
        with pytest.raises(ServerError, match="in use"):
            MeshcatServer(bind, server.port).start()
    finally:
        server.close()
    assert not server._thread.is_alive() and _listening_address(server.port) is None
    assert page_url("0.0.0.0", 7000).endswith(":7000/static/") and "0.0.0.0" not in page_url("0.0.0.0", 7000)


def test_a_second_server_takes_the_next_free_port():
    """Port 0 tries 7000, 7001, ...: a try whose port is taken (another viewer, a replay)
    must not spoil the next (its command socket's address was reused: 'Address already
    in use (addr=inproc://...)', and the viewer died)."""
    first = MeshcatServer("127.0.0.1", 0).start()
    try:
        second = MeshcatServer("127.0.0.1", 0).start()
        try:
            assert second.port > first.port
            second.send(three.set_object(f"{ROOT}/x", three.points(np.zeros((2, 3)))))
            page = urllib.request.urlopen(second.url, timeout=10).read().decode()
            assert "MeshCat" in page
        finally:
            second.close()
    finally:
        first.close()


# -- a real run, rendered -----------------------------------------------------------------------

VOXEL = 0.03
PERSON = np.array([2.4, 1.6])        # where the test's person stands (x, y)
SHIRT = (40, 200, 90)                # RGB of the voxels above the hips
TROUSERS = (70, 80, 235)             # RGB of the voxels below
TRACK_ID = 3


def _person():
    """A standing person of coloured voxels on a 3 cm grid, its track and its pose."""
    lo = tiny_calibration().room_min
    g = np.mgrid[-10:11, -10:11, 0:58].reshape(3, -1).T
    centres = lo + (g + 0.5) * VOXEL + np.r_[PERSON - lo[:2], 0] - np.r_[0.5 * VOXEL, 0.5 * VOXEL, 0]
    d = centres[:, :2] - PERSON
    z = centres[:, 2]
    body = ((d[:, 0] / 0.2) ** 2 + (d[:, 1] / 0.14) ** 2 < 1) & (z < 1.5)
    head = (d ** 2).sum(axis=1) + (z - 1.6) ** 2 < 0.1 ** 2
    keep = body | head
    idx = np.round((centres[keep] - lo) / VOXEL - 0.5).astype(np.int32)
    colours = np.where(z[keep][:, None] > 0.9, SHIRT, TROUSERS).astype(np.uint8)
    joints = {"pelvis": [0, 0, .95], "neck": [0, 0, 1.45], "head": [0, 0, 1.62], "l_shoulder": [.2, 0, 1.42],
              "l_elbow": [.42, 0, 1.25], "l_wrist": [.55, 0, 1.45], "r_shoulder": [-.2, 0, 1.42],
              "r_elbow": [-.28, 0, 1.15], "r_wrist": [-.3, 0, .9], "l_hip": [.1, 0, .92], "l_knee": [.12, 0, .5],
              "l_ankle": [.12, 0, .08], "r_hip": [-.1, 0, .92], "r_knee": [-.12, 0, .5], "r_ankle": [-.12, 0, .08]}
    j = np.array([joints[n] for n in JOINTS]) + np.r_[PERSON, 0]
    active = np.ones(15, bool)
    active[JOINTS.index("l_wrist")] = False
    return idx, colours, j, active


def _publish_person(session, keys, stop: threading.Event):
    idx, colours, joints, active = _person()
    dims = np.ceil((tiny_calibration().room_max - tiny_calibration().room_min) / VOXEL).astype(int).tolist()
    pubs = {k: Publisher(session, k) for k in (keys.voxels(), keys.tracks(), keys.poses())}
    frame = 0
    epoch = time.time_ns() // 1_000_000   # a source's epoch is its start (a run refuses others)
    while not stop.is_set():
        now = time.time()
        pubs[keys.voxels()].put(Voxels(frame=frame, stamp=now, voxel_size=VOXEL, origin=[0.0, 0.0, 0.0], dims=dims,
                                       indices=idx, colours=colours, surface=np.zeros(0, bool), epoch=epoch))
        pubs[keys.tracks()].put(Tracks(frame=frame, stamp=now, ids=np.array([TRACK_ID], np.int64),
                                       positions=np.array([[*PERSON, 0.9]]), epoch=epoch))
        pubs[keys.poses()].put(Poses(frame=frame, stamp=now, tracks=np.array([TRACK_ID], np.int64),
                                     joints=joints[None], active=active[None], epoch=epoch))
        frame += 1
        stop.wait(0.1)
    for p in pubs.values():
        p.undeclare()


def _chromium():
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def _screenshot(chromium, url, png, profile, budget_ms=2500):
    """Load ``url`` in headless Chromium (software WebGL) and save an 800x600 screenshot."""
    cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader",
           "--enable-unsafe-swiftshader", "--disable-background-networking", "--disable-component-update",
           "--disable-sync", "--disable-extensions", "--no-first-run", "--hide-scrollbars",
           f"--user-data-dir={profile}", "--window-size=800,600", f"--virtual-time-budget={budget_ms}",
           f"--screenshot={png}", url]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _, err = proc.communicate(timeout=90)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)   # Chromium's helpers (zygote, GPU, renderer) too
        except ProcessLookupError:
            pass
        proc.wait()
    assert png.is_file(), f"Chromium wrote no screenshot: {err[-2000:]}"
    img = cv2.imread(str(png), cv2.IMREAD_COLOR)
    assert img is not None and img.shape == (600, 800, 3), img.shape if img is not None else None
    return img[..., ::-1].astype(int)   # RGB


def _near(img, rgb, tol=14):
    return (np.abs(img - np.asarray(rgb)) <= tol).all(axis=2)


def _box(px, margin, shape):
    x0, y0 = np.floor(px.min(axis=0) - margin).astype(int)
    x1, y1 = np.ceil(px.max(axis=0) + margin).astype(int)
    mask = np.zeros(shape[:2], bool)
    mask[max(0, y0):max(0, y1), max(0, x0):max(0, x1)] = True
    return mask


class _Run:
    """``smartroom run`` in the background, its output drained, always stopped at the end."""

    def __init__(self, *args):
        self.proc = start_smartroom(*args)
        self.out_lines, self.err_lines = [], []
        self.readers = [threading.Thread(target=self._drain, args=(s, ls), daemon=True)
                        for s, ls in ((self.proc.stdout, self.out_lines), (self.proc.stderr, self.err_lines))]
        for t in self.readers:
            t.start()

    @staticmethod
    def _drain(stream, lines):
        for line in stream:
            lines.append(line)

    def wait_for(self, pattern, timeout):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in list(self.err_lines):
                m = re.search(pattern, line)
                if m:
                    return m
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        raise AssertionError(f"no {pattern!r} on stderr:\n{''.join(self.err_lines)[-3000:]}")

    def stop(self, out, timeout=60):
        """Ctrl-C (the stream ends everywhere), then harder if it must; workers the
        launcher could not stop are killed by the pids they reported."""
        for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 10), (signal.SIGTERM, 10), (signal.SIGKILL, 10)):
            if self.proc.poll() is not None:
                break
            self.proc.send_signal(sig)
            try:
                self.proc.wait(wait)
            except subprocess.TimeoutExpired:
                pass
        try:
            workers = yaml.safe_load((out / "stats.json").read_text())["workers"]
        except (OSError, KeyError, TypeError, yaml.YAMLError):
            workers = {}
        for w in workers.values():
            if w.get("pid") and w["pid"] != os.getpid() and _alive(w["pid"]):
                os.kill(w["pid"], signal.SIGKILL)
        for t in self.readers:
            t.join(5)
        return self.proc.returncode


def _alive(pid):
    """A smartroom worker process with this pid is running (zombies are gone for our purpose)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            state = fh.read().split(")")[-1].split()[0]
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            cmdline = fh.read()
    except OSError:
        return False
    return state != "Z" and b"app.cli" in cmdline and b"worker" in cmdline


@pytest.mark.integration
@pytest.mark.browser
def test_viewer_renders_room_and_people_in_headless_chromium(tmp_path):
    chromium = _chromium()
    if chromium is None:
        pytest.skip("needs headless Chromium (Debian package: chromium)")
    rec = write_tiny_recording(tmp_path / "rec", frames=750)   # 30 s at 25 fps: runs while Chromium looks
    layout = {"room": "smartroom", "bus": {"listen": ["tcp/127.0.0.1:0"]},
              "workers": [{"name": "grabber", "kind": "grabber"}, {"name": "segmentation", "kind": "segmentation"},
                          {"name": "recorder", "kind": "recorder"},
                          {"name": "viewer", "kind": "viewer", "params": {"max_rate": 20.0}}]}
    layout_file = tmp_path / "layout.yaml"
    layout_file.write_text(yaml.safe_dump(layout))
    out = tmp_path / "out"
    run = _Run("run", "--recording", rec, "--layout", layout_file, "--out", out)
    stop_publishing = threading.Event()
    session = None
    figures = {}
    try:
        url = run.wait_for(r"viewer: open (http://127\.0\.0\.1:\d+/static/)", 60).group(1)
        # the room alone, while the pipeline runs
        empty = _screenshot(chromium, url, tmp_path / "empty.png", tmp_path / "profile")

        # people, published on the pipeline's bus as reconstruction, tracking and pose would
        bus = yaml.safe_load((out / "layout.yaml").read_text())["bus"]
        session = open_session(BusConfig(connect=bus["connect"]))
        keys = Keys(layout["room"])

        def on_stats(sample):
            msg = decode_sample(sample)
            if isinstance(msg, Stats):
                figures.update(msg.figures)
        sub = session.declare_subscriber(keys.stats("viewer"), on_stats)
        publisher = threading.Thread(target=_publish_person, args=(session, keys, stop_publishing), daemon=True)
        publisher.start()
        deadline = time.monotonic() + 30
        while figures.get("frames_out", 0) < 3 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert figures.get("frames_out", 0) >= 3, f"the viewer drew nothing: {figures}"
        # a still scene for the screenshot: Chromium's virtual time does not run while the page
        # receives a stream of updates (the viewer keeps the last scene; the pipeline goes on)
        stop_publishing.set()
        publisher.join(5)
        time.sleep(0.3)
        full = _screenshot(chromium, url, tmp_path / "scene.png", tmp_path / "profile")
        assert run.proc.poll() is None, "the pipeline ended before the screenshots"
    finally:
        stop_publishing.set()
        if session is not None:
            time.sleep(0.2)
            session.close()
        rc = run.stop(out)
    assert rc == 0, "".join(run.err_lines)[-3000:]

    # where things are on screen: the viewer's own default view of this room
    cal = tiny_calibration()
    scene = Scene(cal.room_min, cal.room_max, cal.cameras)
    scene.room()
    view = scene.view
    shape = full.shape
    background = np.round(np.asarray(BACKGROUND) * 255)
    for img in (empty, full):
        assert _near(img, background, 3).mean() > 0.5          # a plain background around the room

    # the room: its twelve edges and the camera frustums are drawn, in both shots
    edges = box_edges(cal.room_min, cal.room_max)
    samples = np.concatenate([e[0] + np.linspace(0.05, 0.95, 20)[:, None] * (e[1] - e[0]) for e in edges])
    px = np.round(view.project(samples, 800, 600)).astype(int)
    inside = (px[:, 0] >= 2) & (px[:, 0] < 798) & (px[:, 1] >= 2) & (px[:, 1] < 598)
    for img in (empty, full):
        drawn = ~_near(img, background, 6)
        hits = [drawn[y - 2:y + 3, x - 2:x + 3].any() for x, y in px[inside]]
        assert np.mean(hits) > 0.85, np.mean(hits)
        for cam in cal.cameras:
            frustum = view.project(frustum_segments(cam, 0.4)[:4].reshape(-1, 3), 800, 600)
            x, y = np.round(frustum.mean(axis=0)).astype(int)
            assert _near(img[y - 25:y + 26, x - 25:x + 26], (255, 255, 255), 40).sum() > 20, cam.name

    # the person: voxels in their own colours, the track's ellipsoid, label and skeleton in its colour
    idx, colours, joints, _ = _person()
    centres = (idx + 0.5) * VOXEL
    person = _box(view.project(centres, 800, 600), 8, shape)
    around = _box(view.project(np.concatenate([centres, joints, [[*PERSON, 2.1]]]), 800, 600), 30, shape)
    track_rgb = np.round(track_colour(TRACK_ID) * 255)
    for rgb in (SHIRT, TROUSERS):
        assert _near(full, rgb)[person].sum() > 150, rgb
        assert _near(full, rgb)[~around].sum() < 10, rgb           # nowhere else
        assert _near(empty, rgb).sum() < 10, rgb
    assert _near(full, track_rgb)[around].sum() > 60
    assert _near(empty, track_rgb).sum() < 10
    # the RTF status line at the top of the view
    top = ~_near(full[:45, 200:600], background, 20)
    assert top.sum() > 100

    # the viewer and its page server are gone with the pipeline: nothing left behind
    with pytest.raises((urllib.error.URLError, ConnectionError, OSError)):
        urllib.request.urlopen(url, timeout=5)
    pid = figures.get("pid")
    assert pid and not _alive(pid)
    stats = yaml.safe_load((out / "stats.json").read_text())
    assert stats["workers"]["viewer"]["frames_out"] >= 3 and stats["workers"]["viewer"]["url"] == url
