"""The simulated smart room: walls, door, furniture, lights and calibrated cameras.

The default is the thesis's CLEAR smart room (§4.4.1): a 5 x 4 x 2.5 m meeting room
with a table and chairs, four cameras high in the corners looking at the room centre
and an optional zenithal one in the ceiling. Coordinates are metres, z up, the floor
at z = 0, the room from ``[0, 0, 0]`` to ``[5, 4, 2.5]``. A doorway in the wall
``x = 0`` opens onto a corridor, so people can enter and leave.

Everything here is plain data: furniture is a list of oriented boxes (``(B, 8)`` rows
``[cx, cy, cz, hx, hy, hz, yaw, material]``), the walls carry flat decorations
(window, whiteboard, poster) as rectangles, and the ceiling panels are the lights.
:func:`room_cameras` builds the :class:`~calibration.camera.Camera` set (with a little
radial distortion, so a consumer must use the distortion model) and
:func:`room_calibration` the contract's :class:`~calibration.loader.Calibration`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from calibration import Calibration, Camera

__all__ = [
    "Room", "Chair", "LAYOUTS", "make_room", "room_cameras", "room_calibration",
    "MATERIALS", "WALL_X0", "WALL_X1", "WALL_Y0", "WALL_Y1", "room_look", "DEFAULT_LOOK",
    "FLOOR_PLANKS", "FLOOR_TILES", "FLOOR_CARPET",
]

ROOM_SIZE = (5.0, 4.0, 2.5)

# Wall ids (the plane each wall lies in) and decoration kinds.
WALL_X0, WALL_X1, WALL_Y0, WALL_Y1 = 0, 1, 2, 3
DECOR_FLAT, DECOR_WINDOW, DECOR_BOARD, DECOR_POSTER, DECOR_FRAME = 0, 1, 2, 3, 4

#: Furniture materials: name -> (id, albedo RGB 0-1, texture kind 0 plain, 1 wood, 2 fabric).
MATERIALS = {
    "table_top": (0, (0.72, 0.58, 0.42), 1),
    "metal": (1, (0.55, 0.56, 0.58), 0),
    "black": (2, (0.09, 0.09, 0.10), 0),
    "fabric_blue": (3, (0.16, 0.22, 0.42), 2),
    "fabric_red": (4, (0.50, 0.14, 0.12), 2),
    "fabric_grey": (5, (0.30, 0.31, 0.33), 2),
    "cabinet": (6, (0.80, 0.78, 0.74), 1),
    "dark_wood": (7, (0.38, 0.25, 0.16), 1),
}
MATERIAL_ALBEDO = np.array([m[1] for m in sorted(MATERIALS.values())], dtype=np.float64)
MATERIAL_TEXTURE = np.array([m[2] for m in sorted(MATERIALS.values())], dtype=np.int64)

#: Floor kinds of a room's look.
FLOOR_PLANKS, FLOOR_TILES, FLOOR_CARPET = 0, 1, 2


def room_look(walls=((0.86, 0.84, 0.78), (0.66, 0.74, 0.80), (0.87, 0.85, 0.79), (0.84, 0.82, 0.76)),
              floor=(0.58, 0.43, 0.29), floor_kind: int = FLOOR_PLANKS, floor_scale: float = 0.18,
              light=(1.0, 1.0, 1.0), skirting: float = 1.0, exposure: float = 1.0) -> np.ndarray:
    """A room's look as the renderer takes it (``Room.look``, 22 floats): the base colour
    of the walls x = 0, x = max, y = 0, y = max (RGB 0-1, in that order), the floor's
    colour, kind (planks, tiles, carpet) and scale (plank width, tile size, m), the
    lights' colour (RGB multipliers), the skirting boards' brightness and the camera
    exposure (a multiplier). The defaults are the built-in rooms' look."""
    out = np.empty(22, dtype=np.float64)
    out[0:12] = np.asarray(walls, dtype=np.float64).reshape(12)
    out[12:15] = floor
    out[15] = floor_kind
    out[16] = floor_scale
    out[17:20] = light
    out[20] = skirting
    out[21] = exposure
    return out


