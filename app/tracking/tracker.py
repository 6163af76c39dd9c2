"""Multi-person tracking: one filter per target and the life of tracks (thesis §4.2.2-4.2.3).

Each frame (:meth:`MultiTracker.update`):

1. every target's filter steps (Naive §4.3.1, particle filter §4.3.2 or Sparse Sampling
   §4.3.3, raw or colour; the filters model their interactions themselves); beyond the
   thesis (``refine``), each estimate is then re-centred in xy on the voxels of its
   share that are at least ``refine_min_z`` high (the upper body: the visual hull's
   lower part is fattened by phantom volume that pulls a centroid away from the body);
   the particle filter's cloud moves with its estimate (``refine_particles``), as
   Sparse Sampling's fresh samples are drawn around it (``ss_reseed``); a colour
   target is not re-centred while another is within ``refine_colour`` (the Voronoi
   share would overrule its colours in a merged blob);
2. deletion (§4.2.3): a target that falls within ``duplicate_distance`` of an older one
   for ``duplicate_frames`` frames is a duplicate (with colour, beyond the thesis, only
   if also dressed alike: ``duplicate_similarity``, or within ``same_place``, where two
   bodies do not fit, however dressed); a target whose support (the weight of
   the voxels within ``s_x`` of it, xy) stays under ``min_support_kg`` for ``lost_frames``
   frames has lost its person (the thesis's low efficiency); a target whose component
   the classifier calls no-person for ``no_person_frames`` frames is lost; beyond the
   thesis (``no_person_credit``; 0 is the thesis), a track earns patience by the frames
   its share was a person: ``no_person_credit`` frames per such frame, at most
   ``no_person_cap`` more, so a person who crouches or sits down for seconds (a short,
   wide blob the classifier calls no person) keeps the track that followed them
   standing, while a piece of the hull that passed the person test for a moment does not;
3. creation (§4.2.3): the voxels of each component the classifier calls a person that
   no target claims (farther than ``claim_radius`` from every target, xy) are a
   candidate when the classifier also calls *them* a person (so a person merged into
   the blob of a tracked one is found too) and their centroid is farther than
   ``new_distance`` from every target and higher than ``new_min_z`` (beyond the thesis:
   lower blobs are phantoms and pieces of the hull, not people); a candidate seen at
   about the same place for ``confirm_frames`` frames becomes a track with a new id (a
   component's candidate is placed by its upper body, ``candidate_min_z``, so a phantom
   merged into it for a frame or two does not move it and restart the count); while the
   room has no track, a candidate the classifier calls a person with probability at
   least ``sure_probability`` in each of ``confirm_sure_frames`` frames is confirmed
   then (the first person in is posed 3 frames sooner; with tracks in the room, the
   hull's phantoms near people are "sure" persons too, so the count stays);
4. re-identification (beyond the thesis, ``reid_frames``; 0 turns it off): a track
   confirmed where a track ended for a no-person verdict a moment ago, and, with colour,
   dressed alike, takes the ended track's id, so a person whose track was dropped for
   a few frames (a blob that briefly fails the person test) keeps their identity;
5. places left behind (beyond the thesis, ``vacated_frames``; 0 turns it off): a track
   that stayed within ``vacated_radius`` (xy) of one place for ``vacated_frames`` frames
   and then went farther than ``vacated_depart`` from it has *vacated* that place; no new
   track starts within ``vacated_radius`` of a vacated place. A background that took in
   a person who stood still (a median estimated from a recording that shows them there
   half the time, a live model that learnt them) shows the room where they stood as
   foreground once they go: a ghost of their exact shape, seen by every camera, that no
   silhouette test tells from a person. A person who comes back to the place walks in
   tracked, so no new track is needed there. A track that went where a track it made a
   duplicate ended was dragged off its person onto another's: it vacated nothing. A
   place is kept while something stands there: once no voxel lies within
   ``vacated_radius`` of it for ``vacated_release`` frames (the background let the
   ghost go, or there was none), anyone may start a track there again.

The tracker reports confirmed targets only; ids are never reused otherwise.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, fields

import numpy as np

from app.tracking import columns
from app.tracking.blobs import CLASSIFIER_FEATURES, features_from_sums
from app.tracking.naive import NaiveTarget
from app.tracking.particle import ParticleTarget
from app.tracking.scene import SceneFrame, bhattacharyya
from app.tracking.sparse import SparseTarget

__all__ = ["TrackerParams", "MultiTracker", "FILTERS"]

EVENTS_KEPT = 1000   # MultiTracker.events: the last this many track starts and ends
VACATED_KEPT = 64    # MultiTracker.vacated: the last this many places left behind
MOVED_OVER = 25      # frames a track stays between vacated_radius and vacated_depart of its place: it moved over
ANCHOR_FOLLOW = 0.05  # share of a settled track's drift its place follows each frame


def _near(place, xy, r: float) -> bool:
    """Whether ``place`` (x, y, ...) lies within ``r`` of ``xy`` (x, y, ...), in the floor plane."""
    return (place[0] - xy[0]) ** 2 + (place[1] - xy[1]) ** 2 < r * r

#: filter name -> (target class, uses colour)
FILTERS = {
    "naive": (NaiveTarget, False),
    "pf_raw": (ParticleTarget, False),
    "pf_colour": (ParticleTarget, True),
    "ss_raw": (SparseTarget, False),
    "ss_colour": (SparseTarget, True),
}


@dataclass
class TrackerParams:
    filter: str = "ss_colour"
    samples: int = 400             # N_s, Sparse Sampling
    particles: int = 100           # N_p, particle filter
    sx: float = 0.30               # s_x = s_y, the body ellipsoid's horizontal radius (m)
    alpha: float = 1.5             # region enlargement (naive) and delta = alpha s_x (SS)
    beta: float = 1.2              # naive: vertical enlargement
    lam: float = 0.8               # lambda of Eq. 4.8 / 4.19
    adapt: float = 0.9             # histogram adaptation of Eq. 4.11
    coverage: float = 0.8          # gamma keeps the bins holding this share of H (Eq. 4.21)
    ss_radius: int = 2             # r of C(y, q=26, r)
    ss_step: float = 0.08          # SS propagation: largest offset per axis (m)
    ss_reseed: float = 0.25        # SS: share of samples drawn afresh on the surface (0: the thesis)
    ss_blocking: float = 1.0       # SS blocking k = ss_blocking / s_x^2
    colour_freeze: float = 0.9     # no histogram adaptation while another target is this close (m, xy; 0: the thesis)
    colour_unblock: bool = True    # SS: a sample's blocking is lifted by its colour score (False: the thesis)
    refine_colour: float = 0.45    # colour filters: no re-centring while another target is this close (m; 0: always)
    pf_sigma: tuple = (0.05, 0.05, 0.03)   # PF propagation noise (m)
    z_min: float = 0.3
    z_max: float = 1.4
    new_distance: float = 0.5      # no new track closer than this to a target (m, xy)
    new_distance_merged: float = 0.6   # the same for people merged into a tracked component
    claim_radius: float = 0.45     # voxels this close to a target (xy) are its own
    confirm_frames: int = 5
    confirm_sure_frames: int = 2   # ... or this many when every sighting was a sure person in an empty room
                                   # (beyond the thesis; >= confirm_frames: never sooner)
    sure_probability: float = 0.97  # the classifier's person probability of a sure sighting in an empty room
    new_min_z: float = 0.6         # no new track whose candidate's centroid is lower (m; -inf: any)
    candidate_min_z: float = 0.9   # a new component's candidate placed (xy) by its voxels this high (m; -inf: all)
    duplicate_distance: float = 0.55   # two targets closer than this (xy) ...
    duplicate_frames: int = 6      # ... for this many frames: the younger is a duplicate
    duplicate_similarity: float = 0.5   # colour filters: ... and dressed alike (Bhattacharyya >= this; 0: the thesis)
    same_place: float = 0.2        # ... or closer than this (xy), however dressed: two bodies do not fit (0: off)
    min_support_kg: float = 10.0
    lost_frames: int = 8
    no_person_frames: int = 18
    no_person_credit: float = 1.0   # frames of patience earned by each frame the share was a person (0: the thesis)
    no_person_cap: int = 100       # ... at most this many frames more (4 s at 25 fps)
    share_frames: int = 12         # a younger track whose share is no person this long is a duplicate
    reid_frames: int = 50          # a new track this soon after a track ended near it takes its id (0: never)
    reid_distance: float = 0.75    # ... within this distance (m, xy) of where it ended
    reid_similarity: float = 0.5   # ... with reference histograms this similar (Bhattacharyya), colour filters
    vacated_frames: int = 50       # a track this long within vacated_radius of a place (xy) ... (0: off, the thesis)
    vacated_radius: float = 0.3    # ... that then goes farther than vacated_depart from it has vacated it:
    vacated_depart: float = 0.6    # no new track starts within vacated_radius of it (a background's ghost)
    vacated_release: int = 25      # ... until no voxel has been there for this many frames
    refine: bool = True            # re-centre estimates on their share of the voxels (beyond the thesis)
    refine_radius: float = 0.45
    refine_particles: bool = True   # the particle filter's cloud moves with its re-centred estimate
    refine_min_z: float = 0.9      # re-centre (xy) on the voxels at least this high (the upper body; -inf: all)
    seed: int = 0

    @classmethod
    def from_dict(cls, values: dict) -> "TrackerParams":
        names = {f.name for f in fields(cls)}
        unknown = set(values) - names
        if unknown:
            raise ValueError(f"unknown tracker parameters {sorted(unknown)}")
        p = cls(**values)
        if p.filter not in FILTERS:
            raise ValueError(f"filter {p.filter!r} is not one of {', '.join(FILTERS)}")
        return p


class _Track:
    __slots__ = ("id", "target", "age", "low_support", "no_person", "close", "person", "anchor", "settled", "away")

    def __init__(self, tid, target):
        self.id, self.target = tid, target
        self.age = 0
        self.low_support = self.no_person = self.close = 0
        self.person = 0   # frames its share was a person (the patience it earned, ``no_person_credit``)
        self.anchor = np.array(target.x[:2], dtype=np.float64)   # the place it stays at (``vacated_frames``)
        self.settled = 0  # frames it stayed within vacated_radius of the anchor
        self.away = 0     # frames since it went beyond vacated_radius of it, not yet beyond vacated_depart

    def settle(self, p) -> np.ndarray | None:
        """One frame of the place the track stays at: the anchor when the track has just
        vacated it (stayed ``vacated_frames`` there, now beyond ``vacated_depart``), else
        None. Within ``vacated_radius`` the anchor follows slow drifts; between the two
        distances for a second the track has moved over, not away: a new anchor."""
        d = float(np.hypot(*(self.target.x[:2] - self.anchor)))
        if d < p.vacated_radius:
            self.settled += 1
            self.away = 0
            self.anchor += ANCHOR_FOLLOW * (self.target.x[:2] - self.anchor)
            return None
        left = self.anchor.copy() if d > p.vacated_depart and self.settled >= p.vacated_frames else None
        self.away += 1
        if left is not None or d > p.vacated_depart or self.away > MOVED_OVER:
            self.anchor = np.array(self.target.x[:2], dtype=np.float64)
            self.settled = self.away = 0
        return left


class MultiTracker:
    """Tracks of one room (see module docstring). ``classifier``: the person / no-person
    :class:`~app.tracking.classifier.DecisionTree` used on unclaimed voxels (None: the
    components' own verdicts only)."""

    def __init__(self, params: TrackerParams | None = None, classifier=None, ghost_test=None):
        self.p = params or TrackerParams()
        self.cls, self.colour = FILTERS[self.p.filter]
        self.classifier = classifier
        #: beyond the thesis: ``(centres of a candidate's voxels, centres of the tracked
        #: people's) -> bool``, True for a ghost where tracked people's silhouette cones cross
        #: (:class:`~app.tracking.ghosts.GhostTest`); None: no such test (the thesis)
        self.ghost_test = ghost_test
        self.ghosts = 0   # candidate sightings the ghost test turned away
        self._seen = None
        self.rng = np.random.default_rng(self.p.seed)
        self.tracks: list[_Track] = []
        self.candidates: list[tuple[np.ndarray, int, int]] = []   # (centre, sightings, sure sightings)
        self.next_id = 1
        self.deleted = 0
        self.ended: list[tuple] = []   # (frame, id, position, reference histogram) of recently ended tracks
        #: the last ``VACATED_KEPT`` places tracks stayed at and then left (``vacated_frames``):
        #: ``[x, y, frames nothing stood there]``
        self.vacated: deque = deque(maxlen=VACATED_KEPT)
        #: (frame, "new" | "end", id, why, position) of the last ``EVENTS_KEPT`` tracks created
        #: or ended (a log, bounded: a room that runs for weeks starts and ends tracks for good)
        self.events: deque = deque(maxlen=EVENTS_KEPT)
        self._col_first = None
        self._scratch = None
        #: the ghost test's view of one frame (:meth:`_ghost`): the voxels of the tracked
        #: people's components (mask) and their centres, built once a frame, dropped after it
        self._known_frame = self._known = self._known_centres = self._known_counts = None

    # -- one frame --------------------------------------------------------------------
    def update(self, scene: SceneFrame) -> tuple[np.ndarray, np.ndarray]:
        """Step every filter, delete and create tracks; ``(ids (T,), positions (T, 3))``."""
        if self.tracks:
            self.cls.step_all([t.target for t in self.tracks], scene)
            if self.p.refine:
                self._refine(scene)
        self._delete(scene)
        if self.p.vacated_frames > 0:
            self._vacate(scene)
        self._create(scene)
        self._known_frame = self._known = self._known_centres = self._known_counts = None
        ids = np.array([t.id for t in self.tracks], dtype=np.int64)
        pos = np.array([t.target.x for t in self.tracks], dtype=np.float64).reshape(-1, 3)
        return ids, pos

    def _refine(self, scene: SceneFrame) -> None:
        """Beyond the thesis (``refine``): each target's estimate becomes the centroid of
        the voxels within ``refine_radius`` (xy) that are nearer to it than to any other
        target, so the filter's estimate is re-centred on its share of the mass (the
        filters keep their samples / particles; identities stay theirs)."""
        xs = np.ascontiguousarray([t.target.x for t in self.tracks], dtype=np.float64)
        r = self.p.refine_radius
        o = scene.origin
        acc = np.zeros(3)
        for i, t in enumerate(self.tracks):
            if self.p.refine_colour > 0 and getattr(t.target, "reference", None) is not None:
                d2 = ((np.delete(xs, i, axis=0)[:, :2] - xs[i, :2]) ** 2).sum(axis=1)
                if (d2 < self.p.refine_colour ** 2).any():   # colour, not the Voronoi share, decides
                    continue
            # only targets whose discs overlap compete for voxels
            close = np.nonzero(((xs[:, :2] - xs[i, :2]) ** 2).sum(axis=1) < (2 * r) ** 2)[0]
            k = columns.voronoi_sum(scene.col_start, scene.indices, scene.dims[0], scene.dims[1], o[0], o[1], o[2],
                                    scene.voxel_size, xs, i, close, r, self.p.refine_min_z, acc)
            if k >= 3:
                x = acc / k
                if self.p.refine_min_z > -np.inf:   # the upper body places the target in xy only
                    x[2] = t.target.x[2]
                if self.p.refine_particles and getattr(t.target, "particles", None) is not None:
                    t.target.particles = t.target.particles + (x - t.target.x)   # the cloud follows
                t.target.x = x

    def relocate(self, scene: SceneFrame, radius: float, step: float = 0.1, shifts: int = 8) -> None:
        """After a gap in the frames the tracker saw (a worker restarted from a snapshot,
        live: about a second), before :meth:`update`: every target looks for its person
        within ``radius`` (xy; the distance a person walks in the gap), where the filters'
        own search (``alpha s_x`` around the last estimate) would lose one who moved
        farther. The nearest person first: the disc around the last estimate grows by
        ``step`` from ``refine_radius`` until the target's Voronoi share of its upper-body
        voxels (``refine_min_z``) holds a quarter of ``min_support_kg``; then mean shift
        with ``refine_radius`` (at most ``shifts`` steps) centres it on that person. A
        target that finds nobody stays. Samples are drawn afresh around the new estimate;
        a particle cloud moves with it."""
        if not self.tracks:
            return
        p = self.p
        xs = np.ascontiguousarray([t.target.x for t in self.tracks], dtype=np.float64)
        o = scene.origin
        acc = np.zeros(3)
        everyone = np.arange(len(self.tracks))
        need = max(3, int(0.25 * p.min_support_kg / (1100.0 * scene.voxel_size ** 3)))

        def share(i, r):
            return columns.voronoi_sum(scene.col_start, scene.indices, scene.dims[0], scene.dims[1], o[0], o[1], o[2],
                                       scene.voxel_size, xs, i, everyone, float(r), p.refine_min_z, acc)

        for i, t in enumerate(self.tracks):
            found = False
            for r in np.arange(p.refine_radius, max(radius, p.refine_radius) + step / 2, step):
                k = share(i, r)
                if k >= need:
                    xs[i, :2] = (acc / k)[:2]
                    found = True
                    break
            if not found:
                continue
            for _ in range(shifts):
                k = share(i, p.refine_radius)
                if k < 3:
                    break
                moved = float(((acc[:2] / k - xs[i, :2]) ** 2).sum())
                xs[i, :2] = (acc / k)[:2]
                if moved < (0.25 * scene.voxel_size) ** 2:
                    break
            g = t.target
            shift = xs[i] - g.x
            g.x = xs[i].copy()
            if getattr(g, "particles", None) is not None:
                g.particles = g.particles + shift
            elif hasattr(g, "samples"):
                g._seed(scene)

    def _make(self, position, scene):
        if self.cls is NaiveTarget:
            return NaiveTarget(position, scene, self.rng, self.p)
        return self.cls(position, scene, self.rng, self.p, colour=self.colour)

    def _disc(self, scene: SceneFrame, x, r: float) -> tuple[int, int]:
        """``(voxels, host label)`` within ``r`` (xy) of ``x`` (host -1 when none)."""
        if self._scratch is None or len(self._scratch) < scene.components:
            self._scratch = np.zeros(max(scene.components, 64), dtype=np.int64)
        o = scene.origin
        n, host = columns.disc_support(scene.col_run, scene.run_z0, scene.run_z1, scene.run_label, scene.dims[0],
                                       scene.dims[1], o[0], o[1], scene.voxel_size, float(x[0]), float(x[1]), float(r),
                                       self._scratch)
        return int(n), int(host)

    def _shares(self, scene: SceneFrame):
        """Host component of each track (the label with most voxels within ``s_x``, or -1)
        and the person verdict of the track's share: the voxels of its host that are
        nearer (xy) to it than to any other track the component hosts (§4.2.3: the
        classifier applied to the voxels assigned to a target)."""
        p = self.p
        hosts = np.full(len(self.tracks), -1, dtype=np.int64)
        support = np.zeros(len(self.tracks))
        for i, t in enumerate(self.tracks):
            k, hosts[i] = self._disc(scene, t.target.x, p.sx)
            support[i] = k * scene.voxel_size ** 3 * 1100.0
        person = np.zeros(len(self.tracks), dtype=bool)
        shared = []
        for c in np.unique(hosts[hosts >= 0]):
            mine = np.nonzero(hosts == c)[0]
            if len(mine) == 1 or self.classifier is None:
                person[mine] = bool(scene.person[c])
            else:
                shared.append((c, mine))
        if shared:
            # every voxel of a shared host goes to the nearest (xy) of its tracks
            host_of = np.full(scene.components, -1, dtype=np.int64)
            groups = np.concatenate([mine for _, mine in shared])
            group_start = np.cumsum([0] + [len(mine) for _, mine in shared])
            for g, (c, _) in enumerate(shared):
                host_of[c] = g
            xs = np.ascontiguousarray([t.target.x for t in self.tracks], dtype=np.float64)
            owner = np.empty(len(scene.run_label), dtype=np.int64)
            columns.share_owners(scene.col_run, scene.run_label, scene.dims[0], scene.dims[1], scene.origin[0],
                                 scene.origin[1], scene.voxel_size, host_of, xs, groups, group_start, owner)
            runs = np.nonzero(owner >= 0)[0]
            f = self._run_features(scene, runs, owner[runs], len(groups))
            verdict = self.classifier.predict(f[:, :len(CLASSIFIER_FEATURES)]).astype(bool)
            has = f[:, 8] > 0
            person[groups[has]] = verdict[has]
        return hosts, person, support

    @staticmethod
    def _run_features(scene: SceneFrame, runs: np.ndarray, part: np.ndarray, k: int) -> np.ndarray:
        """Features (k, F) float32 of the voxels of ``runs`` grouped by ``part``, as
        :func:`component_features` computes them over the voxels."""
        mins = np.full((k, 3), np.iinfo(np.int64).max, dtype=np.int64)
        maxs = np.full((k, 3), -1, dtype=np.int64)
        sums = np.zeros((k, 3))
        counts = np.zeros(k, dtype=np.int64)
        columns.run_sums(runs, scene.run_z0, scene.run_z1, scene.run_col, scene.dims[1], part, k, mins, maxs, sums,
                         counts)
        return features_from_sums(mins, maxs, sums, counts, scene.origin, scene.voxel_size)

    def _delete(self, scene: SceneFrame) -> None:
        p = self.p
        hosts, person, support = self._shares(scene)
        oldest = {}
        for i, t in enumerate(self.tracks):
            if hosts[i] >= 0 and (hosts[i] not in oldest or t.id < oldest[hosts[i]]):
                oldest[hosts[i]] = t.id
        keep = []
        for i, t in enumerate(self.tracks):
            t.age += 1
            t.low_support = t.low_support + 1 if support[i] < p.min_support_kg else 0
            t.no_person = 0 if person[i] else t.no_person + 1
            t.person += bool(person[i])
            dup = any(self.duplicate_of(o.target, t.target) for o in keep if o.id < t.id)
            t.close = t.close + 1 if dup else 0
            # a failing share is the younger track's fault while an older track holds the component
            shared_fail = t.no_person >= p.share_frames and hosts[i] >= 0 and oldest[hosts[i]] != t.id
            alone_fail = t.no_person >= p.no_person_frames + min(int(p.no_person_credit * t.person), p.no_person_cap)
            if t.low_support >= p.lost_frames or alone_fail or shared_fail or t.close >= p.duplicate_frames:
                self.deleted += 1
                why = ("lost" if t.low_support >= p.lost_frames else "duplicate" if t.close >= p.duplicate_frames
                       else "no-person" if alone_fail else "shared-no-person")
                self.events.append((scene.frame, "end", t.id, why, t.target.x.copy()))
                if why in ("no-person", "shared-no-person") and p.reid_frames > 0:
                    self.ended.append((scene.frame, t.id, t.target.x.copy(), getattr(t.target, "reference", None)))
                continue
            keep.append(t)
        self.tracks = keep

    def _vacate(self, scene: SceneFrame) -> None:
        """The places left behind this frame (module docstring, 5.): the tracks' new ones
        (one place where two were), the counts of frames nothing stood there, the
        places released."""
        p = self.p
        for t in self.tracks:
            if (left := t.settle(p)) is not None and not self._took_over(t, scene.frame):
                self.vacated = deque([v for v in self.vacated if not _near(v, left, p.vacated_radius)]
                                     + [np.array([left[0], left[1], 0.0])], maxlen=VACATED_KEPT)
        for v in self.vacated:
            v[2] = v[2] + 1 if self._disc(scene, v, p.vacated_radius)[0] == 0 else 0
        if any(v[2] >= p.vacated_release for v in self.vacated):
            self.vacated = deque([v for v in self.vacated if v[2] < p.vacated_release], maxlen=VACATED_KEPT)

    def _took_over(self, track: _Track, frame: int) -> bool:
        """Whether ``track`` went where a track it made a duplicate ended, within the last
        ``vacated_frames`` frames: dragged off its person onto another's, it left nobody's
        place (the person it followed is still there and needs a new track)."""
        p = self.p
        return any(why == "duplicate" and frame - f <= p.vacated_frames
                   and float(np.hypot(*(x[:2] - track.target.x[:2]))) < p.vacated_depart
                   for f, kind, _, why, x in self.events if kind == "end")

    def duplicate_of(self, older, younger) -> bool:
        """``younger`` is on ``older``'s person this frame: within ``duplicate_distance``
        and dressed alike, or (beyond the thesis) within ``same_place`` whatever the
        colours: two people's centres are never that close (a second track on one tall
        person's legs has other colours than the first on the whole body)."""
        d2 = float(((older.x[:2] - younger.x[:2]) ** 2).sum())
        if d2 >= self.p.duplicate_distance ** 2:
            return False
        return d2 < self.p.same_place ** 2 or self._alike(older, younger)

    def _alike(self, a, b) -> bool:
        """Beyond the thesis (``duplicate_similarity``): with colour, two close targets
        are one person's only when their reference histograms are alike (two people
        dressed differently standing close are two people); without colour, or with
        ``duplicate_similarity`` 0 (the thesis), closeness alone decides."""
        ra, rb = getattr(a, "reference", None), getattr(b, "reference", None)
        if self.p.duplicate_similarity <= 0 or ra is None or rb is None:
            return True
        return bhattacharyya(ra, rb) >= self.p.duplicate_similarity

    def _create(self, scene: SceneFrame) -> None:
        p = self.p
        n = scene.n
        if n == 0 or not scene.person.any():
            self.candidates = []
            return
        hosts = set()
        for t in self.tracks:
            k, host = self._disc(scene, t.target.x, p.claim_radius)
            if k:
                hosts.add(host)
        xs = np.ascontiguousarray([t.target.x for t in self.tracks], dtype=np.float64).reshape(-1, 3)
        free = np.empty(len(scene.run_label), dtype=bool)
        o = scene.origin
        columns.free_runs(scene.col_run, scene.dims[0], scene.dims[1], o[0], o[1], scene.voxel_size, xs,
                          float(p.claim_radius), scene.run_label, scene.person, free)
        free_runs = np.nonzero(free)[0]
        free_labels = scene.run_label[free_runs]
        found = []
        targets_xy = xs[:, :2]
        present = np.nonzero(np.bincount(free_labels, minlength=scene.components))[0]
        for c in present:
            if c not in hosts:                           # a component no target holds
                centre = self._candidate_centre(scene, c)
                if len(targets_xy) and (((targets_xy - centre[:2]) ** 2).sum(axis=1) < p.new_distance ** 2).any():
                    continue
                if self._ghost(scene, np.nonzero(scene.labels == c)[0], hosts):
                    continue
                # sure only while the room has no track (the first person in): phantoms of
                # the hull come with people, and crowd6's are "sure" persons too
                found.append((centre, not len(targets_xy) and self._sure(scene.features[c:c + 1])))
                continue
            # the free pieces of a tracked component that look like a person
            runs = free_runs[free_labels == c]
            size = int((scene.run_z1[runs] - scene.run_z0[runs] + 1).sum())
            if size * scene.voxel_size ** 3 * 1100.0 < 4 * p.min_support_kg:
                continue                                 # too little left for a person
            pieces, k = self._run_pieces(scene, runs)
            feats = self._run_features(scene, runs, pieces, k).astype(np.float64)
            if self.classifier is not None:
                looks = self.classifier.predict(feats[:, :len(CLASSIFIER_FEATURES)])
            else:
                looks = feats[:, 0] >= 4 * p.min_support_kg
            for j in np.nonzero(looks)[0]:
                mine = runs[pieces == j]
                centre = scene.centres_at(columns.run_positions(scene.run_start, mine)).mean(axis=0)
                if len(targets_xy) and \
                        (((targets_xy - centre[:2]) ** 2).sum(axis=1) < p.new_distance_merged ** 2).any():
                    continue
                if self._ghost(scene, columns.run_positions(scene.run_start, mine), hosts):
                    continue
                found.append((centre, False))   # a piece of a tracked blob is never sure
        # confirmation: a candidate seen again near where it was the frame before
        nxt = []
        for c, sure in found:
            if c[2] < p.new_min_z:   # a blob this low is a phantom or a piece, not a body
                continue
            if any(_near(v, c, p.vacated_radius) for v in self.vacated):
                continue             # where a person stood still and left: the background's ghost of them
            count, sure_count = 1, int(sure)
            for old, k, ks in self.candidates:
                if ((old[:2] - c[:2]) ** 2).sum() < p.new_distance ** 2:
                    count = max(count, k + 1)
                    sure_count = max(sure_count, ks + 1) if sure else 0
            if count >= p.confirm_frames or sure_count >= p.confirm_sure_frames:
                target = self._make(self._start(c), scene)
                tid = self._reidentify(scene, target)
                self.tracks.append(_Track(tid, target))
                self.events.append((scene.frame, "new", tid, "" if tid == self.next_id - 1 else "re-identified",
                                    c.copy()))
            else:
                nxt.append((c, count, sure_count))
        self.candidates = nxt

    def _ghost(self, scene: SceneFrame, mine: np.ndarray, hosts: set) -> bool:
        """The ghost test of the voxels at list positions ``mine`` against those of the
        components the tracks hold (the people known: whom a ghost is made of)."""
        if self.ghost_test is None or not hosts:
            return False
        if self._known_frame is not scene:   # the known people's voxels, once a frame
            self._known_frame = scene
            self._known = np.isin(scene.labels, np.fromiter(hosts, dtype=np.int64, count=len(hosts)))
            self._known_centres = scene.centres_at(np.nonzero(self._known)[0])
            self._known_counts = None
        theirs = self._known[mine]
        minus = scene.centres_at(mine[theirs]) if theirs.any() else None   # a piece of a tracked component
        if len(self._known_centres) - (0 if minus is None else len(minus)) == 0:
            return False                                   # nobody else: no ghost of anyone
        if self._known_counts is None:                     # the people projected once a frame
            self._known_counts = self.ghost_test.counts(self._known_centres)
            self._seen = self.ghost_test.seen_cells(scene.silhouettes)   # where the frame brought them
        if self.ghost_test.verdict(scene.centres_at(mine), self._known_counts, minus, self._seen):
            self.ghosts += 1
            return True
        return False

    def _component_centre(self, scene: SceneFrame, c: int) -> np.ndarray:
        """Mean voxel centre of component ``c`` (all of the frame's component centres
        are summed in one pass, once per frame, when first asked for)."""
        if getattr(self, "_centres_frame", None) is not scene:
            self._centres_frame = scene
            sums = np.zeros((scene.components, 3))
            counts = np.zeros(scene.components, dtype=np.int64)
            columns.component_sums(scene.indices, scene.labels, scene.origin, scene.voxel_size, sums, counts)
            self._centres = sums / np.maximum(counts, 1)[:, None]
        return self._centres[c].copy()

    def _sure(self, features: np.ndarray) -> bool:
        """Beyond the thesis (``confirm_sure_frames``): the classifier gives the sighting's
        features a person probability of at least ``sure_probability``."""
        if self.classifier is None or self.p.confirm_sure_frames >= self.p.confirm_frames:
            return False
        x = np.asarray(features, dtype=np.float64)[:, :len(CLASSIFIER_FEATURES)]
        return bool(self.classifier.probability(x)[0] >= self.p.sure_probability)

    def _candidate_centre(self, scene: SceneFrame, c: int) -> np.ndarray:
        """Where a component no target holds puts its candidate: beyond the thesis
        (``candidate_min_z``), the xy of the centroid of its voxels at least that high (the
        upper body, as ``refine`` places targets), z the whole component's. The k = 1 hull
        at 2 cm merges a person with the phantom of the room's corner for a few frames
        (gesture1 frames 1-4: the component's centroid 0.55 m off the body, the upper
        voxels' within 2 cm), which moved the candidate, restarted its confirmation and
        delayed the track to frame 9; ``-inf`` keeps the component's centroid (the thesis)."""
        centre = self._component_centre(scene, c)
        if self.p.candidate_min_z == -np.inf:
            return centre
        kz = int(np.floor((self.p.candidate_min_z - scene.origin[2]) / scene.voxel_size))
        upper = (scene.labels == c) & (scene.indices[:, 2] >= kz)
        if upper.sum() >= 3:
            centre[:2] = scene.origin[:2] + (scene.indices[upper, :2].mean(axis=0) + 0.5) * scene.voxel_size
        return centre

    def _reidentify(self, scene: SceneFrame, target) -> int:
        """Beyond the thesis (``reid_frames``): a new track confirmed within
        ``reid_distance`` (xy) of where a track ended for a no-person verdict (not lost:
        a person who left; not a duplicate)
        at most ``reid_frames`` frames ago, and, with colour, with a reference histogram
        at least ``reid_similarity`` like the ended track's, is that person back: it takes
        the ended track's id (the nearest such). Otherwise a new id."""
        p = self.p
        self.ended = [e for e in self.ended if scene.frame - e[0] <= p.reid_frames]
        best, best_d = None, p.reid_distance ** 2
        for k, (_, tid, x, ref) in enumerate(self.ended):
            d = float(((x[:2] - target.x[:2]) ** 2).sum())
            if d > best_d:
                continue
            new_ref = getattr(target, "reference", None)
            if ref is not None and new_ref is not None and bhattacharyya(ref, new_ref) < p.reid_similarity:
                continue
            best, best_d = k, d
        if best is None:
            self.next_id += 1
            return self.next_id - 1
        return self.ended.pop(best)[1]

    def _run_pieces(self, scene: SceneFrame, runs: np.ndarray) -> tuple[np.ndarray, int]:
        """Connected pieces (26-connectivity) of a subset of the frame's runs: the piece
        of each run (numbered in run order) and their count."""
        from app.components import label_runs

        cols = scene.dims[0] * scene.dims[1]
        if self._col_first is None or len(self._col_first) != cols:
            self._col_first = np.full(cols, -1, dtype=np.int64)
        pieces = np.empty(len(runs), dtype=np.int64)
        k = label_runs(scene.run_z0[runs], scene.run_z1[runs], scene.run_col[runs], len(runs), scene.dims[1], 26,
                       self._col_first, pieces)
        return pieces, int(k)

    def _start(self, centre: np.ndarray) -> np.ndarray:
        x = centre.copy()
        x[2] = float(np.clip(x[2], self.p.z_min, self.p.z_max))
        return x


def warm_up() -> None:
    """Compile the numba kernels of every filter on a tiny scene (cached on disk after
    the first time), so a worker's first frame costs what the others do."""
    from app.tracking.blobs import ComponentAnalysis
    from app.tracking.scene import OccupancyIndex

    dims = (12, 12, 12)
    ii, jj, kk = np.meshgrid(np.arange(3, 9), np.arange(3, 9), np.arange(0, 10), indexing="ij")
    idx = np.stack([ii, jj, kk], -1).reshape(-1, 3).astype(np.uint16)
    colours = np.full((len(idx), 3), 128, np.uint8)
    surface = np.ones(len(idx), bool)
    labels, feats, person = ComponentAnalysis(dims, (0, 0, 0), 0.1)(idx)
    occ = OccupancyIndex(dims)
    for name in FILTERS:
        tracker = MultiTracker(TrackerParams(filter=name, samples=20, particles=10, confirm_frames=1))
        for f in range(3):
            tracker.update(SceneFrame(f, 0.0, idx, colours, surface, labels, feats, person, (0, 0, 0), 0.1, occ))
    from app.tracking.ghosts import warm_up as ghosts_warm_up
    ghosts_warm_up()
