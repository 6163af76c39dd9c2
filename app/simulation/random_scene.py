"""Random scenes: rooms, camera rigs, people and what they do, drawn from a seed.

``smartroom simulate --random SEED`` (and ``smartroom bench accuracy``) use this
generator so that accuracy is measured on scenes nothing was tuned on (DESIGN §6): the
built-in scenes are a handful of fixed seeds of one room and one rig. A seed draws:

* **the room**: 4.0-7.5 x 3.5-6.5 m, 2.5-3.2 m high; a door at a random place of the
  wall x = 0 onto a corridor; furniture from a few layouts (a meeting table with chairs,
  two work benches, desks along the walls, an empty room) with cabinets; window, board
  and poster on the walls; the look (:func:`~app.simulation.room.room_look`): wall and
  floor colours (sometimes dark or saturated), planks, tiles or carpet, the lights' level
  and colour temperature;
* **the rig**: 3-8 cameras around the walls at 1.9-3.0 m (sometimes one in the
  ceiling), aimed near the room's centre, 58-100 degree fields of view, 640x360 to
  1024x576 pixels, radial and tangential distortion, off-centre principal points; sensor
  noise and light flicker of the recording;
* **the people**: 1-6 of them, statures uniform over 1.45-2.00 m, builds 0.82-1.30,
  leg / arm / trunk proportions a few per cent off the average, clothes and hair in any
  colour, at times close to the walls', the floor's or another person's;
* **what they do** (a style per person): walk from place to place, stand still for
  seconds, gesture in place, sit at a table and talk, crouch, bend down and reach up,
  come in through the door and leave through it.

Everything comes from ``numpy.random.default_rng(seed)``, so a seed is the same scene
on every machine. :func:`random_scene` returns a :class:`RandomScene`; the
:class:`~app.simulation.simulator.Simulator` renders it like a built-in scene.
"""
from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass

import numpy as np

from calibration import Calibration, Camera

from app.simulation.body import _HAIR, _SHOES, _SKIN, BodyShape, trunk_for_legs
from app.simulation.motion import Enter, Gesture, Leave, Sit, Stand, Turn, Walk
from app.simulation.paths import FloorPlan
from app.simulation.room import (DECOR_BOARD, DECOR_FLAT, DECOR_POSTER, DECOR_WINDOW, FLOOR_CARPET, FLOOR_PLANKS,
                                 FLOOR_TILES, WALL_X0, WALL_X1, WALL_Y0, WALL_Y1, Chair, Room, _box, _with_intrinsics,
                                 chair_boxes, room_look, table_boxes)
from app.simulation.scenes import PersonSpec, Scene

__all__ = ["RandomScene", "random_scene", "STATURE_RANGE", "RANDOM_SECONDS", "STYLES", "GENERATOR_VERSION"]

#: Bumped whenever a seed draws another scene (cached recordings carry it).
GENERATOR_VERSION = 1

STATURE_RANGE = (1.45, 2.00)     # m, uniform: every band as often as any other
RANDOM_SECONDS = 12.0            # a random scene's natural length
PEOPLE_WEIGHTS = (0.14, 0.2, 0.22, 0.18, 0.14, 0.12)   # 1..6 people
STYLES = ("walker", "still", "gesturer", "sitter", "worker", "visitor")
STYLE_WEIGHTS = (0.22, 0.16, 0.16, 0.18, 0.16, 0.12)
RESOLUTIONS = ((640, 480), (800, 600), (640, 360), (960, 540), (1024, 576), (720, 540))
PI = math.pi


