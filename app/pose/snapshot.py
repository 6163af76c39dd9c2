"""The state of a :class:`~app.pose.estimator.PoseEstimator` as plain arrays, so that a
pose worker restarted after a crash carries on with every person's filter where its
earlier incarnation left it (same particles, same random stream: offline, the poses
after the restart are those of an undisturbed run).

:func:`estimator_state` gives ``{name: ndarray}`` for :func:`numpy.savez` (no pickled
objects: a snapshot is data, loading it runs no code); :func:`restore_estimator` builds
an estimator from it, or raises :class:`SnapshotError` when it does not fit (another
format, other settings, missing or malformed arrays).

Per person: the track id, stature (and the tops it was read from), limb proportions (and
their fit's sums while it runs), frames posed, the last track position and smoothed
velocity, the feet's vote for the facing, the state estimate, the random generator's
state, the particle sets (SHBM-APF: one per model, with their sizes; APF: one) and, with
DDM, the limb switch (which units are on, their last check and the scouts of the lost
ones); with the behaviour method once it took over, its tracker (the blobs learnt, the
particles with their velocities, clusters and VLMM states, the fits' count, mean and
summed squared deviation) and the frames SHBM-APF still poses after a failure.
"""
from __future__ import annotations

import json
from dataclasses import asdict

import numpy as np

from app.files import json_entry, read_json_entry
from app.pose.estimator import PersonPose, PoseEstimator, PoseSettings
from app.pose.facing import FacingVote
from app.pose.filters import SHBMAPF
from app.pose.flesh import LIMBS
from app.pose.model import N_DOF, Proportions

__all__ = ["SnapshotError", "estimator_state", "restore_estimator"]

FORMAT = "smartroom-pose-state/1"


class SnapshotError(ValueError):
    """A pose snapshot that cannot be taken over."""


def _settings_key(settings: PoseSettings) -> str:
    return json.dumps(asdict(settings), sort_keys=True, default=list)


def estimator_state(est: PoseEstimator) -> dict[str, np.ndarray]:
    """Everything :func:`restore_estimator` needs, as named arrays."""
    arrays: dict[str, np.ndarray] = {}
    people = []
    for tid, p in est.people.items():
        entry = {"id": int(tid), "tops": [float(t) for t in p.tops], "frames": int(p.frames),
                 "height": None if p.height is None else float(p.height),
                 "rng": p.rng.bit_generator.state, "filter": None,
                 "proportions": [p.proportions.legs, p.proportions.arms]}
        if p.fit is not None:
            entry["fit"] = {"seen": int(p.fit.seen), "sums": [float(v) for v in p.fit.sums.ravel()]}
        for name in ("state", "last_position", "velocity"):
            value = getattr(p, name)
            if value is not None:
                arrays[f"p{tid}.{name}"] = np.asarray(value, dtype=np.float64)
        arrays[f"p{tid}.vote"] = p.vote.vector.copy()
        if p.filter is not None:
            f = p.filter
            if isinstance(f, SHBMAPF):
                entry["filter"] = {"kind": "shbm", "sizes": [int(n) for n in f.sizes],
                                   "sets": 0 if f.sets is None else len(f.sets)}
                for i, s in enumerate(f.sets or []):
                    arrays[f"p{tid}.set{i}"] = np.asarray(s, dtype=np.float64)
            else:
                entry["filter"] = {"kind": "apf", "sets": 0 if f.particles is None else 1}
                if f.particles is not None:
                    arrays[f"p{tid}.set0"] = np.asarray(f.particles, dtype=np.float64)
            arrays[f"p{tid}.frozen"] = np.asarray(f.frozen, dtype=bool)
        if p.switch is not None:
            sw = p.switch
            entry["switch"] = {"active": {u: bool(v) for u, v in sw.active.items()},
                               "last": {u: [float(a), float(b)] for u, (a, b) in sw.last.items()},
                               "scouts": sorted(sw.scouts)}
            for u, s in sw.scouts.items():
                arrays[f"p{tid}.scout.{u}"] = np.asarray(s, dtype=np.float64)
        if p.tracker is not None:
            entry["behaviour"] = {**_tracker_state(p.tracker, f"p{tid}.b.", arrays), "handback": int(p.handback)}
        people.append(entry)
    meta = {"format": FORMAT, "settings": _settings_key(est.settings), "people": people}
    arrays["meta"] = json_entry(meta)
    return arrays


