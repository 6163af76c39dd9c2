"""Viewer: the room, its cameras and the pipeline's results live in a browser (meshcat).

Draws the room box and floor, each camera's frustum and name, and the frame on show:
its voxels in their own colours (thinned for display when there are many), one
ellipsoid, id label and trail per track, one skeleton per pose (bones and joints; a
limb the model lost grey and thinner), and the pipeline's real-time factor at the top of
the view. With the keypoint cue in the layout (``deploy/layouts/keypoints.yaml``) it also
draws each track's keypoints triangulated from the cameras (yellow points over the
skeletons: where the detector put the joints, beside where the filter put them); with
``markers: true`` in marker mode (``deploy/layouts/markers.yaml``), the markers the
cameras' detections place in the room (magenta points: triangulated from every pair of
views and confirmed by a third, :func:`app.markers.likelihood.triangulated_markers`).
What is on show is one frame: a frame's voxels, tracks and poses are put
together (:class:`app.viewer.frames.FrameAssembly`) and drawn in one step once all of
them are in (a stage that is away is not waited for), so the skeletons never lag the
voxels they were fitted to. It is a sink that never slows the pipeline: its inboxes keep
only the newest messages, at most ``max_rate`` frames a second are drawn, and nothing
is redrawn that did not change.

The page is served by meshcat's own server class running inside this process
(:mod:`app.viewer.server`), on ``bind`` (``127.0.0.1`` unless the layout says, e.g.,
``0.0.0.0``) and ``port`` (0: the first free port from 7000; a restarted viewer takes
its earlier incarnation's port again). The URL to open is printed on stderr when the
viewer starts, and the monitor's table keeps it on screen. ``--headless`` runs do not
start it. The page follows its server: when the viewer is restarted after a crash, or
the stream has ended and ``smartroom run --linger`` serves the run's replay at the same
address, it reloads by itself.
"""
from __future__ import annotations

import sys
import time

import numpy as np

from app.errors import InputError
from app.messages import Keypoints, Markers, Poses, Stats, Tracks, Voxels
from app.monitor import REAL_TIME, PipelineView
from app.pose_shares import SharedKeypoints, SharedPoses
from app.viewer.frames import KINDS as PARTS, FrameAssembly
from app.viewer.scene import LIVE, Scene
from app.viewer.server import MeshcatServer, ServerError
from workers import producers_of
from workers.base import Worker

KINDS = ((Voxels, "voxels"), (Tracks, "tracks"), (Poses, "poses"))
KEEP_MARKER_FRAMES = 32   # frames whose markers wait for their voxels, tracks and poses
STATUS_PERIOD_S = 1.0
OK_COLOUR = (0.55, 1.0, 0.55)
BEHIND_COLOUR = (1.0, 0.6, 0.25)


