"""Whole-pipeline profiling against the real-time target (``smartroom bench``).

The pipeline runs on a recording twice: unpaced (``--no-pace``: as fast as the
slowest stage acknowledges frames, which measures its capacity) and paced at the
recording's fps (what a live room would see). Each worker writes per-frame timings;
from them the report gives, per stage, latency from capture over time, fps and drops,
and for the pipeline the real-time factor ``RTF = fps / f_R`` (thesis Eq. 4.27) over
time and the end-to-end latency. ``--sweep`` repeats the whole profile over one
parameter and tabulates RTF against it, as the thesis's Fig. 4.14 does for the voxel
size.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from app.config import Layout, RunSpec, apply_overrides
from app.files import write_json

__all__ = ["profile_run", "profile", "by_stage", "sweep_values", "write_figure", "summary_lines", "SWEEP_ALIASES"]

MODES = {"unpaced": False, "paced": True}
RTF_WINDOW_S = 1.0
#: short names for --sweep: name -> (worker kind, parameter, factor applied to the values)
SWEEP_ALIASES = {"voxel": ("reconstruction", "voxel_size", 0.01)}


def _load_traces(out: Path) -> dict:
    traces = {}
    for f in sorted((out / "trace").glob("*.json")):
        t = json.loads(f.read_text())
        traces[t["worker"]] = t
    return traces


def _rtf_over_time(times: np.ndarray, t0: float, fps: float) -> list[list[float]]:
    """Output rate of the slowest stage in sliding windows (1 s, shorter for short runs),
    divided by the recording fps."""
    if times.size < 2 or not fps:
        return []
    rel = np.sort(times - t0)
    window = max(0.05, min(RTF_WINDOW_S, rel[-1] / 8))
    grid = np.linspace(window, rel[-1], 100)
    counts = np.searchsorted(rel, grid, side="right") - np.searchsorted(rel, grid - window, side="right")
    return [[round(float(g), 4), round(float(c) / window / fps, 4)] for g, c in zip(grid, counts)]


def profile_run(layout: Layout, run: RunSpec, out: Path, progress=True) -> dict:
    """Run the pipeline once with per-frame tracing; its profile (one mode)."""
    from app.launcher import Launcher
    from app.report import Progress

    out.mkdir(parents=True, exist_ok=True)
    layout = layout.copy()
    layout.run = run
    run.out, run.trace, run.headless = str(out), True, True
    t_start = time.time()
    rc = Launcher(layout, progress=Progress(run.frames, run.fps) if progress else None).run()
    wall = time.time() - t_start
    stats = json.loads((out / "stats.json").read_text())
    traces = _load_traces(out)
    fps_rec = stats.get("recording_fps") or run.fps
    stages, t0 = {}, None
    for name, t in traces.items():
        rows = np.array([r for r in t["frames"] if r[3] is not None], dtype=np.float64).reshape(-1, 4)
        if t["order"] is None or rows.size == 0:
            continue
        t0 = rows[:, 1].min() if t0 is None else min(t0, rows[:, 1].min())
        stages[name] = {"stage": t["stage"], "order": t["order"], "rows": rows,
                        "process_ms": np.asarray(t["process_ms"])}
    report = {"exit_code": rc, "wall_s": round(wall, 3), "recording_fps": fps_rec, "frames": run.frames,
              "paced": run.pace, "rtf": stats.get("rtf"), "fps": stats.get("fps"),
              "end_to_end_latency_ms": stats.get("end_to_end_latency_ms"), "stages": {}}
    limiting = stats.get("final_stage")  # frames delivered at the end of the pipeline set its pace
    if limiting not in stages:
        limiting = max(stages, key=lambda n: stages[n]["order"]) if stages else None
    for name, s in sorted(stages.items(), key=lambda kv: kv[1]["order"]):
        rows = s["rows"]
        lat = (rows[:, 3] - rows[:, 1]) * 1e3
        st = stats["stages"].get(name, {})
        report["stages"][name] = {
            "stage": s["stage"], "order": s["order"],
            "frames_in": st.get("frames_in"), "frames_out": st.get("frames_out"),
            "frames_dropped": st.get("frames_dropped"), "frames_missing": st.get("frames_missing"),
            "fps": st.get("fps"), "cpu_percent": st.get("cpu_percent"),
            "cpu_ms_per_frame": st.get("cpu_ms_per_frame"),
            "latency_ms": {"p50": round(float(np.percentile(lat, 50)), 3), "p95": round(float(np.percentile(lat, 95)), 3)},
            "process_ms": {"p50": round(float(np.percentile(s["process_ms"], 50)), 3) if s["process_ms"].size else 0.0,
                           "p95": round(float(np.percentile(s["process_ms"], 95)), 3) if s["process_ms"].size else 0.0},
            # per frame: [frame, seconds since the first capture, latency from capture (ms)]
            "per_frame": [[int(r[0]), round(float(r[3] - t0), 4), round(float(v), 3)] for r, v in zip(rows, lat)],
        }
    report["by_stage"] = by_stage(report["stages"], run.frames)
    if limiting is not None:
        report["rtf_over_time"] = _rtf_over_time(stages[limiting]["rows"][:, 3], t0, fps_rec)
        report["final_stage"] = limiting
    report["bottleneck"] = stats.get("bottleneck")
    report["delivered_ratio"] = stats.get("delivered_ratio")
    return report


def by_stage(stages: dict, frames: int | None = None) -> dict:
    """Per stage (its kind), over the workers that share it (pose shards, a segmentation
    worker per camera, reconstruction workers taking frames in turn): the workers, the
    CPU per frame summed over them (each worker's process CPU from its first input to its
    last output, every thread counted, over the stage's frames: how well the stage scales
    out is this sum against one worker's) and the slowest worker's process time p50 (what
    holds the stage's frame). The stage's frames: the most any worker handled, or, where
    the workers took turns (frame shares), the frames they handled together, at most
    ``frames`` (the run's: workers that each see every frame add up to more)."""
    out: dict = {}
    for name, s in stages.items():
        g = out.setdefault(s["stage"], {"workers": [], "cpu_ms": 0.0, "frames": [], "process_ms_p50": 0.0,
                                        "order": s["order"]})
        g["workers"].append(name)
        n = max(1, int(s.get("frames_in") or 0), int(s.get("frames_out") or 0))
        g["cpu_ms"] += float(s.get("cpu_ms_per_frame") or 0.0) * n
        g["frames"].append(n)
        g["process_ms_p50"] = max(g["process_ms_p50"], float(s["process_ms"]["p50"]))
    for g in out.values():
        handled = max(g["frames"]) if frames is None else max(max(g["frames"]), min(sum(g["frames"]), int(frames)))
        g["cpu_ms_per_frame"] = round(g.pop("cpu_ms") / handled, 3)
        g.pop("frames")
    return dict(sorted(out.items(), key=lambda kv: kv[1]["order"]))


def profile(layout: Layout, run: RunSpec, out: Path, modes=("unpaced", "paced"), progress=True) -> dict:
    """The pipeline's profile in each mode, written to ``out/profile.json`` and ``out/profile.png``."""
    result = {"recording": run.recording, "frames": run.frames, "recording_fps": run.fps,
              "workers": {w.name: {"kind": w.kind, "params": w.params} for w in layout.workers}, "modes": {}}
    for mode in modes:
        r = RunSpec(**{**run.__dict__, "pace": MODES[mode]})
        result["modes"][mode] = profile_run(layout, r, out / mode, progress=progress)
    write_json(out / "profile.json", result)
    write_figure(result, out / "profile.png")
    return result


def sweep_values(layout: Layout, spec: str) -> list[tuple[str, Layout]]:
    """``voxel=2,3,4`` or ``worker.param=v1,v2`` -> [(label, layout with the value)]."""
    import yaml

    from app.errors import InputError

    if "=" not in spec:
        raise InputError(f"--sweep {spec}: expected PARAM=V1,V2,... (e.g. voxel=2,3,4,5)")
    name, values = spec.split("=", 1)
    factor = 1.0
    if name in SWEEP_ALIASES:
        target, param, factor = SWEEP_ALIASES[name]
    elif "." in name:
        target, param = name.rsplit(".", 1)
    else:
        raise InputError(f"--sweep {spec}: {name} is neither WORKER.PARAM nor one of {', '.join(SWEEP_ALIASES)}")
    out = []
    for text in values.split(","):
        value = yaml.safe_load(text)
        if factor != 1.0:
            if not isinstance(value, (int, float)):
                raise InputError(f"--sweep {spec}: {text} is not a number")
            value = round(value * factor, 6)
        out.append((f"{name}={text}", apply_overrides(layout, {target: {param: value}}, "--sweep")))
    return out


def summary_lines(result: dict) -> list[str]:
    """The terminal summary of a profile: per mode, per stage."""
    lines = []
    for mode, r in result["modes"].items():
        lat = r.get("end_to_end_latency_ms") or {}
        rtf = r.get("rtf")
        lines.append(f"{mode}: RTF {rtf if rtf is not None else float('nan'):.2f} ({r.get('fps') or 0:.1f} fps over "
                     f"{r['recording_fps']:g} fps), end-to-end latency p50 {lat.get('p50', 0):.0f} ms "
                     f"p95 {lat.get('p95', 0):.0f} ms, wall {r['wall_s']:.1f} s")
        head = f"  {'stage':<16}{'in':>6}{'out':>6}{'drop':>6}{'fps':>7}{'lat p50':>9}{'lat p95':>9}{'proc p50':>10}{'proc p95':>10}{'cpu%':>6}"
        lines.append(head)
        for name, s in r["stages"].items():
            lines.append(f"  {name:<16}{s['frames_in'] or 0:>6}{s['frames_out'] or 0:>6}{s['frames_dropped'] or 0:>6}"
                         f"{s['fps'] or 0:>7.1f}{s['latency_ms']['p50']:>7.1f}ms{s['latency_ms']['p95']:>7.1f}ms"
                         f"{s['process_ms']['p50']:>8.1f}ms{s['process_ms']['p95']:>8.1f}ms{s['cpu_percent'] or 0:>6.0f}")
        groups = r.get("by_stage") or {}
        lines.append(f"  {'per stage':<16}{'workers':>8}{'cpu ms/frame (summed)':>23}{'slowest proc p50':>18}")
        for stage, g in groups.items():
            lines.append(f"  {stage:<16}{len(g['workers']):>8}{g['cpu_ms_per_frame']:>21.1f}ms"
                         f"{g['process_ms_p50']:>16.1f}ms")
    return lines


def write_figure(result: dict, path: Path) -> None:
    """Per-stage latency over time and RTF over time (with the real-time line), per mode."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = list(result["modes"])
    fig, axes = plt.subplots(2, len(modes), figsize=(6.5 * len(modes), 7.5), squeeze=False)
    for col, mode in enumerate(modes):
        r = result["modes"][mode]
        ax = axes[0][col]
        for name, s in r["stages"].items():
            pf = np.asarray(s["per_frame"], dtype=np.float64).reshape(-1, 3)
            if pf.size:
                ax.plot(pf[:, 1], pf[:, 2], ".-", ms=2, lw=0.8, label=f"{name} (p95 {s['latency_ms']['p95']:.0f} ms)")
        ax.set_title(f"{mode}: latency from capture per stage")
        ax.set_xlabel("time since first capture (s)")
        ax.set_ylabel("latency (ms)")
        ax.set_yscale("symlog", linthresh=10)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
        ax = axes[1][col]
        rt = np.asarray(r.get("rtf_over_time") or [], dtype=np.float64).reshape(-1, 2)
        if rt.size:
            ax.plot(rt[:, 0], rt[:, 1], "-", color="tab:blue", label=f"RTF (whole run {r.get('rtf') or 0:.2f})")
        ax.axhline(1.0, color="tab:red", ls="--", lw=1.2, label="real time (RTF = 1)")
        ax.set_title(f"{mode}: real-time factor of {r.get('final_stage', '-')} (sliding window)")
        ax.set_xlabel("time since first capture (s)")
        ax.set_ylabel("RTF = fps / recording fps")
        ax.set_ylim(bottom=0)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    fig.suptitle(f"smartroom pipeline profile: {Path(result['recording'] or '').name}, {result['frames']} frames "
                 f"at {result['recording_fps']:g} fps")
    fig.tight_layout()
    tmp = path.with_name(path.stem + ".partial.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    os.replace(tmp, path)
