"""Junk on every key of a room, at a set rate (issue 25: "junk at 20,000 msg/s on any key
for 30 s loses no frame offline and costs < 20 % RTF live").

Any process may publish on the bus. :func:`flood` is such a process: it connects to the
room's hub as a client and publishes, round-robin over every key the workers of a layout
listen on (frames, masks and markers per camera, voxels, blobs, tracks, poses, keypoints,
and the control keys: stats, acks, heartbeats, ends of stream per worker), payloads that
no worker may accept:

- random bytes;
- a smartroom header of another protocol version;
- a header whose meta is cut short, or is not JSON;
- a header and meta that announce arrays the payload does not hold;
- a well-formed heartbeat from a worker that is not in the layout.

Their frame indices run over the recording's (a header read alone would look like a real
frame). Congestion control is ``BLOCK``: what is counted as sent reached the hub.
``python -m app.benchmarks.flood --connect EP --room R --keys K,... --rate N --seconds S``
runs it in its own process (so it does not take the measuring process's interpreter);
the last line it prints is ``{"sent": n, "seconds": s, "rate": n / s}``.

Where it comes from: by default from outside the room, over the hub's TCP endpoint, as a
stray process, a viewer or a client of the zenoh feed would; a room on one host (the
default layout) lets nothing linked that way publish in it (:mod:`app.bus_acl`), so the
hub drops the junk. ``--inside LAYOUT`` connects the way the room's own workers do (the
endpoint its resolved ``layout.yaml`` gives them: the private socket), as a worker gone
wrong would: then the junk reaches the workers and their own checks refuse it.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import signal
import time
from pathlib import Path

import numpy as np

from app.bus import BusConfig, Keys, open_session
from app.messages import _HEADER, MAGIC, VERSION, Frame, Heartbeat

__all__ = ["room_keys", "junk_payloads", "flood", "measure", "table"]

TICK_S = 0.005
HUB_WAIT_S = 120.0


def room_keys(room: str, cameras, workers) -> list[str]:
    """Every key a run of ``room`` with these cameras and worker names listens on."""
    k = Keys(room)
    keys = [k.voxels(), k.blobs(), k.tracks(), k.poses(), k.poses_json(), k.keypoints()]
    for cam in cameras:
        keys += [k.frame(cam), k.mask(cam), k.markers(cam)]
    for w in workers:
        keys += [k.stats(w), k.ack(w), k.heartbeat(w), k.eos(w)]
    return keys


def junk_payloads(frames: int, seed: int = 0) -> list[bytes]:
    """Payloads no worker may accept, frame indices in ``0..frames-1``."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(64):
        frame = int(i * 7919 % max(1, frames))
        kind = i % 6
        if kind == 0:
            out.append(rng.integers(0, 256, int(rng.integers(8, 200)), dtype=np.uint8).tobytes())
        elif kind == 1:
            out.append(_HEADER.pack(MAGIC, VERSION + 1, Frame.TYPE_ID, 0, 1, frame, time.time(), 0.0, 0) + b"x" * 16)
        elif kind == 2:
            out.append(_HEADER.pack(MAGIC, VERSION, 1 + i % 13, 0, 1, frame, time.time(), 0.0, 4000) + b"{}")
        elif kind == 3:
            out.append(_HEADER.pack(MAGIC, VERSION, 1 + i % 13, 0, 0, frame, time.time(), 0.0, 7) + b"not json")
        elif kind == 4:
            meta = json.dumps({"m": {"camera": "cam0"}, "a": [["|u1", [480, 640, 3]]]}).encode()
            out.append(_HEADER.pack(MAGIC, VERSION, Frame.TYPE_ID, 0, 1, frame, time.time(), 0.0, len(meta)) + meta)
        else:
            out.append(Heartbeat(frame=frame, stamp=time.time(), worker=f"zz{i}", pid=1, pending=9).to_bytes())
    return out


def flood(connect: str, keys: list[str], rate: float, seconds: float, frames: int = 250,
          stop=None) -> dict:
    """Publish junk round-robin over ``keys`` at ``rate`` messages a second for ``seconds``
    (or until ``stop()`` is true); ``{"sent", "seconds", "rate", "cpu_s"}`` (``cpu_s``: this
    process's CPU seconds, the flooder's own where it runs in a process of its own)."""
    import zenoh

    if not _wait_for_hub(connect, HUB_WAIT_S, stop):
        return {"sent": 0, "seconds": 0.0, "rate": 0.0}
    session = open_session(BusConfig(listen=[], connect=[connect]), mode="client")
    try:
        pubs = [session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK) for key in keys]
        payloads = junk_payloads(frames)
        n_pub, n_pay = len(pubs), len(payloads)
        sent, t0 = 0, time.monotonic()
        while True:
            now = time.monotonic() - t0
            if now >= seconds or (stop is not None and stop()):
                break
            due = int(rate * (now + TICK_S))
            while sent < due:
                pubs[sent % n_pub].put(payloads[sent % n_pay])
                sent += 1
            time.sleep(max(0.0, (sent / rate) - (time.monotonic() - t0)) if rate else TICK_S)
        span = time.monotonic() - t0
    finally:
        session.close()
    return {"sent": sent, "seconds": round(span, 3), "rate": round(sent / span, 1) if span else 0.0,
            "cpu_s": round(time.process_time(), 3)}


