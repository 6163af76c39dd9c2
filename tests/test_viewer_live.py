"""The live viewer over a whole run, as a user sees it: a headless Chromium page opened
before ``smartroom run --linger`` starts, left to follow the run, and read (its meshcat
scene as data) at the moments that matter: the empty room, people coming in, after the
viewer worker was killed and restarted, and after the stream ended (the page goes on to
the run's replay). Every frame the page showed is checked against the run's own result
files: its voxels, tracks and skeletons are those of one and the same frame."""
import json
import os
import signal
import time

import numpy as np
import pytest
import yaml

from app.bus import free_port
from app.results import iter_voxels
from app.viewer.geometry import subsample
from workers.viewer import Viewer
from tests.browser import Page, chromium, scene_state
from tests.conftest import simulated
from tests.test_viewer import _Run

pytestmark = [pytest.mark.integration, pytest.mark.browser]

SECONDS = 4.0          # enter2: the room empty for ~1 s, one person comes in, then a second (~2.8 s)
FRAMES = int(SECONDS * 25)
MAX_POINTS = Viewer.DEFAULTS["max_points"]
JOINT_VERTICES = 14 * 12   # a skeleton's vertices: 14 bones (6-sided prisms) first, then 15 joints (octahedra)


@pytest.fixture(scope="module")
def enter2(tmp_path_factory):
    return simulated(tmp_path_factory, "enter2", SECONDS, size="160x120")


class Watch:
    """The page's state over time (every poll), and full snapshots at chosen moments."""

    def __init__(self, page, run, shots):
        self.page, self.run, self.shots = page, run, shots
        self.states, self.snapshots = [], {}

    def poll(self, vertices=False):
        state = self.page.evaluate(scene_state(vertices), timeout=30)
        if state is not None:
            state["t"] = time.monotonic()
            self.states.append(state)
        return state

    def until(self, cond, timeout, what, vertices=False, period=0.25):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            state = self.poll(vertices)
            if state is not None and cond(state):
                return state
            assert self.run.proc.poll() is None, f"the run ended while waiting for {what}:\n" + \
                "".join(self.run.err_lines)[-3000:]
            time.sleep(period)
        last = self.states[-1] if self.states else None
        raise AssertionError(f"the page never showed {what} within {timeout} s; last state "
                             f"{ {k: v for k, v in (last or {}).items() if k != 'children'} }")

    def snapshot(self, name, cond, timeout, what):
        state = self.until(cond, timeout, what, vertices=True)
        self.snapshots[name] = state
        self.page.screenshot(self.shots / f"{name}.png")
        return state


def _people(state):
    kids = state.get("children") or {}
    return sorted(int(k.split()[1]) for k in kids if k.startswith("track ")), \
        sorted(int(k.split()[1]) for k in kids if k.startswith("skeleton "))


def _results(out):
    tracks = {r["frame"]: {t["id"]: t["position"] for t in r["tracks"]}
              for r in map(json.loads, open(out / "tracks.jsonl"))}
    poses = {r["frame"]: {p["track"]: p["joints"] for p in r["poses"]} for r in map(json.loads, open(out / "poses.jsonl"))}
    voxels = {}
    for v in iter_voxels(out / "voxels.bin"):   # as the viewer draws them: at most max_points, surface first
        centres = v.centres()
        keep = subsample(len(centres), MAX_POINTS, v.surface if v.surface is not None and len(v.surface) else None)
        voxels[v.frame] = centres if keep is None else centres[keep]
    return tracks, poses, voxels


def _check_frame(state, tracks, poses, voxels, frame=None):
    """What the page shows in ``state`` against the result files' frame ``frame`` (default:
    the frame the page says it shows): the same voxels, tracks and skeletons. The mismatches."""
    from app.messages import JOINTS
    f = state["frame"]["frame"] if frame is None else frame
    kids, bad = state["children"], []
    drawn = np.array(kids["voxels"]["vertices"]).reshape(-1, 3) if "voxels" in kids else np.zeros((0, 3))
    truth = voxels.get(f, np.zeros((0, 3)))
    if len(drawn) != len(truth) or not np.allclose(np.sort(drawn, axis=0), np.sort(truth, axis=0), atol=1e-4):
        bad.append(f"voxels: {len(drawn)} drawn, frame {f} has {len(truth)}")
    ids, skeletons = _people(state)
    if ids != sorted(tracks.get(f, {})):
        bad.append(f"tracks {ids}, frame {f} has {sorted(tracks.get(f, {}))}")
    for k in ids:
        if k in tracks.get(f, {}) and not np.allclose(kids[f"track {k}"]["position"], tracks[f][k], atol=2e-3):
            bad.append(f"track {k} at {kids[f'track {k}']['position']}, frame {f} has {tracks[f][k]}")
    if skeletons != sorted(poses.get(f, {})):
        bad.append(f"skeletons {skeletons}, frame {f} has {sorted(poses.get(f, {}))}")
    for k in skeletons:
        if k not in poses.get(f, {}):
            continue
        v = np.array(kids[f"skeleton {k}"]["vertices"]).reshape(-1, 3)
        centres = v[JOINT_VERTICES:].reshape(len(JOINTS), 6, 3).mean(axis=1)
        true = np.array([poses[f][k][j] for j in JOINTS])
        if not np.allclose(centres, true, atol=2e-3):
            bad.append(f"skeleton {k}: joints {np.abs(centres - true).max() * 1000:.0f} mm from frame {f}'s")
    return bad


