"""Viewer: the room, its cameras and the pipeline's results live in a browser (meshcat).

Draws the room box and floor, each camera's frustum and name, the voxels in their own
colours (thinned for display when there are many), one ellipsoid, id label and trail
per track, one skeleton per pose (inactive limbs grey), and the pipeline's real-time
factor at the top of the view. It is a sink that never slows the pipeline: its
inboxes keep only the newest message of each kind, each kind is drawn at most
``max_rate`` times a second, and nothing is redrawn that did not change.

The page is served by meshcat's own server class running inside this process
(:mod:`app.viewer.server`), on ``bind`` (``127.0.0.1`` unless the layout says, e.g.,
``0.0.0.0``) and ``port`` (0: the first free port from 7000). The URL to open is
printed on stderr when the viewer starts, and the monitor's table keeps it on screen.
``--headless`` runs do not start it. With ``linger`` (``smartroom run --linger``) the
page, once the stream has ended and this viewer is gone, reloads into the replay of the
run that ``smartroom run`` then serves at the same address until Ctrl-C.
"""
from __future__ import annotations

import sys
import time

from app.errors import InputError
from app.messages import Poses, Stats, Tracks, Voxels
from app.monitor import REAL_TIME, PipelineView
from app.viewer.scene import VOXELS, Scene
from app.viewer.server import MeshcatServer, ServerError
from workers.base import Worker

KINDS = ((Voxels, "voxels"), (Tracks, "tracks"), (Poses, "poses"))
STATUS_PERIOD_S = 1.0
OK_COLOUR = (0.55, 1.0, 0.55)
BEHIND_COLOUR = (1.0, 0.6, 0.25)


def reload_when_back() -> dict:
    """A page control whose creation makes the page wait, once this server has gone, for
    the page to be served again (``smartroom run --linger`` serves the run's replay at the
    same address) and reload it; the button reloads at once."""
    from app.viewer import three
    js = ("(() => { const retry = () => fetch(location.href, {cache: 'no-store'})"
          ".then(() => location.reload()).catch(() => setTimeout(retry, 500)); "
          "viewer.connection.onclose = () => setTimeout(retry, 500); return () => location.reload(); })()")
    return three.set_control("replay the run", js)


