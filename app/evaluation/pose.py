"""Pose metrics (thesis Ch. 5) and the ones learned-method papers report.

Per frame, each ground-truth person is matched to the estimated pose whose pelvis is
nearest (Hungarian assignment, at most ``match_radius`` m apart); a person with no
pose counts all joints as unmatched for MMTA and is left out of the errors.

* ``mu``, ``sigma`` (Eqs. 5.2-5.3): mean and deviation over time of the per-frame mean
  joint error ``D`` (Eq. 5.1).
* MMTP / MMTA at ``epsilon`` (Eqs. 5.5-5.6): precision over the matched joints (error
  <= epsilon) and the fraction of joints matched. The extracted Eq. 5.6 reads
  ``MMTA = 1 - sum #Omega / (M T)``, which contradicts the text ("MMTA = 1.0 indicates
  that the tracker has correctly produced a valid estimation for all markers", "could
  only track 77 % of the landmarks"); reconstructed as ``sum #Omega / (M T)``.
* ``epsilon_opt`` (§5.3.1, Eqs. 5.7-5.8): the epsilon whose truncated error set
  ``W(eps)`` is most Gaussian, by the Lilliefors statistic (min) and by the Q-Q plot's
  R^2 (max).
* Angle metrics (§5.3.2): the poses are re-parameterised by angles computed
  algebraically from the labelled joints (elbow and knee flexion, shoulder and hip
  elevation from the trunk axis, neck bend), so any model compares with any other;
  ``mu_theta``/``sigma_theta`` over the angles whose joints all matched (Eq. 5.9).
* MPJPE (mean per-joint position error, no alignment) and PCP (a limb is correct when
  both its end joints lie within half the limb's true length of the truth).
"""
from __future__ import annotations

import math

import numpy as np

from app.messages import JOINTS

__all__ = ["match_poses", "point_metrics", "epsilon_opt", "joint_angles", "pose_report", "pose_breakdown", "ANGLES",
           "LIMBS_PCP"]

J = {n: i for i, n in enumerate(JOINTS)}
#: Angles of the reference parameterisation: (name, a, b, c) = angle at b between b->a and b->c.
ANGLES = (
    ("l_elbow", "l_shoulder", "l_elbow", "l_wrist"), ("r_elbow", "r_shoulder", "r_elbow", "r_wrist"),
    ("l_knee", "l_hip", "l_knee", "l_ankle"), ("r_knee", "r_hip", "r_knee", "r_ankle"),
    ("l_shoulder", "neck", "l_shoulder", "l_elbow"), ("r_shoulder", "neck", "r_shoulder", "r_elbow"),
    ("l_hip", "pelvis", "l_hip", "l_knee"), ("r_hip", "pelvis", "r_hip", "r_knee"),
    ("neck", "pelvis", "neck", "head"),
)
LIMBS_PCP = (("l_shoulder", "l_elbow"), ("l_elbow", "l_wrist"), ("r_shoulder", "r_elbow"), ("r_elbow", "r_wrist"),
             ("l_hip", "l_knee"), ("l_knee", "l_ankle"), ("r_hip", "r_knee"), ("r_knee", "r_ankle"),
             ("pelvis", "neck"), ("neck", "head"))


def match_poses(truth: dict, estimates: dict, match_radius: float = 0.5) -> list:
    """Pairs ``(gt id, track id or None)`` of one frame; ``truth`` and ``estimates`` map
    ids to joints ``(15, 3)``."""
    from scipy.optimize import linear_sum_assignment

    gt_ids, est_ids = list(truth), list(estimates)
    pairs = {g: None for g in gt_ids}
    if gt_ids and est_ids:
        d = np.array([[np.linalg.norm(truth[g][J["pelvis"]] - estimates[e][J["pelvis"]]) for e in est_ids]
                      for g in gt_ids])
        rows, cols = linear_sum_assignment(d)
        for r, c in zip(rows, cols):
            if d[r, c] <= match_radius:
                pairs[gt_ids[r]] = est_ids[c]
    return list(pairs.items())


def point_metrics(errors: np.ndarray, epsilon: float = 0.1, missed_joints: int = 0) -> dict:
    """Ch. 5 point metrics from per-frame joint errors ``(T, M)`` in metres;
    ``missed_joints`` counts joints of people without any pose (unmatched for MMTA)."""
    E = np.asarray(errors, dtype=np.float64)
    if E.size == 0:
        return {"frames": 0}
    D = E.mean(axis=1)                                      # Eq. 5.1 per frame
    matched = E <= epsilon
    total = E.size + missed_joints
    out = {
        "frames": int(E.shape[0]),
        "mu_mm": round(1e3 * float(D.mean()), 2),                    # Eq. 5.2
        "sigma_mm": round(1e3 * float(D.std()), 2),                  # Eq. 5.3
        "epsilon_mm": round(1e3 * epsilon, 1),
        "mmtp_mm": round(1e3 * float(E[matched].mean()), 2) if matched.any() else None,   # Eq. 5.5
        "sigma_mmtp_mm": round(1e3 * float(E[matched].std()), 2) if matched.any() else None,
        "mmta": round(float(matched.sum()) / total, 4),              # Eq. 5.6 (reconstructed)
        "mpjpe_mm": round(1e3 * float(E.mean()), 2),
        "per_joint_mmta": {n: round(float(matched[:, j].mean()), 3) for j, n in enumerate(JOINTS)},
    }
    return out


