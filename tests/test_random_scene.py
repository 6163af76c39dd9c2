"""Random scenes (issue 22): a seed draws a room, a rig, people of every stature and what
they do; the same seed is the same scene; people stay out of furniture and each other;
the recording says what was drawn and the ground truth what everyone does."""
from __future__ import annotations

import json
from collections import Counter

import numpy as np
import pytest

from app.simulation.random_scene import STATURE_RANGE, STYLES, random_scene


def test_a_seed_is_the_same_scene_every_time_and_seeds_differ():
    from app.simulation.simulator import Simulator
    assert random_scene(7).summary() == random_scene(7).summary()
    assert random_scene(7).summary() != random_scene(8).summary()
    a, b = Simulator("random", seed=4, fps=5.0), Simulator("random", seed=4, fps=5.0)
    assert a.groundtruth(20) == b.groundtruth(20)


def test_seeds_cover_statures_rigs_rooms_and_styles():
    drawn = [random_scene(s) for s in range(40)]
    statures = [p.shape.height for d in drawn for p in d.scene.people]
    assert STATURE_RANGE[0] <= min(statures) < 1.52 and 1.93 < max(statures) <= STATURE_RANGE[1]
    assert np.histogram(statures, bins=4, range=STATURE_RANGE)[0].min() >= 0.12 * len(statures)   # every band
    cams = Counter(len(d.calibration.cameras) for d in drawn)
    assert min(cams) == 3 and max(cams) == 8
    assert len({(c.width, c.height) for d in drawn for c in d.calibration.cameras}) >= 4
    assert len({d.room.size for d in drawn}) == len(drawn)
    assert {d.room.name for d in drawn} >= {"random-meeting", "random-benches", "random-desks", "random-empty"}
    assert set(s for d in drawn for s in d.styles) == set(STYLES)
    assert len({tuple(np.round(d.room.look[0:3], 3)) for d in drawn}) == len(drawn)   # walls of every colour
    people = Counter(len(d.scene.people) for d in drawn)
    assert min(people) == 1 and max(people) == 6
    for d in drawn:   # a lens never folds back inside its image
        for cam in d.calibration.cameras:
            k1, k2 = cam.dist[0], cam.dist[1]
            corner = np.hypot(*np.linalg.solve(cam.K, [cam.width, cam.height, 1.0])[:2])
            assert 1 + 3 * k1 * corner ** 2 + 5 * k2 * corner ** 4 > 0.2, (d.seed, cam.name)


@pytest.mark.parametrize("seed", [0, 7])
def test_random_people_stay_out_of_furniture_and_each_other_and_sit_crouch_gesture(seed):
    from app.simulation.checks import scene_intersections
    from app.simulation.simulator import Simulator
    sim = Simulator("random", seed=seed, fps=5.0)
    assert sim.conflicts == []
    assert scene_intersections(sim, step_s=0.4, spacing=0.03) == []
    doing = Counter(p["activity"] for i in range(sim.frame_count()) for p in sim.people(i) if sim.in_room(p))
    assert doing["walking"] and doing["standing"] and doing["sitting"]
    assert doing["crouching"] or doing["gesturing"]


def test_simulate_random_writes_a_recording_that_says_what_was_drawn(tmp_path):
    from app.recording import Recording
    from tests.conftest import smartroom
    r = smartroom("simulate", "--random", 3, "--seconds", 0.4, "--out", tmp_path / "rec", "--quiet", timeout=300)
    assert r.returncode == 0, r.stderr
    info = json.loads((tmp_path / "rec" / "simulation.json").read_text())
    drawn = random_scene(3)
    assert info["scene"] == "random" and info["seed"] == 3 and info["random"] == drawn.summary()
    rec = Recording(tmp_path / "rec")
    assert rec.frame_count == 10 and rec.calibration.names == drawn.calibration.names
    assert [(c.width, c.height) for c in rec.calibration.cameras] == \
        [(c.width, c.height) for c in drawn.calibration.cameras]
    truth = [json.loads(line) for line in open(tmp_path / "rec" / "groundtruth.jsonl")]
    people = [p for t in truth for p in t["people"]]
    assert people and all(p["activity"] in ("walking", "standing", "gesturing", "sitting", "crouching")
                          for p in people)
    assert {round(p["height"], 3) for p in people} <= {round(p.shape.height, 3) for p in drawn.scene.people}