def _wait_for_hub(connect: str, timeout: float, stop=None) -> bool:
    """Wait until the hub's TCP endpoint or Unix socket accepts a connection (the flood
    may be started before the run that opens it)."""
    import socket

    proto, _, address = connect.partition("/")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not (stop is not None and stop()):
        try:
            if proto == "unixsock-stream":
                with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                    s.settimeout(0.5)
                    s.connect(address)
            else:
                host, port = address.rsplit(":", 1)
                socket.create_connection((host.strip("[]"), int(port)), timeout=0.5).close()
            return True
        except OSError:
            time.sleep(0.05)
    return False


def inside_endpoint(layout_file, timeout: float, stop=None) -> str | None:
    """The endpoint the room's own workers connect to, from the run's resolved layout
    (written when its launcher starts; None if it does not appear within ``timeout``)."""
    from app.config import LayoutError, load_layout

    deadline = time.monotonic() + timeout
    path = Path(layout_file)
    while time.monotonic() < deadline and not (stop is not None and stop()):
        if path.exists():   # (written whole: Layout.save)
            try:
                return load_layout(path).bus.for_worker().connect[0]
            except (LayoutError, IndexError):
                return None
        time.sleep(0.05)
    return None


def _outputs_equal(a, b) -> bool | None:
    """Whether two runs wrote the same tracks and poses (None where neither wrote them)."""
    same = None
    for name in ("tracks.jsonl", "poses.jsonl"):
        fa, fb = Path(a) / name, Path(b) / name
        if fa.exists() or fb.exists():
            same = (same is not False) and fa.exists() and fb.exists() and fa.read_bytes() == fb.read_bytes()
    return same


def _workers_cpu(stats: dict) -> float:
    """CPU seconds of the run's workers (each from its first input to its last output)."""
    return sum(float(w.get("cpu_ms_per_frame") or 0.0)
               * max(int(w.get("frames_in") or 0), int(w.get("frames_out") or 0))
               for w in stats.get("workers", {}).values()) / 1e3


def _refused(stats: dict) -> int:
    """Messages the workers refused (their ``rejected`` counts in stats.json)."""
    n = 0
    for w in stats.get("workers", {}).values():
        n += sum(int(v) for v in (w.get("rejected") or {}).values())
    return n


def measure(layout, run, out, rate: float, modes=("unpaced", "paced"), progress=True, inside: bool = False) -> dict:
    """The pipeline on ``run`` in each mode, quiet and beside a flood of junk at ``rate``
    messages a second on every key of the room (another process, :func:`flood`; from
    outside the room, or ``inside`` it: module docstring): RTF of both, what the flood
    cost, frames delivered, and (unpaced, a recording's results do not depend on load)
    whether the flooded run wrote the same tracks and poses."""
    import subprocess
    import sys

    from app.benchmarks.pipeline import MODES, profile_run
    from app.bus import free_port
    from app.layout import RunSpec
    from app.recording import Recording

    out = Path(out)
    cameras = Recording(run.recording).calibration.cameras
    result = {"recording": run.recording, "frames": run.frames, "rate": rate, "modes": {},
              "from": "inside" if inside else "outside"}
    for mode in modes:
        row = {}
        for label in ("quiet", "flooded"):
            port = free_port()
            lay = layout.copy()
            lay.bus = dataclasses.replace(lay.bus, listen=[f"tcp/127.0.0.1:{port}"])
            r = RunSpec(**{**run.__dict__, "pace": MODES[mode]})
            flooder = None
            if label == "flooded":
                resolved = out / label / mode / "layout.yaml"
                resolved.unlink(missing_ok=True)   # the run about to start writes it
                where = ["--inside", str(resolved)] if inside else ["--connect", f"tcp/127.0.0.1:{port}"]
                flooder = subprocess.Popen(
                    [sys.executable, "-m", "app.benchmarks.flood", *where,
                     "--room", lay.room, "--cameras", ",".join(c.name for c in cameras),
                     "--workers", ",".join(w.name for w in lay.workers), "--rate", str(rate),
                     "--seconds", "86400", "--frames", str(run.frames or 250)],
                    stdout=subprocess.PIPE, text=True)
            cpu0 = time.process_time()
            try:
                report = profile_run(lay, r, out / label / mode, progress=progress)
            finally:
                hub_cpu = time.process_time() - cpu0
                sent = None
                if flooder is not None:
                    flooder.terminate()
                    text, _ = flooder.communicate(timeout=60)
                    lines = text.strip().splitlines()
                    sent = json.loads(lines[-1]) if lines else {"sent": 0, "seconds": 0.0, "rate": 0.0}
            stats = json.loads((out / label / mode / "stats.json").read_text())
            final = report.get("final_stage")
            row[label] = {"rtf": report.get("rtf"), "exit_code": report["exit_code"],
                          "complete": bool(stats.get("complete")), "wall_s": report["wall_s"],
                          "frames_out": (report["stages"].get(final) or {}).get("frames_out"),
                          "dropped": sum(int(s.get("frames_dropped") or 0) for s in report["stages"].values()),
                          "refused": _refused(stats), "junk": sent,
                          # CPU seconds over the run: the launcher (this process: the hub routes
                          # every message), the workers (from their first input to their last
                          # output), the flooding process (all of its life)
                          "cpu_s": {"hub": round(hub_cpu, 2), "workers": round(_workers_cpu(stats), 2),
                                    "flooder": (sent or {}).get("cpu_s", 0.0)}}
        q, f = row["quiet"], row["flooded"]
        row["rtf_cost"] = round(1.0 - f["rtf"] / q["rtf"], 4) if q["rtf"] and f["rtf"] is not None else None
        row["same_results"] = _outputs_equal(out / "quiet" / mode, out / "flooded" / mode)
        result["modes"][mode] = row
    return result


