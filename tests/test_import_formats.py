"""Every importer on small files the test writes from known cameras, following each
format's documented convention independently of the reader: the imported cameras must
project world points to the same pixels (< 0.1 px). Bad files: one line, file and field."""
import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from calibration import Calibration, Camera, load_calibration
from calibration.loader import save_calibration
from calibration.formats import FormatError, read_cameras, write_opencv, write_toml
from calibration.transform import turned
from tests.conftest import smartroom

POINTS = np.random.default_rng(3).uniform([0.5, 0.5, 0.0], [4.5, 3.5, 2.0], (200, 3))


def known_cameras(tangential=True):
    """Three cameras of different sizes, one portrait, with distortion."""
    d = (-0.11, 0.04, 0.0007, -0.0004, 0.01) if tangential else (-0.11, 0.04, 0.0, 0.0, 0.01)
    a = Camera.look_at("cam0", [0.2, 0.2, 2.6], [2.5, 2.0, 0.8], 640, 480, 70, dist=d)
    b = Camera.look_at("cam1", [4.8, 0.3, 2.4], [2.5, 2.0, 0.8], 1920, 1088, 80, dist=d)
    c = Camera.look_at("cam2", [2.5, 3.9, 2.5], [2.5, 1.5, 0.8], 1088, 1920, 60, dist=d)
    # give one camera a non-centred principal point and fx != fy
    K = a.K.copy()
    K[0, 2] += 7.3
    K[1, 2] -= 4.1
    K[1, 1] *= 1.002
    a = Camera(a.name, a.width, a.height, K, a.dist, a.R, a.t)
    return [a, b, c]


def assert_same_projection(truth, got, tol=0.1):
    assert [c.name for c in got] == [c.name for c in truth]
    for a, b in zip(truth, got):
        assert (b.width, b.height) == (a.width, a.height), b.name
        vis = a.sees(POINTS)
        assert vis.sum() > 20
        err = np.linalg.norm(a.project(POINTS[vis]) - b.project(POINTS[vis]), axis=1).max()
        assert err < tol, f"{a.name}: {err:.4f} px"


def test_opencv_yaml_and_xml(tmp_path):
    truth = known_cameras()
    files = []
    for i, c in enumerate(truth):
        p = tmp_path / (f"{c.name}.yml" if i != 1 else f"{c.name}.xml")
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", c.width)
        fs.write("image_height", c.height)
        fs.write("camera_matrix", c.K)
        fs.write("distortion_coefficients", c.dist.reshape(1, 5))
        if i == 0:
            fs.write("R", c.R)
        else:
            fs.write("rvec", cv2.Rodrigues(c.R)[0])
        fs.write("tvec", c.t.reshape(3, 1))
        fs.release()
        files.append(str(p))
    fmt, got = read_cameras(files)
    assert fmt == "opencv"
    assert_same_projection(truth, got.cameras)


def _toml_text(cams, scale=1.0, name_key="name"):
    out = []
    for i, c in enumerate(cams):
        rv = cv2.Rodrigues(c.R)[0].ravel()
        out += [f"[cam_{i}]", f'{name_key} = "{c.name}"', f"size = [ {float(c.width)}, {float(c.height)},]",
                "matrix = [ " + ", ".join("[ " + ", ".join(repr(float(v)) for v in row) + ",]" for row in c.K) + ",]",
                "distortions = [ " + ", ".join(repr(float(v)) for v in c.dist[:4]) + ",]",
                "rotation = [ " + ", ".join(repr(float(v)) for v in rv) + ",]",
                "translation = [ " + ", ".join(repr(float(v) * scale) for v in c.t) + ",]", "fisheye = false", ""]
    return "\n".join(out + ["[metadata]", "adjusted = false", "error = 0.0", ""])


def test_toml_in_metres_and_millimetres(tmp_path):
    """Pose2Sim writes metres, aniposelib the board's unit (often mm): both come out in metres."""
    truth = known_cameras()
    truth = [Camera(c.name, c.width, c.height, c.K, np.r_[c.dist[:4], 0.0], c.R, c.t) for c in truth]
    (tmp_path / "Calib.toml").write_text(_toml_text(truth))
    (tmp_path / "anipose.toml").write_text(_toml_text(truth, 1000.0))
    fmt, got = read_cameras([tmp_path / "Calib.toml"])
    assert fmt == "toml" and "metres" in got.notes[0]
    assert_same_projection(truth, got.cameras)
    _, got = read_cameras([tmp_path / "anipose.toml"])
    assert "millimetres" in got.notes[0]
    assert_same_projection(truth, got.cameras)
    # Caliscope names its cameras by port
    (tmp_path / "config.toml").write_text(_toml_text(truth, name_key="port"))
    assert_same_projection(truth, read_cameras([tmp_path / "config.toml"])[1].cameras)