DEFAULT_LOOK = room_look()


@dataclass(frozen=True)
class Chair:
    """A chair people can sit on: seat centre (x, y), the yaw its sitter faces, seat height."""

    index: int
    x: float
    y: float
    yaw: float
    seat_height: float = 0.46
    seat_half: float = 0.22

    @property
    def forward(self) -> np.ndarray:
        return np.array([math.cos(self.yaw), math.sin(self.yaw)])


@dataclass(frozen=True)
class Room:
    """A furnished room: size, furniture boxes, chairs, door, corridor, decorations, lights."""

    name: str
    size: tuple[float, float, float]
    boxes: np.ndarray                 # (B, 8) furniture boxes
    chairs: tuple[Chair, ...]
    door: tuple[float, float, float]  # in wall x = 0: (y0, y1, height)
    corridor: tuple[float, float, float, float]  # x0, x1, y0, y1 (x1 = 0, the wall)
    decor: np.ndarray                 # (D, 9) wall, u0, u1, z0, z1, kind, r, g, b
    lights: np.ndarray                # (L, 5) x, y, z, power, panel size
    description: str = ""
    spots: dict = field(default_factory=dict)  # named free standing spots (x, y)
    look: np.ndarray = field(default_factory=lambda: DEFAULT_LOOK.copy())   # colours and light (room_look)

    @property
    def room_min(self) -> np.ndarray:
        return np.zeros(3)

    @property
    def room_max(self) -> np.ndarray:
        return np.array(self.size, dtype=np.float64)

    @property
    def door_inside(self) -> np.ndarray:
        """A point just inside the doorway."""
        y0, y1, _ = self.door
        return np.array([0.45, 0.5 * (y0 + y1)])

    @property
    def door_outside(self) -> np.ndarray:
        """Where people wait, out of sight, before entering and after leaving."""
        x0, _, _, y1 = self.corridor
        return np.array([0.5 * x0, y1 - 0.45])

    def inside(self, xy) -> bool:
        x, y = float(xy[0]), float(xy[1])
        return 0.0 <= x <= self.size[0] and 0.0 <= y <= self.size[1]


def _box(cx, cy, cz, hx, hy, hz, yaw, material) -> list:
    return [cx, cy, cz, hx, hy, hz, yaw, float(MATERIALS[material][0])]


def table_boxes(cx, cy, length, width, height=0.74, top="table_top", yaw=0.0) -> list:
    """A table: a 3 cm top and four 5 cm square metal legs."""
    c, s = math.cos(yaw), math.sin(yaw)
    out = [_box(cx, cy, height - 0.015, length / 2, width / 2, 0.015, yaw, top)]
    lx, ly = length / 2 - 0.08, width / 2 - 0.08
    for sx in (-1, 1):
        for sy in (-1, 1):
            dx, dy = sx * lx, sy * ly
            out.append(_box(cx + c * dx - s * dy, cy + s * dx + c * dy, (height - 0.03) / 2,
                            0.025, 0.025, (height - 0.03) / 2, yaw, "metal"))
    return out


def chair_boxes(x, y, yaw, fabric="fabric_blue", seat_height=0.46, half=0.22) -> list:
    """A chair facing ``yaw``: seat, backrest, two back posts and four legs."""
    c, s = math.cos(yaw), math.sin(yaw)

    def at(fx, ly):  # chair frame (forward, left) -> world xy
        return x + c * fx - s * ly, y + s * fx + c * ly

    out = [_box(x, y, seat_height - 0.03, half, half, 0.03, yaw, fabric)]
    bx, by = at(-half + 0.02, 0.0)
    out.append(_box(bx, by, seat_height + 0.26, 0.02, half - 0.01, 0.17, yaw, fabric))
    for ly in (-half + 0.02, half - 0.02):
        px, py = at(-half + 0.02, ly)
        out.append(_box(px, py, seat_height + 0.06, 0.015, 0.015, 0.06, yaw, "black"))
        for fx in (-half + 0.03, half - 0.03):
            lx_, ly_ = at(fx, ly * 0.95)
            out.append(_box(lx_, ly_, (seat_height - 0.06) / 2, 0.013, 0.013,
                            (seat_height - 0.06) / 2, yaw, "black"))
    return out


