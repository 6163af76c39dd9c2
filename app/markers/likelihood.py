"""The marker likelihood of the annealed particle filter (thesis §6.4.1.2, Eqs. 6.4-6.10).

For a particle's M landmarks ``x_m`` (the 15 contract joints of the body model):

- Eq. 6.4: ``p_mn = P_n(x_m)``, the projection onto view n (ideal pixels,
  :mod:`app.markers.epipolar`);
- Eq. 6.5: ``t_n`` the detection of view n nearest to ``p_mn``, dropped when farther
  than ``rho`` (occluded or missed: ``t_n`` empty);
- Eqs. 6.6-6.8: ``s_m`` proportional to the generalised symmetric epipolar distance of
  the non-empty ``t_n`` (every pair of views), normalised so that ``s_m <= 1``: here
  ``s_m = min(1, sqrt(d_SE^2 / pairs) / rho)`` (the thesis says only "normalised such
  that s_m <= 1"; this is the root mean square pair distance in units of ``rho``), and
  ``s_m = 1`` with fewer than two non-empty ``t_n``;
- Eq. 6.9: ``C = (1/M) sum_m s_m``; Eq. 6.10: ``w = exp(-C^2 / (2 sigma^2))``, sigma = 1.

``cost="reprojection"`` (ours, selectable; the thesis's is ``cost="thesis"``): the
epipolar term says whether the detections a landmark picked are one marker seen from
several views, but not where the landmark is within ``rho`` of them, so every particle
whose projections fall within ``rho`` of the right detections scores alike. It adds the
mean squared distance of the projections to their detections:
``s_m = min(1, sqrt(d_SE^2 / pairs + sum_n |p_mn - t_n|^2 / views) / rho)``.

``cost="both_ways"`` (ours, the default): the landmarks still pick their detections
freely, so two landmarks may share one marker (an elbow on the wrist's detections, the
wrist's own missed) and score as well as the truth. So the detections are asked to be
explained too: each *supported* detection (:func:`supported_detections`: a marker seen
consistently from three views; a false detection rarely is) adds its distance to the
nearest landmark projection of its view, in units of ``rho`` (at most 1), and ``C``
gains ``explain`` times their mean. On the simulated clips it was tuned on the thesis's
likelihood lost the person within a second; this one follows (docs/benchmarks.md).

``picks="exclusive"`` (ours; the thesis's Eq. 6.5 is ``"nearest"``): a limb whose own
markers no camera sees (the far arm, a leg behind another person) is still rewarded for
any detections that agree across views, so it drifted onto the nearest ones, the
person's own head or shoulder markers among them, and stayed there. With exclusive picks
a detection that several landmarks of one view pick is the pick of the landmark
projecting nearest to it only; the others have no detection in that view (``s_m = 1``
with fewer than two). A limb can no longer sit on a marker another landmark explains.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from app.markers.epipolar import fundamentals, ideal_pixels
from app.pose.model import joints_subset, segments_needed

__all__ = ["MarkerScorer", "COSTS", "PICKS", "marker_costs", "pair_distances", "tabled_costs", "exclusive_picks", "supported_detections", "triangulated_markers"]

COSTS = ("thesis", "reprojection", "both_ways")
PICKS = ("nearest", "exclusive")
_ANKLES = np.array([11, 14], dtype=np.int64)   # l_ankle, r_ankle in JOINTS order
ANKLE_HEIGHT = 0.039                          # of the stature: the ankle joint standing (app.pose.model)


@njit(cache=True, nogil=True)
def exclusive_picks(pick, pick_d2):
    """Exclusive picks (ours): where several landmarks of one view picked one detection
    (``pick`` (M, C) detection indices, -1 none; ``pick_d2`` their squared distances), it
    stays the pick of the nearest of them (the first at a tie); the others' become -1."""
    owner = np.full(max(pick.max() + 1, 1), -1, np.int64)
    settle_picks(pick, pick_d2, owner)


