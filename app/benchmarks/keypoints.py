"""``smartroom bench keypoints``: what the keypoint cue's detector costs per person crop
on one core, and how near its sure keypoints fall to the truth (issue 23).

A simulated scene is rendered every ``step`` frames; every person is cropped in every
camera as the keypoints worker crops a track (the true centroid stands for the track)
and run through the network with one thread. Per crop: wall ms of the crop's warp, the
network and the mapping back; per joint: the share of crops where the network is sure
(confidence >= 0.5) and the median distance of those keypoints to the projected true
joint, in pixels and as a share of the crop's side.
"""
from __future__ import annotations

import time

import numpy as np

from app.messages import JOINTS

__all__ = ["run", "format_table"]


def run(scene: str = "meeting3", frames: int = 100, step: int = 10, seed: int = 0, zenithal: bool = False) -> dict:
    from app.keypoints.detector import KeypointDetector, crop_top, person_crop
    from app.simulation.simulator import Simulator

    det = KeypointDetector(threads=1)
    sim = Simulator(scene, seed=seed, seconds=(frames + 1) / 25.0, zenithal=zenithal)
    ms, px, share = [], [], []
    for i in range(0, frames, step):
        people = sim.people(i)
        images, _, _ = sim.render_people(i, people, noise=True)
        for p in sim.groundtruth(i, people)["people"]:
            truth = np.array([p["joints"][n] for n in JOINTS])
            for cam in sim.calibration.cameras:
                t0 = time.perf_counter()
                crop = person_crop(cam, p["centroid"], crop_top(p["centroid"][2]))
                if crop is None:
                    continue
                kp = det.detect(images[cam.name], crop)
                ms.append(1e3 * (time.perf_counter() - t0))
                err = np.linalg.norm(kp[:, :2] - cam.project(truth), axis=1)
                sure = kp[:, 2] >= 0.5
                px.append(np.where(sure, err, np.nan))
                share.append(np.where(sure, err / crop.side, np.nan))
    px, share = np.array(px), np.array(share)
    joints = {}
    for j, name in enumerate(JOINTS):
        ok = np.isfinite(px[:, j])
        joints[name] = {"sure": round(float(ok.mean()), 3),
                        "median_px": round(float(np.median(px[ok, j])), 1) if ok.any() else None,
                        "median_share": round(float(np.median(share[ok, j])), 4) if ok.any() else None}
    return {"scene": scene, "crops": len(ms), "ms_median": round(float(np.median(ms)), 2),
            "ms_p95": round(float(np.percentile(ms, 95)), 2), "model": str(det.model_path), "joints": joints}


def format_table(res: dict) -> str:
    lines = [f"keypoint detector on {res['scene']}: {res['crops']} person crops, one thread: "
             f"{res['ms_median']:.1f} ms median, {res['ms_p95']:.1f} ms p95 per crop",
             "joint        sure  median px  median / crop side", "-" * 48]
    for name, r in res["joints"].items():
        mp = "-" if r["median_px"] is None else f"{r['median_px']:.1f}"
        ms = "-" if r["median_share"] is None else f"{r['median_share']:.3f}"
        lines.append(f"{name:11s} {r['sure']:5.2f} {mp:>10s} {ms:>19s}")
    return "\n".join(lines)