def _decor_common() -> list:
    """Wall decorations shared by every layout: window, whiteboard, poster, clock, switch."""
    return [
        # wall, u0, u1, z0, z1, kind, r, g, b
        [WALL_Y0, 1.0, 4.0, 0.90, 2.15, DECOR_WINDOW, 0.80, 0.86, 0.93],
        [WALL_Y1, 1.05, 2.95, 0.90, 2.00, DECOR_BOARD, 0.94, 0.94, 0.93],
        [WALL_X1, 1.25, 2.05, 1.15, 1.95, DECOR_POSTER, 0.20, 0.45, 0.60],
        [WALL_X0, 1.95, 2.27, 1.95, 2.27, DECOR_FLAT, 0.95, 0.95, 0.95],  # clock
        [WALL_X0, 2.72, 2.80, 1.05, 1.15, DECOR_FLAT, 0.92, 0.92, 0.90],  # light switch
        [WALL_X1, 2.70, 3.50, 0.12, 0.55, DECOR_FLAT, 0.83, 0.83, 0.83],  # radiator
    ]


def _lights() -> np.ndarray:
    rows = []
    for x in (1.0, 2.5, 4.0):
        for y in (1.2, 2.8):
            rows.append([x, y, 2.49, 1.45, 0.6])
    return np.array(rows, dtype=np.float64)


def _meeting_room() -> Room:
    ty = 2.17
    boxes = table_boxes(2.3, ty, 1.6, 0.9)
    chairs = []
    fabrics = ["fabric_blue", "fabric_blue", "fabric_red", "fabric_blue", "fabric_grey"]
    placements = [(1.9, ty - 0.8, math.pi / 2), (2.7, ty - 0.8, math.pi / 2),
                  (1.9, ty + 0.8, -math.pi / 2), (2.7, ty + 0.8, -math.pi / 2),
                  (3.95, ty, math.pi)]  # the last one pulled out at the table's end
    for i, (x, y, yaw) in enumerate(placements):
        boxes += chair_boxes(x, y, yaw, fabrics[i])
        chairs.append(Chair(i, x, y, yaw))
    # a low cabinet (sideboard) against the wall x = 5
    boxes.append(_box(4.775, 0.8, 0.43, 0.22, 0.45, 0.43, 0.0, "cabinet"))
    decor = _decor_common()
    return Room(
        name="meeting",
        size=ROOM_SIZE,
        boxes=np.array(boxes, dtype=np.float64),
        chairs=tuple(chairs),
        door=(2.90, 3.80, 2.05),
        corridor=(-1.6, 0.0, 1.2, 5.6),
        decor=np.array(decor, dtype=np.float64),
        lights=_lights(),
        description="5x4 m meeting room: table, five chairs, sideboard, door to a corridor",
        spots={"stage": (3.75, 1.12), "west": (0.9, 2.2), "board": (1.4, 3.55),
               "south": (1.2, 0.55), "east": (4.45, 1.75), "north_east": (4.5, 3.35)},
    )