_BLOB_ARRAYS = ("local_mean", "local_var", "colour_mean", "colour_cov", "weight")


def _tracker_state(tracker, prefix: str, arrays: dict) -> dict:
    f, blobs = tracker.filter, tracker.blobs
    for name in _BLOB_ARRAYS:
        arrays[prefix + name] = np.asarray(getattr(blobs, name), dtype=np.float64)
    arrays[prefix + "states"] = f.states.copy()
    arrays[prefix + "velocity"] = f.velocity.copy()
    arrays[prefix + "cluster"] = f.cluster.astype(np.int64)
    arrays[prefix + "estimate"] = np.asarray(f.estimate, dtype=np.float64)
    if tracker.last_position is not None:
        arrays[prefix + "last_position"] = np.asarray(tracker.last_position, dtype=np.float64)
    return {"vlmm": [list(map(int, q)) for q in f.vlmm_state], "fit_stats": [float(v) for v in tracker.fits],
            "recoveries": int(tracker.recoveries)}


def _restore_tracker(p: PersonPose, entry: dict, prefix: str, arrays) -> None:
    """``p``'s behaviour tracker as :func:`_tracker_state` saved it."""
    from app.behaviour.blobs import SEG_OF_BLOB, BlobModel

    t = p.behaviour_tracker()
    model = t.model
    B = len(SEG_OF_BLOB)
    blobs = {}
    for name, shape in zip(_BLOB_ARRAYS, ((B, 3), (B, 3), (B, 3), (B, 3, 3), (B,))):
        a = np.asarray(arrays.get(prefix + name, np.zeros(0)))
        if a.dtype != np.float64 or a.shape != shape or not np.isfinite(a).all():
            raise SnapshotError(f"pose snapshot: {prefix}{name} is not a finite {shape} array")
        blobs[name] = a.copy()
    t.blobs = BlobModel(p.height, SEG_OF_BLOB.copy(), **blobs)
    f = t.filter
    f.states = _particles(arrays, prefix + "states", f.n)
    f.velocity = np.asarray(arrays.get(prefix + "velocity", np.zeros(0)), dtype=np.float64).copy()
    cluster = np.asarray(arrays.get(prefix + "cluster", np.zeros(0)))
    vlmm = [tuple(int(k) for k in q) for q in entry["vlmm"]]
    if f.velocity.shape != (f.n, f.d) or cluster.dtype != np.int64 or cluster.shape != (f.n,) \
            or len(vlmm) != f.n or cluster.min() < 0 or cluster.max() >= model.clusters.k \
            or any(q not in model.vlmm.contexts for q in vlmm):
        raise SnapshotError("pose snapshot: the behaviour tracker's particles do not fit its model")
    f.cluster, f.vlmm_state = cluster.copy(), vlmm
    f.estimate = _vector(arrays, prefix + "estimate", N_DOF)
    if f.estimate is None:
        raise SnapshotError(f"pose snapshot: {prefix}estimate is missing")
    t.last_position = _vector(arrays, prefix + "last_position", 3)
    if "fit_stats" in entry:   # count, mean and summed squared deviation of the fits
        fits = [float(v) for v in entry["fit_stats"]]
    else:                      # a snapshot that kept every fit
        old = np.asarray(entry["fits"], dtype=np.float64).reshape(-1)
        mean = float(old.mean()) if len(old) else 0.0
        fits = [len(old), mean, float(((old - mean) ** 2).sum())]
    if len(fits) != 3 or not np.isfinite(fits).all() or fits[0] < 0 or fits[0] != int(fits[0]) or fits[2] < 0:
        raise SnapshotError("pose snapshot: the behaviour tracker's fit statistics are malformed")
    t.fits = (int(fits[0]), fits[1], fits[2])
    t.recoveries = int(entry["recoveries"])
    p.tracker, p.handback = t, int(entry["handback"])


def _particles(arrays, key: str, rows: int | None = None) -> np.ndarray:
    if key not in arrays:
        raise SnapshotError(f"pose snapshot: {key} is missing")
    a = np.asarray(arrays[key])
    if a.dtype != np.float64 or a.ndim != 2 or a.shape[1] != N_DOF or not np.isfinite(a).all() \
            or (rows is not None and len(a) != rows) or len(a) == 0:
        raise SnapshotError(f"pose snapshot: {key} is not a finite (N, {N_DOF}) particle set")
    return a.copy()


