"""``smartroom bench marker``: the marker-based APF (§6.4) over synthetic detections
(§6.6.1), swept like the thesis's Fig. 6.13: MMTA (epsilon 100 mm) for detector
qualities (DR x FP x sigma^2) against the filter's layers x particles per layer.

Each cell tracks the first person of each simulated scene (true joints, no rendering)
from a least-squares fit of the body model to the first frame's true joints, with
detections drawn by :func:`app.markers.synthetic.synthetic_detections` (one detector
seed per scene); the first frame is not scored. Times are the filter's ms per frame on
one core (likelihood, annealing, the detections' epipolar support).

Besides the built-in scenes, ``random-N`` is the random scene of seed N
(:mod:`app.simulation.random_scene`: 3-8 cameras of varied rigs, people of every stature);
:func:`scene_names` reads ``random:A:B`` as seeds A to B-1. Tune on seeds below 1000, report
on 1000 and up (docs/benchmarks.md).
"""
from __future__ import annotations

import time

import numpy as np

from app.evaluation.pose import point_metrics
from app.messages import JOINTS

__all__ = ["bench_marker", "format_table", "scene_names", "DEFAULT_GRID"]

DEFAULT_GRID = {"dr": (0.9,), "fp": (0, 20), "sigma2": (4.0, 20.0), "filters": ((1, 300), (3, 700))}


RANDOM_PREFIX = "random-"


def scene_names(text: str) -> tuple[str, ...]:
    """``--marker-scenes``: scene names, comma-separated; an item ``random:A:B`` stands for
    ``random-A`` to ``random-(B-1)``."""
    from app.benchmarks.accuracy import parse_seeds
    from app.errors import InputError

    names = []
    for item in (s.strip() for s in text.split(",")):
        if item.startswith("random:"):
            try:
                seeds = parse_seeds(item[len("random:"):])
            except InputError:
                raise InputError(f"--marker-scenes {item}: expected random:A:B (the random scenes of seeds A "
                                 "to B-1)") from None
            names += [f"{RANDOM_PREFIX}{seed}" for seed in seeds]
        elif item:
            names.append(item)
    return tuple(names)


def _clip(scene: str, frames: int, seed: int):
    from app.simulation.simulator import RANDOM, Simulator
    if scene.startswith(RANDOM_PREFIX):   # the random scene of that seed; the filter keeps ``seed``
        sim = Simulator(RANDOM, fps=25, seconds=frames / 25.0 + 10.0, seed=int(scene[len(RANDOM_PREFIX):]))
    else:
        sim = Simulator(scene, fps=25, seconds=frames / 25.0 + 10.0, seed=seed, width=640, height=480)
    first = next((i for i in range(sim.frame_count()) if sim.groundtruth(i)["people"]), None)
    if first is None:
        raise ValueError(f"scene {scene}: nobody in its first 10 s")
    gts = [sim.groundtruth(i) for i in range(first, first + frames)]   # from the first person's entry
    pid = gts[0]["people"][0]["id"]
    people = []
    for g in gts:
        all_joints = np.array([[p["joints"][j] for j in JOINTS] for p in g["people"]], float).reshape(-1, 15, 3)
        statures = [p["height"] for p in g["people"]]
        mine = [k for k, p in enumerate(g["people"]) if p["id"] == pid]
        people.append((all_joints, statures, mine[0] if mine else None))
    return sim.calibration.cameras, gts[0]["people"][0]["height"], people


def bench_marker(scenes=("walk1",), frames: int = 75, grid: dict | None = None, cost: str = "both_ways",
                 epsilon: float = 0.1, seed: int = 0, progress=None, **tracker) -> list[dict]:
    """One row per (DR, FP, sigma2, L, N_pL) cell, errors pooled over ``scenes``;
    ``tracker``: other :class:`~app.markers.tracking.MarkerTracker` settings."""
    from app.markers.synthetic import DetectorModel, synthetic_detections
    from app.markers.tracking import MarkerTracker, fit_state

    g = {**DEFAULT_GRID, **(grid or {})}
    tracker_settings = tracker
    clips = {s: _clip(s, frames, seed) for s in scenes}
    rows = []
    for dr in g["dr"]:
        for fp in g["fp"]:
            for sigma2 in g["sigma2"]:
                detector = DetectorModel(float(dr), float(fp), float(sigma2))
                for layers, particles in g["filters"]:
                    errors, ms, per_scene = [], [], {}
                    for k, (scene, (cameras, height, people)) in enumerate(clips.items()):
                        first = len(errors)
                        rng = np.random.default_rng(1000 + k)
                        tracker = MarkerTracker(cameras, height, particles=particles, layers=layers, cost=cost,
                                                seed=seed, **tracker_settings)
                        all0, _, me0 = people[0]
                        tracker.start(fit_state(height, all0[me0]))
                        for n, (all_joints, statures, me) in enumerate(people):
                            dets, _ = synthetic_detections(all_joints, statures, cameras, detector, rng)
                            t0 = time.process_time()
                            tracker.step(dets)
                            ms.append(1e3 * (time.process_time() - t0))
                            if n and me is not None:
                                errors.append(np.linalg.norm(tracker.joints() - all_joints[me], axis=1))
                        if len(errors) > first:
                            per_scene[scene] = round(point_metrics(np.array(errors[first:]), epsilon)["mmta"], 4)
                    m = point_metrics(np.array(errors), epsilon)
                    row = {"dr": dr, "fp": fp, "sigma2": sigma2, "layers": layers, "particles": particles,
                           "cost": cost, "mmta": m["mmta"], "mmtp_mm": m["mmtp_mm"], "mpjpe_mm": m["mpjpe_mm"],
                           "ms_p50": round(float(np.median(ms[3:] or ms)), 1), "mmta_per_scene": per_scene}
                    rows.append(row)
                    if progress:
                        progress(format_row(row))
    return rows


def format_row(r: dict) -> str:
    return (f"{r['dr']:>5.2f}{r['fp']:>6.0f}{r['sigma2']:>8.1f}{r['layers']:>4d}{r['particles']:>6d}"
            f"{r['mmta']:>8.3f}{r['mmtp_mm'] or 0:>8.1f}{r['mpjpe_mm']:>8.1f}{r['ms_p50']:>8.1f}")


def format_table(rows: list[dict], scenes) -> str:
    """The table; with several scenes, each row's worst scene below it."""
    named = ", ".join(scenes) if len(scenes) <= 6 else f"{len(scenes)} scenes ({scenes[0]} ... {scenes[-1]})"
    head = (f"marker APF ({rows[0]['cost'] if rows else ''} cost) on {named}: MMTA at 100 mm\n"
            f"{'DR':>5}{'FP':>6}{'sigma2':>8}{'L':>4}{'N_pL':>6}{'MMTA':>8}{'MMTP':>8}{'MPJPE':>8}{'ms':>8}")
    lines = [head]
    for r in rows:
        lines.append(format_row(r))
        per = r.get("mmta_per_scene") or {}
        if len(per) > 1:
            worst = min(per, key=per.get)
            lines.append(f"{'':>29}worst scene {worst}: MMTA {per[worst]:.3f}")
    return "\n".join(lines)
