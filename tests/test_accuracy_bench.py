"""smartroom bench accuracy's scoring (app/benchmarks/accuracy.py): detection by stature
band and activity, the longest time untracked, phantoms and their poses, the aggregate,
the held-out seeds; on hand-made ground truth and results."""
import json

import pytest

from app.benchmarks.accuracy import HELD_OUT_FROM, aggregate, format_report, parse_seeds, score_scene
from app.errors import InputError
from app.messages import JOINTS


def _joints(x, y):
    return {n: [x, y, 0.1 + 0.1 * k] for k, n in enumerate(JOINTS)}


def _write(folder, name, records):
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / name, "w") as fh:
        for r in records:
            fh.write(json.dumps(r) + "\n")


@pytest.fixture()
def scored(tmp_path):
    """50 frames at 25 fps: a 1.50 m person standing, tracked only from frame 30 (1.2 s
    untracked); a 1.95 m person walking, tracked throughout; a phantom track beside a
    chair for 10 frames, posed."""
    rec, res = tmp_path / "rec", tmp_path / "res"
    truth, tracks, poses = [], [], []
    for f in range(50):
        people = [{"id": 1, "centroid": [1.0, 1.0, 0.8], "height": 1.50, "activity": "standing",
                   "joints": _joints(1.0, 1.0)},
                  {"id": 2, "centroid": [3.0, 1.0 + 0.02 * f, 1.0], "height": 1.95, "activity": "walking",
                   "joints": _joints(3.0, 1.0 + 0.02 * f)}]
        truth.append({"frame": f, "t": f / 25, "people": people})
        t = [{"id": 7, "position": [3.0, 1.0 + 0.02 * f, 1.0]}]
        p = [{"track": 7, "joints": _joints(3.0, 1.0 + 0.02 * f), "active": {}}]
        if f >= 30:
            t.append({"id": 8, "position": [1.05, 1.0, 0.8]})
            p.append({"track": 8, "joints": _joints(1.0, 1.0), "active": {}})
        if 10 <= f < 20:
            t.append({"id": 9, "position": [4.5, 3.0, 0.5]})
            p.append({"track": 9, "joints": _joints(4.5, 3.0), "active": {}})
        tracks.append({"frame": f, "t": f / 25, "tracks": t})
        poses.append({"frame": f, "t": f / 25, "poses": p})
    _write(rec, "groundtruth.jsonl", truth)
    (rec / "simulation.json").write_text(json.dumps({"fps": 25.0}))
    _write(res, "tracks.jsonl", tracks)
    _write(res, "poses.jsonl", poses)
    return score_scene(rec, res)


def test_detection_by_stature_and_activity_and_the_longest_time_untracked(scored):
    assert scored["detection_by_stature"]["1.45-1.60"] == [20, 50]
    assert scored["detection_by_stature"]["1.90-2.00"] == [50, 50]
    assert scored["detection_by_activity"]["standing"] == [20, 50]
    assert scored["detection_by_activity"]["walking"] == [50, 50]
    assert scored["untracked_s"] == {"1": 1.2, "2": 0.0}


def test_phantoms_are_counted_and_their_poses_too(scored):
    assert scored["phantom_share"] == pytest.approx(10 / 100)
    assert scored["phantom_tracks"] == {"9": 10}
    assert scored["phantom_poses"] == 10
    assert scored["tracking"]["misses"] == 30 and scored["tracking"]["false_positives"] == 10
    assert scored["pose"]["mmta"] == pytest.approx(70 / 100)   # 30 person-frames without a pose


def test_the_aggregate_pools_detection_and_takes_mean_and_worst(scored):
    rows = [{"seed": 1000, "scene": {"cameras": 4, "people": 2, "statures": [1.5, 1.95]},
             "run": {"complete": True, "rtf": 1.1}, "score": scored},
            {"seed": 1001, "scene": {"cameras": 5, "people": 0, "statures": []},
             "run": {"complete": False, "error": "boom"}}]
    agg = aggregate(rows)
    assert agg["scored"] == 1 and agg["failed_runs"] == 1
    assert agg["mota"]["mean"] == agg["mota"]["worst"] == scored["tracking"]["mota"]
    assert agg["detection_by_stature"]["1.45-1.60"] == {"rate": 0.4, "person_frames": 50}
    assert agg["people_untracked_over_1s"] == 1 and agg["longest_untracked_s"] == 1.2
    text = format_report(rows, agg)
    assert "1000" in text and "run failed: boom" in text and "1.45-1.60 0.400 (50)" in text


def test_seeds_parse_and_the_held_out_split_is_1000():
    assert parse_seeds("1000:1003") == [1000, 1001, 1002]
    assert parse_seeds("5,7") == [5, 7]
    assert HELD_OUT_FROM == 1000
    for bad in ("a:b", "", "-1:3"):
        with pytest.raises(InputError):
            parse_seeds(bad)