def _vector(arrays, key: str, n: int) -> np.ndarray | None:
    if key not in arrays:
        return None
    a = np.asarray(arrays[key])
    if a.dtype != np.float64 or a.shape != (n,) or not np.isfinite(a).all():
        raise SnapshotError(f"pose snapshot: {key} is not a finite vector of {n}")
    return a.copy()


def restore_estimator(settings: PoseSettings, arrays) -> PoseEstimator:
    """An estimator in the state :func:`estimator_state` saved, for ``settings`` (the
    snapshot's settings must be the same); :class:`SnapshotError` if it does not fit."""
    try:
        meta = read_json_entry(arrays, "meta")
    except (KeyError, ValueError) as exc:
        raise SnapshotError(f"pose snapshot: no readable meta ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise SnapshotError("pose snapshot: not a smartroom pose state")
    if meta.get("settings") != _settings_key(settings):
        raise SnapshotError("pose snapshot: made with other pose settings")
    est = PoseEstimator(settings)
    try:
        for entry in meta["people"]:
            tid = int(entry["id"])
            p = PersonPose(settings, tid, np.random.default_rng([settings.seed, tid]))
            p.rng.bit_generator.state = entry["rng"]
            p.tops = [float(t) for t in entry["tops"]]
            p.frames = int(entry["frames"])
            p.state = _vector(arrays, f"p{tid}.state", N_DOF)
            p.last_position = _vector(arrays, f"p{tid}.last_position", 3)
            p.velocity = _vector(arrays, f"p{tid}.velocity", 3)
            p.vote = FacingVote(_vector(arrays, f"p{tid}.vote", 2))   # a snapshot without it: no vote yet
            if p.fit is not None and "fit" in entry:
                if len(entry["fit"]["sums"]) != p.fit.sums.size:
                    raise SnapshotError("pose snapshot: the proportions' fit does not fit")
                p.fit.seen = int(entry["fit"]["seen"])
                p.fit.sums = np.array(entry["fit"]["sums"], dtype=np.float64).reshape(p.fit.sums.shape)
            if entry["height"] is not None:
                p.build(float(entry["height"]), Proportions(*entry.get("proportions", (1.0, 1.0))))
                f, spec = p.filter, entry["filter"]
                if spec["kind"] != ("shbm" if isinstance(f, SHBMAPF) else "apf"):
                    raise SnapshotError("pose snapshot: made with another pose method")
                if isinstance(f, SHBMAPF):
                    sizes = [int(n) for n in spec["sizes"]]
                    if len(sizes) != len(f.sizes) or spec["sets"] not in (0, len(sizes)):
                        raise SnapshotError("pose snapshot: SHBM-APF sets do not fit")
                    f.sizes = sizes
                    if spec["sets"]:
                        f.sets = [_particles(arrays, f"p{tid}.set{i}", n) for i, n in enumerate(sizes)]
                elif spec["sets"]:
                    f.particles = _particles(arrays, f"p{tid}.set0")
                frozen = np.asarray(arrays.get(f"p{tid}.frozen", np.zeros(N_DOF, bool)))
                if frozen.dtype != bool or frozen.shape != (N_DOF,):
                    raise SnapshotError(f"pose snapshot: p{tid}.frozen is not {N_DOF} flags")
                f.frozen = frozen.copy()
                sw = entry.get("switch")
                if (sw is None) != (p.switch is None):
                    raise SnapshotError("pose snapshot: made with another pose method")
                if sw is not None:
                    if set(sw["active"]) != set(LIMBS):
                        raise SnapshotError("pose snapshot: limb units do not fit")
                    p.switch.active = {u: bool(v) for u, v in sw["active"].items()}
                    p.switch.last = {u: (float(a), float(b)) for u, (a, b) in sw["last"].items()}
                    p.switch.scouts = {u: _particles(arrays, f"p{tid}.scout.{u}") for u in sw["scouts"]}
                if entry.get("behaviour") is not None:
                    _restore_tracker(p, entry["behaviour"], f"p{tid}.b.", arrays)
            est.people[tid] = p
    except SnapshotError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise SnapshotError(f"pose snapshot: malformed ({type(exc).__name__}: {exc})") from None
    return est