class Viewer(Worker):
    KIND = "viewer"
    CONSUMES = ("voxels", "tracks", "poses", "keypoints", "stats")
    ACCEPTS = (Voxels, Tracks, Poses, Keypoints, Markers)
    DISPLAY = True
    INBOX_DEPTH = 4      # a few frames of each kind: a frame waits for its slowest part
    #: a display has no results to duplicate: what comes after a restart is drawn as it comes
    SKIPS_FINISHED = False
    DEFAULTS = {
        "bind": "127.0.0.1",          # address the page listens on (0.0.0.0: every interface)
        "port": 0,                    # 0: the first free port from 7000 (meshcat's default)
        "max_rate": 15.0,             # most frames drawn per second
        "max_points": 30000,          # voxels drawn at most per frame (surface first, then thinned)
        "trail": 25,                  # past positions drawn behind each track
        "ellipsoid": [0.3, 0.3, 0.9],  # semi-axes (m) of a person around the track's centroid
        "markers": False,             # draw the markers the cameras detect (marker mode), triangulated
        "frustum_depth": 0.4,         # length (m) of the drawn camera frustums
        "wait_s": 2.0,                # a kind (voxels, tracks, poses) silent this long is not waited for
        "linger": False,              # smartroom run --linger: the page goes on to the run's replay at the end
    }
    RANGES = {"port": (0, 65535), "max_rate": (0.1, 120.0), "max_points": (0, 10_000_000), "trail": (0, 10000),
              "frustum_depth": (0.0, 10.0), "wait_s": (0.0, 3600.0)}

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
        self.server = self._serve(p["bind"], p["port"] or getattr(self, "_earlier_port", 0))
        self.pipeline = PipelineView(self.layout.run.fps)
        self.period = 1.0 / p["max_rate"]
        kinds = [k for k in PARTS if producers_of(self.layout, k)]   # what the layout's stages make
        self.assembly = FrameAssembly(p["wait_s"], layout_kinds=kinds)
        # several pose workers share a frame's people: their poses are joined first
        self.shares = SharedPoses(producers_of(self.layout, "poses"), max_pending=8)
        self.keypoint_shares = SharedKeypoints(producers_of(self.layout, "keypoints"), max_pending=8)
        self.calibration = calib   # the keypoints are triangulated with it
        self.marker_views: dict[tuple[int, int], dict] = {}   # (epoch, frame) -> camera -> (Q, 2) markers
        self.marker_fundamentals = None
        self.due = 0.0
        self.shown_frame = -1
        self.failed = False
        self._next_status = 0.0
        self._shown_status = None
        self._send(self.scene.setup())
        print(f"{self.name}: open {self.server.url}", file=sys.stderr, flush=True)
        self.log.info("serving the view at %s", self.server.url)

    def _serve(self, bind: str, port: int) -> MeshcatServer:
        """The page's server on ``port`` (the earlier incarnation's, when restarted: the
        open pages come back to it), else on the first free port."""
        try:
            return MeshcatServer(bind, port, latest_only=[LIVE]).start()
        except ServerError as exc:
            if port == self.params["port"] or not port:
                raise InputError(f"viewer {self.name}: {exc}") from None
            self.log.warning("port %d of the earlier viewer is taken (%s): open pages must be opened again", port, exc)
        try:
            return MeshcatServer(bind, 0, latest_only=[LIVE]).start()
        except ServerError as exc:
            raise InputError(f"viewer {self.name}: {exc}") from None

    def extra_state(self) -> dict:
        server = getattr(self, "server", None)
        port = server.port if server is not None else getattr(self, "_earlier_port", None)   # (before set-up)
        return {"port": port} if port else {}

    def restore_state(self, state: dict) -> None:
        port = state.get("port")
        if isinstance(port, int) and 0 < port < 65536:
            self._earlier_port = port

    @classmethod
    def consumes(cls, spec) -> set[str]:
        """The results; the markers too with ``markers: true``."""
        return super().consumes(spec) | ({"markers"} if spec.params.get("markers") else set())

    def _calibration(self):
        calib = self.run_calibration()
        if calib is None:
            self.log.info("no calibration: the room is drawn from the first voxel grid")
        return calib

    # -- messages -------------------------------------------------------------------------
    def handle(self, key: str, msg) -> None:
        now = time.monotonic()
        if isinstance(msg, Poses):
            for joined in self.shares.add(msg):
                self.assembly.add("poses", joined, now)
        elif isinstance(msg, Keypoints):
            for joined in self.keypoint_shares.add(msg):
                self.assembly.add("keypoints", joined, now)
        elif isinstance(msg, Markers):
            if self.calibration is not None and msg.camera in self.calibration.names:
                views = self.marker_views.setdefault((msg.epoch, msg.frame), {})
                views[msg.camera] = msg.points
                for old in sorted(self.marker_views)[:-KEEP_MARKER_FRAMES]:
                    del self.marker_views[old]
            return   # drawn with their frame's voxels, tracks and poses
        else:
            self.assembly.add("voxels" if isinstance(msg, Voxels) else "tracks", msg, now)
        self._draw()

    def new_epoch(self, epoch: int) -> None:
        self.assembly.reset()

    def on_stats(self, msg: Stats) -> None:   # zenoh's thread: PipelineView locks
        if msg.worker != self.name:
            self.pipeline.update(msg)

    def tick(self) -> None:
        self._draw()
        if time.monotonic() >= self._next_status:
            self._status()

    def flush(self) -> None:
        now = time.monotonic()
        for joined in self.shares.flush():
            self.assembly.add("poses", joined, now)
        for joined in self.keypoint_shares.flush():
            self.assembly.add("keypoints", joined, now)
        self._draw(force=True)
        self._status(ended=True)

    def close(self) -> None:
        server = getattr(self, "server", None)
        if server is not None:
            server.close()

    # -- drawing --------------------------------------------------------------------------
    def _draw(self, force: bool = False) -> None:
        now = time.monotonic()
        if now < self.due and not force:
            return
        picked = self.assembly.take(now)
        if picked is None:
            return
        (epoch, frame), parts = picked
        self.due = max(self.due + self.period, now)
        vox, tracks, poses = parts.get("voxels"), parts.get("tracks"), parts.get("poses")
        cmds = []
        if vox is not None:
            cmds += self.scene.room_from_grid(vox.origin, vox.dims, vox.voxel_size)
        cmds += self.scene.frame(
            frame, epoch=epoch,
            voxels=None if vox is None else (vox.centres() if vox.indices is not None and len(vox.indices) else (),
                                              vox.colours, vox.voxel_size, vox.surface),
            tracks=None if tracks is None else (tracks.ids, tracks.positions),
            poses=None if poses is None else (poses.tracks, poses.joints, poses.active),
            keypoints=self._triangulated(parts.get("keypoints")), markers=self._markers(epoch, frame))
        self._send(cmds)
        if frame != self.shown_frame:
            self.shown_frame = frame
            first = min(parts.values(), key=lambda m: m.stamp or float("inf"))
            self.ledger.emitted(frame, first.stamp)

    def _markers(self, epoch: int, frame: int):
        """The frame's markers (K, 3) triangulated from the cameras that sent theirs; None
        unless asked (``markers``) or without calibration."""
        if not self.params.get("markers") or self.calibration is None:
            return None
        from app.markers.likelihood import triangulated_markers
        views = self.marker_views.get((epoch, frame), {})
        cams = self.calibration.cameras
        if self.marker_fundamentals is None:
            from app.markers.epipolar import fundamentals
            self.marker_fundamentals = fundamentals(cams)
        return triangulated_markers(cams, [views.get(c.name, np.zeros((0, 2))) for c in cams], self.marker_fundamentals)

    def _triangulated(self, msg: Keypoints | None):
        """``[(track, points (K, 3))]``: each track's keypoints triangulated from two or
        more cameras (:func:`app.keypoints.fusion.triangulate`); None without keypoints or
        calibration."""
        if msg is None or self.calibration is None:
            return None
        from app.keypoints.fusion import frame_keypoints, triangulate
        out = []
        for tid, person in sorted(frame_keypoints([msg], self.calibration).items()):
            points, found = triangulate(person)
            out.append((tid, points[found]))
        return out

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
            parts.append("stream ended" + (": the replay follows" if self.params["linger"] else ""))
        colour = (1.0, 1.0, 1.0) if rtf is None else OK_COLOUR if rtf >= REAL_TIME else BEHIND_COLOUR
        text = " | ".join(parts)
        if (text, colour) != self._shown_status:   # nothing changed: nothing to send
            self._shown_status = (text, colour)
            self._send(self.scene.status(text, colour, {"frame": self.shown_frame, "ended": ended}))

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
        return {"url": server.url, "clients": server.clients, "voxels_shown": self.scene.voxels_shown,
                "frame_shown": self.shown_frame}