@njit(cache=True, nogil=True)
def settle_picks(pick, pick_d2, owner):
    """:func:`exclusive_picks` with ``owner`` (at least one per detection, all -1) given,
    left all -1 again: each detection's owner is the first landmark that picked it until a
    later one picks it strictly nearer."""
    M, C = pick.shape
    for n in range(C):
        for m in range(M):
            q = pick[m, n]
            if q < 0:
                continue
            o = owner[q]
            if o < 0:
                owner[q] = m
            elif pick_d2[m, n] < pick_d2[o, n]:
                pick[o, n] = -1
                owner[q] = m
            else:
                pick[m, n] = -1
        for m in range(M):
            if pick[m, n] >= 0:
                owner[pick[m, n]] = -1


@njit(cache=True, nogil=True)
def pair_distances(det, start, F):
    """The two halves of Eq. 6.6 for every pair of detections of different views:
    ``E1[qa, qb]`` the squared distance of detection qb to the epipolar line of qa in its
    view, ``E2[qa, qb]`` of qa to that of qb, for qa of a lower view than qb (zero
    elsewhere). A frame's detections are scored by every particle; these are the same for
    all of them."""
    Q = det.shape[0]
    C = start.shape[0] - 1
    E1 = np.zeros((Q, Q))
    E2 = np.zeros((Q, Q))
    for va in range(C):
        for vb in range(va + 1, C):
            f = F[va, vb]
            for qa in range(start[va], start[va + 1]):
                xa = det[qa, 0]
                ya = det[qa, 1]
                # L(t_a, b) = F_ab t_a in view b; L(t_b, a) = F_ab^T t_b in view a (Eq. 6.6)
                la = f[0, 0] * xa + f[0, 1] * ya + f[0, 2]
                lb = f[1, 0] * xa + f[1, 1] * ya + f[1, 2]
                lc = f[2, 0] * xa + f[2, 1] * ya + f[2, 2]
                n1 = la * la + lb * lb
                for qb in range(start[vb], start[vb + 1]):
                    xb = det[qb, 0]
                    yb = det[qb, 1]
                    e1 = la * xb + lb * yb + lc
                    ma = f[0, 0] * xb + f[1, 0] * yb + f[2, 0]
                    mb = f[0, 1] * xb + f[1, 1] * yb + f[2, 1]
                    mc = f[0, 2] * xb + f[1, 2] * yb + f[2, 2]
                    e2 = ma * xa + mb * ya + mc
                    n2 = ma * ma + mb * mb
                    if n1 > 0.0:
                        E1[qa, qb] = e1 * e1 / n1
                    if n2 > 0.0:
                        E2[qa, qb] = e2 * e2 / n2
    return E1, E2


@njit(cache=True, nogil=True)
def marker_costs(X, K, R, t, F, det, start, supported, rho, reprojection, explain, exclusive, out):
    """``out[p]`` = C of Eq. 6.9 for the landmarks ``X`` (P, M, 3) of P particles, plus
    ``explain`` times the mean unexplained share of the supported detections. With
    ``exclusive`` a detection picked by several landmarks of one view stays the pick of
    the landmark projecting nearest to it only (the others have no detection there)."""
    E1, E2 = pair_distances(det, start, F)
    tabled_costs(X, K, R, t, E1, E2, det, start, supported, rho, reprojection, explain, exclusive, out)


