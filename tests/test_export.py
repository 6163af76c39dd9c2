"""Exports (BVH, C3D, TRC, CSV) of simulated people, read back with independent readers
and compared with the simulator's ground-truth joints (written as a poses.jsonl)."""
import json
import re

import numpy as np
import pytest
import yaml

from app.export import export_series
from app.export.axes import to_axes
from app.export.bvh import TO_BVH, matrix_zxy
from app.export.poses import load_poses, series_from_records
from app.export.skeleton import BONES
from app.messages import JOINTS
from tests.conftest import smartroom

FPS = 25.0
MM = 1e-3
DROP = ("l_elbow", "l_wrist")   # a dropped forearm in track 2, frames DROP_FRAMES
DROP_FRAMES = range(30, 50)


def groundtruth_records(scene: str, seconds: float, fps: float, id_offset: int = 0) -> list[dict]:
    """The simulator's ground-truth joints of a clip as poses.jsonl records (no rendering)."""
    from app.simulation.simulator import Simulator
    sim = Simulator(scene, fps=fps, seconds=seconds, width=64, height=48)
    recs = []
    for i in range(sim.frame_count()):
        gt = sim.groundtruth(i)
        recs.append({"frame": i, "t": gt["t"], "poses": [
            {"track": p["id"] + id_offset, "joints": p["joints"], "active": {j: True for j in JOINTS}}
            for p in gt["people"]]})
    return recs


