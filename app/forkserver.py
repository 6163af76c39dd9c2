"""Workers forked from a warm parent instead of started afresh: half the start-up.

A fresh worker process imports numpy, OpenCV, zenoh and numba, builds numba's CPU target
and loads its cached kernels before its first frame: 0.6-1.0 s of CPU each, about 4 s of
wall for the eight workers of a run on a 2-core machine, paid again at every restart. The
launcher instead starts one *fork server* (``python -m app.forkserver``) that does all that
once, then forks each worker from it: a small offline run's start-up to the first frame
went from 4.0-4.3 s to 1.8-2.2 s (docs/benchmarks.md, "The test run").

A forked worker is what ``smartroom worker NAME --layout FILE`` would be, as the launcher
starts it: :func:`app.cli.main` with those arguments, in a session of its own, with the
launcher's environment for it and working directory, ``/proc/PID/cmdline`` saying
``... app.cli worker NAME ...``. It is forked twice, so that it is re-parented to the
launcher (a child subreaper, ``PR_SET_CHILD_SUBREAPER``): the launcher waits for it,
signals it and restarts it as a child of its own, and the worker's watch for its launcher
(``os.getppid()``) is unchanged. ``SMARTROOM_SPAWN=exec`` starts fresh processes instead,
as does any platform without ``prctl`` (Linux only) or a server that fails.

After loading, the server freezes what it has loaded out of the garbage collector
(``gc.freeze``): a worker's collections no longer write to those objects' pages, so they
stay shared with the server instead of being copied into each worker (about 6 MB less
private memory summed over a run's eight workers 9 s in, more the longer it runs).

The server opens no zenoh session and starts no thread of its own (a session's runtime
threads would not survive a fork), and calls nothing of OpenCV's or numba's that starts a
thread pool; its only other threads are the idle pools of the three OpenBLAS libraries
its imports load (numpy's, scipy's and the one OpenCV's wheel bundles), which OpenBLAS
stops and starts again across ``fork`` (its ``pthread_atfork`` handlers). What it imports is
:data:`PRELOADED`'s kinds; the others (the viewer, the streamer, the keypoint cue, plugins)
import their modules after the fork, as before.

Protocol, one JSON object a line: the launcher writes ``{"argv": [...], "env": {...},
"cwd": "..."}`` on the server's standard input, the server answers ``{"pid": N}`` on its
reply pipe once the worker is the launcher's child. The server ends when its standard
input closes.
"""
from __future__ import annotations

import ctypes
import gc
import json
import os
import signal
import subprocess
import sys
import threading
import time

__all__ = ["SPAWN_ENV", "PRELOADED", "ForkServer", "ForkedProcess", "preload", "load_cached_kernels"]

#: ``SMARTROOM_SPAWN=exec``: every worker starts as a fresh process (no fork server)
SPAWN_ENV = "SMARTROOM_SPAWN"
#: the kinds of every run, imported by the server
PRELOADED = ("grabber", "segmentation", "reconstruction", "cca", "tracking", "pose", "recorder", "monitor")
#: bytes of the server's command line a worker's own is written over (``/proc/PID/cmdline``)
TITLE_BYTES = 1024
START_TIMEOUT_S = 30.0      # the server's imports, on a loaded machine
REPARENT_TIMEOUT_S = 5.0    # a forked worker waits this long to become the launcher's child
_PR_SET_CHILD_SUBREAPER = 36


def preload() -> None:
    """What every worker imports first: numpy, OpenCV, zenoh, numba, the worker kinds and
    their cached kernels (loading them builds numba's CPU target, with scipy's BLAS it
    looks for)."""
    import importlib

    for module in ("numpy", "cv2", "yaml", "zenoh", "app.cli", *(f"workers.{kind}" for kind in PRELOADED)):
        importlib.import_module(module)
    load_cached_kernels()


def load_cached_kernels() -> int:
    """Load every kernel of the imported modules that numba's cache holds for this machine
    and these sources; the number loaded. Nothing is compiled here: a kernel not in the
    cache is compiled by the worker that calls it, as before. These are numba's own steps
    for a cache hit (``Dispatcher.compile``), taken ahead of the first call; where numba's
    internals differ, nothing is loaded and the workers load their kernels themselves."""
    from numba.core.registry import CPUDispatcher

    loaded = 0
    for name, module in list(sys.modules.items()):
        if module is None or not name.startswith(("app.", "workers.")):
            continue
        for kernel in list(vars(module).values()):
            if not isinstance(kernel, CPUDispatcher) or kernel.__module__ != name:
                continue
            try:
                for key in kernel._cache._cache_file._load_index():   # (signature, machine, ...)
                    sig = key[0]
                    if tuple(sig) in kernel.overloads:
                        continue
                    cres = kernel._cache.load_overload(sig, kernel.targetctx)   # None: not for this machine
                    if cres is None or cres.objectmode:
                        continue
                    kernel.targetctx.insert_user_function(cres.entry_point, cres.fndesc, [cres.library])
                    kernel.add_overload(cres)
                    loaded += 1
            except Exception:  # noqa: BLE001 - numba's internals changed: the worker loads it itself
                continue
    return loaded


def _set_cmdline(args: list[str]) -> None:
    """``/proc/self/cmdline`` reads ``args`` (written over the command line's own bytes,
    which the server made :data:`TITLE_BYTES` long): ``ps`` and tools that look for
    ``worker NAME`` see the worker."""
    with open("/proc/self/stat", "rb") as fh:
        fields = fh.read().rsplit(b")", 1)[1].split()
    start, end = int(fields[45]), int(fields[46])   # arg_start, arg_end (fields 48, 49 of proc(5))
    title = b"\0".join(a.encode() for a in args)[: end - start - 1]
    ctypes.memmove(start, title.ljust(end - start, b"\0"), end - start)