@njit(cache=True, nogil=True)
def tabled_costs(X, K, R, t, E1, E2, det, start, supported, rho, reprojection, explain, exclusive, out):
    """:func:`marker_costs` with the frame's :func:`pair_distances` given.

    Every particle's landmarks are projected first; a detection farther than ``rho`` from
    the box of all the particles' projections of a landmark in a view can be no
    particle's pick for that landmark nor explained by it, so each landmark searches its
    candidates only (the same picks and costs, to the bit, as searching them all)."""
    P, M = X.shape[0], X.shape[1]
    C = K.shape[0]
    Q = det.shape[0]
    r2 = rho * rho
    U = np.empty((P, M, C))
    V = np.empty((P, M, C))
    seen = np.empty((P, M, C), np.bool_)
    box = np.empty((M, C, 4))
    box[:, :, 0] = np.inf
    box[:, :, 1] = -np.inf
    box[:, :, 2] = np.inf
    box[:, :, 3] = -np.inf
    for p in range(P):
        for m in range(M):
            for n in range(C):
                xc = R[n, 0, 0] * X[p, m, 0] + R[n, 0, 1] * X[p, m, 1] + R[n, 0, 2] * X[p, m, 2] + t[n, 0]
                yc = R[n, 1, 0] * X[p, m, 0] + R[n, 1, 1] * X[p, m, 1] + R[n, 1, 2] * X[p, m, 2] + t[n, 1]
                zc = R[n, 2, 0] * X[p, m, 0] + R[n, 2, 1] * X[p, m, 1] + R[n, 2, 2] * X[p, m, 2] + t[n, 2]
                seen[p, m, n] = zc > 1e-6
                if not seen[p, m, n]:
                    continue
                u = K[n, 0, 0] * xc / zc + K[n, 0, 1] * yc / zc + K[n, 0, 2]
                v = K[n, 1, 1] * yc / zc + K[n, 1, 2]
                U[p, m, n] = u
                V[p, m, n] = v
                box[m, n, 0] = min(box[m, n, 0], u)
                box[m, n, 1] = max(box[m, n, 1], u)
                box[m, n, 2] = min(box[m, n, 2], v)
                box[m, n, 3] = max(box[m, n, 3], v)
    reach = rho * (1.0 + 1e-9)                # rho, and no rounding of d2 left out
    first = np.zeros(M * C + 1, np.int64)    # candidates of (m, n): cand[first[m C + n]:first[m C + n + 1]]
    cand = np.empty(max(M * Q, 1), np.int64)
    k = 0
    for m in range(M):
        for n in range(C):
            for q in range(start[n], start[n + 1]):
                if (box[m, n, 0] - reach <= det[q, 0] <= box[m, n, 1] + reach
                        and box[m, n, 2] - reach <= det[q, 1] <= box[m, n, 3] + reach):
                    cand[k] = q
                    k += 1
            first[m * C + n + 1] = k
    qs = np.empty(C, np.int64)
    pick = np.empty((M, C), np.int64)
    pick_d2 = np.empty((M, C))
    near = np.empty(Q)                       # per detection: the squared distance of the nearest projection
    owner = np.full(max(Q, 1), -1, np.int64)
    n_supported = 0
    for q in range(Q):
        if supported[q]:
            n_supported += 1
    for p in range(P):
        total = 0.0
        near[:] = r2
        for m in range(M):
            for n in range(C):
                pick[m, n] = -1
                if not seen[p, m, n]:
                    continue
                u = U[p, m, n]
                v = V[p, m, n]
                best = r2
                bi = -1
                for i in range(first[m * C + n], first[m * C + n + 1]):
                    q = cand[i]
                    du = det[q, 0] - u
                    dv = det[q, 1] - v
                    d2 = du * du + dv * dv
                    if d2 < near[q]:
                        near[q] = d2
                    if d2 <= best:
                        best = d2
                        bi = q
                pick[m, n] = bi
                pick_d2[m, n] = best
        if exclusive:
            settle_picks(pick, pick_d2, owner)
        for m in range(M):
            k = 0
            reproj = 0.0
            for n in range(C):
                bi = pick[m, n]
                if bi >= 0:
                    qs[k] = bi
                    reproj += pick_d2[m, n]
                    k += 1
            if k < 2:
                total += 1.0
                continue
            d2 = 0.0
            pairs = 0
            for a in range(k - 1):      # qs ascend with their views: E1, E2 hold each pair
                for b in range(a + 1, k):
                    d2 += E1[qs[a], qs[b]]
                    d2 += E2[qs[a], qs[b]]
                    pairs += 1
            s2 = d2 / pairs
            if reprojection:
                s2 += reproj / k
            s = np.sqrt(s2) / rho
            total += s if s < 1.0 else 1.0
        cost = total / M
        if explain > 0 and n_supported > 0:
            # every supported detection's distance to the nearest landmark projection of its view
            unexplained = 0.0
            for q in range(Q):
                if supported[q]:
                    unexplained += np.sqrt(near[q]) / rho
            cost += explain * unexplained / n_supported
        out[p] = cost


