"""meshcat's web server inside the viewer process, bound to a chosen address.

``meshcat.Visualizer()`` starts ``meshcat.servers.zmqserver`` as a separate process
that serves the page on every interface (tornado's ``listen`` without an address)
and outlives a killed parent. Here the same server class (meshcat's
``ZMQWebSocketBridge``: the page, three.js and the websocket that streams the scene)
runs on a daemon thread of the viewer itself:

- the page listens only on ``bind`` (``127.0.0.1`` by default; ``0.0.0.0`` for every
  interface), on ``port`` or, with port 0, on the first free port from 7000 as meshcat
  does;
- commands reach it over an in-process zmq socket (``inproc://``), so no command port
  is open at all;
- it ends with the process, whatever ends the process: nothing to orphan;
- a browser that cannot keep up (a slow link) gets only the newest version of the
  big, self-replacing objects (``latest_only`` paths: the frame on show) instead of a
  queue that grows in this process's memory;
- the page (meshcat's, served from here with :data:`FOLLOW_SCRIPT` added) follows its
  server: when the websocket closes (a viewer that crashed and is being restarted, the
  end of a run that ``--linger`` replays at the same address) it waits until the page is
  served again and reloads, so a page opened once shows the run to its end.

Commands are meshcat's: ``{"type": "set_object" | "set_transform" | "delete" |
"set_property", "path": "/meshcat/...", ...}`` dicts (see :mod:`app.viewer.three`),
sent msgpack-encoded exactly as ``meshcat.Visualizer`` sends them.
"""
from __future__ import annotations

import asyncio
import itertools
import logging
import os
import socket
import threading
import warnings

import tornado.web
import tornado.websocket
import umsgpack
import zmq

with warnings.catch_warnings():   # meshcat 0.3 imports pyzmq's deprecated zmq.eventloop.ioloop
    warnings.simplefilter("ignore", DeprecationWarning)
    from meshcat.servers.zmqserver import (DEFAULT_FILESERVER_PORT, VIEWER_HTML, VIEWER_ROOT,
                                           StaticFileHandlerNoCache, ZMQWebSocketBridge)

__all__ = ["MeshcatServer", "ServerError", "page_url", "page_html", "LatestWins", "FOLLOW_SCRIPT"]

log = logging.getLogger("smartroom.viewer.server")

_COUNTER = itertools.count()
PORT_ATTEMPTS = 100
CLOSE_GRACE_S = 1.0   # at the end, how long the browsers' websockets may take to close


class ServerError(RuntimeError):
    """The server could not start (address or port unavailable) or stopped answering."""


def page_url(bind: str, port: int) -> str:
    """The URL a user opens: the bound address, or this host's name when bound to all."""
    host = bind
    if bind in ("0.0.0.0", "", "::"):
        host = socket.gethostname()
    elif ":" in bind:
        host = f"[{bind}]"
    return f"http://{host}:{port}/static/"


#: Added to meshcat's page: once the websocket has closed, fetch the page until it is
#: served again, then reload (the restarted viewer, or the replay, sends its whole scene).
FOLLOW_SCRIPT = """<script>
(function () {
    const again = () => fetch(location.href, {cache: "no-store"})
        .then((r) => { if (r.ok) { location.reload(); } else { setTimeout(again, 500); } })
        .catch(() => setTimeout(again, 500));
    if (typeof viewer !== "undefined" && viewer.connection) {
        viewer.connection.onclose = () => setTimeout(again, 500);
    }
})();
</script>
"""


def page_html() -> str:
    """meshcat's page with :data:`FOLLOW_SCRIPT` after its own script."""
    with open(os.path.join(VIEWER_ROOT, VIEWER_HTML), encoding="utf-8") as fh:
        html = fh.read()
    return html.replace("</body>", FOLLOW_SCRIPT + "</body>", 1)


class _Page(tornado.web.RequestHandler):
    """The page itself (``/static/`` and ``/static/index.html``), never cached."""

    def initialize(self, html: str):
        self.html = html

    def get(self, *_):
        self.set_header("Cache-Control", "no-store")
        self.set_header("Content-Type", "text/html; charset=utf-8")
        self.write(self.html)


