"""The state of a :class:`~app.tracking.tracker.MultiTracker` as plain arrays, so that a
tracking worker restarted after a crash carries on with every track where its earlier
incarnation left it: same ids, same filter samples / particles, same colour models,
same candidates and recently ended tracks, same random stream (offline, the tracks
after the restart are those of an undisturbed run, byte for byte).

:func:`tracker_state` gives ``{name: ndarray}`` for :func:`numpy.savez` (no pickled
objects: a snapshot is data, loading it runs no code); :func:`restore_tracker` builds
a tracker from it, or raises :class:`SnapshotError` when it does not fit (another
format, other parameters or filter, another grid, missing or malformed arrays).

What is kept: per track its id, counters (age, low support, no person, close), the
filter's estimate, samples (Sparse Sampling) or particles (particle filter) with their
weights, efficiency and reference histogram (21^3 bins, stored sparse: the non-zero
bins and their values, so a track costs a few kB); the candidates (centre, sightings,
sure sightings); the ended tracks kept for re-identification; ``next_id``, ``deleted``
and the random generator's state. Not kept: ``events`` (a log for offline analysis,
unbounded) and per-frame scratch buffers.
"""
from __future__ import annotations

import json
from dataclasses import asdict

import numpy as np

from app.files import json_entry, read_json_entry
from app.tracking.naive import NaiveTarget
from app.tracking.particle import ParticleTarget
from app.tracking.scene import BINS
from app.tracking.sparse import SparseTarget
from app.tracking.tracker import MultiTracker, TrackerParams, _Track

__all__ = ["SnapshotError", "tracker_state", "restore_tracker", "FORMAT"]

FORMAT = "smartroom-tracker-state/1"
MAX_TRACKS = 4096       # a snapshot naming more is not one this project wrote
_HIST = BINS ** 3


class SnapshotError(ValueError):
    """A tracker snapshot that cannot be taken over."""


def params_key(params: TrackerParams) -> str:
    """The tracker's parameters as one canonical string (a snapshot fits only these)."""
    return json.dumps(asdict(params), sort_keys=True, default=list)


def _put_histogram(arrays: dict, name: str, h) -> bool:
    if h is None:
        return False
    h = np.asarray(h, dtype=np.float64)
    nz = np.flatnonzero(h)
    arrays[f"{name}.ref_bins"] = nz.astype(np.int32)
    arrays[f"{name}.ref_values"] = h[nz]
    return True


def tracker_state(tracker: MultiTracker, dims=None) -> dict[str, np.ndarray]:
    """Everything :func:`restore_tracker` needs, as named arrays (``dims``: the voxel
    grid the samples index, checked on restore)."""
    arrays: dict[str, np.ndarray] = {}
    tracks = []
    for k, t in enumerate(tracker.tracks):
        g = t.target
        entry = {"id": int(t.id), "age": int(t.age), "low_support": int(t.low_support),
                 "no_person": int(t.no_person), "close": int(t.close), "person": int(t.person),
                 "settled": int(t.settled), "away": int(t.away)}
        arrays[f"t{k}.x"] = np.asarray(g.x, dtype=np.float64)
        arrays[f"t{k}.anchor"] = np.asarray(t.anchor, dtype=np.float64)
        if isinstance(g, SparseTarget):
            arrays[f"t{k}.samples"] = np.asarray(g.samples).astype(np.uint16).reshape(-1, 3)   # grid indices
        elif isinstance(g, ParticleTarget):
            arrays[f"t{k}.particles"] = np.asarray(g.particles, dtype=np.float64).reshape(-1, 3)
        if not isinstance(g, NaiveTarget):
            arrays[f"t{k}.weights"] = np.asarray(g.weights, dtype=np.float64)
            entry |= {"colour": bool(g.colour), "efficiency": float(getattr(g, "efficiency", 0.0)),
                      "reference": _put_histogram(arrays, f"t{k}", g.reference)}
        tracks.append(entry)
    arrays["candidates"] = np.array([c for c, _, _ in tracker.candidates], dtype=np.float64).reshape(-1, 3)
    arrays["vacated"] = np.array(list(tracker.vacated), dtype=np.float64).reshape(-1, 3)
    ended = []
    for k, (frame, tid, x, ref) in enumerate(tracker.ended):
        arrays[f"e{k}.x"] = np.asarray(x, dtype=np.float64)
        ended.append({"frame": int(frame), "id": int(tid), "reference": _put_histogram(arrays, f"e{k}", ref)})
    meta = {"format": FORMAT, "params": params_key(tracker.p), "dims": None if dims is None else [int(d) for d in dims],
            "next_id": int(tracker.next_id), "deleted": int(tracker.deleted), "rng": tracker.rng.bit_generator.state,
            "tracks": tracks, "sightings": [[int(a), int(b)] for _, a, b in tracker.candidates], "ended": ended}
    arrays["meta"] = json_entry(meta)
    return arrays


