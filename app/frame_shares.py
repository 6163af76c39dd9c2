"""Stages that scale out by frame (issue 26): several workers of one stateless stage
take the frames in turn.

A worker of a kind that allows it (the reconstruction) with ``share: [k, n]`` handles
the frames with ``frame % n == k`` and nothing else: what the others' frames bring is
dropped as it arrives, before the inbox, and not counted as refused (it is not its
input). The layout's shares of one stage must be ``[0, n]`` .. ``[n-1, n]``, each once
(:func:`stage_shares`), so that every frame has exactly one worker.

Downstream, each worker's frames come in its own order, but the shards' outputs
interleave as they finish. A consumer of a sharded stage takes them through
:class:`FrameOrder`, which hands them on in frame order: frame ``f`` goes once every
other shard has sent a frame later than ``f - n`` (a shard sends its frames in order,
so then no frame before ``f`` is still to come from it), or at the end of the stream.
So a tracker downstream sees what it would see behind one worker, and offline the
results are those of one worker, byte for byte. A frame a shard gives up (too few
views) holds the frames after it until that shard sends a later one, which the offline
flow control lets it do (the layout's grabber ``window`` must be at least ``n``); live,
a shard that is away holds nothing longer than ``max_pending`` frames. The offline flow
control asks of a shard only its own frames (:func:`last_own`).
"""
from __future__ import annotations

__all__ = ["frame_share", "valid_share", "owns", "count_own", "last_own", "stage_shares", "FrameOrder"]


def frame_share(params: dict) -> tuple[int, int] | None:
    """``(k, n)`` of a worker's ``share`` parameter (frames, or a pose worker's track ids),
    or None (it takes them all)."""
    share = params.get("share")
    if share is None:
        return None
    return int(share[0]), int(share[1])


def valid_share(share) -> bool:
    """``share`` is ``[k, n]``, integers with ``0 <= k < n``."""
    return (isinstance(share, (list, tuple)) and len(share) == 2 and all(isinstance(v, int) and not isinstance(v, bool)
                                                                          for v in share)
            and 0 <= share[0] < share[1])


def owns(share: tuple[int, int] | None, frame: int) -> bool:
    return share is None or frame % share[1] == share[0]


def count_own(share: tuple[int, int] | None, first: int, count: int) -> int:
    """How many of the frames ``first .. first + count - 1`` are the share's."""
    if share is None or count <= 0:
        return max(0, count)
    k, n = share
    start = first + (k - first) % n   # the share's first frame from ``first`` on
    return max(0, (first + count - start + n - 1) // n)


def last_own(share: tuple[int, int] | None, frame: int) -> int:
    """The share's newest frame at or before ``frame``."""
    if share is None:
        return frame
    k, n = share
    return frame - (frame - k) % n


def stage_shares(specs, where: str = "layout") -> dict[str, tuple[int, int]]:
    """``{worker: (k, n)}`` of one stage's workers (``specs``, WorkerSpec), checked: with
    any ``share``, every worker has one, all of the same ``n``, each ``k`` once. Raises
    ValueError naming what is wrong."""
    shares = {s.name: s.params.get("share") for s in specs}
    if all(v is None for v in shares.values()):
        return {}
    for name, v in shares.items():
        if not valid_share(v):
            raise ValueError(f"{where}: worker {name}: share must be [k, n] with 0 <= k < n, got {v!r}"
                             + (" (the stage's other workers share its frames)" if v is None else ""))
    n = {v[1] for v in shares.values()}
    if len(n) > 1:
        raise ValueError(f"{where}: the workers sharing one stage's frames must have one n, got {sorted(n)}")
    n = n.pop()
    ks = sorted(v[0] for v in shares.values())
    if ks != list(range(n)):
        raise ValueError(f"{where}: the shares [k, {n}] must be k = 0 .. {n - 1} each once, got k = {ks}")
    return {name: (v[0], v[1]) for name, v in shares.items()}


class FrameOrder:
    """Messages of a stage whose workers share its frames, handed on in frame order (see
    the module docstring). :meth:`add` takes one (already admitted, not a repeat) and
    returns those now in order; :meth:`flush` the rest at the end of the stream."""

    def __init__(self, n: int, max_pending: int = 64):
        self.n = int(n)
        self.max_pending = int(max_pending)
        self.newest: dict[int, int] = {}        # shard (frame % n) -> newest frame it sent
        self.pending: dict[int, list] = {}      # frame -> [(key, msg), ...]
        self.forced = 0                         # frames handed on before the frames before them (live)
        self.epoch = None

    def _ready(self, frame: int) -> bool:
        floor = frame - self.n
        # a shard that sent nothing yet is taken to have sent its frame before 0 (r - n)
        return all(self.newest.get(r, r - self.n) > floor for r in range(self.n) if r != frame % self.n)

    def add(self, key: str, msg) -> list:
        out = []
        if msg.epoch != self.epoch:   # a new numbering (the source restarted): the old one's frames first
            out, self.epoch = self.flush(), msg.epoch
            self.newest.clear()
        f = int(msg.frame)
        r = f % self.n
        self.newest[r] = max(f, self.newest.get(r, r - self.n))
        self.pending.setdefault(f, []).append((key, msg))
        for frame in sorted(self.pending):
            if self._ready(frame):
                out += self.pending.pop(frame)
            elif len(self.pending) > self.max_pending:
                self.forced += 1
                out += self.pending.pop(frame)
            else:
                break
        return out

    def flush(self) -> list:
        return [item for f in sorted(self.pending) for item in self.pending.pop(f)]
