"""Throughput of the reconstruction core: carve, surface and colour per frame.

``bench_reconstruction(calibration, frames)`` times :class:`Reconstructor` on a list of
frames (``(masks, images)`` dicts keyed by camera) for every combination of voxel size,
carving method (``flat`` / ``hierarchical``) and colouring (``none`` = raw voxels /
``visibility``), and returns and prints ms per frame (p50 and p95) per step and the
number of occupied voxels per frame. Single-threaded, as the workers run it.

Without frames it renders its own: three people in a 5 x 4 x 2.5 m room seen by five
640x480 cameras, masks and colour images at half size (320x240)::

    python -m app.reconstruction.bench [--frames 20] [--voxel-sizes 0.02 0.04] [--json out.json]
"""
from __future__ import annotations

import argparse
import gc
import json
import time

import numpy as np

from calibration import Calibration

from .reconstructor import Reconstructor
from .synthetic import meeting_scene, room_calibration

__all__ = ["bench_reconstruction", "synthetic_frames", "format_table"]

STEPS = ("carve", "floor", "surface", "colour", "total")


def synthetic_frames(n_frames: int = 20, calibration: Calibration | None = None, mask_size=(320, 240),
                     colour_size=(320, 240), fps: float = 25.0) -> tuple[Calibration, list]:
    """Three people moving in the room, rendered exactly: ``(calibration, frames)``."""
    calib = calibration or room_calibration(5, 640, 480)
    mask_cams = [c.scaled(*mask_size) for c in calib.cameras]
    colour_cams = [c.scaled(*colour_size) for c in calib.cameras]
    frames = []
    for f in range(n_frames):
        scene = meeting_scene(f / fps, room=tuple(calib.room_max - calib.room_min))
        masks, images = {}, {}
        for mc, cc in zip(mask_cams, colour_cams):
            mask, image = scene.render(mc)
            masks[mc.name] = mask
            images[cc.name] = image if tuple(colour_size) == tuple(mask_size) else scene.render(cc)[1]
        frames.append((masks, images))
    return calib, frames


def _sizes(frames, which: int) -> dict:
    sizes = {}
    for fr in frames:
        for name, a in fr[which].items():
            if a is not None:
                sizes[name] = (a.shape[1], a.shape[0])
    return sizes


def bench_reconstruction(calibration: Calibration, frames: list, voxel_sizes=(0.02, 0.03, 0.04, 0.05),
                         methods=("flat", "hierarchical"), colourings=("none", "visibility"), repeat: int = 1,
                         warmup: int = 2, verbose: bool = True, **options) -> list[dict]:
    """Time the reconstruction of ``frames`` (a list of ``(masks, images)``).

    Mask and colour sizes are read from the frames. Each configuration runs ``warmup``
    untimed frames, then every frame ``repeat`` times. Returns one row per
    configuration: ``voxel_size, method, colouring, frames, occupied`` (p50 voxels per
    frame), ``surface_voxels`` (p50), ``<step>_p50`` / ``<step>_p95`` in ms for steps
    carve, surface, colour, total, ``total_per_frame`` (ms, in frame order),
    ``build_ms`` (tables and warm-up) and ``table_mb``.
    ``options`` go to :class:`Reconstructor`.
    """
    mask_sizes = _sizes(frames, 0)
    colour_sizes = _sizes(frames, 1)
    rows = []
    for vs in voxel_sizes:
        for method in methods:
            for colouring in colourings:
                gc.collect()
                t0 = time.perf_counter()
                r = Reconstructor(calibration, vs, mask_sizes=mask_sizes, colour_sizes=colour_sizes or None,
                                  method=method, colouring=colouring, **options)
                build_ms = (time.perf_counter() - t0) * 1e3
                for masks, images in frames[:warmup]:
                    r.reconstruct(masks, images if colouring != "none" else None)
                times = {s: [] for s in STEPS}
                occupied, surface = [], []
                for _ in range(repeat):
                    for masks, images in frames:
                        idx, _, surf, tm = r.reconstruct(masks, images if colouring != "none" else None)
                        for s in STEPS:
                            times[s].append(tm.get(s, 0.0))
                        occupied.append(len(idx))
                        surface.append(int(surf.sum()) if surf.size else 0)
                row = {"voxel_size": vs, "method": method, "colouring": colouring, "frames": len(occupied),
                       "total_per_frame": [round(v, 3) for v in times["total"]],
                       "occupied": int(np.median(occupied)), "surface_voxels": int(np.median(surface)),
                       "occupancy_pct": 100.0 * float(np.median(occupied)) / r.grid.n_voxels,
                       "build_ms": build_ms, "table_mb": r.table_bytes / 1e6}
                for s in STEPS:
                    row[f"{s}_p50"] = float(np.percentile(times[s], 50))
                    row[f"{s}_p95"] = float(np.percentile(times[s], 95))
                rows.append(row)
                if verbose:
                    print(format_row(row), flush=True)
                del r
    return rows


HEADER = (f"{'voxel':>5} {'method':<12} {'colour':<10} {'occupied':>8} {'occ%':>5} {'surface':>7} "
          f"{'carve p50/p95':>14} {'surface p50/p95':>16} {'colour p50/p95':>15} {'total p50/p95':>15} "
          f"{'build ms':>8} {'MB':>5}")


def format_row(r: dict) -> str:
    def pair(s):
        return f"{r[s + '_p50']:6.2f}/{r[s + '_p95']:6.2f}"
    return (f"{r['voxel_size'] * 100:4.0f}cm {r['method']:<12} {r['colouring']:<10} {r['occupied']:8d} "
            f"{r['occupancy_pct']:5.2f} {r['surface_voxels']:7d} {pair('carve'):>14} {pair('surface'):>16} "
            f"{pair('colour'):>15} {pair('total'):>15} {r['build_ms']:8.0f} {r['table_mb']:5.0f}")


def format_table(rows: list[dict]) -> str:
    return "\n".join([HEADER] + [format_row(r) for r in rows])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--voxel-sizes", type=float, nargs="+", default=[0.02, 0.03, 0.04, 0.05])
    p.add_argument("--methods", nargs="+", default=["flat", "hierarchical"])
    p.add_argument("--colourings", nargs="+", default=["none", "visibility"])
    p.add_argument("--colour-size", type=int, nargs=2, default=[320, 240], metavar=("W", "H"))
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--json", metavar="FILE")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    calib, frames = synthetic_frames(args.frames, colour_size=tuple(args.colour_size))
    print(f"{len(frames)} frames of {len(calib.cameras)} cameras rendered in {time.perf_counter() - t0:.1f} s; "
          f"masks 320x240, colour {args.colour_size[0]}x{args.colour_size[1]}", flush=True)
    print(HEADER, flush=True)
    rows = bench_reconstruction(calib, frames, args.voxel_sizes, args.methods, args.colourings, args.repeat)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
