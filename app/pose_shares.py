"""One frame's poses gathered from the pose workers that share the tracks.

A layout may run several pose workers, each posing its share of the tracks
(``pose.share: [k, n]``, issue 11: more people than one worker carries in real time is
a layout matter). Each publishes one ``Poses`` per frame, named by its ``worker``
field; the result writers (recorder, exporter) join them here before writing a frame,
so ``poses.jsonl`` holds every person of every frame, once.

A frame is complete when every pose worker has sent it or a later frame (a worker's
poses arrive in frame order, and one that gave a frame up has moved on). The end of
the stream completes the rest. A pose worker that is away for long (live) must not
hold everything back: past ``max_pending`` frames waiting, the oldest goes out with
the shares that came, and is counted in ``partial``.

The keypoints workers of a layout (each with its cameras) are joined the same way
(:class:`SharedKeypoints`: one message with every camera's keypoints of the frame).
"""
from __future__ import annotations

import numpy as np

from app.messages import JOINTS, Keypoints, Poses

__all__ = ["SharedPoses", "SharedKeypoints"]


class SharedPoses:
    def __init__(self, sources, max_pending: int = 100):
        self.sources = list(dict.fromkeys(sources))
        self.max_pending = int(max_pending)
        self.newest: dict[str, int] = {}
        self.pending: dict[int, dict[str, Poses]] = {}
        self.partial = 0

    def add(self, msg: Poses) -> list[Poses]:
        """Take one worker's poses; the frames now complete, in frame order."""
        if len(self.sources) <= 1 and not self.pending:
            return [msg]                      # one pose worker: nothing to join
        source = msg.worker or "?"
        if source not in self.sources:        # a pose worker the layout did not name (joined by hand)
            self.sources.append(source)
        self.newest[source] = max(msg.frame, self.newest.get(source, msg.frame))
        self.pending.setdefault(msg.frame, {})[source] = msg
        done = []
        for frame in sorted(self.pending):
            if all(self.newest.get(s, -1) >= frame for s in self.sources):
                done.append(self._join(self.pending.pop(frame)))
            elif len(self.pending) > self.max_pending:
                self.partial += 1
                done.append(self._join(self.pending.pop(frame)))
            else:
                break
        return done

    def flush(self) -> list[Poses]:
        """Everything still waiting (the stream has ended), in frame order."""
        out = [self._join(self.pending.pop(f)) for f in sorted(self.pending)]
        return out

    @staticmethod
    def _join(parts: dict[str, Poses]) -> Poses:
        msgs = list(parts.values())
        if len(msgs) == 1:
            return msgs[0]
        first = msgs[0]
        tracks = np.concatenate([np.asarray(m.tracks, np.int64).reshape(-1) for m in msgs])
        joints = np.concatenate([np.asarray(m.joints, np.float64).reshape(-1, len(JOINTS), 3) for m in msgs])
        active = np.concatenate([np.asarray(m.active, bool).reshape(-1, len(JOINTS)) for m in msgs])
        order = np.argsort(tracks, kind="stable")
        _, keep = np.unique(tracks[order], return_index=True)   # a track posed twice: the first
        order = order[keep]
        return Poses(frame=first.frame, epoch=first.epoch, stamp=min(m.stamp for m in msgs), t=first.t, worker="",
                     tracks=tracks[order], joints=joints[order], active=active[order])


class SharedKeypoints(SharedPoses):
    """A frame's :class:`~app.messages.Keypoints` from the keypoints workers, joined into
    one message (their cameras side by side; a track one worker did not see has zero
    confidence in its cameras)."""

    @staticmethod
    def _join(parts: dict[str, Keypoints]) -> Keypoints:
        msgs = list(parts.values())
        if len(msgs) == 1:
            return msgs[0]
        first = msgs[0]
        tracks = sorted({int(t) for m in msgs for t in np.asarray(m.tracks).reshape(-1)})
        cameras = [c for m in msgs for c in m.cameras]
        points = np.zeros((len(tracks), len(cameras), len(JOINTS), 3), np.float32)
        col = 0
        for m in msgs:
            for k, t in enumerate(np.asarray(m.tracks).reshape(-1)):
                points[tracks.index(int(t)), col:col + len(m.cameras)] = m.points[k]
            col += len(m.cameras)
        return Keypoints(frame=first.frame, epoch=first.epoch, stamp=min(m.stamp for m in msgs), t=first.t,
                         worker="joined", cameras=cameras, tracks=np.array(tracks, np.int64), points=points)
