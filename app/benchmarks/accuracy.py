"""Accuracy on random scenes (``smartroom bench accuracy``): the held-out protocol.

Every accuracy target is judged on scenes nothing was tuned on (DESIGN §6). The random
scenes of :mod:`app.simulation.random_scene` are drawn from a seed; the protocol splits
the seeds:

* seeds below :data:`HELD_OUT_FROM` (1000) are for tuning: thresholds, parameters and
  the person classifier are fitted on them, as often as one likes;
* seeds from 1000 up are held out: the figures a target is judged by come from them,
  and nothing is ever changed because of what they show.

For each seed the scene is rendered once into the recordings cache
(:mod:`app.simulation.cache`), the whole pipeline runs on it as ``smartroom run`` does
(headless, unpaced; the layout and ``--set`` overrides given, or another build's
command line for an A/B against it) and its files are scored against the ground truth:

* tracking: CLEAR MOT (MOTA, MOTP) and IDF1 (:mod:`app.evaluation.tracking`; gate 0.5 m);
* pose: MMTA and MMTP at 100 mm, MPJPE (:mod:`app.evaluation.pose`; every joint);
* detection: the share of person-frames a track matched, by stature band and by what
  the person was doing (the ground truth's ``activity``), and the longest time each
  person went untracked;
* phantoms: track-frames that matched nobody (a blob where silhouette cones meet, a
  chair) as a share of the person-frames, and the tracks that never matched anyone.

Pure: no bus; the pipeline runs as a child process.
"""
from __future__ import annotations

import json
import math
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["HELD_OUT_FROM", "STATURE_BANDS", "parse_seeds", "scene_recording", "run_scene", "score_scene",
           "aggregate", "format_report", "bench_accuracy"]

HELD_OUT_FROM = 1000
STATURE_BANDS = ((1.45, 1.60), (1.60, 1.75), (1.75, 1.90), (1.90, 2.001))
ACTIVITIES = ("standing", "walking", "gesturing", "sitting", "crouching")
UNTRACKED_LIMIT_S = 1.0


def parse_seeds(text: str) -> list[int]:
    """``A:B`` (A included, B not), ``A`` or ``A,B,C``."""
    from app.errors import InputError

    try:
        if ":" in text:
            a, b = (int(v) for v in text.split(":"))
            seeds = list(range(a, b))
        else:
            seeds = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--seeds {text}: expected A:B (seeds A to B-1) or a list like 1000,1001") from None
    if not seeds or min(seeds) < 0:
        raise InputError(f"--seeds {text}: no seeds, or a negative one")
    return seeds


def scene_recording(seed: int, seconds: float, fps: float = 25.0, progress=None) -> Path:
    """The random scene of ``seed``, rendered once into the recordings cache."""
    from app.simulation.cache import default_recording
    from app.simulation.simulator import RANDOM

    return default_recording(RANDOM, seconds=seconds, fps=fps, seed=seed, progress=progress)


def run_scene(recording: Path, out: Path, command: list[str], extra: list[str], timeout: float = 3600.0) -> dict:
    """Run the pipeline on ``recording`` into ``out`` (``command``: the CLI to use,
    ``extra``: ``--layout`` / ``--set`` arguments); what the run said of itself."""
    t0 = time.monotonic()
    cmd = [*command, "run", "--recording", str(recording), "--headless", "--no-pace", "--out", str(out), *extra]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        rc, err = r.returncode, r.stderr
    except subprocess.TimeoutExpired:
        rc, err = None, f"timed out after {timeout:.0f} s"
    stats = {}
    try:
        stats = json.loads((out / "stats.json").read_text())
    except (OSError, ValueError):
        pass
    return {"exit": rc, "seconds": round(time.monotonic() - t0, 1), "complete": bool(stats.get("complete")),
            "rtf": stats.get("rtf"), "reasons": stats.get("reasons", []),
            "error": None if rc == 0 else (err.strip().splitlines() or ["?"])[-1][:300]}