def _qca(cams, left=8, top=4, rotation=0):
    """A QTM .qca.txt written as QTM does: the full sensor in 1/64 pixel, the video a
    window of it starting at (left, top), the camera frame y up / z back, millimetres."""
    lines = ['<?xml version="1.0"?>', '<calibration source="test" type="regular">', "<cameras>",
             '<camera active="1" serial="ir1" model="Miqus M3" viewrotation="0"><fov_video left="0" top="0" '
             'right="10" bottom="10"/></camera>']
    for c in cams:
        M = np.diag([1.0, -1.0, -1.0]) @ c.R
        C = c.centre * 1000.0
        k1, k2, p1, p2, k3 = c.dist
        r = " ".join(f'r{i + 1}{j + 1}="{float(M[i, j])!r}"' for i in range(3) for j in range(3))
        lines += [f'<camera active="1" serial="{c.name}" model="Miqus Video" viewrotation="{rotation}" '
                  f'avg-residual="0.4">',
                  f'<fov_video left="{left}" top="{top}" right="{left + c.width - 1}" bottom="{top + c.height - 1}"/>',
                  f'<transform x="{float(C[0])!r}" y="{float(C[1])!r}" z="{float(C[2])!r}" {r}/>',
                  f'<intrinsic focallength="9" focalLengthU="{float(c.K[0, 0] * 64)!r}" focalLengthV="{float(c.K[1, 1] * 64)!r}" '
                  f'centerPointU="{float((c.K[0, 2] + left) * 64)!r}" centerPointV="{float((c.K[1, 2] + top) * 64)!r}" skew="0" '
                  f'radialDistortion1="{float(k1)!r}" radialDistortion2="{float(k2)!r}" radialDistortion3="{float(k3)!r}" '
                  f'tangentalDistortion1="{float(p1)!r}" tangentalDistortion2="{float(p2)!r}"/>', "</camera>"]
    return "\n".join(lines + ["</cameras>", "</calibration>"])


def test_qualisys_qca(tmp_path):
    truth = known_cameras()
    (tmp_path / "room.qca.txt").write_text(_qca(truth))
    fmt, got = read_cameras([tmp_path / "room.qca.txt"])
    assert fmt == "qualisys" and any("ir1" in n for n in got.notes)  # the marker camera is left out
    assert_same_projection(truth, got.cameras)


def test_quarter_turn_moves_pixels_as_the_image_turns():
    """A camera turned 90 degrees clockwise sees pixel (u, v) at (H - 1 - v, u)."""
    for c in known_cameras():
        t = turned(c, 90)
        assert (t.width, t.height) == (c.height, c.width)
        uv = c.project(POINTS)
        expect = np.stack([c.height - 1 - uv[:, 1], uv[:, 0]], axis=1)
        ok = c.sees(POINTS)
        assert np.abs(t.project(POINTS[ok]) - expect[ok]).max() < 1e-6
        back = turned(t, 270)
        assert np.abs(back.project(POINTS[ok]) - uv[ok]).max() < 1e-6


def test_qualisys_view_rotation_is_applied(tmp_path):
    truth = known_cameras()
    (tmp_path / "rot.qca").write_text(_qca(truth, rotation=90))
    _, got = read_cameras([tmp_path / "rot.qca"])
    assert_same_projection([turned(c, 90) for c in truth], got.cameras)
    _, kept = read_cameras([tmp_path / "rot.qca"], view_rotation="ignore")
    assert_same_projection(truth, kept.cameras)


