"""Every message that travels on the bus, and its encoding.

Wire format (version 1), little-endian::

    fixed header  <3sBBBHqddI  magic b"SRM", version, type id, flags, array count,
                               frame index, capture stamp (wall clock, s),
                               recording time t (s), meta length
    meta          UTF-8 JSON: {"m": {scalar fields}, "a": [[dtype, shape], ...]}
    buffers       one per array, each starting on an 8-byte boundary

Decoding maps the buffers with ``np.frombuffer`` (no copy: the arrays are read-only
views of the payload). A malformed or truncated payload raises :class:`MessageError`,
which the worker base counts and skips.
"""
from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field, fields
from typing import ClassVar

import numpy as np

__all__ = [
    "MessageError", "Message", "Frame", "Mask", "Voxels", "Tracks", "Poses", "Stats",
    "EndOfStream", "Ack", "encode", "decode", "JOINTS",
]

MAGIC = b"SRM"
VERSION = 1
_HEADER = struct.Struct("<3sBBBHqddI")
_ALIGN = 8
_DTYPES = {np.dtype(d).str for d in ("u1", "i1", "u2", "i2", "u4", "i4", "u8", "i8", "f4", "f8", "?")}
_MAX_META = 1 << 20

#: The contract's 15 joint names, in the order used by every array of joints.
JOINTS = (
    "pelvis", "neck", "head",
    "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow", "r_wrist",
    "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle",
)


class MessageError(ValueError):
    """A payload that is not a valid message of this protocol version."""


_REGISTRY: dict[int, type["Message"]] = {}


@dataclass(kw_only=True)
class Message:
    """Base of all messages: the frame index and times every stage keeps (DESIGN §3).

    ``stamp`` is the wall-clock capture time (latency is measured from it), ``t`` the
    recording time in seconds (what result files report).
    """

    TYPE_ID: ClassVar[int] = 0
    ARRAYS: ClassVar[tuple[str, ...]] = ()

    frame: int = -1
    stamp: float = 0.0
    t: float = 0.0

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if cls.TYPE_ID in _REGISTRY:
            raise TypeError(f"message type id {cls.TYPE_ID} used twice")
        _REGISTRY[cls.TYPE_ID] = cls

    def to_bytes(self) -> bytes:
        return encode(self)


def _meta_fields(cls) -> list[str]:
    skip = {"frame", "stamp", "t", *cls.ARRAYS}
    return [f.name for f in fields(cls) if f.name not in skip]


def encode(msg: Message) -> bytes:
    """Serialise a message: small header + meta JSON + raw, aligned array buffers."""
    cls = type(msg)
    arrays = []
    for name in cls.ARRAYS:
        a = getattr(msg, name)
        a = np.zeros(0, np.uint8) if a is None else np.ascontiguousarray(a)
        if a.dtype.str not in _DTYPES:
            raise MessageError(f"{cls.__name__}.{name}: dtype {a.dtype} cannot travel")
        arrays.append(a)
    meta = {"m": {k: getattr(msg, k) for k in _meta_fields(cls)},
            "a": [[a.dtype.str, list(a.shape)] for a in arrays]}
    meta_bytes = json.dumps(meta, separators=(",", ":")).encode()
    head = _HEADER.pack(MAGIC, VERSION, cls.TYPE_ID, 0, len(arrays), int(msg.frame),
                        float(msg.stamp), float(msg.t), len(meta_bytes))
    parts = [head, meta_bytes]
    size = len(head) + len(meta_bytes)
    for a in arrays:
        pad = -size % _ALIGN
        if pad:
            parts.append(b"\0" * pad)
            size += pad
        parts.append(memoryview(a).cast("B") if a.size else b"")
        size += a.nbytes
    return b"".join(parts)


def decode(payload) -> Message:
    """Parse bytes (or any buffer) into its message; arrays are read-only views."""
    buf = memoryview(payload).cast("B") if not isinstance(payload, bytes) else payload
    n = len(buf)
    if n < _HEADER.size:
        raise MessageError(f"payload of {n} bytes is shorter than the {_HEADER.size}-byte header")
    magic, version, type_id, _flags, n_arrays, frame, stamp, t, meta_len = _HEADER.unpack_from(buf, 0)
    if magic != MAGIC:
        raise MessageError("payload does not start with the smartroom magic")
    if version != VERSION:
        raise MessageError(f"message version {version} is not supported (this build reads {VERSION})")
    cls = _REGISTRY.get(type_id)
    if cls is None:
        raise MessageError(f"unknown message type {type_id}")
    end = _HEADER.size + meta_len
    if meta_len > _MAX_META or end > n:
        raise MessageError(f"{cls.__name__}: truncated meta ({meta_len} bytes announced, {n - _HEADER.size} present)")
    try:
        meta = json.loads(bytes(buf[_HEADER.size:end]))
        values, descs = meta["m"], meta["a"]
        if not isinstance(values, dict) or not isinstance(descs, list):
            raise TypeError
    except (ValueError, KeyError, TypeError):
        raise MessageError(f"{cls.__name__}: meta is not valid JSON of the expected shape") from None
    if len(descs) != n_arrays or n_arrays != len(cls.ARRAYS):
        raise MessageError(f"{cls.__name__}: expected {len(cls.ARRAYS)} arrays, payload has {n_arrays}")
    kwargs = {"frame": frame, "stamp": stamp, "t": t}
    offset = end
    for name, desc in zip(cls.ARRAYS, descs):
        try:
            dtype_str, shape = desc
            dtype = np.dtype(dtype_str)
            shape = tuple(int(s) for s in shape)
        except (TypeError, ValueError):
            raise MessageError(f"{cls.__name__}.{name}: bad array descriptor") from None
        if dtype.str not in _DTYPES or any(s < 0 for s in shape) or len(shape) > 8:
            raise MessageError(f"{cls.__name__}.{name}: bad array descriptor {desc}")
        offset += -offset % _ALIGN
        count = int(np.prod(shape, dtype=np.int64))
        nbytes = count * dtype.itemsize
        if offset + nbytes > n:
            raise MessageError(f"{cls.__name__}.{name}: truncated ({nbytes} bytes announced, {max(0, n - offset)} present)")
        arr = np.frombuffer(buf, dtype=dtype, count=count, offset=offset).reshape(shape)
        kwargs[name] = arr
        offset += nbytes
    if offset != n:
        raise MessageError(f"{cls.__name__}: {n - offset} unexpected trailing bytes")
    expected = _meta_fields(cls)
    unknown = set(values) - set(expected)
    if unknown:
        raise MessageError(f"{cls.__name__}: unknown fields {sorted(unknown)}")
    kwargs.update(values)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise MessageError(f"{cls.__name__}: {exc}") from None