def supported_detections(ideal, cameras, F, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which detections (flat, view by view) are a marker seen from several views: with
    three views or more that have detections, one detection of another view lies within
    ``tol`` of its epipolar line and the point the two triangulate projects within ``tol``
    of a detection of a third view (a false detection rarely has both); with two such
    views, the first test alone (a rig's other cameras may see nothing of the person).
    Also the 3D points (K, 3) the supported pairs triangulate (marker candidates), and
    those (K2, 3) of every consistent pair (a marker two views see, or a chance match)."""
    det, start = stacked(ideal)
    K, R, t, centres = camera_arrays(cameras)
    E1, E2 = pair_distances(det, start, np.ascontiguousarray(F, dtype=np.float64))
    return _supported(det, start, E1, E2, K, R, t, centres, float(tol))


def stacked(ideal) -> tuple[np.ndarray, np.ndarray]:
    """Per-view detections ``[(Q_n, 2)]`` stacked view by view for the kernels: ``det
    (Q, 2)`` and ``start (C + 1,)``, view ``n``'s rows being ``start[n]:start[n + 1]``."""
    start = np.concatenate([[0], np.cumsum([len(d) for d in ideal])]).astype(np.int64)
    det = np.ascontiguousarray(np.concatenate([np.asarray(d, float).reshape(-1, 2) for d in ideal])
                               if len(ideal) else np.zeros((0, 2)))
    return det, start


def camera_arrays(cameras) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``K (C, 3, 3), R (C, 3, 3), t (C, 3)`` and the optical centres ``(C, 3)`` of
    ``cameras``, for the kernels."""
    cameras = list(cameras)
    return (np.array([c.K for c in cameras], dtype=np.float64).reshape(-1, 3, 3),
            np.array([c.R for c in cameras], dtype=np.float64).reshape(-1, 3, 3),
            np.array([c.t for c in cameras], dtype=np.float64).reshape(-1, 3),
            np.array([c.centre for c in cameras], dtype=np.float64).reshape(-1, 3))


@njit(cache=True, nogil=True)
def _ray(K, R, u, v, out):
    """The unit direction (world) of the ray through ideal pixel (u, v) (skew ignored)."""
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    for i in range(3):
        out[i] = x * R[0, i] + y * R[1, i] + R[2, i]
    norm = np.sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2])
    for i in range(3):
        out[i] /= norm


@njit(cache=True, nogil=True)
def project_ideal(K, R, t, x, y, z, min_depth):
    """The ideal pixel (u, v) of a world point in one view (``K``, ``R``, ``t``); NaN
    unless it lies more than ``min_depth`` in front of the camera."""
    zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
    if not zc > min_depth:
        return np.nan, np.nan
    xn = (R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]) / zc
    yn = (R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]) / zc
    return K[0, 0] * xn + K[0, 1] * yn + K[0, 2], K[1, 1] * yn + K[1, 2]


@njit(cache=True, nogil=True)
def nearest_detection(det, lo, hi, u, v):
    """``(distance, index)`` of the detection of ``det[lo:hi]`` nearest to (u, v), the
    first at a tie; ``(inf, -1)`` with none (or a NaN pixel)."""
    best = np.inf
    bq = -1
    for q in range(lo, hi):
        d = np.hypot(u - det[q, 0], v - det[q, 1])
        if d < best:
            best = d
            bq = q
    return best, bq


@njit(cache=True, nogil=True)
def _supported(det, start, E1, E2, K, R, t, centres, tol):
    """:func:`supported_detections` over detections stacked view by view (``start``),
    with their :func:`pair_distances`."""
    C = start.shape[0] - 1
    Q = det.shape[0]
    flags = np.zeros(Q, np.bool_)
    cap = 0
    for a in range(C):
        for b in range(a + 1, C):
            cap += (start[a + 1] - start[a]) * (start[b + 1] - start[b])
    points = np.empty((cap, 3))
    pairs = np.empty((cap, 3))
    n_points = 0
    n_pairs = 0
    da = np.empty(3)
    db = np.empty(3)
    X = np.empty(3)
    tol2 = tol * tol
    views = 0                                  # views with detections: the third view's test needs one
    for c in range(C):
        if start[c + 1] > start[c]:
            views += 1
    for a in range(C):
        for b in range(a + 1, C):
            oa = centres[a]
            ob = centres[b]
            for qa in range(start[a], start[a + 1]):
                xa = det[qa, 0]
                ya = det[qa, 1]
                for qb in range(start[b], start[b + 1]):
                    if not E1[qa, qb] + E2[qa, qb] < tol2:    # Eq. 6.6, squared
                        continue
                    xb = det[qb, 0]
                    yb = det[qb, 1]
                    # the midpoint of the rays' closest points
                    _ray(K[a], R[a], xa, ya, da)
                    _ray(K[b], R[b], xb, yb, db)
                    w0, w1, w2 = oa[0] - ob[0], oa[1] - ob[1], oa[2] - ob[2]
                    cosab = da[0] * db[0] + da[1] * db[1] + da[2] * db[2]
                    dw = da[0] * w0 + da[1] * w1 + da[2] * w2
                    ew = db[0] * w0 + db[1] * w1 + db[2] * w2
                    denom = max(1.0 - cosab * cosab, 1e-9)
                    sa = (cosab * ew - dw) / denom
                    sb = (ew - cosab * dw) / denom
                    for i in range(3):
                        X[i] = 0.5 * (oa[i] + sa * da[i] + ob[i] + sb * db[i])
                    pairs[n_pairs] = X
                    n_pairs += 1
                    if views < 3:
                        flags[qa] = flags[qb] = True
                        points[n_points] = X
                        n_points += 1
                        continue
                    seen = False
                    for c in range(C):
                        if c == a or c == b or start[c] == start[c + 1]:
                            continue
                        u, v = project_ideal(K[c], R[c], t[c], X[0], X[1], X[2], 1e-9)
                        best, bq = nearest_detection(det, start[c], start[c + 1], u, v)
                        if best < tol:
                            flags[bq] = True
                            seen = True
                    if seen:
                        flags[qa] = flags[qb] = True
                        points[n_points] = X
                        n_points += 1
    return flags, points[:n_points].copy(), pairs[:n_pairs].copy()


def triangulated_markers(cameras, detections, F=None, tol: float = 6.0, radius: float = 0.03) -> np.ndarray:
    """The markers (K, 3) a frame's detections (per camera (Q_n, 2) observed pixels) place
    in the room: the points the supported pairs of views triangulate
    (:func:`supported_detections`), those within ``radius`` of each other merged
    (:func:`app.markers.proposals.agreed_points`); what the viewer draws."""
    from app.markers.proposals import agreed_points

    ideal = [ideal_pixels(c, np.asarray(d, float).reshape(-1, 2)) for c, d in zip(cameras, detections)]
    _, points, _ = supported_detections(ideal, list(cameras), fundamentals(cameras) if F is None else F, tol)
    return agreed_points(points, radius)


class MarkerScorer:
    """Scores body-model particles against one frame's marker detections (the
    ``log_weights`` of a :class:`~app.pose.filters.APF` scorer)."""

    def __init__(self, cameras, height: float, rho: float = 20.0, sigma: float = 1.0, cost: str = "thesis",
                 support_px: float = 6.0, candidates: bool = False, explain: float = 1.0, picks: str = "nearest"):
        if cost not in COSTS:
            raise ValueError(f"marker cost must be one of {', '.join(COSTS)}, got {cost!r}")
        if picks not in PICKS:
            raise ValueError(f"marker picks must be one of {', '.join(PICKS)}, got {picks!r}")
        self.exclusive = picks == "exclusive"   # a detection is the pick of one landmark per view (ours)
        self.cameras = list(cameras)
        self.height = float(height)
        self.rho, self.sigma, self.cost = float(rho), float(sigma), cost
        self.support_px = float(support_px)
        self.explain = float(explain)        # both_ways: the weight of the detections' term
        self.candidates = bool(candidates)   # keep the supported pairs' 3D points (the arms' proposals)
        self.points = np.zeros((0, 3))
        self.pair_points = np.zeros((0, 3))
        self.K, self.R, self.t, self.centres = camera_arrays(self.cameras)
        self.F = fundamentals(self.cameras)
        self.joints = np.arange(15, dtype=np.int64)
        self.need = segments_needed(self.joints)
        self.det = np.zeros((0, 2))
        self.start = np.zeros(len(self.cameras) + 1, np.int64)
        self.supported = np.zeros(0, np.bool_)
        self.E1 = self.E2 = np.zeros((0, 0))
        self.evaluations = 0
        self.floor = 0.0                     # m: the lower ankle's prior (log_weights); 0 = none (the thesis)

    def set_detections(self, detections) -> None:
        """One frame's detections: per camera (Q_n, 2) observed pixels."""
        ideal = [ideal_pixels(c, d) for c, d in zip(self.cameras, detections)]
        self.det, self.start = stacked(ideal)
        self.E1, self.E2 = pair_distances(self.det, self.start, self.F)
        if self.cost == "both_ways" or self.candidates:
            self.supported, self.points, self.pair_points = _supported(
                self.det, self.start, self.E1, self.E2, self.K, self.R, self.t, self.centres, self.support_px)
        else:
            self.supported, self.points = np.zeros(len(self.det), np.bool_), np.zeros((0, 3))
            self.pair_points = np.zeros((0, 3))
        if self.cost != "both_ways":
            self.supported = np.zeros(len(self.det), np.bool_)

    def costs(self, states: np.ndarray) -> np.ndarray:
        return self._costs(joints_subset(states, self.height, self.joints, self.need))

    def _costs(self, X: np.ndarray) -> np.ndarray:
        """The costs of the particles whose landmarks are ``X`` (P, 15, 3)."""
        out = np.empty(len(X))
        tabled_costs(X, self.K, self.R, self.t, self.E1, self.E2, self.det, self.start, self.supported, self.rho,
                     self.cost != "thesis", self.explain if self.cost == "both_ways" else 0.0, self.exclusive, out)
        self.evaluations += len(X)
        return out

    def log_weights(self, states: np.ndarray, active=None) -> np.ndarray:
        """Eq. 6.10: ``log w = -C^2 / (2 sigma^2)``; with ``floor`` (m, ours) also
        ``-(dz / floor)^2 / 2``, ``dz`` the lower ankle's height above its standing height
        (markers the cameras do not see, legs behind furniture, leave the legs free)."""
        X = joints_subset(states, self.height, self.joints, self.need)
        c = self._costs(X)
        out = -(c * c) / (2.0 * self.sigma * self.sigma)
        if self.floor > 0:
            dz = np.maximum(X[:, _ANKLES, 2].min(axis=1) - ANKLE_HEIGHT * self.height, 0.0)
            out -= 0.5 * (dz / self.floor) ** 2
        return out
