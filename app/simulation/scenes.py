"""The scene registry: which room, which people, what they do (:data:`SCENES`).

A scene names a furnished room layout (:mod:`app.simulation.room`) and a script per
person (:mod:`app.simulation.motion` activities). The seed draws each person's body
and clothes, walking speed and idle-motion quirks, the random goals of wandering
people and the details of sitting talk; :func:`build_actors` turns a scene and a seed
into :class:`~app.simulation.poses.Actor` objects whose tracks are collision-free.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from app.errors import InputError
from app.simulation.body import BodyShape, random_shape
from app.simulation.motion import Choreographer, Enter, Gesture, Leave, Sit, Stand, Turn, Walk, Wander
from app.simulation.poses import Actor
from app.simulation.room import Room, make_room

__all__ = ["Scene", "PersonSpec", "SCENES", "get_scene", "build_actors"]

PI = math.pi


@dataclass(frozen=True)
class PersonSpec:
    """One person of a scene: script, start ``(x, y, yaw)`` (unless it enters), whether
    the script repeats, and an optional fixed stature or a whole body (random scenes)."""

    script: tuple
    start: tuple | None = None
    repeat: bool = False
    height: float | None = None
    shape: BodyShape | None = None


@dataclass(frozen=True)
class Scene:
    name: str
    description: str
    layout: str
    seconds: float                  # natural length of the script
    people: tuple = field(default_factory=tuple)
    empty_room_shot: bool = True    # write background/ images (the empty room); False: the room is never empty


_LOOP = (4.1, 0.6), (4.57, 2.2), (4.2, 3.6), (0.85, 3.45), (0.8, 0.75)

SCENES: dict[str, Scene] = {
    "walk1": Scene(
        "walk1", "1 person walking around the meeting table, turning and pausing",
        "meeting", 25.0,
        (PersonSpec((Walk(_LOOP[4], via=_LOOP[:4]), Stand(0.8), Turn(PI / 2),
                     Walk(_LOOP[0], via=(_LOOP[3], _LOOP[2], _LOOP[1])), Stand(1.0), Turn(PI)),
                    start=(0.8, 0.75, 0.0), repeat=True),),
    ),
    "gesture1": Scene(
        "gesture1", "1 person standing in the open, turning, with big arm gestures",
        "meeting", 30.0,
        (PersonSpec((Gesture("wave"), Turn(PI / 2), Gesture("arms_out"), Turn(0.0), Gesture("raise_both"),
                     Turn(-PI / 2), Gesture("circle"), Turn(PI), Gesture("point"), Gesture("explain"),
                     Turn(0.75 * PI), Gesture("reach"), Gesture("stretch"), Turn(PI / 4), Gesture("bow"),
                     Gesture("shrug"), Turn(-0.75 * PI), Gesture("hands_on_hips"), Gesture("look_around"),
                     Turn(PI)),
                    start=(3.75, 1.12, PI), repeat=True),),
    ),
    "meeting3": Scene(
        "meeting3", "3 people: one enters and sits at the table, two walk, cross and gesture, one leaves",
        "meeting", 40.0,
        (
            PersonSpec((Enter((1.0, 2.3)), Sit(4, 14.0, side=1), Walk((1.0, 1.9)), Turn(0.0),
                        Gesture("explain"), Stand(2.0))),
            PersonSpec((Walk((0.9, 3.1)), Turn(0.0), Gesture("explain"), Walk((3.75, 1.12)), Turn(PI / 2),
                        Gesture("raise_both"), Walk((4.45, 3.3)), Stand(1.0)),
                       start=(4.4, 3.45, PI)),
            PersonSpec((Gesture("point"), Walk((0.9, 1.3)), Turn(PI / 2), Gesture("wave"), Walk((0.9, 2.9)),
                        Stand(1.0), Leave()),
                       start=(3.8, 1.05, PI)),
        ),
    ),
    "crowd6": Scene(
        "crowd6", "6 people wandering, pausing and gesturing around the table (load test)",
        "meeting", 30.0,
        (
            PersonSpec((Wander(None),), start=(1.0, 0.6, 0.0)),
            PersonSpec((Wander(None),), start=(4.0, 0.6, PI)),
            PersonSpec((Wander(None),), start=(0.9, 2.6, -PI / 2)),
            PersonSpec((Wander(None),), start=(4.5, 3.2, PI)),
            PersonSpec((Wander(None),), start=(3.6, 1.2, PI / 2)),
            PersonSpec((Enter((0.9, 2.0), after=3.0), Wander(None))),
        ),
    ),
    "still2": Scene(
        "still2", "2 people, never out of the room: one stands still for 4 s, then walks off; the other walks "
                  "around the table (no empty-room images: the background must be estimated with people in it)",
        "meeting", 14.0,
        (
            PersonSpec((Stand(4.0), Walk((4.3, 3.2)), Turn(PI), Stand(1.0), Walk((3.6, 0.8)), Stand(1.0)),
                       start=(1.3, 3.2, -PI / 4)),
            PersonSpec((Walk(_LOOP[1], via=(_LOOP[0],)), Walk(_LOOP[4], via=(_LOOP[2], _LOOP[3])), Stand(0.5),
                        Walk(_LOOP[1], via=(_LOOP[0],))),
                       start=(1.2, 0.7, 0.0), repeat=True),
        ),
        empty_room_shot=False,
    ),
    "enter2": Scene(
        "enter2", "the room empty at first; 2 people come in through the door one after the other, wave and "
                  "raise their arms (short: the live viewer's test, exports of people who appear at different times)",
        "meeting", 6.0,
        (
            PersonSpec((Walk((2.3, 2.5)), Turn(-PI / 2), Gesture("wave"), Stand(3.0)), start=(-0.5, 3.35, 0.0)),
            PersonSpec((Stand(0.6), Walk((1.5, 1.5)), Turn(0.0), Gesture("raise_both"), Stand(3.0)),
                       start=(-1.3, 3.35, 0.0)),
        ),
    ),
    "statures3": Scene(
        "statures3", "3 people of 1.50, 1.95 and 1.62 m: the shortest gestures in place and never walks, the "
                     "tallest walks along the wall and crouches, the third walks to the table and sits down "
                     "(issue 22's people the fixed thresholds missed)",
        "meeting", 10.0,
        (
            PersonSpec((Gesture("wave"), Gesture("raise_both"), Gesture("explain"), Gesture("point")),
                       start=(3.75, 1.0, PI), repeat=True, height=1.50),
            PersonSpec((Walk((0.9, 3.0)), Turn(0.0), Gesture("crouch"), Walk((0.9, 1.0)), Stand(1.0)),
                       start=(0.9, 0.8, PI / 2), repeat=True, height=1.95),
            PersonSpec((Sit(4, 12.0),), start=(4.6, 3.2, PI), height=1.62),
        ),
    ),
    "occluded1": Scene(
        "occluded1", "1 person walking along the aisle between two tables (legs hidden from most views)",
        "two_tables", 20.0,
        (PersonSpec((Walk((4.35, 2.0)), Stand(0.8), Turn(PI), Walk((2.5, 2.0)), Stand(1.5), Turn(PI / 2),
                     Gesture("look_around"), Turn(PI), Walk((0.7, 2.0)), Stand(0.8), Turn(0.0)),
                    start=(0.7, 2.0, 0.0), repeat=True),),
    ),
}


def get_scene(name: str) -> Scene:
    """The scene of a name; :class:`~app.errors.InputError` if there is none."""
    try:
        return SCENES[name]
    except KeyError:
        raise InputError(f"unknown scene {name!r} (have {', '.join(SCENES)})") from None


def build_actors(scene: Scene, seed: int, horizon: float, room: Room | None = None):
    """The scene's people for a seed, choreographed up to ``horizon`` seconds.

    Returns ``(room, actors, conflicts)``; ``conflicts`` lists any situation the
    choreographer could not make collision-free (empty for the built-in scenes).
    """
    room = room or make_room(scene.layout)
    rng = np.random.default_rng(seed)
    shapes = [spec.shape if spec.shape is not None else random_shape(rng, spec.height) for spec in scene.people]
    speeds = [float(rng.uniform(1.0, 1.3)) for _ in scene.people]
    quirks = [rng.uniform(0.0, 2 * PI, 8) for _ in scene.people]
    plan_rng = np.random.default_rng([seed, 1])
    choreo = Choreographer(room, horizon, plan_rng)
    for k, spec in enumerate(scene.people):
        choreo.add_person(spec.script, start=spec.start, speed=speeds[k], name=f"person {k + 1}",
                          repeat=spec.repeat, height=shapes[k].height, build=shapes[k].build)
    tracks = choreo.run()
    actors = [Actor(k + 1, shapes[k], tracks[k], room.chairs, quirks[k]) for k in range(len(tracks))]
    return room, actors, list(choreo.conflicts)