def _records(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    with open(path, encoding="utf-8") as fh:
        return [json.loads(line) for line in fh if line.strip()]


def score_scene(recording: Path, results: Path) -> dict:
    """Tracking, pose, detection and phantom figures of one run (see the module docstring)."""
    from app.evaluation.pose import evaluate_pose_files
    from app.evaluation.tracking import result_frames, score_tracking, truth_frames

    truth = _records(recording / "groundtruth.jsonl")
    fps = json.loads((recording / "simulation.json").read_text()).get("fps", 25.0) \
        if (recording / "simulation.json").is_file() else 25.0
    tracks = _records(results / "tracks.jsonl")
    score = score_tracking(truth_frames(truth), result_frames(tracks))
    out = {"tracking": score.summary()}
    # detection by stature band and activity; the longest run of frames each person is untracked
    found = {f"{lo:.2f}-{min(hi, 2.0):.2f}": [0, 0] for lo, hi in STATURE_BANDS}
    doing = {a: [0, 0] for a in ACTIVITIES}
    run, longest, stature = {}, {}, {}
    for rec in truth:
        f = int(rec["frame"])
        matched = score.matched.get(f, {})
        for p in rec.get("people", []):
            pid, hit = int(p["id"]), int(p["id"]) in matched
            stature[pid] = p.get("height")
            band = _band(p.get("height"))
            if band is not None:
                found[band][0] += hit
                found[band][1] += 1
            act = p.get("activity")
            if act in doing:
                doing[act][0] += hit
                doing[act][1] += 1
            run[pid] = 0 if hit else run.get(pid, 0) + 1
            longest[pid] = max(longest.get(pid, 0), run[pid])
    out["detection_by_stature"] = found
    out["detection_by_activity"] = doing
    out["untracked_s"] = {str(pid): round(n / fps, 2) for pid, n in sorted(longest.items())}
    out["statures"] = {str(pid): h for pid, h in sorted(stature.items())}
    # phantoms: hypothesis-frames matched to nobody; tracks never matched
    hyp_frames, hyp_hits = {}, {}
    for rec in tracks:
        f = int(rec["frame"])
        used = set(score.matched.get(f, {}).values())
        for t in rec.get("tracks", []):
            tid = int(t["id"])
            hyp_frames[tid] = hyp_frames.get(tid, 0) + 1
            hyp_hits[tid] = hyp_hits.get(tid, 0) + (tid in used)
    person_frames = max(1, score.truths)
    out["phantom_share"] = round(score.false_positives / person_frames, 4)
    out["phantom_tracks"] = {str(t): n for t, n in hyp_frames.items() if hyp_hits[t] == 0}
    # pose
    try:
        pose = evaluate_pose_files(recording, results)
    except Exception as exc:  # noqa: BLE001 - a run without poses scores nothing
        pose = {"error": str(exc)[:200]}
    out["pose"] = {k: pose.get(k) for k in ("mmta", "mmtp_mm", "mpjpe_mm", "pcp", "frames_scored", "error")
                   if k in pose}
    # poses of tracks that matched nobody (phantoms posed as people)
    posed = 0
    for rec in _records(results / "poses.jsonl"):
        used = set(score.matched.get(int(rec["frame"]), {}).values())
        posed += sum(1 for p in rec.get("poses", []) if int(p["track"]) not in used)
    out["phantom_poses"] = posed
    return out


def _band(height) -> str | None:
    if height is None:
        return None
    for lo, hi in STATURE_BANDS:
        if lo <= height < hi:
            return f"{lo:.2f}-{min(hi, 2.0):.2f}"
    return None


def aggregate(rows: list[dict]) -> dict:
    """Mean and worst of the per-scene figures; detection pooled over the scenes."""
    scored = [r for r in rows if "score" in r]
    agg: dict = {"scenes": len(rows), "scored": len(scored)}
    if not scored:
        return agg

    def vals(get):
        v = [get(r["score"]) for r in scored]
        return [x for x in v if x is not None and not (isinstance(x, float) and math.isnan(x))]

    for name, get, worst in (("mota", lambda s: s["tracking"]["mota"], min),
                             ("idf1", lambda s: s["tracking"]["idf1"], min),
                             ("motp_mm", lambda s: s["tracking"]["motp_mm"], max),
                             ("mmta", lambda s: s["pose"].get("mmta"), min),
                             ("mmtp_mm", lambda s: s["pose"].get("mmtp_mm"), max),
                             ("mpjpe_mm", lambda s: s["pose"].get("mpjpe_mm"), max),
                             ("phantom_share", lambda s: s["phantom_share"], max)):
        v = vals(get)
        if v:
            agg[name] = {"mean": round(float(np.mean(v)), 4), "worst": round(float(worst(v)), 4)}
    pooled = {}
    for key in ("detection_by_stature", "detection_by_activity"):
        total: dict = {}
        for r in scored:
            for k, (hit, n) in r["score"][key].items():
                t = total.setdefault(k, [0, 0])
                t[0] += hit
                t[1] += n
        pooled[key] = {k: {"rate": round(h / n, 4) if n else None, "person_frames": n} for k, (h, n) in total.items()}
    agg.update(pooled)
    untracked = [s for r in scored for s in r["score"]["untracked_s"].values()]
    agg["people"] = len(untracked)
    agg["people_untracked_over_1s"] = sum(1 for s in untracked if s > UNTRACKED_LIMIT_S)
    agg["longest_untracked_s"] = max(untracked) if untracked else None
    agg["phantom_poses"] = sum(r["score"]["phantom_poses"] for r in scored)
    agg["failed_runs"] = sum(1 for r in rows if not r.get("run", {}).get("complete"))
    return agg


def format_report(rows: list[dict], agg: dict) -> str:
    head = (f"{'seed':>6} {'cams':>4} {'ppl':>3} {'statures':<24} {'MOTA':>6} {'IDF1':>6} {'MOTP':>6} {'MMTA':>6} "
            f"{'MMTP':>6} {'MPJPE':>6} {'phant%':>6} {'untr s':>6} {'RTF':>5}")
    lines = [head]
    for r in rows:
        d = r["scene"]
        if "score" not in r:
            lines.append(f"{r['seed']:>6} {d['cameras']:>4} {d['people']:>3}  run failed: {r['run'].get('error')}")
            continue
        s = r["score"]
        t, p = s["tracking"], s["pose"]
        stat = ",".join(f"{h:.2f}" for h in d["statures"])
        lines.append(f"{r['seed']:>6} {d['cameras']:>4} {d['people']:>3} {stat:<24.24} {t['mota']:>6.3f} "
                     f"{t['idf1']:>6.3f} {t['motp_mm']:>6.1f} {_f(p.get('mmta'), 6, 3)} {_f(p.get('mmtp_mm'), 6, 1)} "
                     f"{_f(p.get('mpjpe_mm'), 6, 1)} {100 * s['phantom_share']:>6.2f} "
                     f"{max(s['untracked_s'].values(), default=0):>6.2f} {_f(r['run'].get('rtf'), 5, 2)}")
    if agg.get("scored"):
        lines.append("")
        lines.append(f"{'':>6} {'mean':>4}     {'':<24} " + " ".join(
            _f(agg.get(k, {}).get("mean"), 6, 3 if k in ("mota", "idf1", "mmta") else 1)
            for k in ("mota", "idf1", "motp_mm", "mmta", "mmtp_mm", "mpjpe_mm")))
        lines.append(f"{'':>6} {'worst':>4}    {'':<24} " + " ".join(
            _f(agg.get(k, {}).get("worst"), 6, 3 if k in ("mota", "idf1", "mmta") else 1)
            for k in ("mota", "idf1", "motp_mm", "mmta", "mmtp_mm", "mpjpe_mm")))
        lines.append(f"phantom track-frames: {100 * agg.get('phantom_share', {}).get('mean', 0):.2f} % of "
                     f"person-frames (worst scene {100 * agg.get('phantom_share', {}).get('worst', 0):.2f} %); "
                     f"phantom poses: {agg['phantom_poses']}")
        lines.append(f"people untracked for more than {UNTRACKED_LIMIT_S:g} s: {agg['people_untracked_over_1s']} "
                     f"of {agg['people']} (longest {agg['longest_untracked_s']} s); runs incomplete: "
                     f"{agg['failed_runs']}")
        for key, title in (("detection_by_stature", "detected, by stature (m)"),
                           ("detection_by_activity", "detected, by activity")):
            cells = "  ".join(f"{k} {_f(v['rate'], 5, 3).strip()} ({v['person_frames']})"
                              for k, v in agg[key].items() if v["person_frames"])
            lines.append(f"{title}: {cells}")
    return "\n".join(lines)


def _f(v, width: int, digits: int) -> str:
    return f"{'-':>{width}}" if v is None else f"{v:>{width}.{digits}f}"


def bench_accuracy(seeds: list[int], out: Path, seconds: float, extra: list[str], command: list[str] | None = None,
                   progress=print) -> dict:
    """The protocol over ``seeds`` (see the module docstring): rows per scene and the aggregate."""
    from app.simulation.simulator import print_progress

    command = command or [sys.executable, "-m", "app.cli"]
    tuning = [s for s in seeds if s < HELD_OUT_FROM]
    if tuning and len(tuning) < len(seeds):
        progress(f"smartroom bench accuracy: seeds {min(tuning)}-{max(tuning)} are tuning seeds, the others "
                 f"held out: their aggregate mixes the two")
    rows = []
    for k, seed in enumerate(seeds):
        rec = scene_recording(seed, seconds, progress=print_progress(f"render random {seed} ({k + 1}/{len(seeds)})"))
        info = json.loads((rec / "simulation.json").read_text()).get("random", {})
        row = {"seed": seed, "recording": str(rec), "scene": info}
        row["run"] = run_scene(rec, out / f"seed{seed}", command, extra)
        if row["run"]["exit"] is not None:
            row["score"] = score_scene(rec, out / f"seed{seed}")
        rows.append(row)
        progress(format_report([row], {}).splitlines()[-1])
    agg = aggregate(rows)
    return {"seeds": seeds, "held_out": all(s >= HELD_OUT_FROM for s in seeds), "seconds": seconds,
            "command": command, "extra": extra, "rows": rows, "aggregate": agg}


def command_line(text: str | None) -> list[str] | None:
    """``--smartroom 'CMD'``: another build's command line (split as a shell would)."""
    return shlex.split(text) if text else None