def test_the_page_follows_a_whole_run_with_one_frame_on_show(enter2, tmp_path):
    binary = chromium()
    if binary is None:
        pytest.skip("needs headless Chromium (Debian package: chromium)")
    port = free_port()
    url = f"http://127.0.0.1:{port}/static/"
    out, shots = tmp_path / "out", tmp_path / "shots"
    shots.mkdir()
    page = Page(binary, tmp_path / "profile")
    page.goto(url)                                  # opened before the run: nothing is served there yet
    assert page.evaluate(scene_state(False)) is None
    run = _Run("run", "--recording", enter2, "--out", out, "--no-pace", "--linger",
               "--set", "recorder.voxels=true", "--set", f"viewer.port={port}")
    watch = Watch(page, run, shots)
    try:
        run.wait_for(rf"viewer: open {url}", 120)
        # a browser shows its error page until the address is served: reloaded, as a user would
        deadline = time.monotonic() + 30
        while (watch.poll() or {}).get("connected") is not True and time.monotonic() < deadline:
            page.goto(url)
            time.sleep(0.5)

        # 1. the empty room: the room is drawn, nobody in it
        empty = watch.snapshot("1-empty-room", lambda s: s["connected"] and s["room"], 30, "the room")
        assert _people(empty) == ([], []), empty["frame"]

        # 2. people coming in: a track with its skeleton
        entering = watch.snapshot("2-people-entering", lambda s: all(_people(s)), 240, "a person with a skeleton")

        # 3. the viewer worker killed mid-run: restarted, and the open page follows it
        workers = json.loads((out / "stats.json").read_text())["workers"]
        pid = workers["viewer"]["pid"]
        killed_at = entering["frame"]["frame"]
        os.kill(pid, signal.SIGKILL)
        watch.until(lambda s: not s["connected"], 30, "the lost connection")
        after = watch.snapshot("3-after-viewer-restart",
                               lambda s: s["connected"] and s["frame"] and s["frame"]["frame"] > killed_at + 2
                               and all(_people(s)), 120, "frames after the restart")
        while run.proc.poll() is None and not (watch.states[-1].get("replay")):   # more moments, to the end
            state = watch.poll(vertices=True)
            if state and state.get("frame") and state["frame"]["frame"] not in \
                    {s["frame"]["frame"] for s in watch.snapshots.values() if s.get("frame")}:
                watch.snapshots[f"during {state['frame']['frame']}"] = state
            time.sleep(0.7)
            if state and state.get("status", {}) and state["status"].get("ended"):
                break

        # 4. the end of the stream, then the replay of the run at the same address
        replay = watch.snapshot("4-replay-after-the-end", lambda s: s["connected"] and s["replay_frames"] == FRAMES,
                                120, "the whole replay")
        assert replay["url"] == url
    finally:
        page.close()
        rc = run.stop(out)
    assert rc == 0, "".join(run.err_lines)[-3000:]

    stats = json.loads((out / "stats.json").read_text())
    frames = stats["frames"]
    viewer = stats["workers"]["viewer"]
    assert stats["restarts"]["viewer"]["count"] == 1 and viewer["pid"] != pid
    assert viewer["repeats_skipped"] == 0                     # nothing taken for a repeat
    tracks, poses, voxels = _results(out)
    assert len(tracks) == len(poses) == len(voxels) == frames

    (tmp_path / "states.json").write_text(json.dumps(
        [{k: v for k, v in st.items() if k != "children"} for st in watch.states], default=str))
    # the page followed the run to its end: the last frame, then "stream ended", then the replay
    live = [s for s in watch.states if s.get("frame") and not s.get("replay")]
    assert live[-1]["frame"]["frame"] == frames - 1
    assert any((s.get("status") or {}).get("ended") for s in watch.states)
    first_replay = next(i for i, s in enumerate(watch.states) if s.get("replay"))
    assert all(not s.get("replay") for s in watch.states[:first_replay])
    assert replay["replay_frames"] == frames

    # every frame the page showed: voxels, tracks and skeletons of that one frame
    checked = {name: s for name, s in watch.snapshots.items() if s.get("frame") and not s.get("replay")}
    assert len(checked) >= 3 and any("during" in n for n in checked)
    for name, state in checked.items():
        assert _check_frame(state, tracks, poses, voxels) == [], (name, state["frame"])
        assert state["frame"]["parts"] == ["voxels", "tracks", "poses"], name
    # ... which says something: the frames before them differ (people move)
    assert any(_check_frame(s, tracks, poses, voxels, s["frame"]["frame"] - 2) for s in checked.values())
    # the frames shown went forward, and after the restart came frames after the kill
    shown = [s["frame"]["frame"] for s in live]
    assert shown == sorted(shown)
    assert after["frame"]["frame"] > killed_at
    # what the page showed at each moment, for the record
    report = {name: {"frame": s.get("frame"), "people": _people(s), "status": s.get("status"),
                     "replay": s.get("replay")} for name, s in watch.snapshots.items()}
    (tmp_path / "moments.json").write_text(json.dumps(report, indent=1, default=str))
    print(yaml.safe_dump(report))