def test_easymocap_intri_extri(tmp_path):
    truth = known_cameras()
    fi = cv2.FileStorage(str(tmp_path / "intri.yml"), cv2.FILE_STORAGE_WRITE)
    fe = cv2.FileStorage(str(tmp_path / "extri.yml"), cv2.FILE_STORAGE_WRITE)
    for fs in (fi, fe):
        fs.startWriteStruct("names", cv2.FileNode_SEQ)
        for c in truth:
            fs.write("", c.name)
        fs.endWriteStruct()
    for c in truth:
        fi.write(f"K_{c.name}", c.K)
        fi.write(f"dist_{c.name}", c.dist.reshape(1, 5))
        fi.write(f"H_{c.name}", c.height)
        fi.write(f"W_{c.name}", c.width)
        fe.write(f"R_{c.name}", cv2.Rodrigues(c.R)[0])
        fe.write(f"Rot_{c.name}", c.R)
        fe.write(f"T_{c.name}", c.t.reshape(3, 1))
    fi.release()
    fe.release()
    fmt, got = read_cameras([tmp_path / "intri.yml"])
    assert fmt == "easymocap"
    assert_same_projection(truth, got.cameras)


def test_vicon_xcp(tmp_path):
    truth = known_cameras(tangential=False)  # Vicon's model has radial terms only
    lines = ['<?xml version="1.0"?>', "<Cameras>"]
    for c in truth:
        q = Rotation.from_matrix(c.R.T).as_quat()  # camera orientation in the world, x y z w
        C = c.centre * 1000.0
        k1, k2, _, _, k3 = c.dist
        lines += [f'<Camera DEVICEID="{c.name}" TYPE="VIDEO" SENSOR_SIZE="{c.width} {c.height}" '
                  f'PIXEL_ASPECT_RATIO="{float(c.K[0, 0] / c.K[1, 1])!r}"><KeyFrames>',
                  f'<KeyFrame FOCAL_LENGTH="{float(c.K[0, 0])!r}" PRINCIPAL_POINT="{float(c.K[0, 2])!r} {float(c.K[1, 2])!r}" '
                  f'ORIENTATION="{" ".join(repr(float(v)) for v in q)}" POSITION="{float(C[0])!r} {float(C[1])!r} {float(C[2])!r}" '
                  f'VICON_RADIAL2="ThirdOrder {float(c.K[0, 2])!r} {float(c.K[1, 2])!r} {float(k1)!r} {float(k2)!r} {float(k3)!r}" WORLD_ERROR="0.2"/>',
                  "</KeyFrames></Camera>"]
    lines += ['<Camera DEVICEID="99" TYPE="MX" SENSOR_SIZE="1 1"/>', "</Cameras>"]
    (tmp_path / "room.xcp").write_text("\n".join(lines))
    fmt, got = read_cameras([tmp_path / "room.xcp"])
    assert fmt == "vicon"
    assert_same_projection(truth, got.cameras)


def test_humaneva_cal(tmp_path):
    truth = [c for c in known_cameras() if (c.width, c.height) == (640, 480)]
    files = []
    for c in truth:
        v = [c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], c.K[0, 1] / c.K[0, 0], *c.dist, *c.R.ravel(), *(c.t * 1000)]
        p = tmp_path / f"{c.name}.cal"
        p.write_text("\n".join(" ".join(repr(float(x)) for x in v[i:i + 3]) for i in range(0, len(v), 3)))
        files.append(p)
    fmt, got = read_cameras(files)
    assert fmt == "humaneva"
    assert_same_projection(truth, got.cameras)


def test_import_and_export_round_trip_on_the_command_line(tmp_path):
    truth = known_cameras()
    (tmp_path / "room.qca.txt").write_text(_qca(truth))
    out = tmp_path / "calibration.yaml"
    r = smartroom("calibrate", "import", tmp_path / "room.qca.txt", "--out", out, "--fps", 50,
                  "--room", "-3,-1.5,0,3,2,2.5")
    assert r.returncode == 0, r.stderr
    assert "room (given): x -3.00..3.00, y -1.50..2.00" in r.stdout
    calib = load_calibration(out)
    assert calib.fps == 50 and calib.room_min.tolist() == [-3, -1.5, 0]
    assert_same_projection(truth, list(calib.cameras))
    for fmt, target in (("toml", tmp_path / "back.toml"), ("opencv", tmp_path / "ocv")):
        r = smartroom("calibrate", "export", out, "--format", fmt, "--out", target)
        assert r.returncode == 0, r.stderr
    r = smartroom("calibrate", "import", tmp_path / "back.toml", "--out", tmp_path / "t.yaml", "--room=-3,-1.5,0,3,2,2.5")
    assert r.returncode == 0, r.stderr
    assert_same_projection(truth, list(load_calibration(tmp_path / "t.yaml").cameras))
    files = [f"{c.name}={tmp_path / 'ocv' / (c.name + '.yml')}" for c in truth]
    r = smartroom("calibrate", "import", *files, "--out", tmp_path / "o.yaml")
    assert r.returncode == 0, r.stderr
    assert "room (estimated" in r.stdout
    assert_same_projection(truth, list(load_calibration(tmp_path / "o.yaml").cameras))


