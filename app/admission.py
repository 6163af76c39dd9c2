"""What a worker lets in from the bus (DESIGN §5, "the bus is untrusted input").

Every message a worker receives has passed the codec and its type's ``validate()``;
here the frame numbers are checked against the stream they claim to belong to:

- :class:`FrameWindow` follows one stream (one key) through the source's epochs. A
  frame number far from the newest one of the current epoch is rejected, never used
  to size anything. A newer epoch (a source that restarted) is followed only once the
  current one has gone quiet for :data:`EPOCH_QUIET_S` (a source that restarts is
  silent while it starts again; a forger beside a running source is not followed),
  and then at once if it carries on the frame numbers (a recording resumed), or
  after :data:`EPOCH_CONFIRM` distinct nearby frames if it starts anew (a live camera).
  Live (``follow_ahead``), a stream whose current frames went quiet here for
  :data:`EPOCH_QUIET_S` and come back far ahead of the window (this worker stood still:
  stopped, swapped out, restarted late) is followed the same way, after
  :data:`EPOCH_CONFIRM` nearby frames: the stage jumps to the newest frames and the
  frames it skipped are counted (:attr:`FrameWindow.skipped`). Offline nothing is
  skipped, so nothing jumps.
  An epoch is its source's start time (ms since 1970). Given the run's start
  (``earliest_epoch``: the launcher's, in the resolved layout), an epoch older than it or
  later than now, by more than :data:`EPOCH_SLACK_MS` (clocks of the room's hosts
  disagreeing), is refused whatever the window: no source of this run has it, so a
  forger's first message cannot set a window the real stream is then refused from
  (issue 25: epoch 2^40 sent before the grabber's first frame held every key).
- :class:`Rejections` counts what was turned away per key and reason and logs it at
  most once per :data:`LOG_PERIOD_S` per reason, with the count since the last line.

Pure Python, no bus: the worker base owns one of each.
"""
from __future__ import annotations

import threading
import time

__all__ = ["FrameWindow", "Rejections", "epoch_outside_run", "WINDOW", "EPOCH_CONFIRM", "EPOCH_QUIET_S",
           "EPOCH_SLACK_MS"]

WINDOW = 1000          # frames either side of the newest accepted one (40 s at 25 fps)
EPOCH_CONFIRM = 2      # distinct, nearby frame numbers that confirm a new epoch starting anew
EPOCH_QUIET_S = 0.5    # silence of the current epoch before a newer one may take over
EPOCH_SLACK_MS = 3_600_000   # how far the hosts' clocks may disagree: an epoch this far outside the run is refused
LOG_PERIOD_S = 5.0