def _worker(request: dict, reply_fd: int) -> None:
    """The twice-forked process: become the worker ``request`` asks for; never returns."""
    rc = 1
    try:
        os.close(reply_fd)
        os.setsid()
        signal.signal(signal.SIGINT, signal.default_int_handler)   # as Python starts (the server ignores it)
        devnull = os.open(os.devnull, os.O_RDONLY)
        os.dup2(devnull, 0)
        os.close(devnull)
        os.environ.clear()
        os.environ.update(request["env"])
        os.chdir(request["cwd"])
        argv = list(request["argv"])
        sys.argv = [sys.modules["app.cli"].__file__, *argv]   # as ``python -m app.cli`` has it
        try:
            _set_cmdline([sys.executable, "-m", "app.cli", *argv])
        except (OSError, ValueError, IndexError):
            pass
        launcher = int(request["launcher"])
        deadline = time.monotonic() + REPARENT_TIMEOUT_S
        while os.getppid() != launcher:   # the middle process exits: the launcher adopts this one
            if time.monotonic() > deadline:
                print(f"smartroom: a forked worker was not adopted by its launcher {launcher}", file=sys.stderr)
                os._exit(1)
            time.sleep(0.001)
        from app.cli import main

        rc = main(argv) or 0
    except SystemExit as exc:
        rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException:  # noqa: BLE001 - as an uncaught exception ends a process
        import traceback

        traceback.print_exc()
        rc = 1
    try:   # what the interpreter does on its way out: other threads, then atexit
        for t in threading.enumerate():
            if t is not threading.main_thread() and not t.daemon:
                t.join()
        import atexit

        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(rc)


def _fork_worker(request: dict, reply_fd: int) -> int:
    """Fork twice; the worker's pid, once it is the launcher's child."""
    r, w = os.pipe()
    middle = os.fork()
    if middle == 0:
        try:
            os.close(r)
            pid = os.fork()
            if pid == 0:
                os.close(w)
                _worker(request, reply_fd)
            os.write(w, f"{pid}\n".encode())
        finally:
            os._exit(0)
    os.close(w)
    with os.fdopen(r, "rb") as fh:
        line = fh.readline()
    os.waitpid(middle, 0)   # gone: the worker is re-parented to the launcher, the nearest subreaper
    return int(line)


def serve(reply_fd: int) -> None:
    """Fork a worker per request line on standard input until it closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # Ctrl-C is the launcher's to handle
    reply = os.fdopen(reply_fd, "w", buffering=1)
    preload()
    gc.collect()
    gc.freeze()   # what was loaded stays shared: a worker's collections no longer write to its pages
    reply.write(json.dumps({"ready": os.getpid()}) + "\n")
    for line in sys.stdin:
        try:
            request = json.loads(line)
            answer = {"pid": _fork_worker(request, reply_fd)}
        except (ValueError, KeyError, TypeError, OSError) as exc:
            answer = {"error": f"{type(exc).__name__}: {exc}"}
        reply.write(json.dumps(answer) + "\n")


class ForkedProcess:
    """A worker forked by the server, now the launcher's child: the part of
    :class:`subprocess.Popen` the launcher uses."""

    def __init__(self, pid: int):
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                pid, status = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:   # reaped elsewhere: gone, its status unknown
                self.returncode = -signal.SIGKILL
                return self.returncode
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            if deadline is not None and time.monotonic() >= deadline:
                raise subprocess.TimeoutExpired(f"worker {self.pid}", timeout)
            time.sleep(0.01)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            os.kill(self.pid, sig)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


def _subreaper(on: bool) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_SET_CHILD_SUBREAPER, int(on), 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER)")


class ForkServer:
    """The launcher's end: starts the server (its imports overlap the launcher's own
    start-up) and forks workers through it. ``OSError`` where it cannot be used."""

    def __init__(self):
        if not sys.platform.startswith("linux"):
            raise OSError("the fork server needs Linux")
        _subreaper(True)
        read_fd, write_fd = os.pipe()
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "app.forkserver", str(write_fd), " " * TITLE_BYTES],
                stdin=subprocess.PIPE, pass_fds=(write_fd,), start_new_session=True,
                env=dict(os.environ, PYTHONUNBUFFERED="1"))
        finally:
            os.close(write_fd)
        self._replies, self._buf = read_fd, b""
        self._lock = threading.Lock()
        self._ready = False

    def _answer(self, timeout: float) -> dict:
        import select

        deadline = time.monotonic() + timeout
        while b"\n" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._replies], [], [], left)[0]:
                raise OSError(f"the fork server did not answer within {timeout:.0f} s")
            chunk = os.read(self._replies, 4096)
            if not chunk:
                raise OSError(f"the fork server is gone (exit {self.proc.poll()})")
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        return json.loads(line)

    def start(self, argv: list[str], env: dict, cwd: str) -> ForkedProcess:
        with self._lock:
            if not self._ready:
                self._answer(START_TIMEOUT_S)
                self._ready = True
            request = {"argv": argv, "env": env, "cwd": cwd, "launcher": os.getpid()}
            try:
                self.proc.stdin.write((json.dumps(request) + "\n").encode())
                self.proc.stdin.flush()
            except (BrokenPipeError, ValueError) as exc:
                raise OSError(f"the fork server is gone ({exc})") from exc
            answer = self._answer(REPARENT_TIMEOUT_S + 5.0)
            if "pid" not in answer:
                raise OSError(answer.get("error", "no pid"))
            return ForkedProcess(int(answer["pid"]))

    def close(self) -> None:
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(5.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self._replies)
        try:
            _subreaper(False)
        except OSError:
            pass


if __name__ == "__main__":
    serve(int(sys.argv[1]))
