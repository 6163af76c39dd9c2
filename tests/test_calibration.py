"""The calibration loader: round trip and one-line errors naming file, camera and field."""
import numpy as np
import pytest
import yaml

from calibration import CalibrationError, load_calibration, save_calibration
from tests.synthetic import tiny_calibration


def _write(tmp_path, data):
    p = tmp_path / "calibration.yaml"
    p.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return p


def _doc():
    return tiny_calibration(3).to_dict()


def test_round_trip(tmp_path):
    calib = tiny_calibration(3)
    save_calibration(calib, tmp_path / "calibration.yaml")
    back = load_calibration(tmp_path)
    assert back.names == ["cam0", "cam1", "cam2"] and back.fps == 25.0
    for a, b in zip(calib.cameras, back.cameras):
        np.testing.assert_allclose(a.K, b.K)
        np.testing.assert_allclose(a.R, b.R)
        np.testing.assert_allclose(a.dist, b.dist)


def test_reflection_is_not_a_rotation(tmp_path):
    d = _doc()
    d["cameras"][2]["R"] = (-np.array(d["cameras"][2]["R"])).tolist()
    p = _write(tmp_path, d)
    with pytest.raises(CalibrationError) as e:
        load_calibration(p)
    assert str(e.value) == f"{p}: camera cam2: R is not a rotation (det -1.0)"


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d["cameras"][1].pop("K"), "camera cam1: K is missing"),
    (lambda d: d["cameras"][0].update(K=[[1, 0], [0, 1]]), "camera cam0: K must be 3x3, got 2x2"),
    (lambda d: d["cameras"][0].update(width=-5), "camera cam0: width must be a positive integer"),
    (lambda d: d["cameras"][0].update(t=[1, 2]), "camera cam0: t must be 3, got 2"),
    (lambda d: d["cameras"][0].update(dist=[1, 2, 3]), "camera cam0: dist must list k1, k2, p1, p2[, k3]"),
    (lambda d: d["cameras"][1].update(name="cam0"), "camera name cam0 appears more than once"),
    (lambda d: d.update(fps=0), "fps must be a positive number"),
    (lambda d: d["room"].update(max=[0, 0, 0]), "room.max must exceed room.min"),
    (lambda d: d.update(cameras=[]), "cameras must be a non-empty list"),
    # what parses but no lens, camera or room is (issue 25: these loaded and gave empty runs or a MemoryError)
    (lambda d: d["cameras"][0]["K"][0].__setitem__(0, 1e300), "degree horizontal field of view"),
    (lambda d: d["cameras"][0]["K"][1].__setitem__(1, 0.01), "degree vertical field of view"),
    (lambda d: d["cameras"][1].update(dist=[1e30, 0, 0, 0, 0]), "camera cam1: dist 1e+30, 0, 0, 0, 0 is no lens"),
    (lambda d: d["cameras"][1].update(dist=[0, 0, 5, 0]), "is no lens's distortion"),
    (lambda d: d["cameras"][2].update(t=[0, 0, 1e6]), "camera cam2 stands"),
    (lambda d: d["room"].update(max=[1e4, 1e4, 3]), "a room of 1e+04 x 1e+04"),
])
def test_errors_name_the_field(tmp_path, mutate, message):
    d = _doc()
    mutate(d)
    p = _write(tmp_path, d)
    with pytest.raises(CalibrationError) as e:
        load_calibration(p)
    assert str(e.value).startswith(str(p)) and message in str(e.value)
    assert "\n" not in str(e.value)


def test_missing_and_unparsable_files(tmp_path):
    with pytest.raises(CalibrationError, match="file not found"):
        load_calibration(tmp_path / "nope.yaml")
    p = _write(tmp_path, "fps: [1, 2\ncameras: {")
    with pytest.raises(CalibrationError, match=r"not valid YAML \(line \d+\)"):
        load_calibration(p)


def test_check_lists_every_problem_at_once(tmp_path):
    """The loader stops at the first bad field (a run needs no more); ``check_calibration``
    (``smartroom calibrate check``) lists them all, with what parses but cannot be right."""
    from calibration.validate import check_calibration

    d = tiny_calibration(5).to_dict()
    d["fps"] = 0
    d["cameras"][0].pop("K")
    d["cameras"][1]["R"] = (-np.array(d["cameras"][1]["R"])).tolist()
    d["cameras"][2]["K"][0][2] = 900.0           # a principal point for a larger image
    d["cameras"][3]["K"][0][0] = d["cameras"][3]["K"][1][1] = 2.0  # a focal length in millimetres
    d["cameras"][4]["t"] = (-np.array(d["cameras"][4]["t"])).tolist()  # the centre mirrored through the origin
    p = _write(tmp_path, d)
    checked = check_calibration(p)
    expected = [f"{p}: fps must be a positive number, got 0",
                f"{p}: camera cam0: K is missing",
                f"{p}: camera cam1: R is not a rotation (det -1.0)",
                f"{p}: camera cam2: principal point (900.0, 59.5) lies outside its 160x120 image",
                f"{p}: camera cam3: fx 2 px gives a 177 degree field of view",
                f"{p}: camera cam4: the camera is 2.40 m under the floor"]
    for line in expected:
        assert sum(q.startswith(line) for q in checked.problems) == 1, (line, checked.problems)
    assert all("\n" not in q for q in checked.problems)
    assert checked.names == ["cam0", "cam1", "cam2", "cam3", "cam4"]
    assert [c.name for c in checked.cameras] == ["cam2", "cam3", "cam4"] and checked.calibration.fps == 0
    save_calibration(tiny_calibration(3), tmp_path / "ok.yaml")
    assert check_calibration(tmp_path / "ok.yaml").problems == []


@pytest.mark.integration
def test_a_room_too_big_for_the_voxel_grid_is_one_line_and_exit_2(tiny_recording, tmp_path):
    """150 m x 150 m at 4 cm is 10^9 voxels: the reconstruction says so before it builds
    tables that do not fit (issue 25: a 10 km room ended in a MemoryError traceback)."""
    import shutil

    from tests.conftest import smartroom

    rec = tmp_path / "rec"
    shutil.copytree(tiny_recording, rec)
    doc = yaml.safe_load((rec / "calibration.yaml").read_text())
    doc["room"] = {"min": [-70.0, -70.0, 0.0], "max": [80.0, 80.0, 3.0]}
    (rec / "calibration.yaml").write_text(yaml.safe_dump(doc))
    r = smartroom("run", "--recording", rec, "--headless", "--no-pace", "--out", tmp_path / "out", timeout=120)
    assert r.returncode == 2, r.stderr[-2000:]
    lines = [ln for ln in r.stderr.splitlines() if "cells, more than" in ln]
    assert lines and "reconstruction: the room (150 x 150 x 3 m) at 4 cm voxels" in lines[0], r.stderr[-2000:]