class LatestWins:
    """Commands on their way to one browser. Commands for a ``latest_only`` path are
    written one at a time: while one is still in flight (the socket has not taken it),
    newer ones for such paths wait, only the newest per path, and go when it lands.
    Other commands are written at once, in order."""

    def __init__(self, write, latest_only=()):
        self.write = write                  # callable(bytes) -> future (None: closed)
        self.latest_only = frozenset(latest_only)
        self.in_flight = None
        self.waiting: dict[str, bytes] = {}

    def push(self, path: str, data: bytes) -> None:
        if path not in self.latest_only:
            self.write(data)
        elif self.in_flight is not None and not self.in_flight.done():
            if not self.waiting:
                self.in_flight.add_done_callback(lambda _: self._drain())
            self.waiting[path] = data
        else:
            self.in_flight = self.write(data)

    def _drain(self) -> None:
        waiting, self.waiting = self.waiting, {}
        for path, data in waiting.items():
            self.push(path, data)


def _retrieved(future) -> None:
    if not future.cancelled():
        future.exception()   # a browser that went away: nothing to report


class _Client(tornado.websocket.WebSocketHandler):
    """One browser: the whole scene when it connects, then every command (meshcat's
    handler, without its prints on stdout/stderr and with :class:`LatestWins`)."""

    def initialize(self, bridge):
        self.bridge = bridge
        self.sender = LatestWins(self._write, bridge.latest_only)

    def open(self):
        self.bridge.websocket_pool.add(self)
        log.info("browser connected (%d open)", len(self.bridge.websocket_pool))
        self.bridge.send_scene(self)

    def on_message(self, message):
        pass   # meshcat's page only talks back for image captures, which the viewer does not use

    def on_close(self):
        self.bridge.websocket_pool.discard(self)
        log.info("browser disconnected (%d open)", len(self.bridge.websocket_pool))

    def _write(self, data: bytes):
        try:
            future = self.write_message(data, binary=True)
        except tornado.websocket.WebSocketClosedError:
            return None
        future.add_done_callback(_retrieved)
        return future


class _Bridge(ZMQWebSocketBridge):
    """meshcat's bridge with its page bound to one address, its command socket
    in-process and its browsers fed through :class:`_Client`."""

    def __init__(self, bind: str, port: int, zmq_url: str, latest_only=()):
        self._bind = bind
        self.latest_only = frozenset(latest_only)
        self.after_scene: dict[tuple, bytes] = {}
        self.http_server = None
        try:
            super().__init__(zmq_url=zmq_url, host=bind, port=port)
        except BaseException:
            stream = getattr(self, "zmq_stream", None)
            if stream is not None:   # the command socket was bound before the page failed to
                stream.close()
            raise

    def make_app(self):
        app = tornado.web.Application([   # meshcat's routes (the page with ours); requests are not logged
            (r"/static/((?:index\.html)?)", _Page, {"html": page_html()}),
            (r"/static/(.*)", StaticFileHandlerNoCache, {"path": VIEWER_ROOT, "default_filename": VIEWER_HTML}),
            (r"/", _Client, {"bridge": self}),
        ], log_function=lambda handler: None)
        bind = self._bind
        plain_listen = app.listen

        def listen(port, address=None, **kw):   # meshcat calls listen(port): every interface
            self.http_server = plain_listen(port, address=bind, **kw)
            return self.http_server

        app.listen = listen
        return app

    def handle_zmq(self, frames):
        """meshcat's commands, except two kept here and sent to a browser after the whole
        scene (meshcat's server would send an animation before the objects it animates,
        and neither forwards nor keeps ``set_control``, a control in the page's panel):
        the newest animation, then the controls in the order they came, one per name."""
        kind = frames[0]
        if kind in (b"set_animation", b"set_control") and len(frames) == 3:
            name = umsgpack.unpackb(frames[2]).get("name", "") if kind == b"set_control" else ""
            self.after_scene[(kind, name)] = frames[2]
            if kind == b"set_animation":   # the animation first
                self.after_scene = dict(sorted(self.after_scene.items(), key=lambda kv: kv[0][0] != kind))
            self.forward_to_websockets(frames)
            self.zmq_socket.send(b"ok")
            return
        super().handle_zmq(frames)

    def send_scene(self, websocket):
        super().send_scene(websocket)
        for data in self.after_scene.values():
            websocket.write_message(data, binary=True)

    def forward_to_websockets(self, frames):
        _, path, data = frames
        path = path.decode("utf-8", "replace")
        for client in list(self.websocket_pool):
            client.sender.push(path, data)


