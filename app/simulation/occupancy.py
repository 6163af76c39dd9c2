"""True body shapes and true voxel occupancy of a simulated recording.

Reconstruction (shape from silhouette, §2.2.4) is scored against the space the bodies
really fill. A simulated recording therefore carries the bodies themselves, so they can
be voxelised at any voxel size:

``bodies.jsonl`` (optional file of a recording): one JSON object per frame, in order::

    {"frame": i, "t": s, "people": [
      {"id": 3, "in_room": true,
       "cones": [[ax, ay, az, bx, by, bz, ra, rb], ...],
       "ellipsoids": [[cx, cy, cz, r00, r01, r02, r10, r11, r12, r20, r21, r22, sx, sy, sz], ...]}]}

A *cone* is a round cone: the convex hull of the spheres ``(a, ra)`` and ``(b, rb)``.
An *ellipsoid* has centre ``c``, rotation ``R`` (row-major; its columns are the local
axes in world coordinates) and semi-axes ``s``: the points with
``|diag(1/s) R^T (p - c)| <= 1``. Metres, world frame, z up. Every rendered person is
listed; ``in_room`` is false for someone seen in the corridor through the door.

``occupancy.npz`` (optional, ``smartroom simulate --occupancy SIZE``): the occupied
voxels of every frame at one voxel size: ``voxel_size``, ``room_min`` (3,), ``dims``
(3,), ``offsets`` (F + 1,) and ``indices`` (N, 3) int16, ``person`` (N,) int16; frame
``i`` owns ``indices[offsets[i]:offsets[i + 1]]``. Voxel ``(i, j, k)`` has its centre at
``room_min + (index + 0.5) * voxel_size`` and is occupied when its centre lies inside a
body.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from numba import njit

from app.errors import InputError
from app.files import read_jsonl
from app.simulation.geometry import CONE, ELLIPSOID, PRIM_WIDTH, inside_primitive, primitive_bounds

__all__ = ["body_record", "load_bodies", "true_occupancy", "record_primitives", "OccupancyWriter",
           "load_occupancy", "grid_dims"]


def _round(rows, decimals=5) -> list:
    return [[round(float(v), decimals) + 0.0 for v in row] for row in rows]


def body_record(index: int, t: float, people: list[dict], in_room) -> dict:
    """The ``bodies.jsonl`` record of a frame from the simulator's people."""
    out = []
    for p in people:
        kinds, rows = p["kinds"], p["rows"]
        out.append({
            "id": int(p["id"]),
            "in_room": bool(in_room(p)),
            "cones": _round(rows[kinds == CONE, :8]),
            "ellipsoids": _round(rows[kinds == ELLIPSOID, :15]),
        })
    return {"frame": int(index), "t": round(float(t), 4), "people": out}


def load_bodies(recording) -> list[dict]:
    """The parsed ``bodies.jsonl`` of a recording folder (one record per frame)."""
    path = Path(recording)
    if path.is_dir():
        path = path / "bodies.jsonl"
    if not path.is_file():
        raise InputError(f"{path}: file not found (record it with smartroom simulate)")
    return read_jsonl(path)


def record_primitives(record: dict, people=None):
    """``(kinds (M,), rows (M, 16), person ids (M,))`` of a ``bodies.jsonl`` record,
    optionally only for the given person ids."""
    kinds, rows, ids = [], [], []
    for p in record.get("people", []):
        if people is not None and p["id"] not in people:
            continue
        for c in p.get("cones", []):
            row = np.zeros(PRIM_WIDTH)
            row[:8] = c
            kinds.append(CONE)
            rows.append(row)
            ids.append(p["id"])
        for e in p.get("ellipsoids", []):
            row = np.zeros(PRIM_WIDTH)
            row[:15] = e
            kinds.append(ELLIPSOID)
            rows.append(row)
            ids.append(p["id"])
    return (np.array(kinds, dtype=np.int64), np.array(rows, dtype=np.float64).reshape(-1, PRIM_WIDTH),
            np.array(ids, dtype=np.int64))


def grid_dims(room_min, room_max, voxel_size: float) -> np.ndarray:
    """Voxel grid dimensions covering the room at a voxel size."""
    return np.ceil((np.asarray(room_max, float) - np.asarray(room_min, float)) / voxel_size - 1e-9).astype(np.int64)


