"""The simulated smart room as a frame source: images, true silhouettes, ground truth.

:class:`Simulator` ties a scene (:mod:`app.simulation.scenes`) to the room's cameras
and renderer (:mod:`app.simulation.render`): ``render(i)`` gives frame ``i`` of every
camera with the true person-id image and the ground-truth record of the contract's
``groundtruth.jsonl``; :func:`render_recording` writes a whole recording folder.

Ground-truth record (CONTRACT §1, optional fields added)::

    {"frame": i, "t": s, "people": [{"id", "centroid", "head", "joints": {15 names},
      "visible": {joint: false, ...},         # joints no camera sees
      "height": m, "sitting": bool, "activity": "walking",   # or standing, gesturing, sitting, crouching
      "colours": {"shirt", "trousers", "skin", "hair"}}]}

``centroid`` is the volume centroid of the body's primitives, ``head`` the head centre
(the ``head`` joint). People count while their centroid is inside the room (not in the
corridor, not after they left). A joint is *seen* by a camera when it projects inside
the image and the segment from the optical centre to it crosses no furniture and no
other person (the person's own body does not hide their joints: they lie inside it).
Floats are rounded to 4 decimals, so a seed gives byte-identical files.
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from app.errors import InputError
from app.messages import JOINTS
from app.simulation.body import FrameBodies, body_centroid, body_primitives, forward_kinematics
from app.simulation.poses import activity
from app.simulation.room import room_calibration
from app.simulation.scenes import build_actors, get_scene

__all__ = ["Simulator", "render_recording", "DEFAULT_SCENE", "RANDOM"]

DEFAULT_SCENE = "meeting3"
RANDOM = "random"          # the scene drawn from the seed (app.simulation.random_scene)
GT_DECIMALS = 4


def _r(v) -> list:
    return [round(float(x), GT_DECIMALS) + 0.0 for x in v]


class Simulator:
    """A scene rendered by the room's calibrated cameras.

    ``cameras`` selects camera names (default: the four corner cameras, plus ``cam4``,
    the zenithal one, when ``zenithal``). ``width``/``height`` scale the cameras (the
    intrinsics scale with them). ``calibration`` replaces the room's cameras altogether
    (e.g. cameras of different sizes, portrait ones, other frame rates: its fps is used).

    The scene :data:`RANDOM` is drawn from ``seed`` (:mod:`app.simulation.random_scene`):
    its room, its look, its cameras (count, sizes: ``width``, ``height`` and ``zenithal``
    do not apply), its people and their scripts, its sensor noise and light flicker.
    """

    def __init__(self, scene: str = DEFAULT_SCENE, seed: int = 0, fps: float = 25.0, seconds: float | None = None,
                 width: int = 640, height: int = 480, zenithal: bool = False, cameras=None, calibration=None,
                 markers: bool = False):
        room = None
        self.noise_sigma, self.flicker, self.drawn = _noise_sigma(), 1.0, None
        if scene == RANDOM:
            from app.simulation.random_scene import RANDOM_SECONDS, random_scene
            self.drawn = random_scene(seed, seconds if seconds is not None else RANDOM_SECONDS, fps)
            self.scene, room = self.drawn.scene, self.drawn.room
            self.noise_sigma, self.flicker = self.drawn.noise_sigma, self.drawn.flicker
            calibration = calibration or self.drawn.calibration
            zenithal = False
        else:
            self.scene = get_scene(scene)
        if calibration is not None:
            fps = calibration.fps
        if not (fps > 0 and math.isfinite(fps)):
            raise InputError(f"fps must be a positive number, got {fps!r}")
        if seconds is not None and not (seconds > 0 and math.isfinite(seconds)):
            raise InputError(f"seconds must be a positive number, got {seconds!r}")
        if width < 16 or height < 16:
            raise InputError(f"image size {width}x{height} is too small")
        self.seed = int(seed)
        self.fps = float(fps)
        self.seconds = float(seconds) if seconds is not None else self.scene.seconds
        self.room, self.actors, self.conflicts = build_actors(self.scene, self.seed, self.seconds + 1.0, room)
        zenithal = zenithal or (cameras is not None and "cam4" in cameras)
        calib = calibration or room_calibration(self.room, self.fps, width, height, zenithal)
        if cameras is not None:
            calib = calib.select(list(cameras))
        self.calibration = calib
        self.markers = bool(markers)   # coloured markers on the people's joints (app.simulation.markers)
        self._views = None
        self._lighting = None
        self._noise = None
        self._boxes = np.ascontiguousarray(self.room.boxes)

    # -- sizes and times ----------------------------------------------------------
    def frame_count(self, seconds: float | None = None) -> int:
        """Frames in ``seconds`` (default: the simulator's duration)."""
        return int(round((self.seconds if seconds is None else seconds) * self.fps))

    def time(self, index: int) -> float:
        return index / self.fps

    @property
    def cameras(self) -> list[str]:
        return self.calibration.names

    # -- bodies -------------------------------------------------------------------
    def people(self, index: int) -> list[dict]:
        """Everyone present at frame ``index`` (rendered; in the room or in the corridor
        in sight of the door): id, shape, pose, skeleton and primitives."""
        t = self.time(index)
        out = []
        for actor in self.actors:
            if not actor.sample(t)["present"]:
                continue
            pose = actor.pose(t)
            skel = forward_kinematics(actor.shape, pose)
            kinds, rows, mats = body_primitives(actor.shape, skel)
            sample = actor.sample(t)
            out.append({"id": actor.id, "actor": actor, "shape": actor.shape, "pose": pose, "skeleton": skel,
                        "kinds": kinds, "rows": rows, "materials": mats,
                        "centroid": body_centroid(kinds, rows), "sitting": sample["sit"] > 0.5,
                        "activity": activity(sample)})
        return out

    def bodies(self, index: int) -> FrameBodies:
        """The frame's bodies flattened for the renderer."""
        return FrameBodies.build([(p["id"], p["shape"], p["kinds"], p["rows"], p["materials"])
                                  for p in self.people(index)])

    def in_room(self, person: dict) -> bool:
        c = person["centroid"]
        return 0.0 <= c[0] <= self.room.size[0] and 0.0 <= c[1] <= self.room.size[1]

    # -- ground truth ---------------------------------------------------------------
    def joint_visibility(self, people: list[dict]) -> np.ndarray:
        """``(P, 15, C)`` booleans: joint j of person p is seen by camera c."""
        from app.simulation.geometry import segment_blocked

        fb = FrameBodies.build([(p["id"], p["shape"], p["kinds"], p["rows"], p["materials"]) for p in people])
        out = np.zeros((len(people), len(JOINTS), len(self.calibration.cameras)), dtype=bool)
        for c, cam in enumerate(self.calibration.cameras):
            o = cam.centre
            for p, person in enumerate(people):
                joints = person["skeleton"].joints
                inside = cam.sees(joints)
                for j in range(len(JOINTS)):
                    if not inside[j]:
                        continue
                    q = joints[j]
                    out[p, j, c] = not segment_blocked(o[0], o[1], o[2], q[0], q[1], q[2], self._boxes,
                                                       fb.kinds, fb.prims, fb.owner, p)
        return out

    def groundtruth(self, index: int, people: list[dict] | None = None) -> dict:
        """The contract's ground-truth record of frame ``index``."""
        people = self.people(index) if people is None else people
        vis = self.joint_visibility(people) if people else None
        listed = []
        for p, person in enumerate(people):
            if not self.in_room(person):
                continue
            joints = person["skeleton"].joints
            rec = {
                "id": int(person["id"]),
                "centroid": _r(person["centroid"]),
                "head": _r(joints[JOINTS.index("head")]),
                "joints": {name: _r(joints[j]) for j, name in enumerate(JOINTS)},
                "visible": {name: False for j, name in enumerate(JOINTS) if not vis[p, j].any()},
                "height": round(float(person["shape"].height), GT_DECIMALS),
                "sitting": bool(person["sitting"]),
                "activity": person["activity"],
                "colours": person["shape"].colours(),
            }
            listed.append(rec)
        return {"frame": int(index), "t": round(self.time(index), GT_DECIMALS), "people": listed}

    def body_record(self, index: int, people: list[dict] | None = None) -> dict:
        """The frame's body primitives (the ``bodies.jsonl`` record, see
        :mod:`app.simulation.occupancy`)."""
        from app.simulation.occupancy import body_record
        people = self.people(index) if people is None else people
        return body_record(index, self.time(index), people, self.in_room)

    # -- images -----------------------------------------------------------------------
    def _ensure_views(self):
        if self._views is None:
            from app.simulation.render import CameraView, RoomLighting
            self._lighting = RoomLighting(self.room)
            self._views = {cam.name: CameraView(cam, self.room, self._lighting) for cam in self.calibration.cameras}
            n = max(c.width * c.height for c in self.calibration.cameras) * 3
            rng = np.random.default_rng([self.seed, 7])
            self._noise = rng.normal(0.0, self.noise_sigma, n + 65536).astype(np.float32)
            self._noise_span = 65536
        return self._views

    def background(self, cam: str, noise: bool = True) -> np.ndarray:
        """The empty room seen by a camera (BGR uint8): one shot of the empty room, as a
        recording's ``background/`` holds (optics blur and sensor noise, no people)."""
        views = self._ensure_views()
        empty = FrameBodies.build([])
        c = self.cameras.index(cam)
        img, _ = views[cam].render(empty, None, noise=self._noise if noise else None,
                                   noise_offset=(c * 104729 + 12345) % self._noise_span)
        return img

    def gain(self, index: int, cam_index: int) -> float:
        """Slight illumination flicker (mains-driven lights, auto exposure) of a frame."""
        t = self.time(index)
        ph = 1.7 * cam_index + 0.3 * self.seed
        k = self.flicker
        return (1.0 + k * 0.012 * math.sin(2 * math.pi * 0.9 * t + ph)
                + k * 0.006 * math.sin(2 * math.pi * 3.1 * t + 2 * ph)
                + k * 0.004 * math.sin(2 * math.pi * 11.3 * t + ph * 3.0))

    def render(self, index: int, noise: bool = True):
        """Frame ``index``: ``(images {cam: BGR uint8}, labels {cam: int16 person id per
        pixel, -1 background}, groundtruth record)``."""
        return self.render_people(index, self.people(index), noise=noise)

    def render_people(self, index: int, people: list[dict], noise: bool = True):
        """:meth:`render` for people already posed by :meth:`people`."""
        views = self._ensure_views()
        fb = FrameBodies.build([(p["id"], p["shape"], p["kinds"], p["rows"], p["materials"]) for p in people])
        shadow = self._lighting.people_shadows(fb.kinds, fb.prims, fb.owner, len(fb.ids)) if len(fb.ids) else None
        images, labels = {}, {}
        for c, cam in enumerate(self.calibration.cameras):
            offset = (index * 7919 + c * 104729 + self.seed * 31) % self._noise_span
            img, lab = views[cam.name].render(fb, shadow, gain=self.gain(index, c),
                                              noise=self._noise if noise else None, noise_offset=offset)
            if self.markers:
                from app.simulation.markers import paint_markers
                paint_markers(img, lab, cam, [(p["id"], p["skeleton"].joints, p["shape"].height) for p in people
                                              if self.in_room(p)], np.random.default_rng(offset))
            images[cam.name] = img
            labels[cam.name] = lab
        return images, labels, self.groundtruth(index, people)

    def frames(self, start: int = 0, stop: int | None = None):
        """Yield ``(index, images, labels, record)``."""
        stop = self.frame_count() if stop is None else stop
        for i in range(start, stop):
            images, labels, rec = self.render(i)
            yield i, images, labels, rec


def _noise_sigma() -> float:
    from app.simulation.render import NOISE_SIGMA
    return NOISE_SIGMA


def render_recording(scene: str = DEFAULT_SCENE, out=None, seconds: float | None = None, fps: float = 25.0,
                     seed: int = 0, zenithal: bool = False, width: int = 640, height: int = 480,
                     occupancy: float | None = None, progress=None, codec: str = "mp4v",
                     overwrite: bool = False, calibration=None, markers: bool = False) -> Path:
    """Write a recording folder (CONTRACT §1) of a scene and return its path.

    ``videos/<cam>.mp4`` (the codec's compression included), ``background/<cam>.png``
    (the empty room, no noise; not for scenes whose room is never empty), ``calibration.yaml``, ``groundtruth.jsonl``,
    ``bodies.jsonl`` (the body primitives per frame, for reconstruction scoring) and,
    with ``occupancy`` (a voxel size in metres), ``occupancy.npz`` (the true occupied
    voxels per frame, see :mod:`app.simulation.occupancy`). ``progress(done, total,
    elapsed_s)`` is called after each frame. The folder appears complete or not at all
    (written as ``<out>.partial`` then renamed). ``markers``: coloured markers painted on
    the people's joints (:mod:`app.simulation.markers`), and ``markers.json``, their colour
    model learnt as a user would (``smartroom markers learn``: a few clicks on the markers
    of the first frame that shows some). ``calibration``: other cameras (see
    :class:`Simulator`).
    """
    from app.recording import RecordingWriter
    from app.simulation.occupancy import OccupancyWriter

    if out is None:
        raise InputError("render_recording needs an output folder")
    sim = Simulator(scene, seed=seed, fps=fps, seconds=seconds, width=width, height=height, zenithal=zenithal,
                    calibration=calibration, markers=markers)
    fps = sim.fps
    total = sim.frame_count()
    if total < 1:
        raise InputError(f"{seconds} s at {fps} fps is less than one frame")
    writer = RecordingWriter(out, sim.calibration, codec=codec, overwrite=overwrite)
    started = time.perf_counter()
    try:
        for cam in sim.cameras if sim.scene.empty_room_shot else ():   # a room never empty has no such shot
            writer.write_background(cam, sim.background(cam))
        occ = OccupancyWriter(writer.file("occupancy.npz"), sim.calibration, occupancy) if occupancy else None
        with open(writer.file("bodies.jsonl"), "w", encoding="utf-8") as bodies:
            for i in range(total):
                people = sim.people(i)
                images, _labels, rec = sim.render_people(i, people)
                writer.write(images)
                writer.write_groundtruth(rec)
                if markers and not writer.file("markers.json").exists():
                    _learn_marker_colour(sim, images, rec, writer.file("markers.json"))
                brec = sim.body_record(i, people)
                bodies.write(json.dumps(brec, separators=(",", ":")) + "\n")
                if occ is not None:
                    occ.add(brec)
                if progress is not None:
                    progress(i + 1, total, time.perf_counter() - started)
        if occ is not None:
            occ.close()
        with open(writer.file("simulation.json"), "w", encoding="utf-8") as fh:
            info = {"scene": scene, "seed": int(seed), "fps": float(fps), "seconds": sim.seconds,
                    "frames": total, "zenithal": bool(zenithal), "layout": sim.room.name,
                    "renderer_version": _renderer_version()}
            if sim.drawn is not None:
                info["random"] = sim.drawn.summary()
            json.dump(info, fh, indent=1)
    except BaseException:
        writer.abort()
        raise
    return writer.close()


def _learn_marker_colour(sim, images: dict, rec: dict, path) -> None:
    """``markers.json`` from the frame's visible markers in the camera that sees most of
    them (five clicks on their true centres), once some camera sees three."""
    from app.markers.detector import learn_chroma
    from app.markers.synthetic import visible_markers

    if not rec["people"]:
        return
    X = np.array([[p["joints"][j] for j in JOINTS] for p in rec["people"]], float)
    best = None
    for cam in sim.calibration.cameras:
        seen = visible_markers(X, [p["height"] for p in rec["people"]], cam)
        uv = cam.project(X.reshape(-1, 3)).reshape(len(X), len(JOINTS), 2)[seen]
        uv = uv[(uv[:, 0] >= 2) & (uv[:, 1] >= 2) & (uv[:, 0] < cam.width - 2) & (uv[:, 1] < cam.height - 2)]
        if len(uv) >= 3 and (best is None or len(uv) > len(best[1])):
            best = (cam.name, uv)
    if best is not None:
        Path(path).write_text(learn_chroma(images[best[0]], best[1][:5]).to_json() + "\n")


def _renderer_version() -> int:
    from app.simulation.render import RENDERER_VERSION
    return RENDERER_VERSION


def print_progress(prefix: str = "rendering", clock=time.perf_counter, stream=None):
    """A ``progress`` callback printing frames done and the ETA to stderr. The first
    frame carries one-off costs (the renderer's kernels compiled, the empty room's
    backgrounds drawn: 40 s of a 78 s render), so the ETA is the pace of the frames after
    it; until the second frame there is none."""
    last = [0.0]
    first = [None]   # elapsed time at the first frame

    def report(done, total, elapsed):
        if first[0] is None:
            first[0] = elapsed
        now = clock()
        if done == total or now - last[0] > 1.0:
            last[0] = now
            eta = "eta -"
            if done > 1:
                eta = f"eta {(elapsed - first[0]) / (done - 1) * (total - done):.0f} s"
            out = stream or sys.stderr
            print(f"\r{prefix}: {done}/{total} frames, {elapsed:.0f} s, {eta}   ", end="", file=out, flush=True)
            if done == total:
                print(file=out)
    return report