def test_export_into_a_folder_that_does_not_exist_yet(tmp_path):
    """``--out`` in a folder not made yet: made (a traceback before), like the opencv folder;
    a path that cannot be written: one line."""
    calib = tmp_path / "calibration.yaml"
    save_calibration(Calibration(25.0, np.zeros(3), np.array([5.0, 4.0, 2.5]), tuple(known_cameras())), calib)
    target = tmp_path / "new" / "deeper" / "Calib.toml"
    r = smartroom("calibrate", "export", calib, "--format", "toml", "--out", target)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    assert_same_projection(known_cameras(), list(read_cameras([target])[1].cameras))
    r = smartroom("calibrate", "export", calib, "--format", "opencv", "--out", tmp_path / "new2" / "ocv")
    assert r.returncode == 0 and len(list((tmp_path / "new2" / "ocv").glob("*.yml"))) == len(known_cameras())
    (tmp_path / "file").write_text("")
    for fmt, out, message in (("toml", tmp_path / "file" / "x.toml", "cannot write there"),
                              ("toml", tmp_path / "new", "is a folder")):
        r = smartroom("calibrate", "export", calib, "--format", fmt, "--out", out)
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and message in r.stderr, r.stderr


def test_exported_toml_reads_back_with_tomllib(tmp_path):
    import tomllib

    truth = known_cameras()
    write_toml(truth, tmp_path / "x.toml")
    doc = tomllib.loads((tmp_path / "x.toml").read_text())
    assert doc["cam_2"]["size"] == [1088, 1920] and doc["cam_0"]["name"] == "cam0"
    write_opencv(truth[1], tmp_path / "one.xml")
    assert_same_projection(truth[1:2], read_cameras([f"cam1={tmp_path / 'one.xml'}"])[1].cameras)


BAD = {
    "Calib.toml": ('[cam_0]\nname = "a"\nsize = [640, 480]\nmatrix = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]\n'
                   "rotation = [0, 0, 0]\n", "[cam_0]: translation is missing"),
    "broken.toml": ("[cam_0\nname = 1", "not valid TOML"),
    "size.toml": ('[cam_0]\nsize = [640]\nmatrix = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]\nrotation = [0, 0, 0]\n'
                  "translation = [0, 0, 3]\n", "[cam_0] size: must have 2 numbers, got 1"),
    "room.qca.txt": ('<calibration><cameras><camera serial="c1" model="Miqus Video"><fov_video left="0" top="0" '
                     'right="639" bottom="479"/><transform x="0" y="0" z="0" r11="1" r12="0" r13="0" r21="0" r22="1" '
                     'r23="0" r31="0" r32="0" r33="1"/><intrinsic focalLengthV="1" centerPointU="1" '
                     'centerPointV="1"/></camera></cameras></calibration>', "camera c1: focalLengthU is missing"),
    "bad.qca": ("<calibration><cameras>", "not valid XML"),
    "room.xcp": ('<Cameras><Camera DEVICEID="7" TYPE="VIDEO" SENSOR_SIZE="640 480"><KeyFrames><KeyFrame '
                 'FOCAL_LENGTH="500" PRINCIPAL_POINT="320 240" POSITION="0 0 0"/></KeyFrames></Camera></Cameras>',
                 "camera 7 KeyFrame: ORIENTATION is missing"),
    "C1.cal": ("1 2 3", "fc cc alpha_c kc Rc Tc: must have 22 numbers, got 3"),
    "cam0.yml": ("%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n", "no camera matrix"),
}


@pytest.mark.parametrize("name", sorted(BAD))
def test_bad_files_are_one_line_naming_file_and_field(tmp_path, name):
    text, message = BAD[name]
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(FormatError) as e:
        read_cameras([p])
    msg = str(e.value)
    assert msg.startswith(str(p)) and message in msg and "\n" not in msg, msg


