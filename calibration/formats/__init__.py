"""Calibration formats of other tools, read into :class:`calibration.Camera` lists and
written back. Each reader's docstring states its conventions and where they come from.

| format       | files                         | reader                          |
| ------------ | ----------------------------- | ------------------------------- |
| ``opencv``   | one ``.yml``/``.yaml``/``.xml`` per camera | :func:`read_opencv`  |
| ``toml``     | aniposelib/Anipose, Pose2Sim, FreeMoCap, Caliscope ``.toml`` | :func:`read_toml` |
| ``qualisys`` | QTM ``.qca`` / ``.qca.txt``   | :func:`read_qualisys`           |
| ``easymocap``| ``intri.yml`` + ``extri.yml`` | :func:`read_easymocap`          |
| ``vicon``    | ``.xcp``                      | :func:`read_vicon`              |
| ``humaneva`` | HumanEva-I ``.cal`` per camera| :func:`read_humaneva`           |
| ``smartroom``| our own ``calibration.yaml``  | :func:`calibration.load_calibration` |
"""
from __future__ import annotations

from pathlib import Path

from calibration.formats.common import FormatError, Imported
from calibration.formats.humaneva import read_humaneva
from calibration.formats.opencv import read_easymocap, read_opencv, write_opencv
from calibration.formats.qualisys import read_qualisys
from calibration.formats.toml import read_toml, write_toml
from calibration.formats.vicon import read_vicon

__all__ = ["FORMATS", "FormatError", "Imported", "guess_format", "read_cameras", "write_opencv", "write_toml",
           "read_opencv", "read_toml", "read_qualisys", "read_easymocap", "read_vicon", "read_humaneva"]

FORMATS = ("opencv", "toml", "qualisys", "easymocap", "vicon", "humaneva", "smartroom")


def guess_format(path) -> str:
    """The format of a file from its name, and from its first bytes where the name is not enough."""
    p = Path(path)
    name = p.name.lower()
    if p.is_dir() and (p / "intri.yml").is_file():
        return "easymocap"
    if name.endswith((".qca", ".qca.txt")):
        return "qualisys"
    if name.endswith(".xcp"):
        return "vicon"
    if name.endswith(".toml"):
        return "toml"
    if name.endswith(".cal"):
        return "humaneva"
    if name in ("intri.yml", "intri.yaml", "extri.yml", "extri.yaml"):
        return "easymocap"
    if not p.is_file():
        raise FormatError(f"{p}: file not found")
    head = p.read_bytes()[:4096].decode("utf-8", "replace")
    if name.endswith((".yml", ".yaml", ".xml")):
        if head.lstrip().startswith("%YAML") or "opencv_storage" in head or "opencv-matrix" in head:
            return "easymocap" if "names:" in head and "K_" in head else "opencv"
        if "cameras:" in head and "room:" in head:
            return "smartroom"
        if "<calibration" in head and "<camera " in head:
            return "qualisys"
        if "<Cameras" in head or "<Camera " in head:
            return "vicon"
        return "opencv"
    if "[cam" in head and "matrix" in head:
        return "toml"
    raise FormatError(f"{p}: cannot tell the format from the name; give --format ({', '.join(FORMATS)})")


def read_cameras(files, fmt: str | None = None, *, units: str = "auto", size=None, binning: int = 1,
                 view_rotation: str = "apply") -> tuple[str, Imported]:
    """Read cameras from ``files`` (a list of paths; ``NAME=PATH`` names a single-camera
    file's camera). Returns the format used and what was imported."""
    files = [str(f) for f in files]
    if not files:
        raise FormatError("no calibration file given")
    named = []
    for f in files:
        n, _, rest = f.partition("=")
        named.append((n, rest) if rest and not Path(f).exists() else (None, f))
    fmt = fmt or guess_format(named[0][1])
    if fmt not in FORMATS:
        raise FormatError(f"--format {fmt!r} is not one of {', '.join(FORMATS)}")
    single = fmt in ("opencv", "humaneva")
    if not single and len(files) > 1 and fmt != "easymocap":
        raise FormatError(f"{fmt} files hold every camera: give one file, got {len(files)}")
    if fmt == "opencv":
        cams, notes = [], []
        for n, f in named:
            got = read_opencv(f, name=n, units="m" if units == "auto" else units, size=size)
            cams += got.cameras
            notes += got.notes
        return fmt, Imported(cams, None, notes)
    if fmt == "humaneva":
        return fmt, read_humaneva([f for _, f in named], size=size)
    path = named[0][1]
    if fmt == "toml":
        return fmt, read_toml(path, units=units)
    if fmt == "qualisys":
        return fmt, read_qualisys(path, binning=binning, view_rotation=view_rotation)
    if fmt == "vicon":
        return fmt, read_vicon(path)
    if fmt == "easymocap":
        p = Path(path)
        intri = p if p.is_dir() or "intri" in p.name else p.with_name("intri.yml")
        extri = named[1][1] if len(named) > 1 else None
        return fmt, read_easymocap(intri, extri, units="m" if units == "auto" else units, size=size)
    from calibration.loader import load_calibration

    calib = load_calibration(path)
    return fmt, Imported(list(calib.cameras), calib.fps, [])