def _lilliefors(w: np.ndarray) -> float:
    """Kolmogorov-Smirnov distance of ``w`` to the normal with its own mean and deviation."""
    from scipy.stats import norm
    w = np.sort(w)
    n = len(w)
    if n < 8:   # (before the deviation: numpy warns of one taken over fewer than two values)
        return math.inf
    sd = w.std(ddof=1)
    if sd <= 0:
        return math.inf
    cdf = norm.cdf((w - w.mean()) / sd)
    i = np.arange(1, n + 1)
    return float(max(np.max(i / n - cdf), np.max(cdf - (i - 1) / n)))


def _qq_r2(w: np.ndarray) -> float:
    """R^2 of the linear regression of ``w``'s quantiles on the normal quantiles."""
    from scipy.stats import norm
    w = np.sort(w)
    n = len(w)
    if n < 8 or w.std() <= 0:
        return -math.inf
    q = norm.ppf((np.arange(1, n + 1) - 0.5) / n)
    r = np.corrcoef(q, w)[0, 1]
    return float(r * r)


def epsilon_opt(errors, grid=None) -> dict:
    """``epsilon_opt`` (Eqs. 5.7-5.8) by Lilliefors (minimum statistic) and by Q-Q R^2
    (maximum) over ``grid`` (default 20 .. 300 mm every 10 mm)."""
    e = np.asarray(errors, dtype=np.float64).ravel()
    grid = np.arange(0.02, 0.301, 0.01) if grid is None else np.asarray(grid)
    if len(e) > 20000:   # a subsample keeps it quick on long runs (order statistics barely move)
        e = np.random.default_rng(0).choice(e, 20000, replace=False)
    ks = [_lilliefors(e[e <= g]) for g in grid]
    r2 = [_qq_r2(e[e <= g]) for g in grid]
    return {"lilliefors_mm": round(1e3 * float(grid[int(np.argmin(ks))]), 1),
            "qq_r2_mm": round(1e3 * float(grid[int(np.argmax(r2))]), 1)}


def joint_angles(joints: np.ndarray) -> np.ndarray:
    """The reference angles (radians, :data:`ANGLES` order) of joints ``(15, 3)``."""
    out = np.empty(len(ANGLES))
    for k, (_, a, b, c) in enumerate(ANGLES):
        u = joints[J[a]] - joints[J[b]]
        v = joints[J[c]] - joints[J[b]]
        cosang = u @ v / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-12)
        out[k] = math.acos(max(-1.0, min(1.0, cosang)))
    return out


def pose_report(frames, epsilon: float = 0.1, match_radius: float = 0.5, hidden: str = "all") -> dict:
    """All metrics over ``frames``: a list of ``(truth {id: joints}, estimates {id: joints},
    visible {id: (15,) bool})``. ``hidden``: ``all`` scores every joint, ``visible``
    only the joints some camera sees."""
    errors, angle_err, missed = [], [], 0
    pcp_hits = pcp_total = 0
    for truth, est, visible in frames:
        for gid, tid in match_poses(truth, est, match_radius):
            if tid is None:
                missed += len(JOINTS)
                continue
            X, Xh = truth[gid], est[tid]
            e = np.linalg.norm(X - Xh, axis=1)
            if hidden == "visible" and visible.get(gid) is not None:
                e = np.where(visible[gid], e, np.nan)
            errors.append(e)
            ok = e <= epsilon
            ga, ea = joint_angles(X), joint_angles(Xh)
            for k, (_, a, b, c) in enumerate(ANGLES):
                if ok[J[a]] and ok[J[b]] and ok[J[c]]:
                    angle_err.append(abs((ga[k] - ea[k] + math.pi) % (2 * math.pi) - math.pi))
            for a, b in LIMBS_PCP:
                L = np.linalg.norm(X[J[a]] - X[J[b]])
                if np.isnan(e[J[a]]) or np.isnan(e[J[b]]):
                    continue
                pcp_total += 1
                pcp_hits += int(e[J[a]] <= 0.5 * L and e[J[b]] <= 0.5 * L)
    if not errors:
        return {"frames": 0, "missed_joints": missed}
    E = np.array(errors)
    if hidden == "visible":
        vals = E[~np.isnan(E)]
        rep = point_metrics(np.nan_to_num(E, nan=0.0), epsilon, missed)
        matched = (vals <= epsilon)
        rep.update({"mmtp_mm": round(1e3 * float(vals[matched].mean()), 2) if matched.any() else None,
                    "mmta": round(float(matched.sum()) / (len(vals) + missed), 4),
                    "mpjpe_mm": round(1e3 * float(vals.mean()), 2)})
        flat = vals
    else:
        rep = point_metrics(E, epsilon, missed)
        flat = E.ravel()
    rep["missed_joints"] = missed
    rep["epsilon_opt"] = epsilon_opt(flat)
    a = np.degrees(np.array(angle_err)) if angle_err else np.zeros(0)
    rep["mu_theta_deg"] = round(float(a.mean()), 2) if len(a) else None
    rep["sigma_theta_deg"] = round(float(a.std()), 2) if len(a) else None
    rep["pcp"] = round(pcp_hits / pcp_total, 4) if pcp_total else None
    return rep