# -- restoring: every array checked before use -------------------------------------------
def _array(arrays, key: str, dtype, shape) -> np.ndarray:
    """``arrays[key]`` of ``dtype`` and ``shape`` (None: any length), finite."""
    if key not in arrays:
        raise SnapshotError(f"tracker snapshot: {key} is missing")
    a = np.asarray(arrays[key])
    ok = a.dtype == dtype and a.ndim == len(shape) and all(s is None or s == n for s, n in zip(shape, a.shape))
    if not ok or (a.dtype.kind == "f" and not np.isfinite(a).all()):
        raise SnapshotError(f"tracker snapshot: {key} is not a finite {np.dtype(dtype).name} array of shape "
                            f"{tuple('N' if s is None else s for s in shape)}")
    return a.copy()


def _histogram(arrays, name: str, present) -> np.ndarray | None:
    if not present:
        return None
    bins = _array(arrays, f"{name}.ref_bins", np.int32, (None,))
    values = _array(arrays, f"{name}.ref_values", np.float64, (len(bins),))
    if len(bins) == 0 or (bins < 0).any() or (bins >= _HIST).any() or (values < 0).any() \
            or len(np.unique(bins)) != len(bins):
        raise SnapshotError(f"tracker snapshot: {name}'s reference histogram is malformed")
    h = np.zeros(_HIST)
    h[bins] = values
    return h


def _weights(arrays, key: str, n: int) -> np.ndarray:
    w = _array(arrays, key, np.float64, (n,))
    if (w < 0).any():
        raise SnapshotError(f"tracker snapshot: {key} has negative weights")
    return w


def _target(tracker: MultiTracker, arrays, k: int, entry: dict, dims):
    p, cls = tracker.p, tracker.cls
    x = _array(arrays, f"t{k}.x", np.float64, (3,))
    if cls is NaiveTarget:
        g = NaiveTarget.__new__(NaiveTarget)
        g.x, g.p = x, p
        return g
    g = cls.__new__(cls)
    g.p, g.rng, g.x = p, tracker.rng, x
    g.colour = bool(entry["colour"]) and tracker.colour
    g.reference = _histogram(arrays, f"t{k}", entry["reference"])
    if cls is SparseTarget:
        s = _array(arrays, f"t{k}.samples", np.uint16, (None, 3)).astype(np.int64)
        if dims is None or (s >= np.asarray(dims, dtype=np.int64)).any():
            raise SnapshotError(f"tracker snapshot: t{k}.samples lie outside the grid")
        g.samples = s
        g.weights = _weights(arrays, f"t{k}.weights", len(s))
        g.efficiency = float(entry["efficiency"])
    else:
        g.particles = _array(arrays, f"t{k}.particles", np.float64, (None, 3))
        if len(g.particles) != int(p.particles):
            raise SnapshotError(f"tracker snapshot: t{k} has {len(g.particles)} particles, not {p.particles}")
        g.weights = _weights(arrays, f"t{k}.weights", len(g.particles))
        if g.weights.sum() <= 0:
            raise SnapshotError(f"tracker snapshot: t{k}.weights sum to zero")
    return g