class Viewer(Worker):
    KIND = "viewer"
    CONSUMES = ("voxels", "tracks", "poses", "stats")
    ACCEPTS = (Voxels, Tracks, Poses)
    DISPLAY = True
    DEFAULTS = {
        "bind": "127.0.0.1",          # address the page listens on (0.0.0.0: every interface)
        "port": 0,                    # 0: the first free port from 7000 (meshcat's default)
        "max_rate": 15.0,             # most redraws per second of each kind (voxels, tracks, poses)
        "max_points": 30000,          # voxels drawn at most per frame (surface first, then thinned)
        "trail": 25,                  # past positions drawn behind each track
        "ellipsoid": [0.3, 0.3, 0.9],  # semi-axes (m) of a person around the track's centroid
        "frustum_depth": 0.4,         # length (m) of the drawn camera frustums
        "linger": False,              # smartroom run --linger: the page reloads into the run's replay at the end
    }
    RANGES = {"port": (0, 65535), "max_rate": (0.1, 120.0), "max_points": (0, 10_000_000), "trail": (0, 10000),
              "frustum_depth": (0.0, 10.0)}

    def setup(self) -> None:
        p = self.params
        if p["max_rate"] <= 0:
            raise InputError(f"viewer {self.name}: max_rate must be positive, got {p['max_rate']}")
        if len(p["ellipsoid"]) != 3:
            raise InputError(f"viewer {self.name}: ellipsoid takes three semi-axes, got {p['ellipsoid']}")
        calib = self._calibration()
        self.scene = Scene(calib.room_min if calib else None, calib.room_max if calib else None,
                           calib.cameras if calib else (), frustum_depth=p["frustum_depth"],
                           ellipsoid=p["ellipsoid"], trail=p["trail"], max_points=p["max_points"])
        try:
            self.server = MeshcatServer(p["bind"], p["port"], latest_only=[VOXELS]).start()
        except ServerError as exc:
            raise InputError(f"viewer {self.name}: {exc}") from None
        self.pipeline = PipelineView(self.layout.run.fps)
        self.period = 1.0 / p["max_rate"]
        self.pending: dict[str, object] = {}
        self.due = {kind: 0.0 for _, kind in KINDS}
        self.shown_frame = -1
        self.failed = False
        self._next_status = 0.0
        self._shown_status = None
        self._send(self.scene.setup())
        print(f"{self.name}: open {self.server.url}", file=sys.stderr, flush=True)
        self.log.info("serving the view at %s", self.server.url)

    def _calibration(self):
        calib = self.run_calibration()
        if calib is None:
            self.log.info("no calibration: the room is drawn from the first voxel grid")
        return calib

    # -- messages -------------------------------------------------------------------------
    def handle(self, key: str, msg) -> None:
        for cls, kind in KINDS:
            if isinstance(msg, cls):
                self.pending[kind] = msg   # the newest of each kind wins
                break
        self._draw()

    def on_stats(self, msg: Stats) -> None:   # zenoh's thread: PipelineView locks
        if msg.worker != self.name:
            self.pipeline.update(msg)

    def tick(self) -> None:
        self._draw()
        if time.monotonic() >= self._next_status:
            self._status()

    def flush(self) -> None:
        self._draw(force=True)
        self._status(ended=True)
        if self.params["linger"]:
            self._send([reload_when_back()])

    def close(self) -> None:
        server = getattr(self, "server", None)
        if server is not None:
            server.close()

    # -- drawing --------------------------------------------------------------------------
    def _draw(self, force: bool = False) -> None:
        now = time.monotonic()
        for _, kind in KINDS:
            msg = self.pending.get(kind)
            if msg is None or (now < self.due[kind] and not force):
                continue
            del self.pending[kind]
            self.due[kind] = max(self.due[kind] + self.period, now)
            self._send(getattr(self, f"_{kind}")(msg))
            self.shown_frame = max(self.shown_frame, msg.frame)
            self.ledger.emitted(msg.frame, msg.stamp)

    def _voxels(self, msg: Voxels) -> list[dict]:
        cmds = self.scene.room_from_grid(msg.origin, msg.dims, msg.voxel_size)
        if msg.indices is None or len(msg.indices) == 0:
            return cmds + self.scene.voxels([], None, msg.voxel_size)
        return cmds + self.scene.voxels(msg.centres(), msg.colours, msg.voxel_size, msg.surface)

    def _tracks(self, msg: Tracks) -> list[dict]:
        return self.scene.tracks(msg.ids, msg.positions)

    def _poses(self, msg: Poses) -> list[dict]:
        return self.scene.poses(msg.tracks, msg.joints, msg.active)

    def _status(self, ended: bool = False) -> None:
        self._next_status = time.monotonic() + STATUS_PERIOD_S
        rows = self.pipeline.rows()
        rtf = self.pipeline.rtf(rows)
        limiting = self.pipeline.limiting(rows)
        parts = []
        if self.shown_frame >= 0:
            parts.append(f"frame {self.shown_frame}")
        if rtf is None:
            parts.append("RTF - (waiting for the stages)" if limiting is None else f"{limiting.fps_out:.1f} fps")
        else:
            parts += [f"RTF {rtf:.2f}", f"{limiting.fps_out:.1f} fps"]
        late = self.pipeline.late_views()
        if late:   # live views the reconstruction gave up on, per camera
            parts.append("late " + " ".join(f"{c}:{n}" for c, n in sorted(late.items())))
        if ended:
            parts.append("stream ended")
        colour = (1.0, 1.0, 1.0) if rtf is None else OK_COLOUR if rtf >= REAL_TIME else BEHIND_COLOUR
        text = " | ".join(parts)
        if (text, colour) != self._shown_status:   # nothing changed: nothing to send
            self._shown_status = (text, colour)
            self._send(self.scene.status(text, colour))

    def _send(self, commands: list[dict]) -> None:
        if self.failed:
            return
        try:
            for cmd in commands:
                self.server.send(cmd)
        except ServerError as exc:   # the view is lost, the pipeline goes on
            self.failed = True
            self.log.error("%s; the view stops updating", exc)

    def extra_figures(self) -> dict:
        server = getattr(self, "server", None)
        if server is None:
            return {}
        return {"url": server.url, "clients": server.clients, "voxels_shown": self.scene.voxels_shown}
