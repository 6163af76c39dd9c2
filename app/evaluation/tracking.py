"""Multi-person tracking scores against ground truth (thesis §4.4.1, CLEAR MOT; IDF1).

CLEAR MOT (Bernardin & Stiefelhagen, Eq. 4.22-4.23), as CLEAR 2007 scored the thesis:
positions compared in the xy plane only, a hypothesis matches a true person within
``gate`` (500 mm). Per frame, a correspondence of the previous frame is kept while it
stays within the gate; the remaining people and hypotheses are matched by the
Hungarian algorithm on distance. A person matched to a different hypothesis id than
at its last match is a mismatch. A frame of the ground truth without a line in the
results counts as a frame with no hypothesis (all misses).

IDF1 (Ristani et al. 2016): the one-to-one assignment of true identities to hypothesis
ids that maximises the frames where the pair is within the gate (IDTP);
``IDF1 = 2 IDTP / (true detections + hypothesis detections)``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["TrackingScore", "score_tracking", "truth_frames", "result_frames"]

GATE_M = 0.5


@dataclass
class TrackingScore:
    frames: int = 0
    truths: int = 0           # sum_t g_t
    hypotheses: int = 0
    matches: int = 0          # sum_t c_t
    distance_m: float = 0.0   # sum of d_{i,t}
    misses: int = 0
    false_positives: int = 0
    mismatches: int = 0
    idtp: int = 0
    gt_ids: int = 0
    hyp_ids: int = 0
    per_frame: list = field(default_factory=list, repr=False)
    #: frame -> {true id: hypothesis id} of the frame's matches (who was found, by which track)
    matched: dict = field(default_factory=dict, repr=False)

    @property
    def motp_mm(self) -> float:
        """Eq. 4.22, in millimetres."""
        return 1e3 * self.distance_m / self.matches if self.matches else float("nan")

    @property
    def mota(self) -> float:
        """Eq. 4.23."""
        if not self.truths:
            return float("nan")
        return 1.0 - (self.misses + self.false_positives + self.mismatches) / self.truths

    @property
    def idf1(self) -> float:
        n = self.truths + self.hypotheses
        return 2.0 * self.idtp / n if n else float("nan")

    def summary(self) -> dict:
        g = max(self.truths, 1)
        return {
            "frames": self.frames, "truths": self.truths, "hypotheses": self.hypotheses,
            "motp_mm": round(self.motp_mm, 1), "mota": round(self.mota, 4), "idf1": round(self.idf1, 4),
            "miss_ratio": round(self.misses / g, 4), "false_positive_ratio": round(self.false_positives / g, 4),
            "mismatch_ratio": round(self.mismatches / g, 4), "misses": self.misses,
            "false_positives": self.false_positives, "mismatches": self.mismatches,
            "mismatches_per_1000": round(1000.0 * self.mismatches / g, 3),
            "true_ids": self.gt_ids, "track_ids": self.hyp_ids, "gate_mm": 1e3 * GATE_M,
        }


def truth_frames(records) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """``{frame: (ids (N,), centroids (N, 3))}`` from ``groundtruth.jsonl`` records."""
    out = {}
    for rec in records:
        people = rec.get("people", [])
        ids = np.asarray([p["id"] for p in people], dtype=np.int64)
        pos = np.asarray([p["centroid"] for p in people], dtype=np.float64).reshape(-1, 3)
        out[int(rec["frame"])] = (ids, pos)
    return out


def result_frames(records) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """``{frame: (ids, positions)}`` from ``tracks.jsonl`` records."""
    out = {}
    for rec in records:
        tracks = rec.get("tracks", [])
        ids = np.asarray([t["id"] for t in tracks], dtype=np.int64)
        pos = np.asarray([t["position"] for t in tracks], dtype=np.float64).reshape(-1, 3)
        out[int(rec["frame"])] = (ids, pos)
    return out


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """xy distances (len a, len b)."""
    return np.linalg.norm(a[:, None, :2] - b[None, :, :2], axis=2)


def score_tracking(truth: dict, results: dict, gate: float = GATE_M, frames=None) -> TrackingScore:
    """CLEAR MOT and IDF1 of ``results`` against ``truth`` (both ``{frame: (ids, positions)}``)
    over ``frames`` (default: every frame of the ground truth)."""
    frames = sorted(truth) if frames is None else list(frames)
    s = TrackingScore()
    last_match: dict[int, int] = {}    # true id -> hypothesis id of its last match
    current: dict[int, int] = {}       # correspondences of the previous frame
    pair_hits: dict[tuple[int, int], int] = {}
    gt_seen, hyp_seen = set(), set()
    empty = (np.zeros(0, np.int64), np.zeros((0, 3)))
    for f in frames:
        gid, gpos = truth.get(f, empty)
        hid, hpos = results.get(f, empty)
        s.frames += 1
        s.truths += len(gid)
        s.hypotheses += len(hid)
        gt_seen.update(gid.tolist())
        hyp_seen.update(hid.tolist())
        d = _distances(gpos, hpos) if len(gid) and len(hid) else np.zeros((len(gid), len(hid)))
        # IDF1 co-occurrences within the gate
        for i, j in zip(*np.nonzero(d <= gate)):
            key = (int(gid[i]), int(hid[j]))
            pair_hits[key] = pair_hits.get(key, 0) + 1
        # CLEAR: keep last frame's correspondences that are still valid
        matched = {}
        g_index = {int(g): i for i, g in enumerate(gid)}
        h_index = {int(h): j for j, h in enumerate(hid)}
        for g, h in current.items():
            if g in g_index and h in h_index and d[g_index[g], h_index[h]] <= gate:
                matched[g_index[g]] = h_index[h]
        free_g = [i for i in range(len(gid)) if i not in matched]
        used_h = set(matched.values())
        free_h = [j for j in range(len(hid)) if j not in used_h]
        if free_g and free_h:
            sub = d[np.ix_(free_g, free_h)]
            cost = np.where(sub <= gate, sub, 1e6)
            rows, cols = linear_sum_assignment(cost)
            for r, c in zip(rows, cols):
                if sub[r, c] <= gate:
                    i, j = free_g[r], free_h[c]
                    matched[i] = j
                    g, h = int(gid[i]), int(hid[j])
                    if g in last_match and last_match[g] != h:
                        s.mismatches += 1
        current = {}
        for i, j in matched.items():
            g, h = int(gid[i]), int(hid[j])
            current[g] = h
            last_match[g] = h
            s.distance_m += float(d[i, j])
        s.matches += len(matched)
        s.misses += len(gid) - len(matched)
        s.false_positives += len(hid) - len(matched)
        s.per_frame.append((f, len(gid), len(hid), len(matched)))
        s.matched[f] = {int(gid[i]): int(hid[j]) for i, j in matched.items()}
    s.idtp = _idtp(pair_hits)
    s.gt_ids, s.hyp_ids = len(gt_seen), len(hyp_seen)
    return s


def _idtp(pair_hits: dict) -> int:
    """The largest total co-occurrence of a one-to-one assignment of ids."""
    if not pair_hits:
        return 0
    gts = sorted({g for g, _ in pair_hits})
    hyps = sorted({h for _, h in pair_hits})
    gi = {g: i for i, g in enumerate(gts)}
    hi = {h: j for j, h in enumerate(hyps)}
    m = np.zeros((len(gts), len(hyps)))
    for (g, h), n in pair_hits.items():
        m[gi[g], hi[h]] = n
    rows, cols = linear_sum_assignment(-m)
    return int(m[rows, cols].sum())