@dataclass(frozen=True)
class RandomScene:
    """A drawn scene: the room (with its look), the cameras, the people's scripts and
    bodies, and the recording's sensor noise and light flicker."""

    seed: int
    room: Room
    calibration: Calibration
    scene: Scene                  # name "random", the people's specs (with their bodies)
    noise_sigma: float            # sensor noise (grey levels, standard deviation)
    flicker: float                # light flicker amplitude (x the built-in scenes')
    styles: tuple                 # each person's style (one of STYLES)

    def summary(self) -> dict:
        """What was drawn, for ``simulation.json`` and the benchmark's table."""
        cams = self.calibration.cameras
        return {"room": [round(v, 2) for v in self.room.size], "furniture": self.room.description,
                "cameras": len(cams), "sizes": sorted({f"{c.width}x{c.height}" for c in cams}),
                "people": len(self.scene.people), "statures": [round(p.shape.height, 3) for p in self.scene.people],
                "styles": list(self.styles), "noise_sigma": round(self.noise_sigma, 2),
                "flicker": round(self.flicker, 2)}


def random_scene(seed: int, seconds: float = RANDOM_SECONDS, fps: float = 25.0) -> RandomScene:
    """The scene of ``seed`` (see the module docstring). The scripts are drawn for
    :data:`RANDOM_SECONDS` whatever ``seconds`` is: a shorter recording is the start of
    the same scene (a longer one goes on with people wandering after their scripts)."""
    rng = np.random.default_rng([int(seed), 22])
    room = _random_room(rng)
    calibration = _random_rig(rng, room, fps)
    plan = FloorPlan(room)
    n = int(rng.choice(np.arange(1, 7), p=PEOPLE_WEIGHTS))
    people, styles = [], []
    chairs = list(rng.permutation(len(room.chairs)))
    starts: list[np.ndarray] = []
    for k in range(n):
        shape = _random_body(rng, room, [p.shape for p in people])
        style = str(rng.choice(STYLES, p=STYLE_WEIGHTS))
        if style == "sitter" and not chairs:
            style = "walker"
        script, start = _script(rng, style, room, plan, starts, chairs, RANDOM_SECONDS)
        if start is not None:
            starts.append(np.asarray(start[:2]))
        people.append(PersonSpec(tuple(script), start=start, shape=shape))
        styles.append(style)
    scene = Scene("random", f"random scene {seed}", room.name, float(seconds), tuple(people),
                  empty_room_shot=bool(rng.random() < 0.8))
    return RandomScene(int(seed), room, calibration, scene, float(rng.uniform(1.5, 4.0)),
                       float(rng.uniform(0.0, 3.0)), tuple(styles))


# -- the room -----------------------------------------------------------------------------

def _random_room(rng) -> Room:
    """A furnished room whose floor stays walkable: layouts are drawn until the floor plan
    leaves the door and most of the floor reachable."""
    sx, sy, sz = float(rng.uniform(4.0, 7.5)), float(rng.uniform(3.5, 6.5)), float(rng.uniform(2.5, 3.2))
    look = _random_look(rng)
    for _ in range(50):
        y0 = float(rng.uniform(0.45, sy - 1.35))
        door = (y0, y0 + 0.9, 2.05)
        corridor = (-1.6, 0.0, y0 - 1.7, y0 + 2.7)
        kind = str(rng.choice(["meeting", "benches", "desks", "empty"], p=[0.4, 0.2, 0.25, 0.15]))
        boxes, chairs = _furniture(rng, kind, sx, sy, door)
        room = Room(name=f"random-{kind}", size=(sx, sy, sz), boxes=np.array(boxes, dtype=np.float64).reshape(-1, 8),
                    chairs=tuple(chairs), door=door, corridor=corridor, decor=_decor(rng, sx, sy, door),
                    lights=_lights(rng, sx, sy, sz), look=look,
                    description=f"{sx:.1f}x{sy:.1f} m, {kind}, {len(chairs)} chairs")
        if _walkable(room):
            return room
    raise RuntimeError("no walkable room drawn in 50 tries")   # never seen: the layouts leave room