# -- message types ----------------------------------------------------------------

@dataclass(kw_only=True)
class Frame(Message):
    """One camera image as grabbed (H, W, 3) uint8, BGR."""

    TYPE_ID: ClassVar[int] = 1
    ARRAYS: ClassVar[tuple[str, ...]] = ("image",)
    camera: str = ""
    image: np.ndarray = None


@dataclass(kw_only=True)
class Mask(Message):
    """Foreground mask of one camera, bit-packed along rows (``np.packbits(axis=1)``).

    ``colour`` is the camera image for voxel colouring, possibly downscaled by
    ``colour_scale`` (1 = full size); an empty array when not sent.
    """

    TYPE_ID: ClassVar[int] = 2
    ARRAYS: ClassVar[tuple[str, ...]] = ("bits", "colour")
    camera: str = ""
    width: int = 0
    height: int = 0
    colour_scale: int = 1
    bits: np.ndarray = None
    colour: np.ndarray = None

    @classmethod
    def pack(cls, mask: np.ndarray, **kw) -> "Mask":
        h, w = mask.shape
        return cls(width=w, height=h, bits=np.packbits(mask.astype(bool), axis=1), **kw)

    def unpack(self) -> np.ndarray:
        """The boolean (H, W) mask."""
        if self.bits.shape != (self.height, (self.width + 7) // 8):
            raise MessageError(f"Mask: bits shape {self.bits.shape} does not fit {self.width}x{self.height}")
        return np.unpackbits(self.bits, axis=1, count=self.width).view(bool)


@dataclass(kw_only=True)
class Voxels(Message):
    """Occupied voxels of one frame (§2.2.4): grid indices (N, 3), colours (N, 3) RGB uint8
    (empty when not coloured) and the surface flag (N,) (``V^S``; empty when not computed).

    Voxel ``(i, j, k)`` has its centre at ``origin + (index + 0.5) * voxel_size``.
    """

    TYPE_ID: ClassVar[int] = 3
    ARRAYS: ClassVar[tuple[str, ...]] = ("indices", "colours", "surface")
    voxel_size: float = 0.0
    origin: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    dims: list = field(default_factory=lambda: [0, 0, 0])
    cameras: list = field(default_factory=list)
    indices: np.ndarray = None
    colours: np.ndarray = None
    surface: np.ndarray = None

    def centres(self) -> np.ndarray:
        """World coordinates of the voxel centres (N, 3)."""
        return np.asarray(self.origin) + (self.indices.astype(np.float64) + 0.5) * self.voxel_size


@dataclass(kw_only=True)
class Tracks(Message):
    """Tracked people of one frame: ids (N,) and centroid positions (N, 3)."""

    TYPE_ID: ClassVar[int] = 4
    ARRAYS: ClassVar[tuple[str, ...]] = ("ids", "positions")
    ids: np.ndarray = None
    positions: np.ndarray = None


@dataclass(kw_only=True)
class Poses(Message):
    """Body poses of one frame: track ids (N,), joints (N, 15, 3) in :data:`JOINTS`
    order and the active flag of each joint (N, 15)."""

    TYPE_ID: ClassVar[int] = 5
    ARRAYS: ClassVar[tuple[str, ...]] = ("tracks", "joints", "active")
    tracks: np.ndarray = None
    joints: np.ndarray = None
    active: np.ndarray = None


@dataclass(kw_only=True)
class Stats(Message):
    """A worker's figures, published once a second and once more when it ends."""

    TYPE_ID: ClassVar[int] = 6
    worker: str = ""
    stage: str = ""
    final: bool = False
    figures: dict = field(default_factory=dict)


@dataclass(kw_only=True)
class EndOfStream(Message):
    """A worker has handled its last frame. ``frames`` is how many frames the source
    produced (indices ``first .. first+frames-1``), ``fps`` its rate, and ``figures``
    the worker's final stats (one message, so no consumer sees one without the other)."""

    TYPE_ID: ClassVar[int] = 7
    worker: str = ""
    stage: str = ""
    frames: int = 0
    first: int = 0
    fps: float = 0.0
    figures: dict = field(default_factory=dict)


@dataclass(kw_only=True)
class Ack(Message):
    """A stage has handled frame ``frame`` (flow control of an unpaced source)."""

    TYPE_ID: ClassVar[int] = 8
    worker: str = ""