@njit(cache=True, nogil=True)
def _voxelise(kinds, rows, ids, origin, size, dims, grid):
    """Mark into ``grid`` (person id + 1) every voxel whose centre is inside a primitive."""
    lohi = np.empty(6)
    for m in range(rows.shape[0]):
        primitive_bounds(kinds[m], rows[m], lohi)
        i0 = max(0, int(np.floor((lohi[0] - origin[0]) / size - 0.5)))
        j0 = max(0, int(np.floor((lohi[1] - origin[1]) / size - 0.5)))
        k0 = max(0, int(np.floor((lohi[2] - origin[2]) / size - 0.5)))
        i1 = min(dims[0] - 1, int(np.ceil((lohi[3] - origin[0]) / size - 0.5)))
        j1 = min(dims[1] - 1, int(np.ceil((lohi[4] - origin[1]) / size - 0.5)))
        k1 = min(dims[2] - 1, int(np.ceil((lohi[5] - origin[2]) / size - 0.5)))
        for i in range(i0, i1 + 1):
            x = origin[0] + (i + 0.5) * size
            for j in range(j0, j1 + 1):
                y = origin[1] + (j + 0.5) * size
                for k in range(k0, k1 + 1):
                    if grid[i, j, k] != 0:
                        continue
                    z = origin[2] + (k + 0.5) * size
                    if inside_primitive(x, y, z, kinds[m], rows[m], 0.0):
                        grid[i, j, k] = ids[m] + 1


def true_occupancy(record: dict, room_min, voxel_size: float, dims, with_person: bool = False):
    """Indices ``(N, 3)`` (int) of the voxels whose centre lies inside a body in a
    ``bodies.jsonl`` record; voxel ``(i, j, k)`` has its centre at
    ``room_min + (index + 0.5) * voxel_size``. With ``with_person`` also the person id
    of each voxel ``(N,)``."""
    kinds, rows, ids = record_primitives(record)
    dims = np.asarray(dims, dtype=np.int64).reshape(3)
    if len(kinds) == 0:
        empty = np.zeros((0, 3), dtype=np.int64)
        return (empty, np.zeros(0, dtype=np.int64)) if with_person else empty
    grid = np.zeros(tuple(int(d) for d in dims), dtype=np.int32)
    _voxelise(kinds, rows, ids, np.asarray(room_min, dtype=np.float64).reshape(3), float(voxel_size), dims, grid)
    idx = np.argwhere(grid > 0)
    if with_person:
        return idx, grid[idx[:, 0], idx[:, 1], idx[:, 2]].astype(np.int64) - 1
    return idx


class OccupancyWriter:
    """Collects per-frame true occupancy and writes ``occupancy.npz`` on :meth:`close`."""

    def __init__(self, path, calibration, voxel_size: float):
        if not voxel_size > 0:
            raise InputError(f"--occupancy needs a positive voxel size in metres, got {voxel_size!r}")
        self.path = Path(path)
        self.voxel_size = float(voxel_size)
        self.room_min = np.asarray(calibration.room_min, dtype=np.float64)
        self.dims = grid_dims(calibration.room_min, calibration.room_max, voxel_size)
        if np.prod(self.dims) > 2e8:
            raise InputError(f"--occupancy {voxel_size} m makes a grid of {int(np.prod(self.dims))} voxels; "
                             "use 0.01 m or more")
        self.chunks, self.persons, self.offsets = [], [], [0]

    def add(self, record: dict) -> None:
        idx, who = true_occupancy(record, self.room_min, self.voxel_size, self.dims, with_person=True)
        self.chunks.append(idx.astype(np.int16))
        self.persons.append(who.astype(np.int16))
        self.offsets.append(self.offsets[-1] + len(idx))

    def close(self) -> None:
        indices = np.concatenate(self.chunks) if self.chunks else np.zeros((0, 3), np.int16)
        person = np.concatenate(self.persons) if self.persons else np.zeros(0, np.int16)
        with open(self.path, "wb") as fh:
            np.savez_compressed(fh, voxel_size=self.voxel_size, room_min=self.room_min, dims=self.dims,
                                offsets=np.array(self.offsets, dtype=np.int64), indices=indices, person=person)


def load_occupancy(path):
    """``occupancy.npz`` as a dict of arrays plus ``frame(i) -> (indices, person)``."""
    p = Path(path)
    if p.is_dir():
        p = p / "occupancy.npz"
    if not p.is_file():
        raise InputError(f"{p}: file not found (record with smartroom simulate --occupancy SIZE)")
    data = dict(np.load(p))
    off = data["offsets"]

    def frame(i: int):
        return data["indices"][off[i]:off[i + 1]], data["person"][off[i]:off[i + 1]]
    data["frame"] = frame
    return data