@pytest.fixture(scope="session")
def results(tmp_path_factory):
    """A results folder: meeting3 (3 people walking, sitting, gesturing) and gesture1 (big arm
    gestures: arms out, raised, circles) 6 s at 25 fps, with a dropped forearm in track 2."""
    recs = groundtruth_records("meeting3", 6.0, FPS)
    extra = groundtruth_records("gesture1", 6.0, FPS, id_offset=10)
    for r, e in zip(recs, extra):
        r["poses"] += e["poses"]
    for r in recs:
        for p in r["poses"]:
            if p["track"] == 2 and r["frame"] in DROP_FRAMES:
                for j in DROP:
                    p["active"][j] = False
                    p["joints"][j] = [0.0, 0.0, 0.0]   # whatever a dropped limb reports
    out = tmp_path_factory.mktemp("results")
    (out / "poses.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    (out / "layout.yaml").write_text(yaml.safe_dump({"run": {"fps": FPS}}))
    return out


@pytest.fixture(scope="session")
def series(results):
    return load_poses(results)


@pytest.fixture(scope="session")
def exported(series, tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    return {fmt: export_series(series, fmt, out) for fmt in ("bvh", "c3d", "trc", "csv")}


def _compare(series, track, positions, frames=None, tol=1 * MM):
    """Max error (m) between read-back positions (F, 15, 3) and the active joints of ``track``."""
    tp = series.tracks[track]
    frames = tp.frames if frames is None else frames
    idx = frames - tp.first
    ok = tp.active[idx]
    err = np.linalg.norm(positions - tp.joints[idx], axis=-1)
    assert ok.sum() > 0.9 * ok.size or track == 2
    worst = float(np.max(err[ok]))
    assert worst < tol, (track, worst)
    return worst


# -- BVH ----------------------------------------------------------------------------------

def parse_bvh(text: str):
    """A small reader of our own: the hierarchy (name, parent, offset, channels, End Site)
    and the motion table."""
    tokens = text.split("MOTION")[0].split()
    bones, stack, i = [], [], 0
    while i < len(tokens):
        tok = tokens[i]
        if tok in ("ROOT", "JOINT"):
            bones.append({"name": tokens[i + 1], "parent": stack[-1] if stack else None, "end": None})
            i += 2
        elif tok == "End":
            bones[-1]["pending_end"] = True
            i += 2
        elif tok == "{":
            stack.append(bones[-1]["name"] if not bones[-1].get("pending_end") else "__end__")
            i += 1
        elif tok == "}":
            stack.pop()
            i += 1
        elif tok == "OFFSET":
            v = np.array([float(x) for x in tokens[i + 1:i + 4]])
            if bones[-1].get("pending_end") and stack[-1] == "__end__":
                bones[-1]["end"], bones[-1]["pending_end"] = v, False
            else:
                bones[-1]["offset"] = v
            i += 4
        elif tok == "CHANNELS":
            n = int(tokens[i + 1])
            bones[-1]["channels"] = tokens[i + 2:i + 2 + n]
            i += 2 + n
        else:
            i += 1
    motion = text.split("MOTION")[1].strip().splitlines()
    frames = int(motion[0].split(":")[1])
    frame_time = float(motion[1].split(":")[1])
    data = np.array([[float(x) for x in ln.split()] for ln in motion[2:]])
    assert data.shape == (frames, sum(len(b["channels"]) for b in bones))
    return bones, frame_time, data


def bvh_fk(bones, data) -> dict:
    """World positions (F, 3) of every joint, by forward kinematics of the parsed file."""
    F = len(data)
    pos, rot, col = {}, {}, 0
    for b in bones:
        ch = b["channels"]
        values = data[:, col:col + len(ch)]
        col += len(ch)
        p = np.zeros((F, 3))
        angles = {}
        for name, v in zip(ch, values.T):
            if name.endswith("position"):
                p[:, "XYZ".index(name[0])] = v
            else:
                angles[name[0]] = v
        order = "".join(n[0] for n in ch if n.endswith("rotation"))
        assert order == "ZXY"
        R = matrix_zxy(np.stack([angles["Z"], angles["X"], angles["Y"]], axis=-1))
        if b["parent"] is None:
            pos[b["name"]] = b["offset"] + p
            rot[b["name"]] = R
        else:
            q = b["parent"]
            pos[b["name"]] = pos[q] + rot[q] @ b["offset"]
            rot[b["name"]] = rot[q] @ R
    return pos


def _own(series, tp) -> slice:
    """The rows of a BVH file (on the run's timeline) that are the track's own frames."""
    return slice(tp.first - series.first, tp.first - series.first + len(tp.joints))


def test_bvh_forward_kinematics_reproduces_the_joints(series, exported):
    paths = exported["bvh"]
    assert [p.name for p in paths] == [f"track{k}.bvh" for k in sorted(series.tracks)]
    for path in paths:
        k = int(re.findall(r"\d+", path.stem)[0])
        bones, frame_time, data = parse_bvh(path.read_text())
        assert frame_time == pytest.approx(1 / FPS)
        assert [b["name"] for b in bones] == [b.name for b in BONES]
        assert bones[0]["channels"][:3] == ["Xposition", "Yposition", "Zposition"]
        pos = bvh_fk(bones, data)
        world = np.stack([pos[j] for j in JOINTS], axis=1) @ TO_BVH   # back to z-up
        tp = series.tracks[k]
        assert len(data) == series.count                             # the run's timeline (below)
        _compare(series, k, world[_own(series, tp)])
        # the person's limb lengths are the offsets
        thigh = np.linalg.norm(tp.joints[:, JOINTS.index("l_knee")] - tp.joints[:, JOINTS.index("l_hip")], axis=-1)
        knee = next(b for b in bones if b["name"] == "l_knee")
        assert np.linalg.norm(knee["offset"]) == pytest.approx(np.median(thigh), abs=0.2 * MM)


def test_bvh_opens_in_a_maintained_reader(series, exported):
    """bvhio (maintained, 2025) computes world positions by its own forward kinematics."""
    bvhio = pytest.importorskip("bvhio")
    for path in exported["bvh"]:
        k = int(re.findall(r"\d+", path.stem)[0])
        root = bvhio.readAsHierarchy(str(path))
        joints = {j.Name: j for j, *_ in root.layout()}
        assert set(JOINTS) <= set(joints)
        tp = series.tracks[k]
        frames = np.arange(0, len(tp.joints), 7)
        got = np.zeros((len(frames), len(JOINTS), 3))
        for n, f in enumerate(frames):
            root.loadPose(int(f + tp.first - series.first), recursive=True)
            for m, name in enumerate(JOINTS):
                got[n, m] = list(joints[name].PositionWorld)
        _compare(series, k, got @ TO_BVH, frames=tp.first + frames)


def test_bvh_parses_with_the_bvh_package(exported):
    """The older ``bvh`` reader (0.3) agrees on the hierarchy, channels and frame count."""
    from bvh import Bvh
    path = exported["bvh"][0]
    mocap = Bvh(path.read_text())
    assert mocap.get_joints_names() == [b.name for b in BONES]
    assert mocap.joint_channels("l_elbow") == ["Zrotation", "Xrotation", "Yrotation"]
    bones, _, data = parse_bvh(path.read_text())
    assert mocap.nframes == len(data)
    assert mocap.frame_joint_channel(5, "pelvis", "Yposition") == pytest.approx(data[5, 1])


def test_bvh_dropped_limb_holds_its_last_angles(series, exported):
    path = next(p for p in exported["bvh"] if p.stem == "track2")
    bones, _, data = parse_bvh(path.read_text())
    tp = series.tracks[2]
    col = {}
    c = 0
    for b in bones:
        col[b["name"]] = slice(c + len(b["channels"]) - 3, c + len(b["channels"]))
        c += len(b["channels"])
    before = DROP_FRAMES[0] - 1 - series.first
    for f in DROP_FRAMES:
        i = f - series.first
        for name in ("l_shoulder", "l_elbow"):   # the upper arm ends at the dropped elbow
            assert np.array_equal(data[i, col[name]], data[before, col[name]]), (f, name)
        # and the rest of the body keeps moving
    moved = np.abs(data[DROP_FRAMES[-1] - series.first, :3] - data[before, :3]).max()
    assert moved > 0.05
    pos = bvh_fk(bones, data)
    world = np.stack([pos[j] for j in JOINTS], axis=1) @ TO_BVH
    _compare(series, 2, world[_own(series, tp)])   # active joints, the dropped frames included, within 1 mm


def test_bvh_files_of_a_run_share_its_timeline(results, tmp_path):
    """Blender imports every BVH at its frame 1: each file starts at the run's first frame
    and has the run's frame count, the person held at their first pose until they come in
    and at their last after they leave (read back with bvhio)."""
    bvhio = pytest.importorskip("bvhio")
    recs = [json.loads(line) for line in open(results / "poses.jsonl")]
    for r in recs:   # track 11 leaves at frame 110; meeting3's person 1 comes in late
        r["poses"] = [p for p in r["poses"] if p["track"] != 11 or r["frame"] <= 110]
    series = series_from_records(recs, FPS)
    late, early = series.tracks[1], series.tracks[11]
    assert late.first > series.first + 25 and early.first + len(early.joints) - 1 == 110 < series.last
    paths = {p.stem: p for p in export_series(series, "bvh", tmp_path)}
    read = {k: bvhio.readAsBvh(str(paths[f"track{k}"])) for k in (1, 11)}
    for k, bvh in read.items():
        assert bvh.FrameCount == series.count and bvh.FrameTime == pytest.approx(1 / FPS), k
    roots = {}
    for k in (1, 11):
        root = bvhio.readAsHierarchy(str(paths[f"track{k}"]))
        joints = {j.Name: j for j, *_ in root.layout()}
        pelvis = []
        for f in range(series.count):
            root.loadPose(f, recursive=True)
            pelvis.append(list(joints["pelvis"].PositionWorld))
        roots[k] = np.array(pelvis) @ TO_BVH                # (F, 3) z-up, on the run's timeline
    p = JOINTS.index("pelvis")
    i = late.first - series.first                           # the late person: held until they come in
    np.testing.assert_allclose(roots[1][:i + 1], np.repeat(late.joints[:1, p], i + 1, axis=0), atol=1 * MM)
    np.testing.assert_allclose(roots[1][i + 20], late.joints[20, p], atol=1 * MM)   # then moving, in step
    j = 110 - series.first                                  # the one who left: held after
    np.testing.assert_allclose(roots[11][j:], np.repeat(early.joints[-1:, p], series.count - j, axis=0), atol=1 * MM)
    np.testing.assert_allclose(roots[11][50], early.joints[50 - early.first, p], atol=1 * MM)
    # the same frame number is the same instant in both files
    f = 100
    np.testing.assert_allclose(roots[1][f - series.first], late.joints[f - late.first, p], atol=1 * MM)
    np.testing.assert_allclose(roots[11][f - series.first], early.joints[f - early.first, p], atol=1 * MM)


# -- C3D, TRC, CSV --------------------------------------------------------------------------

def test_c3d_reads_back_through_ezc3d(series, exported):
    ezc3d = pytest.importorskip("ezc3d")
    (path,) = exported["c3d"]
    c = ezc3d.c3d(str(path))
    labels = c["parameters"]["POINT"]["LABELS"]["value"]
    assert labels == [f"{k}_{j}" for k in sorted(series.tracks) for j in JOINTS]
    assert c["parameters"]["POINT"]["RATE"]["value"][0] == FPS
    assert c["parameters"]["POINT"]["UNITS"]["value"] == ["mm"]
    pts = c["data"]["points"][:3] / 1000.0          # (3, P, F), NaN where residual -1
    res = c["data"]["meta_points"]["residuals"][0]  # (P, F)
    assert pts.shape[2] == series.count
    for n, k in enumerate(sorted(series.tracks)):
        tp = series.tracks[k]
        block = pts[:, n * 15:(n + 1) * 15, tp.first - series.first:tp.first - series.first + len(tp.joints)]
        _compare(series, k, block.transpose(2, 1, 0))
        r = res[n * 15:(n + 1) * 15, tp.first - series.first:tp.first - series.first + len(tp.joints)].T
        assert np.all((r < 0) == ~tp.active)
        assert np.all(np.isnan(block.transpose(2, 1, 0)[~tp.active]))
    # a track absent from a frame: every point invalid
    absent = [(k, f) for k, tp in series.tracks.items() for f in range(series.first, series.last + 1)
              if not tp.first <= f < tp.first + len(tp.joints)]
    assert absent   # meeting3's third person enters late
    k, f = absent[0]
    n = sorted(series.tracks).index(k)
    assert np.all(res[n * 15:(n + 1) * 15, f - series.first] < 0)


def parse_trc(path):
    lines = path.read_text().split("\n")
    assert lines[0].split("\t")[:3] == ["PathFileType", "4", "(X/Y/Z)"]
    head = dict(zip(lines[1].split("\t"), lines[2].split("\t")))
    markers = [m for m in lines[3].split("\t")[2:] if m]
    assert lines[4].split("\t")[2:5] == ["X1", "Y1", "Z1"]
    assert lines[5] == ""
    rows = [ln.split("\t") for ln in lines[6:] if ln]
    frames = np.array([int(r[0]) for r in rows])
    times = np.array([float(r[1]) for r in rows])
    xyz = np.array([[float(v) if v else np.nan for v in r[2:]] for r in rows]).reshape(len(rows), -1, 3)
    return head, markers, frames, times, xyz


def test_trc_reads_back(series, exported):
    for path in exported["trc"]:
        k = int(re.findall(r"\d+", path.stem)[0])
        head, markers, frames, times, xyz = parse_trc(path)
        tp = series.tracks[k]
        assert markers == list(JOINTS)
        assert head["Units"] == "mm" and float(head["DataRate"]) == FPS
        assert int(head["NumFrames"]) == len(frames) == len(tp.joints) and int(head["NumMarkers"]) == 15
        assert np.array_equal(frames, tp.frames)
        assert np.allclose(times, frames / FPS)
        world = xyz / 1000.0 @ np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # y-up -> z-up
        assert np.all(np.isnan(world[~tp.active]))
        _compare(series, k, world)


def test_trc_and_csv_can_be_written_z_up(series, tmp_path):
    (path,) = export_series(series.select(11), "trc", tmp_path / "p.trc", up="z")
    _, _, _, _, xyz = parse_trc(path)
    _compare(series, 11, xyz / 1000.0)
    assert np.nanmin(xyz[:, :, 2]) > -50   # z up: nothing below the floor


def test_csv_reads_back(series, exported):
    import csv
    (path,) = exported["csv"]
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert rows
    by = {}
    for r in rows:
        by.setdefault(int(r["track"]), []).append(r)
    assert sorted(by) == sorted(series.tracks)
    for k, rs in by.items():
        tp = series.tracks[k]
        frames = np.array([int(r["frame"]) for r in rs])
        pos = np.array([[[float(r[f"{j}_{c}"]) for c in "xyz"] for j in JOINTS] for r in rs])
        act = np.array([[r[f"{j}_active"] == "1" for j in JOINTS] for r in rs])
        present = np.isfinite(tp.joints[:, 0, 0])
        assert np.array_equal(frames, tp.frames[present])
        assert np.array_equal(act, tp.active[present])
        _compare(series, k, pos, frames=frames)


def test_axes_y_up_is_a_rotation():
    p = np.array([[1.0, 2.0, 3.0]])
    assert np.allclose(to_axes(p, "y"), [[1.0, 3.0, -2.0]])
    assert np.isclose(np.linalg.det(TO_BVH), 1.0)


# -- the command ----------------------------------------------------------------------------

def test_export_command_writes_every_format(results, series, tmp_path):
    out = tmp_path / "exp"
    r = smartroom("export", results, "--out", out)
    assert r.returncode == 0, r.stderr
    names = sorted(p.name for p in out.iterdir())
    tracks = sorted(series.tracks)
    assert names == sorted([f"track{k}.bvh" for k in tracks] + [f"track{k}.trc" for k in tracks]
                           + ["poses.c3d", "poses.csv"])
    r = smartroom("export", results, "--format", "trc", "--track", 11, "--out", tmp_path / "one.trc")
    assert r.returncode == 0, r.stderr
    one, full = (tmp_path / "one.trc").read_text(), (out / "track11.trc").read_text()
    assert one.split("\n", 1)[1] == full.split("\n", 1)[1]   # the same but for the file name in line 1


def test_export_leaves_out_short_tracks_and_says_so(results, tmp_path):
    """A tracker's brief false starts (6 and 12 frames here, as on the default scene) get no
    files of their own: ``--min-frames`` (default one second of frames) leaves them out."""
    recs = [json.loads(line) for line in open(results / "poses.jsonl")]
    for r in recs:
        ghost = next(p for p in r["poses"] if p["track"] == 11)
        for k, span in ((98, range(40, 52)), (99, range(10, 16))):
            if r["frame"] in span:
                r["poses"].append({**ghost, "track": k})
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "poses.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    (folder / "layout.yaml").write_text(yaml.safe_dump({"run": {"fps": FPS}}))
    r = smartroom("export", folder, "--format", "bvh", "--format", "trc", "--out", tmp_path / "a")
    assert r.returncode == 0, r.stderr
    assert "left out 2 tracks of fewer than 25 frames: 98 (12 frames), 99 (6 frames)" in r.stderr
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == sorted(
        f"track{k}.{f}" for k in (1, 2, 3, 11) for f in ("bvh", "trc"))
    r = smartroom("export", folder, "--format", "trc", "--min-frames", 0, "--out", tmp_path / "b")
    assert r.returncode == 0 and "left out" not in r.stderr
    assert {"track98.trc", "track99.trc"} <= {p.name for p in (tmp_path / "b").iterdir()}
    r = smartroom("export", folder, "--format", "trc", "--min-frames", 10, "--out", tmp_path / "c")
    assert "left out 1 track of fewer than 10 frames: 99 (6 frames)" in r.stderr
    r = smartroom("export", folder, "--format", "trc", "--track", 99, "--out", tmp_path / "d.trc")
    assert r.returncode == 0 and (tmp_path / "d.trc").is_file()          # asked for by name
    r = smartroom("export", folder, "--min-frames", 1000)
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("smartroom: error:")]
    assert r.returncode == 2 and len(lines) == 1 and "lower --min-frames" in lines[0], r.stderr


@pytest.mark.parametrize("args, message", [
    (["--track", "77"], "track 77 is not in the results"),
    (["--format", "bvh", "--out", "x.bvh"], "give a folder or --track K"),
])
def test_export_command_one_line_errors(results, tmp_path, args, message):
    r = smartroom("export", results, *args)
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("smartroom: error:")]
    assert r.returncode == 2 and len(lines) == 1 and message in lines[0], r.stderr
    r = smartroom("export", tmp_path / "nothing")
    assert r.returncode == 2 and "results folder not found" in r.stderr


def test_records_from_the_bus_equal_the_file(series, results):
    """The live exporter's records (built from Poses arrays) round like poses.jsonl."""
    from app.export.poses import pose_record
    tp = series.tracks[11]
    rec = pose_record(3, 3 / FPS, np.array([11]), tp.joints[3:4].astype(np.float32), tp.active[3:4])
    again = series_from_records([rec], FPS)
    assert np.array_equal(again.tracks[11].joints[0], tp.joints[3])