def table(result: dict) -> str:
    head = (f"{'mode':<10}{'RTF quiet':>10}{'flooded':>9}{'cost':>7}{'out quiet':>10}{'flooded':>9}"
            f"{'dropped':>9}{'junk/s':>9}{'sent':>9}{'refused':>9}{'same results':>14}")
    lines = [f"junk on every key of the room at {result['rate']:g} msg/s from {result.get('from', 'outside')} the room "
             f"beside {result['frames']} frames of {result['recording']}", head]
    for mode, r in result["modes"].items():
        q, f = r["quiet"], r["flooded"]
        junk = f["junk"] or {}
        same = {True: "yes", False: "NO", None: "-"}[r["same_results"]]
        lines.append(f"{mode:<10}{q['rtf'] or 0:>10.3f}{f['rtf'] or 0:>9.3f}{100 * (r['rtf_cost'] or 0):>6.1f}%"
                     f"{q['frames_out'] or 0:>10}{f['frames_out'] or 0:>9}{f['dropped']:>9}"
                     f"{junk.get('rate', 0):>9.0f}{junk.get('sent', 0):>9}{f['refused']:>9}{same:>14}")
        cq, cf = q["cpu_s"], f["cpu_s"]
        lines.append(f"  CPU s quiet / flooded: hub {cq['hub']:.1f} / {cf['hub']:.1f}, workers {cq['workers']:.1f} / "
                     f"{cf['workers']:.1f}, flooder {cf['flooder']:.1f}; wall {q['wall_s']:.1f} / {f['wall_s']:.1f} s")
        for label, x in (("quiet", q), ("flooded", f)):
            if x["exit_code"] != 0 or not x["complete"]:
                lines.append(f"  {mode} {label}: exit {x['exit_code']}, complete {x['complete']}")
    return "\n".join(lines)


def _main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--connect", help="the hub's endpoint, e.g. tcp/127.0.0.1:7447")
    where.add_argument("--inside", metavar="LAYOUT", help="a run's resolved layout.yaml: connect as its workers do")
    p.add_argument("--room", required=True)
    p.add_argument("--cameras", default="", help="camera names, comma-separated")
    p.add_argument("--workers", default="", help="worker names, comma-separated")
    p.add_argument("--rate", type=float, default=20000.0, help="messages a second (default 20000)")
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--frames", type=int, default=250, help="frame indices of the junk run over 0..N-1")
    a = p.parse_args()
    stopping = []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append(1))
    keys = room_keys(a.room, [c for c in a.cameras.split(",") if c], [w for w in a.workers.split(",") if w])
    connect = a.connect or inside_endpoint(a.inside, HUB_WAIT_S, stop=lambda: bool(stopping))
    if connect is None:
        print(json.dumps({"sent": 0, "seconds": 0.0, "rate": 0.0}), flush=True)
        return
    print(json.dumps(flood(connect, keys, a.rate, a.seconds, a.frames, stop=lambda: bool(stopping))), flush=True)


if __name__ == "__main__":
    _main()
