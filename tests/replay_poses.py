"""A test-only source that publishes a poses.jsonl file as Poses messages, as the pose
stage would (loaded as a plugin kind: ``tests.replay_poses:ReplayPoses``).

It waits until every other worker of the layout is on the bus (so no sink misses the
first frames), then sends one frame each ``1 / rate`` seconds and ends its stream.
"""
import json
import time

import numpy as np

from app.messages import JOINTS, Poses
from workers.base import Worker


class ReplayPoses(Worker):
    KIND = "replay_poses"
    ORDER = 1
    PRODUCES = ("poses",)
    DEFAULTS = {"file": "", "rate": 50.0}

    def setup(self):
        with open(self.params["file"], encoding="utf-8") as fh:
            self.records = [json.loads(line) for line in fh if line.strip()]
        self.next = 0
        self.wait_for_others(60.0)
        time.sleep(0.3)

    def produce(self):
        if self.next >= len(self.records):
            return False
        rec = self.records[self.next]
        poses = rec["poses"]
        self.publish(self.keys.poses(), Poses(
            frame=rec["frame"], stamp=time.time(), t=rec["t"],
            tracks=np.array([p["track"] for p in poses], np.int64),
            joints=np.array([[p["joints"][j] for j in JOINTS] for p in poses], np.float64).reshape(-1, 15, 3),
            active=np.array([[p["active"][j] for j in JOINTS] for p in poses], bool).reshape(-1, 15)))
        self.next += 1
        self.sleep(1.0 / self.params["rate"])
        return True

    def stream_info(self):
        return len(self.records), self.records[0]["frame"] if self.records else 0, float(self.layout.run.fps or 0)
