"""A headless Chromium page that stays open while a test goes on, driven over the
DevTools protocol on a pipe (``--remote-debugging-pipe``: no port, nothing to install):
navigate, evaluate JavaScript in the page and read the result back, take screenshots.

The viewer tests read the meshcat scene's state this way (:func:`scene_state`) at the
moments they choose, from a page opened before the run and left to follow it.
"""
from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import subprocess
import threading
import time

__all__ = ["chromium", "Page", "BrowserError", "scene_state"]


class BrowserError(RuntimeError):
    pass


def chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def _above(fd: int, lowest: int) -> int:
    import fcntl
    new = fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, lowest)
    os.close(fd)
    return new


class Page:
    """One page of a headless Chromium of its own (software WebGL, as the screenshot
    tests); closed with :meth:`close` (its helper processes too)."""

    def __init__(self, binary: str, profile, width: int = 640, height: int = 480):
        to_chrome_r, to_chrome_w = os.pipe()
        from_chrome_r, from_chrome_w = os.pipe()
        # the child's ends moved above 3 and 4, so that setting fds 3 and 4 cannot close them
        to_chrome_r, from_chrome_w = (_above(fd, 10) for fd in (to_chrome_r, from_chrome_w))
        args = ["--headless", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader", "--enable-unsafe-swiftshader",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--disable-extensions", "--no-first-run", "--hide-scrollbars", "--remote-debugging-pipe",
                f"--user-data-dir={profile}", f"--window-size={width},{height}", "about:blank"]
        # Chromium reads the protocol on fd 3 and writes on fd 4
        shell = f'exec "$0" "$@" 3<&{to_chrome_r} 4>&{from_chrome_w} {to_chrome_r}<&- {from_chrome_w}>&-'
        self.proc = subprocess.Popen(["bash", "-c", shell, binary, *args], pass_fds=(to_chrome_r, from_chrome_w),
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._out = os.fdopen(to_chrome_w, "wb", buffering=0)
        self._in = os.fdopen(from_chrome_r, "rb", buffering=0)
        self._next = 0
        self._replies: dict[int, dict] = {}
        self._cond = threading.Condition()
        self._closed = False
        threading.Thread(target=self._read, daemon=True).start()
        targets = self.call("Target.getTargets")["targetInfos"]
        page = next(t for t in targets if t["type"] == "page")
        self.session = self.call("Target.attachToTarget", targetId=page["targetId"], flatten=True)["sessionId"]
        self.call("Page.enable", session=True)
        self.call("Runtime.enable", session=True)

    def _read(self) -> None:
        buf = b""
        while True:
            try:
                chunk = self._in.read(1 << 16)
            except OSError:
                chunk = b""
            if not chunk:
                break
            buf += chunk
            *messages, buf = buf.split(b"\0")
            for raw in messages:
                msg = json.loads(raw)
                if "id" in msg:
                    with self._cond:
                        self._replies[msg["id"]] = msg
                        self._cond.notify_all()
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def call(self, method: str, session: bool = False, timeout: float = 60.0, **params) -> dict:
        """One protocol command; its result (raises :class:`BrowserError` on an error reply)."""
        with self._cond:
            self._next += 1
            n = self._next
        msg = {"id": n, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        self._out.write(json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        with self._cond:
            while n not in self._replies:
                left = deadline - time.monotonic()
                if left <= 0 or self._closed:
                    raise BrowserError(f"no answer to {method} ({'closed' if self._closed else 'timeout'})")
                self._cond.wait(left)
            reply = self._replies.pop(n)
        if "error" in reply:
            raise BrowserError(f"{method}: {reply['error']}")
        return reply.get("result", {})

    def goto(self, url: str) -> None:
        self.call("Page.navigate", session=True, url=url)

    def evaluate(self, expression: str, timeout: float = 30.0):
        """The value of a JavaScript expression in the page (JSON-able; None on a
        page error, e.g. while it reloads)."""
        r = self.call("Runtime.evaluate", session=True, timeout=timeout, expression=expression, returnByValue=True,
                      awaitPromise=True)
        if "exceptionDetails" in r:
            return None
        return r.get("result", {}).get("value")

    def screenshot(self, path) -> None:
        data = self.call("Page.captureScreenshot", session=True, format="png")["data"]
        with open(path, "wb") as fh:
            fh.write(base64.b64decode(data))

    def close(self) -> None:
        try:
            self._out.close()
        except OSError:
            pass
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)   # Chromium's helpers (zygote, GPU, renderer) too
        except ProcessLookupError:
            pass
        self.proc.wait()


def scene_state(vertices: bool = True) -> str:
    """JavaScript giving the viewer's page as data: whether it is connected, the status
    line's facts, the frame on show (its userData, and per child its name, userData,
    position and, with ``vertices``, its vertices), and whether the replay of a finished
    run is loaded (and how many frames it has)."""
    return SCENE_STATE.replace("WITH_VERTICES", "true" if vertices else "false")


SCENE_STATE = """(() => {
    if (typeof viewer === "undefined") { return null; }
    const node = (path) => {
        let n = viewer.scene_tree;
        for (const p of path) { n = n.children[p]; if (n === undefined) { return null; } }
        return n;
    };
    const replay = node(["meshcat", "smartroom", "replay"]);
    const out = {url: location.href, connected: !!viewer.connection && viewer.connection.readyState === 1,
                 room: node(["meshcat", "smartroom", "room", "box", "<object>"]) !== null,
                 replay: replay !== null, replay_frames: replay ? Object.keys(replay.children).length : 0,
                 status: null, frame: null, children: {}};
    const status = node(["Cameras", "default", "rotated", "<object>", "smartroom_status", "<object>"]);
    if (status) { out.status = status.object.userData; }
    const live = node(["meshcat", "smartroom", "live", "<object>"]);
    if (live && live.object.userData && live.object.userData.frame !== undefined) {
        out.frame = live.object.userData;
        for (const c of live.object.children) {
            const e = {userData: c.userData, position: c.position.toArray()};
            if (WITH_VERTICES && c.geometry && c.geometry.attributes.position) {
                e.vertices = Array.from(c.geometry.attributes.position.array);
            }
            out.children[c.name] = e;
        }
    }
    return out;
})()"""


def watch_live_run(layout: str, recording, out, tmp, shown, extra=(), timeout: float = 120.0):
    """Run ``layout`` paced over ``recording`` with its viewer on a free port, read the page
    in headless Chromium until a frame on show satisfies ``shown(state)`` (the
    :func:`scene_state` data, without vertices) or ``timeout``; ``(run's exit code, that
    state or None)``. ``extra``: more ``smartroom run`` arguments. Skips without Chromium."""
    import re
    import subprocess
    import sys
    import time

    import pytest

    from app.bus import free_port
    from tests.conftest import ROOT

    binary = chromium()
    if binary is None:
        pytest.skip("needs headless Chromium (Debian package: chromium)")
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--layout", layout, "--recording", str(recording),
                             "--out", str(out), "--set", f"viewer.port={port}", *map(str, extra)],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    page = Page(binary, tmp / "profile")
    seen = None
    try:
        url = None
        for line in proc.stderr:
            m = re.search(r"viewer: open (http://\S+)", line)
            if m:
                url = m.group(1)
                break
        assert url == f"http://127.0.0.1:{port}/static/"
        page.goto(url)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and seen is None:
            state = page.evaluate(scene_state(False), timeout=30)
            if state and state.get("frame") and shown(state):
                seen = state
            time.sleep(0.3)
        proc.communicate(timeout=300)
    finally:
        page.close()
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, seen
