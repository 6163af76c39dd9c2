"""``smartroom bench``: throughput profiling against the real-time target.

- ``smartroom bench bus``: codec + zenoh latency and throughput between two processes.
"""
from __future__ import annotations

import json
from pathlib import Path

TARGETS = ("bus",)


def add_arguments(p) -> None:
    p.add_argument("target", nargs="?", default="bus", choices=TARGETS, help="what to measure (default bus)")
    p.add_argument("--frames", type=int, metavar="N", help="frames to measure")
    p.add_argument("--out", metavar="DIR", help="write the figures as JSON into DIR")


def _bus(args) -> dict:
    from app.benchmarks import bus

    n = args.frames or 300
    results = [bus.run(frames=n, throughput_frames=max(n, 200), shm=shm) for shm in (True, False)]
    print(bus.table(results))
    return {"bus": results}


def main(args) -> int:
    figures = {"bus": _bus}[args.target](args)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / f"bench_{args.target}.json").write_text(json.dumps(figures, indent=1))
    return 0
