"""The ``smartroom`` command line (CONTRACT §3).

Each verb lives in its own module, which provides ``add_arguments(parser)`` and
``main(args) -> int``; this file only wires them. Bad input is reported as one line
(``smartroom: error: ...``) with exit code 2, never a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from app.errors import InputError

VERBS = {
    "run": ("app.commands.run", "start the whole pipeline as separate processes over zenoh"),
    "worker": ("app.commands.worker", "start one worker process by itself (multi-host deployment)"),
    "simulate": ("app.simulation.command", "write a simulated recording folder with ground truth"),
    "record": ("app.commands.record", "write a recording folder from what the grabber reads"),
    "eval": ("app.commands.evaluate", "score results against ground truth"),
    "bench": ("app.commands.bench", "throughput profiling against the real-time target"),
    "calibrate": ("app.commands.calibrate", "check, import and export camera calibrations"),
    "train": ("app.commands.train", "train the person / no-person classifier of the tracker"),
    "export": ("app.commands.export", "write a run's people as BVH, C3D, TRC or CSV for other tools"),
    "view": ("app.commands.view", "replay a finished run in the viewer (meshcat in a browser)"),
    "markers": ("app.commands.markers", "learn the colour of the markers (marker-based capture) and check it"),
}


def build_parser(verb: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``verb``'s module is imported (all of them when None)."""
    parser = argparse.ArgumentParser(
        prog="smartroom",
        description="Real-time multi-camera human motion capture for smart rooms.",
    )
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    sub.required = True
    for name, (module, help_text) in VERBS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if verb is None or name == verb:
            mod = importlib.import_module(module)
            mod.add_arguments(p)
            p.set_defaults(_main=mod.main)
    return parser


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    verb = argv[0] if argv and argv[0] in VERBS else ""
    parser = build_parser(verb)
    args = parser.parse_args(argv)
    try:
        return int(args._main(args) or 0)
    except InputError as exc:
        print(f"smartroom: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