def _two_tables_room() -> Room:
    # two workbenches (0.92 m high, like a lab's) with a 0.84 m aisle between them
    boxes = (table_boxes(2.5, 1.18, 2.4, 0.8, height=0.92)
             + table_boxes(2.5, 2.82, 2.4, 0.8, height=0.92))
    chairs = []
    placements = [(1.9, 0.42, math.pi / 2), (3.1, 0.42, math.pi / 2),
                  (1.9, 3.58, -math.pi / 2), (3.1, 3.58, -math.pi / 2)]
    for i, (x, y, yaw) in enumerate(placements):
        boxes += chair_boxes(x, y, yaw, "fabric_grey" if i % 2 else "fabric_blue", seat_height=0.62)
        chairs.append(Chair(i, x, y, yaw, seat_height=0.62))
    decor = _decor_common()
    return Room(
        name="two_tables",
        size=ROOM_SIZE,
        boxes=np.array(boxes, dtype=np.float64),
        chairs=tuple(chairs),
        door=(2.90, 3.80, 2.05),
        corridor=(-1.6, 0.0, 1.2, 5.6),
        decor=np.array(decor, dtype=np.float64),
        lights=_lights(),
        description="5x4 m room with two workbenches and an aisle between them",
        spots={"aisle_west": (0.75, 2.0), "aisle_east": (4.3, 2.0)},
    )


LAYOUTS = {"meeting": _meeting_room, "two_tables": _two_tables_room}


def make_room(layout: str = "meeting") -> Room:
    """The furnished room of a layout name (see :data:`LAYOUTS`)."""
    return LAYOUTS[layout]()


# -- cameras -------------------------------------------------------------------------

# Corner cameras: (name, corner xy, hfov, k1, k2, p1, p2, principal point offset px)
_CORNERS = (
    ("cam0", (0.15, 0.15), 72.0, -0.09, 0.015, 0.0004, -0.0003, (3.0, -2.0)),
    ("cam1", (4.85, 0.15), 73.0, -0.11, 0.020, -0.0002, 0.0004, (-4.0, 2.5)),
    ("cam2", (4.85, 3.85), 71.5, -0.08, 0.012, 0.0003, 0.0002, (2.0, 3.0)),
    ("cam3", (0.15, 3.85), 72.5, -0.12, 0.022, -0.0004, -0.0002, (-2.5, -3.5)),
)
CAMERA_HEIGHT = 2.40
ZENITHAL_HEIGHT = 2.45


def _with_intrinsics(cam: Camera, dist, offset, aspect=1.0015) -> Camera:
    K = cam.K.copy()
    K[0, 2] += offset[0] * cam.width / 640.0
    K[1, 2] += offset[1] * cam.height / 480.0
    K[1, 1] *= aspect
    return Camera(cam.name, cam.width, cam.height, K, np.asarray(dist, dtype=np.float64), cam.R, cam.t)


def room_cameras(width: int = 640, height: int = 480, zenithal: bool = False,
                 size=ROOM_SIZE) -> tuple[Camera, ...]:
    """The four corner cameras (and the zenithal one), ``width x height`` pixels."""
    cams = []
    target = (size[0] / 2, size[1] / 2, 0.85)
    for name, (x, y), hfov, k1, k2, p1, p2, off in _CORNERS:
        cx = x if x < size[0] / 2 else size[0] - (ROOM_SIZE[0] - x)
        cy = y if y < size[1] / 2 else size[1] - (ROOM_SIZE[1] - y)
        cam = Camera.look_at(name, (cx, cy, CAMERA_HEIGHT), target, width, height, hfov)
        cams.append(_with_intrinsics(cam, (k1, k2, p1, p2, 0.0), off))
    if zenithal:
        cam = Camera.look_at("cam4", (size[0] / 2, size[1] / 2, ZENITHAL_HEIGHT),
                             (size[0] / 2, size[1] / 2, 0.0), width, height, 98.0, up=(0.0, 1.0, 0.0))
        cams.append(_with_intrinsics(cam, (-0.05, 0.004, 0.0, 0.0, 0.0), (1.5, -1.0), aspect=1.0))
    return tuple(cams)


def room_calibration(room: Room | None = None, fps: float = 25.0, width: int = 640, height: int = 480,
                     zenithal: bool = False) -> Calibration:
    """The contract's calibration of the simulated room (room bounds = the room)."""
    size = room.size if room is not None else ROOM_SIZE
    return Calibration(float(fps), np.zeros(3), np.array(size, dtype=np.float64),
                       room_cameras(width, height, zenithal, size))
