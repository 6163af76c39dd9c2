"""``smartroom eval --recording DIR --results DIR``: score results against ground truth.

Scores what the results hold: the reconstruction (``voxels.bin``, written when the
recorder runs with ``voxels: true``) against the true body volume of a simulated
recording (``bodies.jsonl``): recall, precision, spurious voxels, floor shadows, the
hull's volume over the true body volume and whether a person is in pieces.
Writes ``eval.json`` into the results folder and prints a summary.
"""
from __future__ import annotations

from pathlib import Path


def add_arguments(p) -> None:
    p.add_argument("--recording", required=True, metavar="DIR", help="recording folder with ground truth")
    p.add_argument("--results", required=True, metavar="DIR", help="results folder of smartroom run")
    p.add_argument("--near", type=float, default=0.10,
                   help="a voxel within this distance (m) of a body is not spurious (default 0.10)")
    p.add_argument("--epsilon", type=float, default=100.0,
                   help="pose: a joint within this distance (mm) of the truth is matched (MMTP/MMTA, default 100)")


def evaluate_reconstruction(recording: Path, voxels_path: Path, near: float = 0.10) -> dict:
    """Per-frame scores and their summary for a ``voxels.bin`` of a simulated recording."""
    from app.evaluation.reconstruction import score_frame, summarise_scores
    from app.results import iter_voxels
    from app.simulation.occupancy import load_bodies, true_occupancy

    bodies = {rec["frame"]: rec for rec in load_bodies(recording)}
    scores = []
    for msg in iter_voxels(voxels_path):
        record = bodies.get(msg.frame)
        if record is None:
            continue
        truth, person = true_occupancy(record, msg.origin, msg.voxel_size, msg.dims, with_person=True)
        scores.append(score_frame(msg.frame, msg.indices, truth, msg.dims, msg.voxel_size, near=near,
                                  truth_person=person))
    summary = summarise_scores(scores)
    summary["voxel_size"] = msg.voxel_size if scores else None
    return {"summary": summary, "frames": [s.as_dict() for s in scores]}


def evaluate_tracking(recording: Path, tracks_path: Path) -> dict:
    """CLEAR MOT (MOTP, MOTA, error ratios; Eq. 4.22-4.23) and IDF1 of ``tracks.jsonl``."""
    from app.errors import InputError
    from app.evaluation.tracking import result_frames, score_tracking, truth_frames
    from app.files import read_jsonl
    from app.recording import Recording

    truth = Recording(recording).groundtruth()
    if truth is None:
        raise InputError(f"{recording}: has no groundtruth.jsonl to score tracks against")
    try:
        results = result_frames(read_jsonl(tracks_path))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{tracks_path}: not valid tracks ({exc})") from None
    truth = truth_frames(truth)
    # the frames the run covered: every ground-truth frame up to its last result line
    last = max(results) if results else -1
    s = score_tracking(truth, results, frames=[f for f in sorted(truth) if f <= last])
    out = s.summary()
    print(f"tracking over {out['frames']} frames: MOTP {out['motp_mm']} mm, MOTA {out['mota']}, "
          f"IDF1 {out['idf1']}, misses {out['miss_ratio']}, false positives {out['false_positive_ratio']}, "
          f"mismatches {out['mismatch_ratio']} ({out['mismatches']}), ids {out['track_ids']} for "
          f"{out['true_ids']} people")
    return out


def check_results_belong(rec, results: Path) -> None:
    """Results are scored only against the recording they were made from: the run's
    ``layout.yaml`` names the recording and its fingerprint (calibration and frame count)."""
    from app.errors import InputError
    from app.files import read_yaml
    from app.recording import fingerprint

    layout = results / "layout.yaml"
    if not layout.is_file():
        return   # results made by other means: nothing to check against
    run = (read_yaml(layout, "results layout") or {}).get("run") or {}
    made = run.get("recording_id")
    if made and made != fingerprint(rec):
        raise InputError(f"{results}: these results were made from {run.get('recording')} "
                         f"(fingerprint {made}), not from {rec.path} ({fingerprint(rec)})")


def main(args) -> int:
    from app.errors import InputError
    from app.files import write_json
    from app.recording import Recording

    recording = Path(args.recording)
    rec = Recording(recording)  # validates the folder
    results = Path(args.results)
    if not results.is_dir():
        raise InputError(f"{results}: results folder not found")
    check_results_belong(rec, results)
    report = {}
    if (results / "voxels.bin").is_file():
        if not (recording / "bodies.jsonl").is_file():
            raise InputError(f"{recording}: has no bodies.jsonl (true body volume) to score voxels against")
        rec = evaluate_reconstruction(recording, results / "voxels.bin", args.near)
        report["reconstruction"] = rec
        s = rec["summary"]
        print(f"reconstruction at {100 * (s['voxel_size'] or 0):.0f} cm over {s['frames']} frames: "
              f"recall {s['recall']}, precision {s['precision']}, spurious voxels {s['spurious_mean']} per frame, "
              f"floor shadow blobs > 20 voxels in {100 * s['frames_with_floor_blob_over_20']:.1f}% of frames "
              f"(largest {s['floor_blob_max']})")
        if s.get("volume_ratio") is not None:
            print(f"hull: {s['volume_ratio']}x the true body volume ({s['volume_ratio_near']}x within {args.near} m "
                  f"of a body); largest component near each person holds at least {s['largest_share_min']} of its "
                  f"voxels; person in pieces (< 0.9) in {100 * s['frames_in_pieces']:.1f}% of frames")
    if (results / "tracks.jsonl").is_file():
        report["tracking"] = evaluate_tracking(recording, results / "tracks.jsonl")
    if (results / "poses.jsonl").is_file() and (recording / "groundtruth.jsonl").is_file():
        from app.evaluation.pose import evaluate_pose_files
        pose = report["pose"] = evaluate_pose_files(recording, results, epsilon=args.epsilon / 1000.0)
        print(f"pose over {pose.get('frames_scored', 0)} frames: MMTA {pose.get('mmta')} and MMTP "
              f"{pose.get('mmtp_mm')} mm at {args.epsilon:g} mm, mu {pose.get('mu_mm')} mm, sigma "
              f"{pose.get('sigma_mm')} mm, MPJPE {pose.get('mpjpe_mm')} mm, PCP {pose.get('pcp')}, angles "
              f"{pose.get('mu_theta_deg')} +- {pose.get('sigma_theta_deg')} deg, epsilon_opt {pose.get('epsilon_opt')}")
        b = pose.get("breakdown") or {}
        if b.get("joints"):
            worst = sorted(b["joint_loss"].items(), key=lambda x: -x[1])[:5]
            print(f"pose MMTA lost: {b['unposed_share']} to people without a pose ({b['unposed']}), "
                  + ", ".join(f"{n} {v}" for n, v in worst if v > 0) + " (eval.json: pose.breakdown)")
    if not report:
        raise InputError(f"{results}: holds nothing this version can score (voxels.bin: run with "
                         "--set recorder.voxels=true)")
    write_json(results / "eval.json", report)
    return 0
