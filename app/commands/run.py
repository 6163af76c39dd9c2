"""``smartroom run``: the whole pipeline as separate processes over zenoh."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from app.commands.options import add_pipeline_arguments, resolve_layout, resolve_out, resolve_source


def add_arguments(p) -> None:
    add_pipeline_arguments(p)


def main(args) -> int:
    from app.launcher import Launcher
    from app.report import Progress, summary_table

    layout = resolve_layout(args)
    run = resolve_source(args)
    run.out = str(resolve_out(args))
    run.headless = args.headless
    layout.run = run
    source = run.recording or ", ".join(f"{c}={s}" for c, s in run.live.items())
    print(f"smartroom: {len(layout.workers)} workers on {source}; results in {run.out}", file=sys.stderr)
    # the monitor worker, when the layout has one, shows progress itself
    has_monitor = any(w.kind == "monitor" for w in layout.workers)
    progress = None if has_monitor else Progress(run.frames, run.fps)
    rc = Launcher(layout, verbose=args.verbose, progress=progress).run()
    stats = Path(run.out) / "stats.json"
    if stats.is_file():
        print(summary_table(json.loads(stats.read_text())))
    print(f"smartroom: results in {run.out}", file=sys.stderr)
    return rc