def _ranges(frames: list) -> list:
    """``[[first, last], ...]`` of runs of consecutive frame numbers."""
    out = []
    for f in sorted(frames):
        if out and f == out[-1][1] + 1:
            out[-1][1] = f
        else:
            out.append([f, f])
    return out


def pose_breakdown(frames, epsilon: float = 0.1, match_radius: float = 0.5, worst: int = 10) -> dict:
    """Where the MMTA goes: ``frames`` a list of ``(frame number, truth {id: joints},
    estimates {id: joints})``. ``unposed_share``: the share of all joints lost to people
    without a pose (e.g. before the tracker confirms them); ``joint_loss``: per joint, the
    share of all joints lost to that joint being posed farther than ``epsilon``
    (``1 - MMTA = unposed_share + sum(joint_loss)``); ``unposed``: per person, the frame
    ranges without a pose; ``bad_frames``: per person and joint, the frame ranges where
    it is farther; ``worst``: the frames with most joints farther."""
    total = 0
    unposed, lost, bad, per_frame = {}, np.zeros(len(JOINTS)), {}, []
    for f, truth, est in frames:
        for gid, tid in match_poses(truth, est, match_radius):
            total += len(JOINTS)
            if tid is None:
                unposed.setdefault(gid, []).append(f)
                continue
            far = np.linalg.norm(truth[gid] - est[tid], axis=1) > epsilon
            lost += far
            for j in np.flatnonzero(far):
                bad.setdefault(gid, {}).setdefault(JOINTS[j], []).append(f)
            if far.any():
                per_frame.append((int(far.sum()), f, gid))
    if not total:
        return {"joints": 0}
    per_frame.sort(key=lambda x: (-x[0], x[1]))
    return {
        "joints": total,
        "unposed_share": round(sum(len(v) for v in unposed.values()) * len(JOINTS) / total, 4),
        "joint_loss": {n: round(float(lost[j]) / total, 4) for j, n in enumerate(JOINTS)},
        "unposed": {str(g): _ranges(v) for g, v in unposed.items()},
        "bad_frames": {str(g): {n: _ranges(v) for n, v in sorted(d.items(), key=lambda x: -len(x[1]))}
                       for g, d in bad.items()},
        "worst": [{"frame": f, "person": g, "joints_off": k} for k, f, g in per_frame[:worst]],
    }


def ground_truth_poses(records) -> dict:
    """``{frame: (truth {id: (15, 3) joints}, visible {id: (15,) bool})}`` of a recording's
    ``groundtruth.jsonl`` records."""
    out = {}
    for rec in records:
        truth, visible = {}, {}
        for p in rec.get("people", []):
            truth[int(p["id"])] = np.array([p["joints"][n] for n in JOINTS], dtype=float)
            hid = p.get("visible", {})
            visible[int(p["id"])] = np.array([hid.get(n, True) for n in JOINTS], dtype=bool)
        out[int(rec["frame"])] = (truth, visible)
    return out


def evaluate_pose_files(recording, results, epsilon: float = 0.1, hidden: str = "all") -> dict:
    """Score ``<results>/poses.jsonl`` against ``<recording>/groundtruth.jsonl``."""
    from pathlib import Path

    from app.errors import InputError
    from app.files import read_jsonl

    gt_path, pose_path = Path(recording) / "groundtruth.jsonl", Path(results) / "poses.jsonl"
    for p in (gt_path, pose_path):
        if not p.is_file():
            raise InputError(f"{p}: file not found")
    poses = {}
    for rec in read_jsonl(pose_path):
        try:
            poses[int(rec["frame"])] = {int(p["track"]): np.array([p["joints"][n] for n in JOINTS], dtype=float)
                                        for p in rec.get("poses", [])}
        except (KeyError, TypeError, ValueError):
            raise InputError(f"{pose_path}: frame {rec.get('frame')!r} has a pose without the 15 joints") from None
    frames, numbers = [], []
    for f, (truth, visible) in ground_truth_poses(read_jsonl(gt_path)).items():
        if f not in poses:
            continue   # a frame the pipeline dropped is absent from its files (CONTRACT §2)
        frames.append((truth, poses[f], visible))
        numbers.append(f)
    report = pose_report(frames, epsilon=epsilon, hidden=hidden)
    report["frames_scored"] = len(frames)
    report["breakdown"] = pose_breakdown([(f, t, e) for f, (t, e, _) in zip(numbers, frames)], epsilon=epsilon)
    return report