def _walkable(room: Room) -> bool:
    plan = FloorPlan(room)
    inside = (plan.clearance >= 0.45)
    xs = plan.x0 + (np.arange(plan.nx) + 0.5) * plan.cell
    ys = plan.y0 + (np.arange(plan.ny) + 0.5) * plan.cell
    X, Y = np.meshgrid(xs, ys)
    room_cells = (X > 0) & (X < room.size[0]) & (Y > 0) & (Y < room.size[1])
    if (inside & room_cells).sum() < 0.3 * room_cells.sum():
        return False
    import cv2
    n, labels = cv2.connectedComponents(inside.astype(np.uint8))
    door = room.door_inside
    i = int((door[1] - plan.y0) / plan.cell)
    j = int((door[0] - plan.x0) / plan.cell)
    if not inside[i, j]:
        return False
    main = labels[i, j]
    return bool(((labels == main) & room_cells).sum() >= 0.8 * (inside & room_cells).sum())


def _furniture(rng, kind, sx, sy, door):
    boxes, chairs = [], []
    fabrics = ["fabric_blue", "fabric_red", "fabric_grey"]
    tops = ["table_top", "dark_wood", "cabinet"]

    def chair(x, y, yaw, seat=0.46):
        if min(x, sx - x, y, sy - y) < 0.4:   # no room for it between the table and the wall
            return
        boxes.extend(chair_boxes(x, y, yaw, fabrics[int(rng.integers(3))], seat_height=seat))
        chairs.append(Chair(len(chairs), x, y, yaw, seat_height=seat))

    if kind == "meeting":
        length, width = float(rng.uniform(1.2, min(2.6, sx - 2.6))), float(rng.uniform(0.75, 1.1))
        along_x = sx - 2.6 >= length and (sx >= sy or rng.random() < 0.5)
        if not along_x:
            length = float(min(length, sy - 2.6))
        if length >= 1.0:
            span = (sx, sy) if along_x else (sy, sx)
            cu = float(rng.uniform(1.3 + length / 2, span[0] - 1.3 - length / 2))
            cv = float(rng.uniform(1.5 + width / 2, span[1] - 1.5 - width / 2)) if span[1] > 3.0 + width else span[1] / 2
            cx, cy = (cu, cv) if along_x else (cv, cu)
            yaw = 0.0 if along_x else PI / 2
            boxes.extend(table_boxes(cx, cy, length, width, top=tops[int(rng.integers(3))], yaw=yaw))
            per_side = max(1, int(length // 0.75))
            for side in (-1, 1):
                for k in range(per_side):
                    if rng.random() < 0.25:
                        continue
                    u = (k - (per_side - 1) / 2) * 0.75
                    off = side * (width / 2 + 1.0)   # pushed back: room to step in front and sit down
                    x, y = (cx + u, cy + off) if along_x else (cx - off, cy + u)
                    chair(x, y, _snap(math.atan2(cy - y, cx - x)))
    elif kind == "benches":
        for k in range(2 if sy > 4.6 else 1):
            length = float(rng.uniform(1.6, min(3.0, sx - 2.4)))
            cy = sy * (0.3 if k == 0 else 0.7) if sy > 4.6 else sy / 2
            cx = float(rng.uniform(1.2 + length / 2, sx - 1.2 - length / 2))
            boxes.extend(table_boxes(cx, cy, length, 0.8, height=0.92))
            if rng.random() < 0.7:   # pulled out (room to sit down), facing the bench
                chair(cx + float(rng.uniform(-length / 3, length / 3)), cy - 1.4, PI / 2, seat=0.62)
    elif kind == "desks":
        for wall_y, facing in ((0.45, -PI / 2), (sy - 0.45, PI / 2)):   # a chair faces its desk
            for k in range(int(rng.integers(1, 3))):
                cx = float(rng.uniform(1.6, sx - 1.0))
                if any(abs(cx - b[0]) < 1.5 and abs(wall_y - b[1]) < 0.6 for b in boxes):
                    continue
                boxes.extend(table_boxes(cx, wall_y, 1.4, 0.7))
                if rng.random() < 0.8:
                    chair(cx, wall_y - 1.35 * math.sin(facing), facing)
    # chairs against the wall x = max, facing the room (a waiting corner)
    for k in range(int(rng.choice([0, 0, 1, 2]))):
        y = float(rng.uniform(0.8, sy - 0.8))
        if all(abs(y - c.y) > 0.8 or c.x < sx - 1.5 for c in chairs):
            chair(sx - 0.45, y, PI)
    # a cabinet against the wall x = max or along y = 0
    if rng.random() < 0.7:
        depth, length, height = float(rng.uniform(0.4, 0.5)), float(rng.uniform(0.8, 1.6)), float(rng.uniform(0.75, 1.1))
        if rng.random() < 0.5:
            boxes.append(_box(sx - depth / 2 - 0.005, float(rng.uniform(0.3 + length / 2, sy - 0.3 - length / 2)),
                              height / 2, depth / 2, length / 2, height / 2, 0.0, "cabinet"))
        else:
            boxes.append(_box(float(rng.uniform(1.3 + length / 2, sx - 0.3 - length / 2)), depth / 2 + 0.005,
                              height / 2, length / 2, depth / 2, height / 2, 0.0, "dark_wood"))
    return boxes, chairs


def _snap(yaw: float) -> float:
    """A chair faces its table square (to a quarter turn)."""
    return round(yaw / (PI / 2)) * (PI / 2)


def _decor(rng, sx, sy, door) -> np.ndarray:
    rows = []
    length = {WALL_X0: sy, WALL_X1: sy, WALL_Y0: sx, WALL_Y1: sx}
    walls = [WALL_X1, WALL_Y0, WALL_Y1]
    for kind, (w0, w1), (z0, z1) in ((DECOR_WINDOW, (1.2, 3.2), (0.9, 2.15)), (DECOR_BOARD, (1.0, 2.2), (0.9, 2.0)),
                                     (DECOR_POSTER, (0.5, 0.9), (1.15, 1.95))):
        wall = walls[int(rng.integers(len(walls)))]
        w = float(min(rng.uniform(w0, w1), length[wall] - 0.6))
        u0 = float(rng.uniform(0.3, length[wall] - 0.3 - w))
        r, g, b = rng.uniform(0.2, 0.95, 3)
        rows.append([wall, u0, u0 + w, z0, z1, kind, r, g, b])
    clock = float(rng.uniform(0.4, sy - 0.8))
    if not door[0] - 0.5 < clock < door[1] + 0.2:
        rows.append([WALL_X0, clock, clock + 0.32, 1.95, 2.27, DECOR_FLAT, 0.95, 0.95, 0.95])
    return np.array(rows, dtype=np.float64)


def _lights(rng, sx, sy, sz) -> np.ndarray:
    nx, ny = max(2, int(round(sx / 1.6))), max(2, int(round(sy / 1.6)))
    level = float(rng.uniform(0.55, 1.35))
    rows = [[(i + 0.5) * sx / nx, (j + 0.5) * sy / ny, sz - 0.01, 1.45 * level, 0.6]
            for i in range(nx) for j in range(ny)]
    return np.array(rows, dtype=np.float64)


def _random_look(rng) -> np.ndarray:
    def wall_colour():
        if rng.random() < 0.2:    # a dark or saturated wall
            h, s, v = rng.random(), float(rng.uniform(0.2, 0.7)), float(rng.uniform(0.25, 0.75))
        else:                     # off-white, pastel
            h, s, v = rng.random(), float(rng.uniform(0.0, 0.2)), float(rng.uniform(0.72, 0.92))
        return colorsys.hsv_to_rgb(h, s, v)

    base = wall_colour()
    walls = [base if rng.random() < 0.7 else wall_colour() for _ in range(4)]
    kind = int(rng.choice([FLOOR_PLANKS, FLOOR_TILES, FLOOR_CARPET]))
    if kind == FLOOR_PLANKS:
        floor, scale = colorsys.hsv_to_rgb(float(rng.uniform(0.05, 0.11)), float(rng.uniform(0.3, 0.6)),
                                           float(rng.uniform(0.3, 0.75))), float(rng.uniform(0.12, 0.24))
    elif kind == FLOOR_TILES:
        floor, scale = colorsys.hsv_to_rgb(rng.random(), float(rng.uniform(0.0, 0.25)),
                                           float(rng.uniform(0.35, 0.85))), float(rng.uniform(0.3, 0.6))
    else:
        floor, scale = colorsys.hsv_to_rgb(rng.random(), float(rng.uniform(0.1, 0.6)),
                                           float(rng.uniform(0.2, 0.6))), 1.0
    kelvin = float(rng.uniform(2900.0, 6500.0))
    return room_look(walls=walls, floor=floor, floor_kind=kind, floor_scale=scale, light=_light_colour(kelvin),
                     skirting=float(rng.uniform(0.6, 1.6)), exposure=float(rng.uniform(0.85, 1.2)))


def _light_colour(kelvin: float) -> tuple:
    """RGB multipliers of a light of colour temperature ``kelvin`` against daylight
    (Tanner Helland's fit of the Planckian locus), normalised to a green of 1."""
    t = kelvin / 100.0
    r = 255.0 if t <= 66 else 329.7 * (t - 60) ** -0.1332
    g = 99.47 * math.log(t) - 161.1 if t <= 66 else 288.1 * (t - 60) ** -0.0755
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.5 * math.log(t - 10) - 305.0)
    r, g, b = (min(255.0, max(0.0, c)) for c in (r, g, b))
    return r / g, 1.0, b / g


# -- the rig --------------------------------------------------------------------------------

def _random_rig(rng, room: Room, fps: float) -> Calibration:
    sx, sy, sz = room.size
    n = int(rng.integers(3, 9))
    inset = 0.12
    corners = [(inset, inset), (sx - inset, inset), (sx - inset, sy - inset), (inset, sy - inset)]
    mids = [(sx / 2, inset), (sx - inset, sy / 2), (sx / 2, sy - inset), (inset, sy / 2),
            (sx / 4, inset), (3 * sx / 4, sy - inset), (sx - inset, sy / 4), (inset, 3 * sy / 4)]
    d0, d1, _ = room.door
    spots = [p for p in corners + mids if not (p[0] < 0.5 and d0 - 0.3 < p[1] < d1 + 0.3)]
    weight = np.array([3.0 if p in corners else 1.0 for p in spots])   # corners are the usual places
    pick = rng.choice(len(spots), size=min(n, len(spots)), replace=False, p=weight / weight.sum())
    chosen = [spots[i] for i in pick]
    zenithal = rng.random() < 0.2
    width, height = RESOLUTIONS[int(rng.integers(len(RESOLUTIONS)))]
    cams = []
    for k, (x, y) in enumerate(chosen):
        if zenithal and k == len(chosen) - 1:
            pos = (sx / 2 + float(rng.uniform(-0.3, 0.3)), sy / 2 + float(rng.uniform(-0.3, 0.3)), sz - 0.05)
            target, up, hfov = (pos[0], pos[1], 0.0), (0.0, 1.0, 0.0), float(rng.uniform(95.0, 115.0))
        else:
            x += float(rng.uniform(-0.3, 0.3)) * (inset < x < sx - inset)
            y += float(rng.uniform(-0.3, 0.3)) * (inset < y < sy - inset)
            pos = (x, y, float(rng.uniform(1.9, min(3.0, sz - 0.05))))
            target = (sx / 2 + float(rng.uniform(-0.2, 0.2)) * sx, sy / 2 + float(rng.uniform(-0.2, 0.2)) * sy,
                      float(rng.uniform(0.5, 1.2)))
            up = (0.0, 0.0, 1.0)
            far = max(math.hypot(cx - x, cy - y) for cx, cy in ((0, 0), (sx, 0), (sx, sy), (0, sy)))
            need = 2 * math.degrees(math.atan2(0.55 * far, math.hypot(target[0] - x, target[1] - y)))
            hfov = float(np.clip(rng.uniform(0.85, 1.15) * need, 58.0, 100.0))
        w, h = (width, height) if rng.random() < 0.8 else RESOLUTIONS[int(rng.integers(len(RESOLUTIONS)))]
        cam = Camera.look_at(f"cam{k}", pos, target, w, h, hfov, up=up)
        dist = (*_radial(rng, hfov, w, h), float(rng.uniform(-0.001, 0.001)), float(rng.uniform(-0.001, 0.001)), 0.0)
        off = (float(rng.uniform(-8.0, 8.0)), float(rng.uniform(-8.0, 8.0)))
        cams.append(_with_intrinsics(cam, dist, off, aspect=float(rng.uniform(0.998, 1.003))))
    return Calibration(float(fps), np.zeros(3), np.array(room.size, dtype=np.float64), tuple(cams))


def _radial(rng, hfov: float, width: int, height: int) -> tuple[float, float]:
    """Radial distortion ``(k1, k2)``: barrel, from none to strong, but never folding back
    inside the image (the model's radius must keep growing past its corners, with a
    margin: a wide lens takes a milder k1)."""
    corner = 1.3 * math.tan(math.radians(hfov) / 2.0) * math.hypot(1.0, height / width)
    k1 = float(rng.uniform(-0.28, 0.02))
    k2 = float(rng.uniform(0.0, 0.06)) if k1 < -0.1 else 0.0
    while 1.0 + 3.0 * k1 * corner ** 2 + 5.0 * k2 * corner ** 4 < 0.35 or (k2 > 0 and 1.0 + 3.0 * k1 * corner ** 2 < 0.1):
        k1 *= 0.8
        k2 *= 0.8
    return k1, k2


# -- the people ------------------------------------------------------------------------------

def _colour(rng, near=None, spread: float = 0.05) -> tuple:
    if near is not None:
        return tuple(float(c) for c in np.clip(np.asarray(near) + rng.normal(0.0, spread, 3), 0.03, 0.97))
    h, s, v = rng.random(), float(rng.uniform(0.0, 0.85)), float(rng.uniform(0.08, 0.95))
    return colorsys.hsv_to_rgb(h, s, v)


def _random_body(rng, room: Room, others: list) -> BodyShape:
    look = room.look
    height = float(rng.uniform(*STATURE_RANGE))
    build = float(rng.uniform(0.82, 1.3))
    legs = float(rng.uniform(0.95, 1.05))
    r = rng.random()
    if r < 0.2:
        shirt = _colour(rng, look[0:3])                       # close to the walls
    elif r < 0.3:
        shirt = _colour(rng, look[12:15])                     # close to the floor
    elif r < 0.45 and others:
        shirt = _colour(rng, others[-1].shirt, 0.03)          # close to another person's
    else:
        shirt = _colour(rng)
    if rng.random() < 0.15:
        trousers = _colour(rng, look[12:15])
    elif rng.random() < 0.5:
        trousers = _colour(rng, (0.14, 0.20, 0.36), 0.06)     # jeans
    else:
        trousers = _colour(rng)
    long_hair = rng.random() < 0.35
    return BodyShape(
        height=height, build=build, belly=float(np.clip(rng.normal(1.0, 0.1) * build ** 1.5, 0.85, 1.4)),
        skin=_SKIN[int(rng.integers(len(_SKIN)))], hair=_HAIR[int(rng.integers(len(_HAIR)))],
        shirt=tuple(float(c) for c in shirt), trousers=tuple(float(c) for c in trousers),
        shoes=_SHOES[int(rng.integers(len(_SHOES)))], short_sleeves=bool(rng.random() < 0.35),
        stripes=float(rng.choice([0.0, 0.0, 0.0, 0.0, 0.045, 0.06])),
        hair_front=float(rng.uniform(0.35, 0.55)),
        hair_back=float(rng.uniform(-0.85, -0.65) if long_hair else rng.uniform(-0.4, -0.2)),
        legs=legs, arms=float(rng.uniform(0.94, 1.06)), torso=trunk_for_legs(legs))


def _free_point(rng, room: Room, plan: FloorPlan, away=(), min_gap: float = 1.2, clearance: float = 0.5):
    """A random floor point with room to stand and gesture, away from ``away`` points."""
    sx, sy = room.size[0], room.size[1]
    for _ in range(400):
        p = np.array([rng.uniform(0.6, sx - 0.6), rng.uniform(0.6, sy - 0.6)])
        walls = min(p[0], sx - p[0], p[1], sy - p[1])   # the doorway leaves the plan open there
        if (min(walls, plan.clearance_at(p)) >= clearance
                and all(np.hypot(*(p - q)) >= min_gap for q in away)):
            return p
    return None


_TALK = ("explain", "point", "shrug", "wave", "look_around")
_BIG = ("wave", "raise_both", "arms_out", "circle", "reach", "stretch", "bow", "hands_on_hips", "reach_up")


def _script(rng, style: str, room: Room, plan: FloorPlan, starts: list, chairs: list, seconds: float):
    """``(activities, start)`` of one person in ``style`` (start None: comes in through the door)."""
    start = None
    acts: list = []
    if style == "sitter":   # starts a step from the chair, so that the scene sees them sit
        c = room.chairs[chairs[-1]]
        side = np.array([-math.sin(c.yaw), math.cos(c.yaw)]) * (1.0 if rng.random() < 0.5 else -1.0)
        p = np.array([c.x, c.y]) + 0.9 * np.array([math.cos(c.yaw), math.sin(c.yaw)]) + 0.6 * side
        if plan.clearance_at(p) >= 0.45 and all(np.hypot(*(p - q)) >= 1.0 for q in starts):
            start = (float(p[0]), float(p[1]), float(rng.uniform(-PI, PI)))
    if style != "visitor" and start is None:
        p = _free_point(rng, room, plan, starts, clearance=1.0) if style in ("still", "gesturer") else None
        if p is None:
            p = _free_point(rng, room, plan, starts)
        if p is None:
            p = _free_point(rng, room, plan, starts, min_gap=0.8, clearance=0.45)
        if p is None:
            style = "visitor"
        else:
            start = (float(p[0]), float(p[1]), float(rng.uniform(-PI, PI)))

    def goal(roomy: bool = False):
        """A place to walk to; ``roomy``: with room around for the arms and a crouch
        (a gesture without room is skipped by the choreographer)."""
        q = _free_point(rng, room, plan, min_gap=0.0, clearance=1.0) if roomy else None
        if q is None:
            q = _free_point(rng, room, plan, min_gap=0.0, clearance=0.45)
        return None if q is None else (float(q[0]), float(q[1]))

    def gesture(names):
        return Gesture(str(names[int(rng.integers(len(names)))]))

    budget = seconds + 4.0
    t = 0.0
    if style == "visitor":
        g = goal()
        acts.append(Enter(g, after=float(rng.uniform(0.0, 0.4 * seconds))))
        t += 4.0
    elif style == "sitter":
        c = int(chairs.pop())
        acts.append(Sit(c, float(rng.uniform(4.0, 0.8 * seconds)), talk=bool(rng.random() < 0.8)))
        t += 12.0
    while t < budget:
        if style in ("walker", "visitor", "sitter"):
            gesturing = rng.random() < 0.4
            g = goal(roomy=gesturing)
            if g is not None:
                acts.append(Walk(g))
            acts.append(Stand(float(rng.uniform(0.3, 2.0))))
            if gesturing:
                acts.append(gesture(_TALK + _BIG))
            t += 5.0
        elif style == "still":
            acts.append(Stand(float(rng.uniform(3.0, 7.0))))
            if rng.random() < 0.5:
                acts.append(gesture(_TALK + ("reach_up",)))
            t += 6.0
        elif style == "gesturer":
            acts += [gesture(_BIG + _TALK), Turn(float(rng.uniform(-PI, PI)))]
            t += 3.5
        else:   # worker: walk somewhere, crouch, bend down, reach up
            g = goal(roomy=True)
            if g is not None:
                acts.append(Walk(g))
            acts.append(gesture(("crouch", "bend_down", "reach_up", "crouch")))
            acts.append(Stand(float(rng.uniform(0.3, 1.5))))
            t += 7.0
    if style == "visitor" and rng.random() < 0.6:
        acts.append(Leave())
    return acts, start
