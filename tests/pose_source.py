"""A test-only source that publishes a simulated clip's voxels and true tracks, as the
reconstruction and tracking stages would (plugin kind ``tests.pose_source:ClipSource``),
so the pose worker is tested over the bus before and apart from the tracking stage.

The clip file (``.npz``): ``voxel_size``, ``origin`` (3,), ``dims`` (3,), ``frames``
(F,), ``offsets`` (F + 1,), ``indices`` (N, 3), ``track_offsets`` (F + 1,), ``ids``
(T,), ``positions`` (T, 3); optional ``misses`` (N,) uint8 (:class:`Voxels` ``misses``).
"""
import time

import numpy as np

from app.messages import Tracks, Voxels
from workers.base import Worker
from workers.flow import SourceFlow


class ClipSource(Worker):
    """Held back by the spine's flow control (:mod:`workers.flow`) as the grabber is: a
    frame goes once the pose workers have finished the one ``window`` frames before."""

    KIND = "clip_source"
    ORDER = 1
    PRODUCES = ("voxels", "tracks")
    DEFAULTS = {"file": "", "window": 2}

    def setup(self):
        self.clip = dict(np.load(self.params["file"]))
        self.next = 0
        self.epoch = self._epoch = time.time_ns() // 1_000_000
        self.flow = SourceFlow(self, self.params["window"], stall_timeout_s=120.0, ready_note_s=10.0)

    def produce(self):
        c = self.clip
        if self.next >= len(c["frames"]):
            return False
        k = self.next
        frame = int(c["frames"][k])
        if k == 0:
            self.flow.ready(frame)
        self.flow.hold(frame)
        t = frame / 25.0
        idx = c["indices"][c["offsets"][k]:c["offsets"][k + 1]].astype(np.int32)
        self.publish(self.keys.voxels(), Voxels(
            frame=frame, stamp=time.time(), t=t, voxel_size=float(c["voxel_size"]),
            origin=[float(v) for v in c["origin"]], dims=[int(v) for v in c["dims"]], cameras=[],
            indices=idx, colours=np.zeros((0, 3), np.uint8), surface=np.zeros(0, bool),
            misses=(c["misses"][c["offsets"][k]:c["offsets"][k + 1]] if "misses" in c else np.zeros(0, np.uint8))))
        a, b = c["track_offsets"][k], c["track_offsets"][k + 1]
        time.sleep(0.01)   # tracks follow the voxels, as from the tracking stage
        self.publish(self.keys.tracks(), Tracks(frame=frame, stamp=time.time(), t=t,
                                                ids=c["ids"][a:b].astype(np.int64),
                                                positions=c["positions"][a:b].astype(np.float64)))
        self.next += 1
        return True

    def close(self):
        self.flow.close()

    def stream_info(self):
        return len(self.clip["frames"]), int(self.clip["frames"][0]), 25.0


def run_clip(clip_file, tmp_path, recording, pose_workers: list[dict]) -> list[dict]:
    """Run ``clip_file`` through the pose workers given (``{"name", "params"}``) and the
    recorder over the bus; the records of ``poses.jsonl``."""
    import json

    import yaml

    from tests.conftest import smartroom
    layout = {"room": "smartroom", "bus": {"listen": ["tcp/127.0.0.1:0"]},
              "workers": [{"name": "source", "kind": "tests.pose_source:ClipSource",
                           "params": {"file": str(clip_file)}},
                          *({"kind": "pose", **w} for w in pose_workers),
                          {"name": "recorder", "kind": "recorder"}]}
    (tmp_path / "layout.yaml").write_text(yaml.safe_dump(layout))
    out = tmp_path / "out"
    r = smartroom("run", "--recording", recording, "--layout", tmp_path / "layout.yaml", "--headless",
                  "--out", out, timeout=180)
    assert r.returncode == 0, r.stderr[-3000:]
    return [json.loads(line) for line in (out / "poses.jsonl").read_text().splitlines()]
