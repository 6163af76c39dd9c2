"""Where each person is, and what they do, over time: activities -> dense tracks.

A person's script is a list of activities (:class:`Walk`, :class:`Stand`,
:class:`Turn`, :class:`Gesture`, :class:`Sit`, :class:`Enter`, :class:`Leave`,
:class:`Wander`). The :class:`Choreographer` plays everybody's script together, one
time step (:data:`DT`) at a time, and records per person a :class:`Track`: the root's
floor position, heading, walking speed, turning rate, sit blend and gesture state.
:mod:`app.simulation.poses` turns one sample into joint angles.

Walking follows smooth collision-free paths (:mod:`app.simulation.paths`) with
acceleration at the start, deceleration at the end, slower speed in tight curves and a
heading that turns at a human rate. People keep their distance like pedestrians do:
everyone occupies a footprint disc (bigger with outstretched arms, shifted forward when
seated); a walker brakes when someone is in the way ahead on its path, waits while a
moving person passes, and replans around people who stay in the way (a wanderer picks
another goal). Gestures and sitting down start only when there is room. Everything is
seeded, so a scene is the same for a seed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from app.simulation.gestures import (GESTURE_IDS, GESTURES, REACH, REFERENCE_BUILD, REFERENCE_HEIGHT, STAND_REACH,
                                    WANDER_GESTURES)
from app.simulation.paths import FloorPlan, PathError, _resample
from app.simulation.room import Chair, Room

__all__ = [
    "DT", "Track", "Walk", "Stand", "Turn", "Gesture", "Sit", "Enter", "Leave", "Wander",
    "Choreographer", "Footprint", "WALK_RADIUS", "GESTURES", "CONFLICT_MARGIN",
]

DT = 0.02                 # track sampling period (s)
WALK_RADIUS = 0.40        # planning clearance of a walker from furniture (m): half width, swing, stride
TURN_RATE = 1.9           # max heading rate (rad/s)
ACCEL = 0.9               # walking acceleration (m/s^2)
BRAKE = 1.6               # deceleration when someone is in the way (m/s^2)
LATERAL_ACCEL = 0.7       # limits speed in curves (m/s^2)
CONFLICT_MARGIN = 0.06    # extra distance kept between footprints (m)
SIT_TIME = 1.6            # sitting down / standing up (s)
SPOT_AHEAD = 0.45         # where one stands, back to the chair, before sitting (m ahead of its centre)

_SIT_FWD = 0.2            # a seated person's footprint is centred this far ahead of the root (m)


class Footprint:
    """The footprint discs of one person (m), from the body's size: the reach of the
    reference (largest) body scaled by stature and build (see
    :mod:`app.simulation.gestures`)."""

    def __init__(self, height: float = 1.75, build: float = 1.0):
        self.k = (height / REFERENCE_HEIGHT) * (build / REFERENCE_BUILD) ** 0.3
        self.stand = STAND_REACH * self.k + 0.01
        self.walk = self.stand + 0.05
        self.sit = 0.46 * self.k + 0.02

    def gesture(self, name: str) -> float:
        return REACH[name][0] * self.k + 0.02

    def gesture_low(self, name: str) -> float:
        return REACH[name][1] * self.k + 0.02

    def seated_gesture(self, name: str) -> float:
        return max(self.sit + 0.08, REACH[name][0] * self.k + 0.05)



# -- activities -------------------------------------------------------------------------

@dataclass(frozen=True)
class Walk:
    """Walk to a point (or a named spot of the room) through optional via points."""
    goal: object
    via: tuple = ()
    speed: float | None = None


@dataclass(frozen=True)
class Stand:
    seconds: float


@dataclass(frozen=True)
class Turn:
    """Turn in place to a heading (radians) or towards a point / named spot."""
    towards: object


@dataclass(frozen=True)
class Gesture:
    name: str


@dataclass(frozen=True)
class Sit:
    """Walk to a chair, sit down, stay ``seconds`` (talking with the hands if ``talk``),
    stand up and step back out. ``side`` (+1 / -1, the chair's left / right) picks the
    side to come in from; by default the nearer one."""
    chair: int
    seconds: float
    talk: bool = True
    side: int = 0


@dataclass(frozen=True)
class Enter:
    """Come in from the corridor through the door to a point (or spot) in the room,
    after waiting ``after`` seconds out of sight. Only as a script's first activity."""
    goal: object = None
    after: float = 0.0


@dataclass(frozen=True)
class Leave:
    """Walk out through the door; the person is gone afterwards."""


@dataclass(frozen=True)
class Wander:
    """Walk between random free points, pausing, turning and gesturing at times."""
    seconds: float | None = None
    gestures: bool = True


# -- tracks ---------------------------------------------------------------------------

_FIELDS = ("x", "y", "yaw", "speed", "turn", "sit", "chair", "gesture", "gtime", "gweight",
           "present", "fx", "fy", "fr")


@dataclass
class Track:
    """Dense samples (every :data:`DT` s from t = 0) of one person's motion."""

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray       # heading (unwrapped)
    speed: np.ndarray     # walking speed (m/s)
    turn: np.ndarray      # turning in place rate (rad/s)
    sit: np.ndarray       # 0 standing .. 1 seated
    chair: np.ndarray     # chair index while sitting (-1 otherwise)
    gesture: np.ndarray   # gesture id (-1 none)
    gtime: np.ndarray     # time since the gesture started (s)
    gweight: np.ndarray   # gesture blend weight 0..1
    present: np.ndarray   # rendered (in the room or in sight in the corridor)
    fx: np.ndarray        # footprint disc centre and radius (for planning)
    fy: np.ndarray
    fr: np.ndarray
    phase: np.ndarray = field(default=None)  # gait phase (cycles), set by the poses model

    def __len__(self) -> int:
        return len(self.x)

    def index(self, t: float) -> tuple[int, float]:
        """Sample index and interpolation weight for time ``t`` (clamped to the track)."""
        f = t / DT
        k = int(math.floor(f))
        if k >= len(self.x) - 1:
            return len(self.x) - 2, 1.0
        if k < 0:
            return 0, 0.0
        return k, f - k


class _Samples:
    """A growing list of samples (the candidate of one activity)."""

    def __init__(self):
        self.cols = {k: [] for k in _FIELDS}

    def add(self, x, y, yaw, speed=0.0, turn=0.0, sit=0.0, chair=-1, gesture=-1, gtime=0.0,
            gweight=0.0, present=True, fr=0.3, fwd=0.0):
        c = self.cols
        c["x"].append(x)
        c["y"].append(y)
        c["yaw"].append(yaw)
        c["speed"].append(speed)
        c["turn"].append(turn)
        c["sit"].append(sit)
        c["chair"].append(chair)
        c["gesture"].append(gesture)
        c["gtime"].append(gtime)
        c["gweight"].append(gweight)
        c["present"].append(present)
        c["fx"].append(x + fwd * math.cos(yaw))
        c["fy"].append(y + fwd * math.sin(yaw))
        c["fr"].append(fr)

    def extend(self, other: "_Samples"):
        for k in _FIELDS:
            self.cols[k].extend(other.cols[k])

    def __len__(self):
        return len(self.cols["x"])

    def last(self, key):
        return self.cols[key][-1]

    def arrays(self):
        return {k: np.asarray(v) for k, v in self.cols.items()}


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


# -- the choreographer ----------------------------------------------------------------

class _Agent:
    """One person being simulated: current state, recorded samples, script."""

    def __init__(self, index, name, script, start, speed, repeat, footprint):
        self.index, self.name = index, name
        self.fp = footprint
        self.script, self.repeat = list(script), repeat
        self.speed_pref = speed
        self.samples = _Samples()
        if self.script and isinstance(self.script[0], Enter):
            self.x, self.y, self.yaw, self.present = 0.0, 0.0, -math.pi / 2, False
        else:
            self.x, self.y, self.yaw = (float(v) for v in start)
            self.present = True
        self.speed = 0.0
        self.fx, self.fy, self.fr = self.x, self.y, footprint.stand
        self.life = None
        self.path = None          # the path being walked (for others to keep off it)
        self.path_s = 0.0
        self.blocked_by = None    # who stands in the way right now

    def emit(self, speed=0.0, turn=0.0, sit=0.0, chair=-1, gesture=-1, gtime=0.0, gweight=0.0,
             fr=None, fwd=0.0):
        fr = self.fp.stand if fr is None else fr
        self.speed = speed
        self.fx = self.x + fwd * math.cos(self.yaw)
        self.fy = self.y + fwd * math.sin(self.yaw)
        self.fr = fr
        self.samples.add(self.x, self.y, self.yaw, speed=speed, turn=turn, sit=sit, chair=chair,
                         gesture=gesture, gtime=gtime, gweight=gweight, present=self.present, fr=fr, fwd=fwd)


class Choreographer:
    """Plays the scripts of a scene's people together and records their tracks."""

    def __init__(self, room: Room, horizon: float, rng: np.random.Generator, plan: FloorPlan | None = None):
        self.room = room
        self.plan = plan or FloorPlan(room)
        self.horizon = horizon
        self.n = int(math.ceil(horizon / DT)) + 2
        self.rng = rng
        self.agents: list[_Agent] = []
        self.conflicts: list[str] = []

    def add_person(self, script, start=None, speed: float = 1.15, name: str = "", repeat: bool = False,
                   height: float = 1.75, build: float = 1.0) -> int:
        """Register a person (stature and build size their footprints); with ``repeat``
        the script starts over until the end, else the person wanders after it.
        Returns the person's index."""
        ag = _Agent(len(self.agents), name or f"person {len(self.agents) + 1}", script, start, speed, repeat,
                    Footprint(height, build))
        if not ag.present:
            ag.x, ag.y = (float(v) for v in self.room.door_outside)
            ag.fx, ag.fy = ag.x, ag.y
        self.agents.append(ag)
        return ag.index

    def run(self) -> list[Track]:
        """Simulate everybody up to the horizon; the tracks in the order added."""
        for ag in self.agents:
            ag.life = self._life(ag)
        for _ in range(self.n):
            for ag in self.agents:
                next(ag.life)
        tracks = []
        for ag in self.agents:
            arr = {k: v[: self.n] for k, v in ag.samples.arrays().items()}
            arr["yaw"] = np.unwrap(arr["yaw"])
            tracks.append(Track(**arr))
        self._audit(tracks)
        return tracks

    def _audit(self, tracks):
        for i in range(len(tracks)):
            for j in range(i + 1, len(tracks)):
                a, b = tracks[i], tracks[j]
                d = np.hypot(a.fx - b.fx, a.fy - b.fy)
                bad = a.present & b.present & (d < a.fr + b.fr - 1e-6)
                if bad.any():
                    k = int(np.argmax(bad))
                    self.conflicts.append(f"{self.agents[i].name} and {self.agents[j].name} closer than "
                                          f"their footprints at t={k * DT:.2f}s")

    # -- the world as others see it ------------------------------------------------
    def _others(self, ag):
        return [o for o in self.agents if o is not ag and o.present]

    def _clear(self, ag, x, y, r, moving: bool = False):
        """The first other person whose footprint comes within the margin of a disc of
        radius ``r`` at ``(x, y)`` (None if none). For a ``moving`` person, a step that
        takes them away from someone already too close is allowed."""
        for o in self._others(ag):
            d = math.hypot(x - o.fx, y - o.fy)
            if d < r + o.fr + CONFLICT_MARGIN:
                if moving and d > math.hypot(ag.x - o.fx, ag.y - o.fy) + 1e-4:
                    continue
                return o
        return None

    def _point(self, p) -> np.ndarray:
        if isinstance(p, str):
            return np.array(self.room.spots[p], dtype=float)
        return np.asarray(p, dtype=float)

    def _heading_to(self, ag, towards) -> float:
        if isinstance(towards, (int, float)):
            return float(towards)
        p = self._point(towards)
        return math.atan2(p[1] - ag.y, p[0] - ag.x)

    # -- a person's life -------------------------------------------------------------
    def _life(self, ag):
        while True:
            for act in ag.script:
                yield from self._activity(ag, act)
            if not ag.repeat or not ag.present or not ag.script:
                break
        while True:
            if ag.present:
                yield from self._wander(ag, None, True)
            else:
                ag.emit()
                yield

    def _activity(self, ag, act):
        if isinstance(act, Walk):
            points = [self._point(v) for v in act.via] + [self._point(act.goal)]
            yield from self._walk(ag, points, act.speed)
        elif isinstance(act, Stand):
            yield from self._stand(ag, act.seconds)
        elif isinstance(act, Turn):
            yield from self._turn(ag, self._heading_to(ag, act.towards))
        elif isinstance(act, Gesture):
            yield from self._gesture(ag, act.name)
        elif isinstance(act, Sit):
            yield from self._sit(ag, self.room.chairs[act.chair], act.seconds, act.talk, act.side)
        elif isinstance(act, Enter):
            yield from self._stand(ag, act.after)
            while self._clear(ag, ag.x, ag.y, ag.fp.walk) is not None:  # wait, out of sight
                ag.emit()
                yield
            ag.present = True
            goal = self._point(act.goal) if act.goal is not None else self.room.door_inside + np.array([0.6, -0.3])
            yield from self._walk(ag, [self.room.door_inside, goal], None, tight=True, patience=1e9)
        elif isinstance(act, Leave):
            yield from self._walk(ag, [self.room.door_inside, self.room.door_outside], None, tight=True,
                                  patience=1e9)
            ag.present = False
            ag.emit()
            yield
        elif isinstance(act, Wander):
            yield from self._wander(ag, act.seconds, act.gestures)
        else:
            raise TypeError(f"unknown activity {act!r}")

    # -- motion primitives ------------------------------------------------------------
    def _stand(self, ag, seconds):
        for _ in range(int(round(seconds / DT))):
            ag.emit()
            yield

    def _turn(self, ag, target: float):
        """Turn in place (trapezoidal heading rate) to ``target``."""
        delta = _wrap(target - ag.yaw)
        if abs(delta) < 0.03:
            return
        acc, rate, done = 7.0, 0.0, 0.0
        sign = 1.0 if delta > 0 else -1.0
        total = abs(delta)
        while done < total - 1e-4:
            rate = min(TURN_RATE, rate + acc * DT, math.sqrt(2 * acc * (total - done)))
            step = min(rate * DT, total - done)
            done += step
            ag.yaw += sign * step
            ag.emit(turn=sign * rate)
            yield

    def _room_for(self, ag, name: str) -> bool:
        """Whether the walls (full height) and the furniture (low) leave room for a
        gesture's reach where the person stands."""
        walls = min(ag.x, self.room.size[0] - ag.x, ag.y, self.room.size[1] - ag.y)
        return (walls >= ag.fp.gesture(name) + 0.03
                and self.plan.base_clearance_at((ag.x, ag.y)) >= ag.fp.gesture_low(name) + 0.05)

    def _gesture(self, ag, name: str, wait: float = 3.0):
        seconds, radius = GESTURES[name], ag.fp.gesture(name)
        if not self._room_for(ag, name):
            return  # no room for the arms here
        waited = 0.0
        while self._clear(ag, ag.x, ag.y, radius) is not None:  # not enough room (yet)
            if waited >= wait:
                return
            ag.emit()
            yield
            waited += DT
        gid = GESTURE_IDS[name]
        ramp = 0.45
        for k in range(int(round(seconds / DT))):
            t = k * DT
            w = min(1.0, t / ramp, (seconds - t) / ramp)
            w = w * w * (3 - 2 * w)
            ag.emit(gesture=gid, gtime=t, gweight=w, fr=max(radius, ag.fp.stand))
            yield

    def _path(self, ag, points, tight: bool, avoid: bool) -> np.ndarray:
        plan = self.plan
        if avoid:
            discs = [(o.fx, o.fy, o.fr + ag.fp.walk + CONFLICT_MARGIN + 0.03 - WALK_RADIUS) for o in self._others(ag)]
            plan = plan.with_obstacles(discs)
        pieces = []
        cur = np.array([ag.x, ag.y])
        for p in points:
            if tight and plan.segment_clear(cur, p, 0.15):
                seg = np.array([cur, p])
            else:
                seg = plan.plan(cur, p, WALK_RADIUS)
            pieces.append(seg if not pieces else seg[1:])
            cur = np.asarray(p, dtype=float)
        path = np.concatenate(pieces, axis=0)
        if len(points) > 1:
            path = plan._round_corners(path, WALK_RADIUS, fillet=0.35)
        path = np.concatenate([[[ag.x, ag.y]], path[1:]]) if np.linalg.norm(path[0] - [ag.x, ag.y]) < 0.05 \
            else np.concatenate([[[ag.x, ag.y]], path])
        return _resample(path, 0.02)

    def _walk(self, ag, points, speed, tight: bool = False, patience: float = 8.0, avoid: bool = False,
              yielding: bool = True):
        """Walk through ``points``: turn first if needed, accelerate, slow down in curves
        and at the end, brake for people in the way, replan around people who stay,
        and step aside for a person coming the other way."""
        try:
            path = self._path(ag, points, tight, avoid)
        except PathError:
            if not avoid:
                return
            try:  # nobody's way around now: take the usual path and wait if needed
                path = self._path(ag, points, tight, False)
            except PathError:
                return
        vmax = float(speed or ag.speed_pref)
        replans, blocked, waited = 0, 0.0, 0.0
        tried_avoid = made_way = False
        started = len(ag.samples)
        budget = None
        try:
            while True:
                seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
                s_at = np.concatenate([[0.0], np.cumsum(seg)])
                total = float(s_at[-1])
                if total < 0.03:
                    return
                heading = np.arctan2(np.gradient(path[:, 1]), np.gradient(path[:, 0]))
                w = min(6, max(1, len(path) // 4))
                dh = np.abs(np.angle(np.exp(1j * (np.roll(heading, -w) - np.roll(heading, w)))))
                dh[:w] = dh[w] if len(dh) > w else 0.0
                dh[-w:] = 0.0
                vcurve = np.sqrt(LATERAL_ACCEL / np.maximum(dh / (2 * w * 0.02), 1e-3))
                # anticipate: slow down before a tight curve, not in it
                for i in range(len(vcurve) - 2, -1, -1):
                    vcurve[i] = min(vcurve[i], math.sqrt(vcurve[i + 1] ** 2 + 2 * ACCEL * seg[i]))
                ag.path, ag.path_s = path, 0.0
                if budget is None:  # a walk gives up when it takes far longer than it should
                    budget = (total / 0.4 + 10.0 + min(patience, 60.0)) / DT
                first = float(heading[min(3, len(heading) - 1)])
                if abs(_wrap(first - ag.yaw)) > 0.45:
                    yield from self._turn(ag, first)
                s, v = 0.0, 0.0
                again = False
                while s < total - 1e-3:
                    k = min(int(np.searchsorted(s_at, s)), len(path) - 1)
                    vdes = min(vmax, float(vcurve[k]), math.sqrt(2 * ACCEL * max(total - s, 0.0)) + 0.05)
                    blocker = self._ahead(ag, path, s_at, s, v)
                    ag.blocked_by = blocker
                    if blocker is not None:
                        vdes = 0.0
                    v = min(vdes, v + ACCEL * DT) if v < vdes else max(vdes, v - BRAKE * DT)
                    if vdes == 0.0 and v < 0.1:
                        v = 0.0
                    moved = False
                    if v > 0.0:
                        v = max(v, 0.08)
                        ns = min(total, s + v * DT)
                        x = float(np.interp(ns, s_at, path[:, 0]))
                        y = float(np.interp(ns, s_at, path[:, 1]))
                        if self._clear(ag, x, y, ag.fp.walk, moving=True) is None:
                            if math.hypot(x - ag.x, y - ag.y) > 1e-6:
                                dyaw = _wrap(math.atan2(y - ag.y, x - ag.x) - ag.yaw)
                                ag.yaw += max(-TURN_RATE * DT * 1.4, min(TURN_RATE * DT * 1.4, dyaw))
                            ag.x, ag.y, s = x, y, ns
                            ag.path_s = s
                            moved = True
                    if moved:
                        if v > 0.3:
                            blocked = 0.0
                            tried_avoid = made_way = False
                        ag.emit(speed=v, fr=ag.fp.walk)
                    else:
                        v = 0.0
                        blocked += DT
                        waited += DT
                        ag.emit()
                    yield
                    if waited > patience or len(ag.samples) - started > budget:
                        return
                    b = ag.blocked_by
                    if blocked > 1.0 and not tried_avoid and (b is None or b.path is None or b.blocked_by is ag):
                        # someone stands in the way (or we block each other): a short detour?
                        tried_avoid = True
                        try:
                            detour = self._path(ag, points[-1:] if not tight else points, tight, avoid=True)
                            if len(detour) * 0.02 <= 1.5 * (total - s) + 1.0:
                                path = detour
                                again = True
                                break
                        except PathError:
                            pass
                    if blocked > 1.0 and yielding and not made_way and b is not None and b.path is not None \
                            and b.blocked_by is ag and ag.index > b.index:
                        # face to face: the later person steps aside and lets the other pass
                        made_way = True
                        if (yield from self._make_way(ag, b)):
                            try:
                                path = self._path(ag, points[-1:] if not tight else points, tight, avoid=False)
                            except PathError:
                                return
                            again = True
                            break
                    if blocked > 3.0 and replans < 6:
                        replans += 1
                        tried_avoid = made_way = False
                        blocked = 0.0
                if not again:
                    ag.emit()  # the speed settles to zero
                    yield
                    return
                blocked = 0.0
        finally:
            ag.path, ag.blocked_by = None, None

    def _make_way(self, ag, other):
        """Walk to a free spot near by, off ``other``'s path, and wait there until they
        have passed. Returns False (nothing done) when there is no such spot."""
        opath = other.path
        rest = opath[int(other.path_s / 0.02):][: int(3.5 / 0.02)] if opath is not None else None
        if rest is None or len(rest) < 2:
            return False
        keep = ag.fp.stand + other.fp.walk + CONFLICT_MARGIN + 0.03
        discs = [(o.fx, o.fy, o.fr + 0.05) for o in self._others(ag)]
        plan = self.plan.with_obstacles(discs)
        for r in (0.5, 0.8, 1.1, 1.5, 2.0, 2.5, 3.0):
            for k in range(16):
                ang = k * math.pi / 8 + 0.1
                p = np.array([ag.x + r * math.cos(ang), ag.y + r * math.sin(ang)])
                if not self.room.inside(p) or self.plan.clearance_at(p) < WALK_RADIUS:
                    continue
                if np.min(np.hypot(rest[:, 0] - p[0], rest[:, 1] - p[1])) < keep:
                    continue
                if self._clear(ag, p[0], p[1], ag.fp.stand + 0.05) is not None:
                    continue
                try:
                    path = plan.plan((ag.x, ag.y), p, WALK_RADIUS)
                except PathError:
                    continue
                if len(path) * 0.02 > 2.5 * r + 0.5:
                    continue
                yield from self._walk(ag, [p], 0.7, patience=3.0, yielding=False, avoid=True)
                waited = 0.0
                while waited < 8.0 and other.path is not None and other.present:
                    ahead = other.path[int(other.path_s / 0.02):][: int(3.5 / 0.02)]
                    if len(ahead) == 0 or np.min(np.hypot(ahead[:, 0] - ag.x, ahead[:, 1] - ag.y)) >= keep - 0.05:
                        break
                    ag.emit()
                    yield
                    waited += DT
                return True
        return False

    def _ahead(self, ag, path, s_at, s, v):
        """Someone whose footprint is on my path within braking distance, or None."""
        look = v * v / (2 * BRAKE) + 0.3
        s_end = min(float(s_at[-1]), s + look)
        for q in np.arange(s + 0.1, s_end + 1e-9, 0.1):
            x = float(np.interp(q, s_at, path[:, 0]))
            y = float(np.interp(q, s_at, path[:, 1]))
            o = self._clear(ag, x, y, ag.fp.walk, moving=True)
            if o is not None:
                return o
        return None

    def _sit(self, ag, chair: Chair, seconds: float, talk: bool, side_pick: int = 0):
        fwd = chair.forward
        side = np.array([-fwd[1], fwd[0]])
        spot = np.array([chair.x, chair.y]) + fwd * SPOT_AHEAD
        seat = np.array([chair.x, chair.y]) + fwd * 0.02
        approach, best = None, float("inf")
        sides = (spot + side * 0.8, spot - side * 0.8) if side_pick == 0 else (spot + side * 0.8 * side_pick,)
        for p in sides:  # from the nearer side
            try:
                length = len(self.plan.plan((ag.x, ag.y), p, WALK_RADIUS))
            except PathError:
                continue
            if length < best:
                approach, best = p, length
        if approach is None:
            return
        yield from self._walk(ag, [approach], None, patience=30.0)
        yield from self._walk(ag, [spot], 0.6, tight=True, patience=30.0)
        yield from self._turn(ag, chair.yaw)
        n = int(round(SIT_TIME / DT))
        while self._clear(ag, *(seat + fwd * _SIT_FWD), ag.fp.sit) is not None:
            ag.emit()
            yield
        for k in range(1, n + 1):
            b = k / n
            p = spot + (seat - spot) * (b * b * (3 - 2 * b))
            ag.x, ag.y = float(p[0]), float(p[1])
            ag.emit(sit=b, chair=chair.index, fr=ag.fp.stand + (ag.fp.sit - ag.fp.stand) * b, fwd=_SIT_FWD * b)
            yield
        t = 0.0
        talk_names = ("explain", "shrug", "point")
        while t < seconds:
            if talk and self.rng.random() < 0.7 and seconds - t > 4.0:
                name = talk_names[int(self.rng.integers(len(talk_names)))]
                gs = GESTURES[name]
                gid = GESTURE_IDS[name]
                gr = ag.fp.seated_gesture(name)
                clear = self._clear(ag, *(seat + fwd * 0.1), gr) is None  # else someone is too close
                for k in range(int(round(gs / DT)) if clear else 0):
                    tt = k * DT
                    w = min(1.0, tt / 0.45, (gs - tt) / 0.45)
                    ag.emit(sit=1.0, chair=chair.index, gesture=gid, gtime=tt, gweight=w * w * (3 - 2 * w),
                            fr=gr, fwd=0.1)
                    yield
                t += gs if clear else 0.0
            pause = float(self.rng.uniform(1.0, 2.5))
            for _ in range(int(pause / DT)):
                ag.emit(sit=1.0, chair=chair.index, fr=ag.fp.sit, fwd=_SIT_FWD)
                yield
            t += pause
        for k in range(n - 1, -1, -1):
            b = k / n
            p = spot + (seat - spot) * (b * b * (3 - 2 * b))
            ag.x, ag.y = float(p[0]), float(p[1])
            ag.emit(sit=b, chair=chair.index, fr=ag.fp.stand + (ag.fp.sit - ag.fp.stand) * b, fwd=_SIT_FWD * b)
            yield
        yield from self._walk(ag, [approach], 0.7, tight=True, patience=30.0)

    def _wander(self, ag, seconds, gestures: bool):
        end = None if seconds is None else len(ag.samples) + int(seconds / DT)
        while end is None or len(ag.samples) < end:
            goal = self._random_goal(ag)
            if goal is None:
                yield from self._stand(ag, 0.5)
                continue
            speed = float(self.rng.uniform(0.85, 1.0)) * ag.speed_pref
            yield from self._walk(ag, [goal], speed, patience=3.0, avoid=True)
            r = self.rng.random()
            yaw = float(self.rng.uniform(-math.pi, math.pi))
            fitting = [g for g in WANDER_GESTURES if self._room_for(ag, g)]
            if gestures and r < 0.35 and fitting:
                yield from self._turn(ag, yaw)
                yield from self._gesture(ag, fitting[int(self.rng.integers(len(fitting)))], wait=1.5)
            elif r < 0.6:
                yield from self._turn(ag, yaw)
                yield from self._stand(ag, float(self.rng.uniform(0.3, 1.5)))
            else:
                yield from self._stand(ag, float(self.rng.uniform(0.4, 2.0)))

    def _random_goal(self, ag):
        for _ in range(200):
            p = np.array([self.rng.uniform(0.5, self.room.size[0] - 0.5),
                          self.rng.uniform(0.5, self.room.size[1] - 0.5)])
            if (self.plan.clearance_at(p) >= 0.5 and math.hypot(p[0] - ag.x, p[1] - ag.y) > 1.0
                    and self._clear(ag, p[0], p[1], 0.5) is None):
                return p
        return None
