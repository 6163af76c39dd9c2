"""Which frame the live view shows: a frame's voxels, tracks and poses put together
before it is drawn, so that what the page shows belongs to one frame.

The stages deliver a frame's parts at different times (tracks after the voxels they are
made from, poses after both, each stage's latency its own), and a display that drew each
part as it came showed current voxels with older tracks and skeletons. Here each part is
kept by its frame (``(epoch, frame)``) until the frame is complete, and the newest
complete frame is the one to draw.

A frame is complete when it has every *expected* part: the kinds that have arrived within
the last ``wait_s`` seconds, and, until ``first_wait_s`` after the first part of the stream,
the kinds the layout produces (``layout_kinds``) that have not arrived yet (at the start
a frame's voxels are in before any tracks ever came, and the first frame drawn had voxels
only). A stage that is away (crashed and restarting, still loading
its kernels, or absent from the layout) is not waited for: after ``wait_s`` of silence
its kind is no longer expected, and frames are drawn without it (nothing of another
frame is shown in its place). When it comes back, its kind is expected again. A part
that arrives for the frame on show after it was drawn (a kind that had been silent) is
drawn with it. Older frames than the one on show are dropped; at most ``keep`` newer
ones wait. Pure: no bus, no clock of its own.
"""
from __future__ import annotations

__all__ = ["FrameAssembly", "KINDS"]

KINDS = ("voxels", "tracks", "poses", "keypoints")


class FrameAssembly:
    def __init__(self, wait_s: float = 2.0, keep: int = 64, layout_kinds=(), first_wait_s: float = 20.0):
        self.wait_s = float(wait_s)
        self.keep = max(1, int(keep))
        self.layout_kinds = set(layout_kinds) & set(KINDS)
        self.first_wait_s = float(first_wait_s)
        self.first_arrival: float | None = None
        self.frames: dict[tuple[int, int], dict[str, object]] = {}
        self.last_arrival: dict[str, float] = {}
        self.shown: tuple[int, int] | None = None   # (epoch, frame) on show
        self.shown_kinds: frozenset = frozenset()

    def add(self, kind: str, msg, now: float) -> None:
        """One part of a frame (a Voxels, Tracks or Poses message) arrived at ``now``."""
        if kind not in KINDS:
            raise ValueError(f"unknown part {kind!r}")
        self.last_arrival[kind] = now
        if self.first_arrival is None:
            self.first_arrival = now
        key = (int(getattr(msg, "epoch", 0) or 0), int(msg.frame))
        if self.shown is not None and key < self.shown:
            return   # older than the frame on show: too late to be seen
        self.frames.setdefault(key, {})[kind] = msg
        while len(self.frames) > self.keep:
            del self.frames[min(self.frames)]

    def expected(self, now: float) -> set[str]:
        """The kinds a frame waits for now: those heard of within ``wait_s``, and early in
        the stream those of the layout not heard of yet."""
        heard = {k for k, t in self.last_arrival.items() if now - t <= self.wait_s}
        if self.first_arrival is not None and now - self.first_arrival <= self.first_wait_s:
            heard |= self.layout_kinds - set(self.last_arrival)
        return heard

    def take(self, now: float) -> tuple[tuple[int, int], dict[str, object]] | None:
        """The frame to draw now and its parts, or None (nothing new): the newest complete
        frame after the one on show, or the one on show when parts of it came late."""
        want = self.expected(now)
        complete = [key for key, parts in self.frames.items()
                    if (self.shown is None or key > self.shown) and want <= parts.keys()]
        if complete:
            key = max(complete)
        elif self.shown in self.frames and set(self.frames[self.shown]) - self.shown_kinds:
            key = self.shown
        else:
            return None
        for old in [k for k in self.frames if k < key]:
            del self.frames[old]
        self.shown = key
        parts = dict(self.frames[key])
        self.shown_kinds = frozenset(parts)
        return key, parts

    def reset(self) -> None:
        """A new stream (the source restarted: a new epoch, frame numbers start again)."""
        self.frames.clear()
        self.shown = None
        self.shown_kinds = frozenset()
