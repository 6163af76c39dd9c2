"""Which cameras' masks make up a frame, and when a frame is ready to be built: the
reconstruction worker's assembly of the masks it receives, one camera at a time, into
frames (:mod:`workers.reconstruction`). Plain sets and numbers, the clock passed in: no bus.

A frame is ready, in frame order, once every camera of its set (the cameras the grabber
sent for that index) has delivered, or is not worth waiting for:

- a camera whose every mask producer has left the bus sends nothing more, except offline
  while it is away and not ended (a restart, a link outage): it is sent the frames again
  when it is back, so it is waited for;
- a camera that has sent a later frame will not send this one (a camera's masks come in
  order);
- live, a camera silent for ``camera_timeout_s`` is not waited for, and a frame waits at
  most ``wait_ms`` (or until a newer frame is complete);
- offline, a view that has not come ``stall_s`` after the frame's first mask while its
  producer is on the bus is given up all the same (a safety net: a stage on the bus that
  finishes nothing stalls the run at the source first). Time a producer is away does not
  count (a link cut for 90 s lost a frame whose other camera's mask had crossed before the
  cut); every frame built so is counted (:attr:`FrameAssembly.stalled`), and the run is not
  complete.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["FrameAssembly", "Ready", "MAX_BACKLOG", "STALL_S"]

MAX_BACKLOG = 3   # live: frames ready at once beyond which the stage is behind and skips to the newest
STALL_S = 30.0    # offline safety net: a view this late is given up (and counted) all the same


@dataclass(slots=True)
class Ready:
    """A frame to build: its masks by camera, the cameras of its set it goes without,
    those of them it waited for in vain (offline, ``stall_s``), and how long it waited (s)."""
    frame: int
    masks: dict
    partial: set
    stalled: set
    waited: float


class FrameAssembly:
    """Masks by frame until each frame is ready (module docstring).

    ``names``: the cameras; ``producers``: camera -> the workers publishing its masks;
    ``lossless``: a recording (nothing given up but at ``stall_s``)."""

    def __init__(self, names, producers: dict[str, set], lossless: bool, wait_s: float,
                 camera_timeout_s: float, stall_s: float = STALL_S):
        self.names = list(names)
        self.producers = producers
        self.lossless = lossless
        self.wait_s, self.camera_timeout_s, self.stall_s = wait_s, camera_timeout_s, stall_s
        self.pending: dict[int, dict] = {}     # frame -> {"first", "masks", "expected", "frame"}
        self.last_seen: dict[str, float] = {}  # camera -> its latest mask (live silence), from its first mask on
        self.newest_mask: dict[str, int] = {}  # camera -> its newest frame
        self.newest_done = -1
        self.late = {n: 0 for n in self.names}  # views given up on, per camera
        self.stalled = 0                         # offline: frames built without a view waited for in vain

    def reset(self) -> int:
        """A new stream (epoch): the unfinished frames are given up; how many."""
        n = len(self.pending)
        self.pending, self.newest_done, self.newest_mask = {}, -1, {}
        return n

    def add(self, camera: str, frame: int, cameras, mask, now: float) -> bool:
        """A camera's mask of a frame; False when that frame was built (or given up) without it."""
        self.last_seen[camera] = now
        self.newest_mask[camera] = max(frame, self.newest_mask.get(camera, -1))
        if frame <= self.newest_done:
            self.late[camera] += 1
            return False
        entry = self.pending.get(frame)
        if entry is None:
            expected = set(cameras) & set(self.names) or set(self.names)
            entry = self.pending[frame] = {"first": now, "masks": {}, "expected": expected, "frame": frame}
        entry["masks"][camera] = mask
        return True

    def _away(self, camera: str, alive: set) -> bool:
        producers = self.producers.get(camera)
        return bool(producers) and not producers & alive

    def missing(self, entry: dict, now: float, alive: set, ended: set) -> set[str]:
        """Cameras of the frame's set still worth waiting for."""
        missing = entry["expected"] - set(entry["masks"])
        missing = {c for c in missing
                   if (not self._away(c, alive) or (self.lossless and not self.producers[c] <= ended))
                   and self.newest_mask.get(c, -1) < entry["frame"]}
        if not self.lossless:
            missing = {c for c in missing
                       if c not in self.last_seen or now - self.last_seen[c] <= self.camera_timeout_s}
        return missing

    def ready(self, now: float, alive: set, ended: set, final: bool = False) -> list[Ready]:
        """The frames to build now, in frame order (``final``: the stream ended, every
        pending frame). Live, a stage more than :data:`MAX_BACKLOG` complete frames behind
        skips to the newest complete one (the frames skipped are not returned)."""
        if not self.lossless and not final:
            complete = [f for f, e in self.pending.items() if not self.missing(e, now, alive, ended)]
            if len(self.pending) > MAX_BACKLOG and complete:
                newest = max(complete)
                for f in [f for f in self.pending if f < newest][:-MAX_BACKLOG]:
                    del self.pending[f]
        out = []
        while self.pending:
            frame = min(self.pending)
            entry = self.pending[frame]
            missing = set() if final else self.missing(entry, now, alive, ended)
            stalled: set = set()
            if missing:
                if self.lossless:
                    if any(self._away(c, alive) for c in missing):
                        entry["first"] = now   # a producer away (restart, link outage): not a stall
                        break
                    if now - entry["first"] < self.stall_s:
                        break
                    stalled = missing
                    self.stalled += 1
                else:
                    newer_complete = any(not self.missing(e, now, alive, ended)
                                         for f, e in self.pending.items() if f > frame)
                    if now - entry["first"] < self.wait_s and not newer_complete:
                        break
            del self.pending[frame]
            partial = entry["expected"] - set(entry["masks"])
            for c in partial:
                self.late[c] += 1
            self.newest_done = max(self.newest_done, frame)
            out.append(Ready(frame, entry["masks"], partial, stalled, now - entry["first"]))
        return out