def epoch_outside_run(epoch: int, earliest: int | None, now_ms: int | None = None) -> str | None:
    """Why ``epoch`` is no source's of a run that started at ``earliest`` (ms since 1970;
    None: unknown, nothing is refused), or None: older than the start or later than now by
    more than :data:`EPOCH_SLACK_MS`. Stateless, so a worker asks it in zenoh's thread,
    before a message takes a place in its inbox."""
    if earliest is None:
        return None
    if epoch < earliest - EPOCH_SLACK_MS:
        return "epoch before the run"
    if epoch > (time.time_ns() // 1_000_000 if now_ms is None else now_ms) + EPOCH_SLACK_MS:
        return "epoch from the future"
    return None


class FrameWindow:
    """The epoch and newest frame of one stream; :meth:`admit` says whether a frame
    belongs to it (None) or why not (a short reason)."""

    def __init__(self, window: int = WINDOW, clock=time.monotonic, follow_ahead: bool = False,
                 earliest_epoch: int | None = None, wall_ms=None):
        self.window = int(window)
        self.clock = clock
        self.earliest_epoch = earliest_epoch   # the run's start (ms since 1970) or None: no bound
        self.wall_ms = wall_ms or (lambda: time.time_ns() // 1_000_000)
        self.follow_ahead = follow_ahead
        self.skipped = 0              # frames jumped over (follow_ahead)
        self.epoch: int | None = None
        self.newest = -1
        self.last_seen = 0.0          # when the current epoch last delivered
        self._candidate: tuple[int, set] | None = None   # (epoch, frames seen) of a newer epoch

    def admit(self, epoch: int, frame: int) -> str | None:
        now = self.clock()
        if frame < 0:
            return "negative frame"
        if self.earliest_epoch is not None:
            outside = epoch_outside_run(epoch, self.earliest_epoch, self.wall_ms())
            if outside:
                return outside
        if self.epoch is None:          # the first frame of the stream sets it
            self.epoch, self.newest, self.last_seen = epoch, frame, now
            return None
        if epoch == self.epoch:
            if abs(frame - self.newest) > self.window:
                if self.follow_ahead and frame > self.newest and now - self.last_seen >= EPOCH_QUIET_S:
                    return self._follow(epoch, frame, now, "frame outside the window")
                return "frame outside the window"
            self.newest = max(self.newest, frame)
            self.last_seen = now
            return None
        if epoch < self.epoch:
            return "old epoch"
        if now - self.last_seen < EPOCH_QUIET_S:
            return "new epoch while the current one is running"
        if abs(frame - self.newest) <= self.window:   # the same numbering carried on
            self.epoch, self.newest, self.last_seen, self._candidate = epoch, frame, now, None
            return None
        return self._follow(epoch, frame, now, "unconfirmed epoch")   # a new numbering

    def _follow(self, epoch: int, frame: int, now: float, refusal: str) -> str | None:
        """Follow ``epoch`` from ``frame`` on once :data:`EPOCH_CONFIRM` distinct nearby
        frames confirm it; until then the refusal."""
        cand_epoch, frames = self._candidate if self._candidate and self._candidate[0] == epoch else (epoch, set())
        if frames and min(abs(frame - f) for f in frames) > self.window:
            frames = set()
        frames.add(frame)
        self._candidate = (cand_epoch, frames)
        if len(frames) < EPOCH_CONFIRM:
            return refusal
        if epoch == self.epoch:   # the same stream, far ahead: what lies between is skipped
            self.skipped += max(0, frame - self.newest - 1)
        self.epoch, self.newest, self.last_seen, self._candidate = epoch, max(frames), now, None
        return None

    def state(self) -> dict:
        return {"epoch": self.epoch, "newest": self.newest}


class Rejections:
    """Messages turned away, per ``(key, reason)``, with rate-limited log lines; counted
    from zenoh's threads and read from the worker's loop (guarded by a lock)."""

    def __init__(self, log, clock=time.monotonic):
        self.log = log
        self.clock = clock
        self.counts: dict[tuple[str, str], int] = {}
        self._per_reason: dict[str, int] = {}
        self._logged: dict[str, tuple[float, int]] = {}   # reason -> (time, count then)
        self._total = 0   # kept as it goes: read for every message turned away (a flood)
        self._lock = threading.Lock()

    def add(self, key: str, reason: str, detail: str = "") -> None:
        k = (key, reason)
        now = self.clock()
        with self._lock:
            self.counts[k] = self.counts.get(k, 0) + 1
            self._total += 1
            total = self._per_reason[reason] = self._per_reason.get(reason, 0) + 1
            last = self._logged.get(reason)
            say = last is None or now - last[0] >= LOG_PERIOD_S
            if say:
                self._logged[reason] = (now, total)
        if say:
            since = total - (last[1] if last else 0)
            more = f" ({since} such messages since the last report)" if last else ""
            self.log.warning("dropped a message on %s: %s%s%s", key, reason, f": {detail}" if detail else "", more)

    @property
    def total(self) -> int:
        return self._total

    def figures(self) -> dict:
        """``{"key: reason": count}`` for the stats."""
        with self._lock:
            return {f"{k}: {r}": n for (k, r), n in sorted(self.counts.items())}

    def restore(self, figures: dict) -> None:
        with self._lock:
            for text, n in (figures or {}).items():
                key, _, reason = str(text).rpartition(": ")
                if isinstance(n, int):
                    self.counts[(key, reason)] = self.counts.get((key, reason), 0) + n
                    self._total += n
                    self._per_reason[reason] = self._per_reason.get(reason, 0) + n
