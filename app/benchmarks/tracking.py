"""``smartroom bench tracking``: the Table 4.3 / Fig. 4.14 analogue (thesis §4.4.2-4.4.3).

For every recording (default: the simulated meeting3 and crowd6) and voxel size, the
voxels are reconstructed once offline (:func:`app.tracking.offline.recording_voxels`,
cached) and every tracker configuration (filter x sample / particle count) runs CCA,
the person test and the tracker over the same frames on one core, in this process.
Each row: MOTP (mm), MOTA, IDF1, the error ratios and the ms per frame of CCA +
tracking (median and p95; the timing is of this process on a possibly shared machine)
and the median CPU time of the same (``cpu p50``: this thread's CPU time, what one core
spends on a frame even when other processes share the cores).
A filter marked ``*`` runs as the thesis has it (``:thesis`` in ``--filters``).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

__all__ = ["CONFIGS", "parse_configs", "run", "format_table", "HEADER"]

#: the default grid: (filter, samples or particles); None for the naive tracker
CONFIGS = (
    ("naive", None),
    ("pf_raw", 25), ("pf_raw", 100), ("pf_raw", 250),
    ("pf_colour", 25), ("pf_colour", 100), ("pf_colour", 250),
    ("ss_raw", 100), ("ss_raw", 400), ("ss_raw", 1000),
    ("ss_colour", 100), ("ss_colour", 400), ("ss_colour", 1000),
)

HEADER = (f"{'recording':<11}{'voxel':>6} {'filter':<10}{'N':>5}{'MOTP mm':>9}{'MOTA':>8}{'IDF1':>8}"
          f"{'miss':>7}{'fp':>7}{'mme':>5}{'ids':>5}{'ms p50':>8}{'ms p95':>8}{'cpu p50':>8}")


def parse_configs(text: str) -> list[tuple]:
    """``naive,ss_colour:400,pf_raw:100,ss_colour:400:thesis`` -> configs; ``:thesis``
    runs the filter as the thesis has it (no re-centring on the voxel share, so no moving
    of the particle cloud either, no fresh samples in Sparse Sampling) to show what the
    improvements change; the track life (creation, deletion, re-identification) is the
    same for every row."""
    from app.errors import InputError
    from app.tracking.tracker import FILTERS

    out = []
    for item in (t.strip() for t in text.split(",") if t.strip()):
        name, _, rest = item.partition(":")
        n, _, variant = rest.partition(":")
        if name not in FILTERS:
            raise InputError(f"--filters: unknown filter {name!r} ({', '.join(FILTERS)})")
        if variant not in ("", "thesis"):
            raise InputError(f"--filters: {item!r}: the variant after the count can only be 'thesis'")
        try:
            out.append((name, int(n) if n else None, variant == "thesis"))
        except ValueError:
            raise InputError(f"--filters: {item!r}: the count after ':' must be an integer") from None
    return out


def _params(name: str, n: int | None, thesis: bool = False):
    from app.tracking.tracker import TrackerParams

    kw = {"filter": name}
    if thesis:
        kw.update(refine=False, ss_reseed=0.0)
    if n is not None:
        kw["particles" if name.startswith("pf") else "samples"] = int(n)
    return TrackerParams(**kw)


def run(recordings, voxel_sizes=(0.02, 0.05, 0.10), configs=CONFIGS, frames: int | None = None,
        classifier=None, progress=print) -> dict:
    """Rows of the table (one per recording x voxel size x configuration)."""
    from app.evaluation.tracking import score_tracking, truth_frames
    from app.recording import Recording
    from app.tracking.classifier import load_tree
    from app.tracking.offline import recording_voxels, track_frames

    tree = classifier or load_tree()
    rows = []
    for rec in recordings:
        truth = truth_frames(Recording(rec).groundtruth() or [])
        for vs in voxel_sizes:
            t0 = time.perf_counter()
            vox, grid = recording_voxels(rec, vs, None)
            vox = vox[:frames] if frames else vox
            if progress:
                progress(f"  {Path(rec).name} at {100 * vs:g} cm: {len(vox)} frames of voxels "
                         f"({time.perf_counter() - t0:.0f} s)")
            for config in configs:
                name, n, thesis = (tuple(config) + (False,))[:3]
                timings: dict = {}
                res = track_frames(vox, grid, _params(name, n, thesis), tree, timings)
                s = score_tracking(truth, res, frames=[f for f in sorted(truth) if f in res]).summary()
                ms = np.asarray(timings.get("cca", [0])) + np.asarray(timings.get("tracking", [0]))
                cpu = np.asarray(timings.get("cca_cpu", [0])) + np.asarray(timings.get("tracking_cpu", [0]))
                row = {"recording": Path(rec).name, "voxel_size": vs, "filter": name + ("*" if thesis else ""), "n": n,
                       "ms_p50": round(float(np.median(ms)), 2), "ms_p95": round(float(np.percentile(ms, 95)), 2),
                       "cpu_ms_p50": round(float(np.median(cpu)), 2), "cpu_ms_p95": round(float(np.percentile(cpu, 95)), 2),
                       "cca_ms_p50": round(float(np.median(timings.get("cca", [0]))), 2),
                       "cca_cpu_ms_p50": round(float(np.median(timings.get("cca_cpu", [0]))), 2),
                       "tracking_ms_p50": round(float(np.median(timings.get("tracking", [0]))), 2), **s}
                rows.append(row)
                if progress:
                    progress(format_row(row))
    return {"rows": rows}


def format_row(r: dict) -> str:
    n = "" if r["n"] is None else str(r["n"])
    return (f"{r['recording']:<11}{100 * r['voxel_size']:>4g}cm {r['filter']:<10}{n:>5}{r['motp_mm']:>9.1f}"
            f"{r['mota']:>8.3f}{r['idf1']:>8.3f}{r['miss_ratio']:>7.3f}{r['false_positive_ratio']:>7.3f}"
            f"{r['mismatches']:>5}{r['track_ids']:>5}{r['ms_p50']:>8.1f}{r['ms_p95']:>8.1f}{r.get('cpu_ms_p50', 0):>8.1f}")


def format_table(result: dict) -> str:
    return "\n".join([HEADER] + [format_row(r) for r in result["rows"]])
