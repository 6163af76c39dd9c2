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