def test_bad_easymocap_and_cli_error_line(tmp_path):
    fi = cv2.FileStorage(str(tmp_path / "intri.yml"), cv2.FILE_STORAGE_WRITE)
    fe = cv2.FileStorage(str(tmp_path / "extri.yml"), cv2.FILE_STORAGE_WRITE)
    for fs in (fi, fe):
        fs.startWriteStruct("names", cv2.FileNode_SEQ)
        fs.write("", "01")
        fs.endWriteStruct()
    fi.write("K_01", np.eye(3))
    fe.write("R_01", np.zeros((3, 1)))
    fi.release()
    fe.release()
    r = smartroom("calibrate", "import", tmp_path / "intri.yml", "--out", tmp_path / "c.yaml", "--room=0,0,0,1,1,1")
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("smartroom: error:")]
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr
    assert f"{tmp_path / 'extri.yml'}: T_01: is missing" in lines[0]


def test_negative_room_bounds_and_bad_room(tmp_path):
    from calibration.room import parse_room

    lo, hi = parse_room("-3,-1.5,0,3,2,2.5")
    assert lo.tolist() == [-3, -1.5, 0] and hi.tolist() == [3, 2, 2.5]
    (tmp_path / "c.yaml").write_text(yaml.safe_dump({"fps": 25, "room": {"min": [0, 0, 0], "max": [1, 1, 1]},
                                                     "cameras": [known_cameras()[0].to_dict()]}))
    r = smartroom("calibrate", "import", tmp_path / "c.yaml", "--format", "smartroom", "--out", tmp_path / "d.yaml",
                  "--room", "-3,-1.5,0,3,-2,2.5")
    assert r.returncode == 2 and "each max must exceed its min" in r.stderr


def _video(path, fps, frames=3, size=(160, 120)):
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), float(fps), size)
    for i in range(frames):
        w.write(np.full((size[1], size[0], 3), 40 * i, np.uint8))
    w.release()


def test_import_takes_the_fps_from_the_recordings_videos(tmp_path):
    """A calibration with no frame rate (TOML), imported for a recording at 30 fps: the
    videos' fps is taken; videos that disagree are named on one line; image folders carry
    no fps, so --fps is asked for; --fps still wins, with a note when the videos differ."""
    from tests.synthetic import write_tiny_recording

    rec = write_tiny_recording(tmp_path / "rec", frames=3, fps=30.0, background=False)
    write_toml(list(load_calibration(rec).cameras), tmp_path / "Calib.toml")
    out = tmp_path / "calibration.yaml"
    r = smartroom("calibrate", "import", tmp_path / "Calib.toml", "--recording", rec, "--out", out)
    assert r.returncode == 0, r.stderr
    assert f"fps 30 from the videos of {rec} (videos/cam0.avi, videos/cam1.avi)" in r.stdout
    assert "25 assumed" not in r.stdout and load_calibration(out).fps == 30
    # a renamed camera has no video: said, with the fix
    r = smartroom("calibrate", "import", tmp_path / "Calib.toml", "--recording", rec, "--out", out,
                  "--rename", "cam1=side")
    assert r.returncode == 0 and "note: side has no video in" in r.stdout and "--rename OLD=NEW" in r.stdout
    # --fps is the user's word; a mismatch with the videos is noted
    r = smartroom("calibrate", "import", tmp_path / "Calib.toml", "--recording", rec, "--out", out, "--fps", 25)
    assert r.returncode == 0 and load_calibration(out).fps == 25
    assert f"note: --fps 25 given, but the videos of {rec} are 30 fps" in r.stdout
    # the videos disagree: one line naming them
    _video(rec / "videos" / "cam1.avi", 25)
    r = smartroom("calibrate", "import", tmp_path / "Calib.toml", "--recording", rec, "--out", tmp_path / "x.yaml")
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("smartroom: error:")]
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr
    assert f"{rec / 'videos'}: the videos disagree on their frame rate: cam0.avi 30, cam1.avi 25 fps; give --fps" \
        in lines[0]
    # image folders: no fps to take
    (tmp_path / "images" / "frames" / "cam0").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "images" / "frames" / "cam0" / "000000.png"), np.zeros((120, 160, 3), np.uint8))
    r = smartroom("calibrate", "import", tmp_path / "Calib.toml", "--recording", tmp_path / "images", "--out",
                  tmp_path / "x.yaml")
    assert r.returncode == 2 and "frames: image folders carry no frame rate: give --fps" in r.stderr
    # no recording: 25 assumed, as before, and the way to do better said
    r = smartroom("calibrate", "import", tmp_path / "Calib.toml", "--out", tmp_path / "x.yaml")
    assert r.returncode == 0 and "fps 25 assumed" in r.stdout and "--recording DIR" in r.stdout