def read_meta(arrays) -> dict:
    """The snapshot's meta (format checked), or :class:`SnapshotError`."""
    try:
        meta = read_json_entry(arrays, "meta")
    except (KeyError, ValueError) as exc:
        raise SnapshotError(f"tracker snapshot: no readable meta ({type(exc).__name__})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise SnapshotError("tracker snapshot: not a smartroom tracker state")
    return meta


def restore_tracker(params: TrackerParams, classifier, arrays, dims=None) -> MultiTracker:
    """A tracker in the state :func:`tracker_state` saved, for ``params`` (the snapshot's
    parameters, filter included, and grid ``dims`` must be the same) and ``classifier``;
    :class:`SnapshotError` if it does not fit."""
    meta = read_meta(arrays)
    if meta.get("params") != params_key(params):
        raise SnapshotError("tracker snapshot: made with other tracker parameters")
    want = None if dims is None else [int(d) for d in dims]
    if meta.get("dims") != want:
        raise SnapshotError(f"tracker snapshot: made on another voxel grid ({meta.get('dims')}, not {want})")
    tracker = MultiTracker(params, classifier)
    try:
        tracker.rng.bit_generator.state = meta["rng"]
        tracker.next_id, tracker.deleted = int(meta["next_id"]), int(meta["deleted"])
        if not isinstance(meta["tracks"], list) or len(meta["tracks"]) > MAX_TRACKS or tracker.next_id < 1:
            raise SnapshotError("tracker snapshot: malformed track list")
        for k, entry in enumerate(meta["tracks"]):
            t = _Track(int(entry["id"]), _target(tracker, arrays, k, entry, dims))
            t.age, t.low_support, t.no_person, t.close = (int(entry[n]) for n in
                                                          ("age", "low_support", "no_person", "close"))
            t.person = int(entry.get("person", 0))   # snapshots before the patience rule have none
            t.settled, t.away = int(entry.get("settled", 0)), int(entry.get("away", 0))   # ... or places left
            if f"t{k}.anchor" in arrays:
                t.anchor = _array(arrays, f"t{k}.anchor", np.float64, (2,)).copy()
            if not 0 < t.id < tracker.next_id or min(t.age, t.low_support, t.no_person, t.close, t.person,
                                                     t.settled, t.away) < 0:
                raise SnapshotError(f"tracker snapshot: track {k} has a malformed id or counters")
            tracker.tracks.append(t)
        if len({t.id for t in tracker.tracks}) != len(tracker.tracks):
            raise SnapshotError("tracker snapshot: two tracks share an id")
        centres = _array(arrays, "candidates", np.float64, (None, 3))
        sightings = meta["sightings"]
        if len(sightings) != len(centres) or len(centres) > MAX_TRACKS:
            raise SnapshotError("tracker snapshot: candidates and their sightings differ in number")
        tracker.candidates = [(c, int(a), int(b)) for c, (a, b) in zip(centres, sightings)]
        if "vacated" in arrays:
            places = _array(arrays, "vacated", np.float64, (None, None))
            if places.shape[1] == 2:   # the build before counted no frames: none yet
                places = np.hstack([places, np.zeros((len(places), 1))])
            if places.shape[1] != 3:
                raise SnapshotError("tracker snapshot: vacated is not a finite float64 array of shape (N, 3)")
            tracker.vacated.extend(np.array(v) for v in places)
        if len(meta["ended"]) > MAX_TRACKS:
            raise SnapshotError("tracker snapshot: malformed ended tracks")
        for k, e in enumerate(meta["ended"]):
            tracker.ended.append((int(e["frame"]), int(e["id"]), _array(arrays, f"e{k}.x", np.float64, (3,)),
                                  _histogram(arrays, f"e{k}", e["reference"])))
    except SnapshotError:
        raise
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise SnapshotError(f"tracker snapshot: malformed ({type(exc).__name__}: {exc})") from None
    return tracker