class MeshcatServer:
    """meshcat's page and websocket on a thread; :meth:`send` pushes scene commands."""

    def __init__(self, bind: str = "127.0.0.1", port: int = 0, timeout_s: float = 5.0, latest_only=()):
        self.bind = bind
        self.latest_only = tuple(latest_only)
        self.requested_port = int(port)
        self.timeout_ms = int(timeout_s * 1000)
        self.port: int | None = None
        self._zmq_url = f"inproc://smartroom-viewer-{next(_COUNTER)}"
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._loop = None
        self._bridge = None
        self._thread = threading.Thread(target=self._serve, name="meshcat-server", daemon=True)
        self._socket = None

    # -- the server thread ----------------------------------------------------------
    def _listen(self) -> _Bridge:
        if self.requested_port:
            return _Bridge(self.bind, self.requested_port, self._zmq_url, self.latest_only)
        last = None
        for port in range(DEFAULT_FILESERVER_PORT, DEFAULT_FILESERVER_PORT + PORT_ATTEMPTS):
            # each try its own command socket address: the one of a failed try (its port
            # taken, e.g. by another viewer) is not free again at once ("Address already in use")
            self._zmq_url = f"inproc://smartroom-viewer-{next(_COUNTER)}"
            try:
                return _Bridge(self.bind, port, self._zmq_url, self.latest_only)
            except OSError as exc:
                last = exc
        raise OSError(f"no free port in {DEFAULT_FILESERVER_PORT}..{DEFAULT_FILESERVER_PORT + PORT_ATTEMPTS - 1}"
                      f" ({last})")

    def _serve(self) -> None:
        try:
            self._loop = asyncio.new_event_loop()
            asyncio.set_event_loop(self._loop)
            self._bridge = self._listen()
            self.port = self._bridge.fileserver_port
        except BaseException as exc:  # reported to start()
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        try:
            self._loop.run_forever()
        finally:
            try:
                self._bridge.http_server.stop()   # the listening socket: the port is free again
                for client in list(self._bridge.websocket_pool):
                    client.close()
                self._bridge.zmq_stream.close()
            finally:
                self._loop.close()

    # -- the viewer's side ------------------------------------------------------------
    def start(self) -> "MeshcatServer":
        self._thread.start()
        if not self._ready.wait(30.0):
            raise ServerError("the meshcat server did not start within 30 s")
        if self._error is not None:
            where = f"{self.bind}:{self.requested_port}" if self.requested_port else self.bind
            raise ServerError(f"cannot serve the viewer on {where}: {self._error}")
        self._connect()
        return self

    def _connect(self) -> None:
        if self._socket is not None:
            self._socket.close(linger=0)
        self._socket = ZMQWebSocketBridge.context.socket(zmq.REQ)
        self._socket.setsockopt(zmq.RCVTIMEO, self.timeout_ms)
        self._socket.setsockopt(zmq.SNDTIMEO, self.timeout_ms)
        self._socket.connect(self._zmq_url)

    @property
    def url(self) -> str:
        return page_url(self.bind, self.port)

    @property
    def clients(self) -> int:
        """Browsers connected right now."""
        return len(self._bridge.websocket_pool) if self._bridge is not None else 0

    def send(self, command: dict) -> None:
        """One meshcat command (raises :class:`ServerError` if the server does not answer)."""
        try:
            self._socket.send_multipart([command["type"].encode(), command.get("path", "").encode(),
                                         umsgpack.packb(command)])
            reply = self._socket.recv()
        except zmq.Again:
            self._connect()  # a REQ socket that missed its reply cannot be reused
            raise ServerError("the meshcat server did not answer") from None
        if reply != b"ok":
            raise ServerError(f"the meshcat server refused {command['type']} {command.get('path')}: {reply!r}")

    def close(self) -> None:
        """Stop serving (the page keeps showing the last scene) and end the thread. The
        browsers get what was sent before, then the websocket's close (their pages then
        wait for the page to be served again)."""
        if self._socket is not None:
            self._socket.close(linger=0)
            self._socket = None
        if self._loop is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._say_goodbye)
            self._thread.join(5.0)

    def _say_goodbye(self) -> None:
        """On the server's loop: a close frame to every browser, queued after the commands
        still on their way, and the loop's end once they have left (or after a second)."""
        clients = list(self._bridge.websocket_pool) if self._bridge is not None else []
        for client in clients:
            client.close()
        deadline = self._loop.time() + CLOSE_GRACE_S

        def stop_when_gone():
            if self._bridge.websocket_pool and self._loop.time() < deadline:
                self._loop.call_later(0.02, stop_when_gone)
            else:
                self._loop.stop()
        stop_when_gone()
