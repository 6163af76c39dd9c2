"""Render-time benchmark of the simulator (``smartroom bench simulate``).

Reports milliseconds per multi-camera frame (p50 / p95) for the stages of writing a
recording: posing the people and the ground truth, rendering every camera, and
encoding the videos, and extrapolates the time a recording of ``seconds`` takes.
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["bench_render", "add_arguments", "main"]


def bench_render(scene: str = "meeting3", frames: int = 50, seconds: float = 10.0, fps: float = 25.0,
                 zenithal: bool = False, width: int = 640, height: int = 480, encode: bool = True,
                 seed: int = 0, quiet: bool = False) -> dict:
    """Time ``frames`` frames spread over the scene; print a table, return the figures."""
    import cv2

    from app.simulation.simulator import Simulator

    t0 = time.perf_counter()
    sim = Simulator(scene, seed=seed, fps=fps, seconds=seconds, width=width, height=height, zenithal=zenithal)
    setup_plan = time.perf_counter() - t0
    t0 = time.perf_counter()
    sim.render(0)  # builds the camera views (static room) and compiles the kernels
    setup_render = time.perf_counter() - t0
    total = sim.frame_count()
    idx = np.linspace(0, total - 1, min(frames, total)).astype(int)
    pose_ms, render_ms, encode_ms = [], [], []
    tmp = tempfile.TemporaryDirectory(prefix="smartroom-bench-")
    writers = {}
    if encode:
        for cam in sim.calibration.cameras:
            writers[cam.name] = cv2.VideoWriter(str(Path(tmp.name) / f"{cam.name}.mp4"),
                                                cv2.VideoWriter_fourcc(*"mp4v"), fps, (cam.width, cam.height))
    try:
        for i in idx:
            a = time.perf_counter()
            people = sim.people(int(i))
            b = time.perf_counter()
            images, _labels, _rec = sim.render_people(int(i), people)
            c = time.perf_counter()
            for name, w in writers.items():
                w.write(images[name])
            d = time.perf_counter()
            pose_ms.append((b - a) * 1e3)
            render_ms.append((c - b) * 1e3)
            encode_ms.append((d - c) * 1e3)
    finally:
        for w in writers.values():
            w.release()
        tmp.cleanup()
    per = np.array(pose_ms) + np.array(render_ms) + np.array(encode_ms)
    res = {
        "scene": scene, "cameras": len(sim.cameras), "size": f"{width}x{height}", "frames_timed": len(idx),
        "setup_s": round(setup_plan + setup_render, 2), "plan_s": round(setup_plan, 2),
        "pose_ms_p50": _p(pose_ms, 50), "render_ms_p50": _p(render_ms, 50), "render_ms_p95": _p(render_ms, 95),
        "encode_ms_p50": _p(encode_ms, 50), "frame_ms_p50": _p(per, 50), "frame_ms_p95": _p(per, 95),
        "fps": round(1000.0 / float(np.mean(per)), 1), "seconds": seconds, "frames": total,
    }
    res["extrapolated_s"] = round(res["setup_s"] + float(np.mean(per)) * total / 1000.0, 1)
    res["realtime"] = res["fps"] >= fps
    if not quiet:
        print(f"simulate bench: {scene}, {res['cameras']} cameras {res['size']}, {res['frames_timed']} frames timed")
        print(f"  setup (plan + static room + compile)  {res['setup_s']:8.2f} s")
        print(f"  pose + ground truth    p50 {res['pose_ms_p50']:7.1f} ms")
        print(f"  render all cameras     p50 {res['render_ms_p50']:7.1f} ms   p95 {res['render_ms_p95']:7.1f} ms")
        print(f"  encode videos          p50 {res['encode_ms_p50']:7.1f} ms")
        print(f"  per multi-camera frame p50 {res['frame_ms_p50']:7.1f} ms   p95 {res['frame_ms_p95']:7.1f} ms"
              f"   ({res['fps']} fps, real time at {fps:g} fps: {'yes' if res['realtime'] else 'no'})")
        print(f"  {seconds:g} s recording ({total} frames): about {res['extrapolated_s']} s")
    return res


def _p(values, q) -> float:
    return round(float(np.percentile(values, q)), 1)


def add_arguments(parser) -> None:
    parser.add_argument("--scene", default="meeting3")
    parser.add_argument("--frames", type=int, default=50, help="frames to time (spread over the scene)")
    parser.add_argument("--seconds", type=float, default=10.0, help="recording length to extrapolate to")
    parser.add_argument("--fps", type=float, default=25.0)
    parser.add_argument("--zenithal", action="store_true")
    parser.add_argument("--no-encode", action="store_true", help="time rendering only")


def main(args) -> int:
    bench_render(args.scene, frames=args.frames, seconds=args.seconds, fps=args.fps, zenithal=args.zenithal,
                 encode=not args.no_encode)
    return 0
