"""``smartroom worker NAME``: one worker process by itself (multi-host deployment).

On another host, point it at the hub: ``smartroom worker segmentation --layout
deploy/layouts/two_hosts.yaml --connect tcp/10.0.0.1:7447``.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path


def add_arguments(p) -> None:
    p.add_argument("name", help="the worker's name in the layout")
    p.add_argument("--layout", metavar="FILE", help="process layout YAML (default deploy/layouts/local.yaml)")
    p.add_argument("--recording", metavar="DIR", help="recording folder (overrides the layout's run section)")
    p.add_argument("--out", metavar="DIR", help="results folder (overrides the layout's run section)")
    p.add_argument("--frames", type=int, metavar="N", help="stop after N frames (sources)")
    p.add_argument("--no-pace", dest="pace", action="store_false", default=None,
                   help="read a recording as fast as the pipeline takes it")
    p.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="zenoh endpoint of the hub, e.g. tcp/10.0.0.1:7447 (repeatable)")
    p.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")


def main(args) -> int:
    import faulthandler
    import logging
    import signal

    # a stop requested while the worker still loads (a Ctrl-C in the first seconds) is
    # held here and acted on once the worker runs: a source then ends its stream at once
    early: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: early.append(signum))
    # the launcher asks for every thread's stack before it kills a worker that would not
    # stop (hung, or deaf to SIGTERM): the stacks reach its stderr, where the cause shows
    from app.watchdog import STACKS_SIGNAL

    faulthandler.register(STACKS_SIGNAL, all_threads=True, chain=False)

    from app.config import load_layout
    from app.errors import InputError, Stalled
    from app.launcher import ERROR_DIR
    from workers import worker_class
    from workers.base import FILE_ONLY, configure_logging

    layout = load_layout(args.layout)
    run = layout.run
    if args.recording:
        run.recording = str(Path(args.recording).resolve())
    if args.out:
        run.out = str(Path(args.out).resolve())
    if args.frames is not None:
        run.frames = args.frames
    if args.pace is not None:
        run.pace = args.pace
    if args.connect:
        layout.bus.connect = list(args.connect)
    spec = layout.worker(args.name)
    log_file = configure_logging(spec.name, logging.INFO if args.verbose else logging.WARNING,
                                 Path(run.out) / ERROR_DIR if run.out else None)
    try:
        worker = worker_class(spec.kind)(spec, layout)
        worker.early_signals = early
        return _exit(worker.run())
    except (InputError, Stalled) as exc:
        logging.getLogger(f"smartroom.{spec.name}").error("%s", exc, extra=FILE_ONLY)   # said once, by the launcher
        return _exit(_bad_input(exc, spec, run))
    except Exception as exc:  # noqa: BLE001 - a crash: its traceback in the log file, one line here
        if log_file is None:
            raise
        logging.getLogger(f"smartroom.{spec.name}").critical("crashed", exc_info=True, extra=FILE_ONLY)
        what = str(exc).splitlines()[0][:200] if str(exc) else ""
        print(f"smartroom: worker {spec.name} crashed: {type(exc).__name__}: {what} (traceback in {log_file})",
              file=sys.stderr, flush=True)
        return 1


def _bad_input(exc, spec, run) -> int:
    """Bad input or a stall: its one-line reason in ``<out>/logs/<name>.error`` for the
    launcher to report, or on stderr for a worker started by hand; the exit code."""
    from app.errors import InputError, Stalled
    from app.launcher import ERROR_DIR, LAUNCHED_ENV
    from workers.base import EXIT_INPUT, EXIT_STALLED

    code = EXIT_STALLED if isinstance(exc, Stalled) else EXIT_INPUT
    written = False
    if run.out:
        d = Path(run.out) / ERROR_DIR
        for attempt in range(2):
            try:
                d.mkdir(parents=True, exist_ok=True)
                (d / f"{spec.name}.error").write_text(f"{exc}\n", encoding="utf-8")
                written = True
                break
            except OSError:   # the disk is full: free the launcher's reserve once, else say it here
                (Path(run.out) / ".reserve").unlink(missing_ok=True)
    if os.environ.get(LAUNCHED_ENV):  # the launcher reports it, once
        if not written:
            print(f"smartroom: error: {exc}", file=sys.stderr)
        return code
    if code == EXIT_STALLED:
        print(f"smartroom: {spec.name}: {exc}", file=sys.stderr)
        return code
    raise InputError(str(exc)) from None   # the CLI's one line


def _exit(code: int) -> int:
    """End the worker process now: its files are complete, its state saved and its zenoh
    session closed by then (Worker.run), so the interpreter's teardown (a second or more
    for numba's and zenoh's modules on a loaded machine) only delays the launcher, which
    waits for every worker to be gone before a run ends."""
    import logging
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
