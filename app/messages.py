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
import math
import struct
from dataclasses import dataclass, field, fields
from typing import ClassVar

import numpy as np

__all__ = [
    "MessageError", "Message", "Frame", "Mask", "Voxels", "Tracks", "Poses", "Stats",
    "EndOfStream", "Ack", "encode", "decode", "JOINTS", "Blobs", "Keypoints", "Markers", "Heartbeat",
]

MAGIC = b"SRM"
VERSION = 2   # 2: Voxels carry per-voxel camera misses
_HEADER = struct.Struct("<3sBBBHqddI")
_ALIGN = 8
_DTYPES = {np.dtype(d).str for d in ("u1", "i1", "u2", "i2", "u4", "i4", "u8", "i8", "f4", "f8", "?")}
_MAX_META = 1 << 20
_MAX_NAME = 64          # camera and worker names
_MAX_SIDE = 16384       # image and mask sides (pixels)
_MAX_VOXELS = 1 << 27   # grid cells of one voxel grid
MAX_GRID_CELLS = _MAX_VOXELS   # (the reconstruction refuses a room whose grid would be larger)

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
    #: how many of the last ``ARRAYS`` were added after the type first travelled: a payload
    #: of an older build without them decodes with them empty
    ADDED_ARRAYS: ClassVar[int] = 0

    frame: int = -1
    stamp: float = 0.0
    t: float = 0.0
    #: which run of the source the frame numbers belong to: a source that restarts
    #: starts a new, larger epoch and downstream stages follow it (DESIGN §5)
    epoch: int = 0

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if cls.TYPE_ID in _REGISTRY:
            raise TypeError(f"message type id {cls.TYPE_ID} used twice")
        _REGISTRY[cls.TYPE_ID] = cls

    def to_bytes(self) -> bytes:
        return encode(self)

    def validate(self) -> None:
        """Check what a decoded message says before a worker uses it (any process may
        publish on the bus): raises :class:`MessageError` naming the first problem.
        Subclasses extend it with their own fields and array shapes."""
        _int(self, "frame", -1)
        _int(self, "epoch", 0)
        for name in ("stamp", "t"):
            v = getattr(self, name)
            if not isinstance(v, float) or not math.isfinite(v):
                raise MessageError(f"{type(self).__name__}: {name} is not a finite number")


def _int(msg, name: str, lo: int = 0, hi: int = 1 << 62) -> int:
    v = getattr(msg, name)
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise MessageError(f"{type(msg).__name__}: {name} {v!r} is not an integer in {lo}..{hi}")
    return v


def _name(msg, field_name: str, value=None) -> str:
    v = getattr(msg, field_name) if value is None else value
    if not isinstance(v, str) or not v or len(v) > _MAX_NAME or any(c in v for c in "/*$?# "):
        raise MessageError(f"{type(msg).__name__}: {field_name} {str(v)[:40]!r} is not a plain name")
    return v


def _names(msg, field_name: str) -> list:
    v = getattr(msg, field_name)
    if not isinstance(v, list) or len(v) > 256:
        raise MessageError(f"{type(msg).__name__}: {field_name} is not a list of names")
    for x in v:
        _name(msg, field_name, x)
    return v


def _array(msg, name: str, dtypes: str, shape: tuple, allow_empty: bool = False):
    """Check an array's dtype kind(s) and shape (None: any length on that axis)."""
    a = getattr(msg, name)
    cls = type(msg).__name__
    if not isinstance(a, np.ndarray):
        raise MessageError(f"{cls}.{name} is missing")
    if allow_empty and a.size == 0:
        return a
    if a.dtype.str not in dtypes.split():
        raise MessageError(f"{cls}.{name}: dtype {a.dtype} (expected {dtypes})")
    if a.ndim != len(shape) or any(want is not None and have != want for have, want in zip(a.shape, shape)):
        raise MessageError(f"{cls}.{name}: shape {a.shape} (expected {shape})")
    if a.dtype.kind == "f" and a.size and not np.isfinite(a).all():
        raise MessageError(f"{cls}.{name}: not finite")
    return a


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
    if len(descs) != n_arrays or not len(cls.ARRAYS) - cls.ADDED_ARRAYS <= n_arrays <= len(cls.ARRAYS):
        raise MessageError(f"{cls.__name__}: expected {len(cls.ARRAYS)} arrays, payload has {n_arrays}")
    kwargs = {"frame": frame, "stamp": stamp, "t": t}
    kwargs.update({name: np.zeros(0, np.uint8) for name in cls.ARRAYS[n_arrays:]})
    offset = end
    for name, desc in zip(cls.ARRAYS, descs):
        try:
            dtype_str, shape = desc
            if not isinstance(dtype_str, str) or dtype_str not in _DTYPES or not isinstance(shape, list):
                raise TypeError
            dtype = np.dtype(dtype_str)
            if len(shape) > 8 or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape):
                raise TypeError
            shape = tuple(shape)
        except (TypeError, ValueError, OverflowError):
            raise MessageError(f"{cls.__name__}.{name}: bad array descriptor {str(desc)[:80]}") from None
        offset += -offset % _ALIGN
        count = math.prod(shape)          # Python integers: a huge shape cannot overflow
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
    except (TypeError, ValueError, OverflowError) as exc:
        raise MessageError(f"{cls.__name__}: {exc}") from None


def peek_frame(payload) -> int:
    """The frame index of an encoded message, from its header alone."""
    if len(payload) < _HEADER.size or bytes(payload[:3]) != MAGIC:
        raise MessageError("not a smartroom message")
    return _HEADER.unpack_from(payload, 0)[5]


# -- message types ----------------------------------------------------------------

@dataclass(kw_only=True)
class Frame(Message):
    """One camera image as grabbed (H, W, 3) uint8, BGR. ``cameras`` is the frame set:
    every camera the grabber sent for this frame index, so the stages after it know
    which views of the frame to wait for (a camera that failed is not in it)."""

    TYPE_ID: ClassVar[int] = 1
    ARRAYS: ClassVar[tuple[str, ...]] = ("image",)
    camera: str = ""
    cameras: list = field(default_factory=list)
    scale: int = 1    # the image is 1/scale of the camera's calibrated size (the grabber reduced it)
    image: np.ndarray = None

    def validate(self) -> None:
        super().validate()
        _name(self, "camera")
        _names(self, "cameras")
        _int(self, "scale", 1, 16)
        img = _array(self, "image", "|u1", (None, None, 3))
        if not (0 < img.shape[0] <= _MAX_SIDE and 0 < img.shape[1] <= _MAX_SIDE):
            raise MessageError(f"Frame: image of {img.shape[1]}x{img.shape[0]} pixels")


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
    cameras: list = field(default_factory=list)   # the frame set (see Frame)
    bits: np.ndarray = None
    colour: np.ndarray = None

    def validate(self) -> None:
        super().validate()
        _name(self, "camera")
        _names(self, "cameras")
        _int(self, "width", 1, _MAX_SIDE)
        _int(self, "height", 1, _MAX_SIDE)
        _int(self, "colour_scale", 1, 64)
        _array(self, "bits", "|u1", (self.height, (self.width + 7) // 8))
        _array(self, "colour", "|u1", (None, None, 3), allow_empty=True)

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
    (empty when not coloured), the surface flag (N,) (``V^S``; empty when not computed) and
    ``misses`` (N,) uint8, how many of the frame's cameras did not see the voxel as
    foreground (empty when not computed): with tolerance k every voxel has misses <= k,
    and the voxels with 0 are the k = 0 hull, tighter, for consumers that want it (pose).

    ``silhouettes``: the foreground masks the frame was carved from, reduced (to
    ``silhouette_sizes`` ``[[w, h], ...]``, one per camera of ``cameras``, in that order),
    each bit-packed along rows and the cameras concatenated (empty when not sent; the pose
    stage's silhouette term, :mod:`app.pose.silhouette`). Added after the first builds:
    their payloads decode with it empty.

    Voxel ``(i, j, k)`` has its centre at ``origin + (index + 0.5) * voxel_size``.
    """

    TYPE_ID: ClassVar[int] = 3
    ARRAYS: ClassVar[tuple[str, ...]] = ("indices", "colours", "surface", "misses", "silhouettes")
    ADDED_ARRAYS: ClassVar[int] = 1
    voxel_size: float = 0.0
    origin: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    dims: list = field(default_factory=lambda: [0, 0, 0])
    cameras: list = field(default_factory=list)
    silhouette_sizes: list = field(default_factory=list)
    indices: np.ndarray = None
    colours: np.ndarray = None
    surface: np.ndarray = None
    misses: np.ndarray = None
    silhouettes: np.ndarray = None

    def validate(self) -> None:
        super().validate()
        n = check_voxel_fields(self)
        misses = _array(self, "misses", "|u1", (n,), allow_empty=True)
        if misses.size and int(misses.max()) > max(len(self.cameras), 1):
            raise MessageError("Voxels: misses exceed the number of cameras")
        check_silhouettes(self)

    def with_silhouettes(self, masks: list) -> "Voxels":
        """Attach the boolean masks (one per camera of ``cameras``, in order) as silhouettes."""
        self.silhouette_sizes = [[int(m.shape[1]), int(m.shape[0])] for m in masks]
        self.silhouettes = (np.concatenate([np.packbits(np.asarray(m, bool), axis=1).ravel() for m in masks])
                            if masks else np.zeros(0, np.uint8))
        return self

    def silhouette_masks(self) -> list:
        """The silhouettes as boolean (h, w) arrays, one per camera of ``cameras``; [] when none."""
        return silhouette_masks(self)

    def centres(self, where=None) -> np.ndarray:
        """World coordinates of the voxel centres (N, 3); ``where``: a boolean mask or index
        array, the centres of those voxels alone (the same values as ``centres()[where]``)."""
        idx = self.indices if where is None else self.indices[where]
        return np.asarray(self.origin) + (idx.astype(np.float64) + 0.5) * self.voxel_size


def check_silhouettes(msg) -> None:
    """Validate the bit-packed ``silhouettes`` and their ``silhouette_sizes`` that
    :class:`Voxels` and :class:`Blobs` carry (both may be empty)."""
    cls = type(msg).__name__
    sil = _array(msg, "silhouettes", "|u1", (None,), allow_empty=True)
    sizes = msg.silhouette_sizes
    if not sil.size:
        if sizes:
            raise MessageError(f"{cls}: silhouette_sizes without silhouettes")
        return
    if (not isinstance(sizes, list) or len(sizes) != len(msg.cameras)
            or not all(isinstance(wh, list) and len(wh) == 2
                       and all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= _MAX_SIDE for v in wh)
                       for wh in sizes)):
        raise MessageError(f"{cls}: silhouette_sizes is not one [width, height] per camera")
    need = sum(h * ((w + 7) // 8) for w, h in sizes)
    if sil.shape != (need,):
        raise MessageError(f"{cls}: silhouettes hold {sil.size} bytes, their sizes need {need}")


def silhouette_masks(msg) -> list:
    """The ``silhouettes`` of a (validated) :class:`Voxels` or :class:`Blobs` as boolean
    (h, w) arrays, one per camera of ``cameras``; [] when none."""
    if msg.silhouettes is None or not msg.silhouettes.size:
        return []
    out, at = [], 0
    for w, h in msg.silhouette_sizes:
        row = (w + 7) // 8
        bits = np.asarray(msg.silhouettes[at:at + h * row]).reshape(h, row)
        out.append(np.unpackbits(bits, axis=1, count=w).view(bool))
        at += h * row
    return out


def check_voxel_fields(msg) -> int:
    """Validate the grid and voxel fields a message shares with :class:`Voxels`
    (voxel_size, origin, dims, cameras, indices, colours, surface); the voxel count."""
    cls = type(msg).__name__
    if not isinstance(msg.voxel_size, float) or not 1e-3 <= msg.voxel_size <= 1.0:
        raise MessageError(f"{cls}: voxel_size {msg.voxel_size!r} is not 0.001 .. 1 m")
    if (not isinstance(msg.origin, list) or len(msg.origin) != 3
            or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in msg.origin)):
        raise MessageError(f"{cls}: origin is not three numbers")
    if (not isinstance(msg.dims, list) or len(msg.dims) != 3
            or not all(isinstance(v, int) and not isinstance(v, bool) and 0 < v <= 1 << 16 for v in msg.dims)
            or math.prod(msg.dims) > _MAX_VOXELS):
        raise MessageError(f"{cls}: dims {str(msg.dims)[:60]} is not a grid size")
    _names(msg, "cameras")
    idx = _array(msg, "indices", "<i2 <u2 <i4 <u4 <i8", (None, 3), allow_empty=True)
    n = len(idx) if idx.size else 0
    # a column at a time: numpy's max(axis=0) over (N, 3) walks the array 3 values a step,
    # 3 ms a frame of crowd6 at 2 cm against 0.2 for the columns (every consumer of the
    # voxels validates them: each pose shard too, issue 26)
    if n and (idx.min() < 0 or any(int(idx[:, c].max()) >= msg.dims[c] for c in range(3))):
        raise MessageError(f"{cls}: indices outside the grid")
    _array(msg, "colours", "|u1", (n, 3), allow_empty=True)
    _array(msg, "surface", "|b1", (n,), allow_empty=True)
    return n


@dataclass(kw_only=True)
class Tracks(Message):
    """Tracked people of one frame: ids (N,) and centroid positions (N, 3)."""

    TYPE_ID: ClassVar[int] = 4
    ARRAYS: ClassVar[tuple[str, ...]] = ("ids", "positions")
    ids: np.ndarray = None
    positions: np.ndarray = None

    def validate(self) -> None:
        super().validate()
        ids = _array(self, "ids", "<i4 <i8 <u4", (None,), allow_empty=True)
        _array(self, "positions", "<f4 <f8", (ids.size, 3), allow_empty=ids.size == 0)


@dataclass(kw_only=True)
class Poses(Message):
    """Body poses of one frame: track ids (N,), joints (N, 15, 3) in :data:`JOINTS`
    order and the active flag of each joint (N, 15). ``worker`` names the pose worker
    that sent them (several may share a frame's tracks: :mod:`app.pose_shares`)."""

    TYPE_ID: ClassVar[int] = 5
    ARRAYS: ClassVar[tuple[str, ...]] = ("tracks", "joints", "active")
    worker: str = ""
    tracks: np.ndarray = None
    joints: np.ndarray = None
    active: np.ndarray = None

    def validate(self) -> None:
        super().validate()
        if not isinstance(self.worker, str) or len(self.worker) > 64:
            raise MessageError("Poses: worker is not a name")
        tracks = _array(self, "tracks", "<i4 <i8 <u4", (None,), allow_empty=True)
        n = tracks.size
        _array(self, "joints", "<f4 <f8", (n, len(JOINTS), 3), allow_empty=n == 0)
        _array(self, "active", "|b1", (n, len(JOINTS)), allow_empty=n == 0)


@dataclass(kw_only=True)
class Stats(Message):
    """A worker's figures, published once a second and once more when it ends."""

    TYPE_ID: ClassVar[int] = 6
    worker: str = ""
    stage: str = ""
    final: bool = False
    figures: dict = field(default_factory=dict)

    def validate(self) -> None:
        super().validate()
        _name(self, "worker")
        if not isinstance(self.stage, str) or not isinstance(self.final, bool) or not isinstance(self.figures, dict):
            raise MessageError("Stats: stage, final or figures of the wrong type")


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

    def validate(self) -> None:
        super().validate()
        _name(self, "worker")
        _int(self, "frames")
        _int(self, "first")
        if not isinstance(self.fps, (int, float)) or not 0 <= self.fps <= 10000 or not isinstance(self.figures, dict):
            raise MessageError("EndOfStream: fps or figures of the wrong type")


@dataclass(kw_only=True)
class Ack(Message):
    """A stage has finished frame ``frame`` (put it out or given it up; flow control of an
    unpaced or offline source); ``out`` is the newest frame it has put out, so the source
    never waits for a stage after it on frames it gave up."""

    TYPE_ID: ClassVar[int] = 8
    worker: str = ""
    out: int = -1

    def validate(self) -> None:
        super().validate()
        _name(self, "worker")
        _int(self, "out", -1)


@dataclass(kw_only=True)
class Heartbeat(Message):
    """A worker's pulse, once a second from a thread of its own (the launcher's watchdog,
    :mod:`app.watchdog`): the process lives; ``loop_age`` seconds since its loop last
    turned, ``pending`` messages waiting in its inbox, ``busy`` what it does that may
    legitimately hold the loop ("setup", "compiling"; empty otherwise), ``pid`` its process."""

    TYPE_ID: ClassVar[int] = 12
    worker: str = ""
    pid: int = 0
    loop_age: float = 0.0
    pending: int = 0
    busy: str = ""

    def validate(self) -> None:
        super().validate()
        _name(self, "worker")
        _int(self, "pid", 0, 1 << 31)
        _int(self, "pending", 0, 1 << 31)
        if not isinstance(self.loop_age, float) or not 0 <= self.loop_age < 1e9:
            raise MessageError("Heartbeat: loop_age is not a number of seconds")
        if self.busy not in ("", "setup", "compiling"):
            raise MessageError(f"Heartbeat: busy {str(self.busy)[:20]!r} is not '', 'setup' or 'compiling'")


@dataclass(kw_only=True)
class Blobs(Message):
    """Connected components of one frame's voxels (§4.2.3): the voxels themselves (as in
    :class:`Voxels`, so the tracker needs no second stream), the component ``labels`` (N,)
    int32 of each voxel, the ``features`` (K, len(FEATURES)) float32 of each component
    (Table 4.1 first, then the centroid and size) and the classifier's ``person`` verdict
    (K,) uint8 (1 = person). ``silhouettes`` and ``silhouette_sizes``: the frame's
    silhouettes as the voxels brought them (:class:`Voxels`; empty when they had none),
    for the tracker's ghost test. Added after the first builds: their payloads decode
    with them empty."""

    TYPE_ID: ClassVar[int] = 10
    ARRAYS: ClassVar[tuple[str, ...]] = ("indices", "colours", "surface", "labels", "features", "person",
                                         "silhouettes")
    ADDED_ARRAYS: ClassVar[int] = 1
    #: weight (kg), z-centroid, top, height, larger and smaller horizontal extent (m;
    #: Table 4.1), then the centroid x, y (m) and the voxel count
    FEATURES: ClassVar[tuple[str, ...]] = ("weight", "z_centroid", "top", "height", "extent_major",
                                           "extent_minor", "x", "y", "voxels")
    voxel_size: float = 0.0
    origin: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    dims: list = field(default_factory=lambda: [0, 0, 0])
    cameras: list = field(default_factory=list)
    silhouette_sizes: list = field(default_factory=list)
    indices: np.ndarray = None
    colours: np.ndarray = None
    surface: np.ndarray = None
    labels: np.ndarray = None
    features: np.ndarray = None
    person: np.ndarray = None
    silhouettes: np.ndarray = None

    def validate(self) -> None:
        """Raise :class:`MessageError` unless shapes, dtypes and labels are consistent."""
        super().validate()
        n = check_voxel_fields(self)
        if self.indices.size and self.indices.dtype != np.uint16:
            raise MessageError("Blobs: indices must be uint16")
        f = _array(self, "features", "<f4", (None, len(self.FEATURES)), allow_empty=True)
        k = len(f) if f.size else 0
        lab = _array(self, "labels", "<i4", (n,), allow_empty=n == 0)
        if n and (lab.min() < 0 or lab.max() >= k):
            raise MessageError(f"Blobs: labels outside 0 .. {k - 1}")
        _array(self, "person", "|u1", (k,), allow_empty=k == 0)
        check_silhouettes(self)

    def silhouette_masks(self) -> list:
        """The silhouettes as boolean (h, w) arrays, one per camera of ``cameras``; [] when none."""
        return silhouette_masks(self)

    def centres(self, where=None) -> np.ndarray:
        """World coordinates of the voxel centres (N, 3); ``where``: a boolean mask or index
        array, the centres of those voxels alone (the same values as ``centres()[where]``)."""
        idx = self.indices if where is None else self.indices[where]
        return np.asarray(self.origin) + (idx.astype(np.float64) + 0.5) * self.voxel_size


@dataclass(kw_only=True)
class Keypoints(Message):
    """2D body keypoints of one frame's tracked people in some cameras (a keypoints
    worker's share, :mod:`app.keypoints`): track ids (N,), the ``cameras`` (C names) and
    ``points`` (N, C, 15, 3) float32: u, v in the camera's calibrated pixels and the
    detector's confidence 0..1 (0: that camera gave nothing for the joint), joints in
    :data:`JOINTS` order. ``worker`` names the sender (a pose worker waits for every
    keypoints worker of the layout)."""

    TYPE_ID: ClassVar[int] = 11
    ARRAYS: ClassVar[tuple[str, ...]] = ("tracks", "points")
    worker: str = ""
    cameras: list = field(default_factory=list)
    tracks: np.ndarray = None
    points: np.ndarray = None

    def validate(self) -> None:
        super().validate()
        _name(self, "worker")
        cams = _names(self, "cameras")
        if len(set(cams)) != len(cams):
            raise MessageError("Keypoints: a camera named twice")
        tracks = _array(self, "tracks", "<i4 <i8 <u4", (None,), allow_empty=True)
        n = tracks.size
        if n and len(np.unique(tracks)) != n:
            raise MessageError("Keypoints: a track named twice")
        p = _array(self, "points", "<f4", (n, len(cams), len(JOINTS), 3), allow_empty=n == 0 or not cams)
        if p.size:
            c = p[..., 2]
            if c.min() < 0 or c.max() > 1:
                raise MessageError("Keypoints: a confidence outside 0..1")
            if np.abs(p[..., :2]).max() > 4 * _MAX_SIDE:
                raise MessageError("Keypoints: a point far outside every image")


@dataclass(kw_only=True)
class Markers(Message):
    """The colour markers one camera saw in one frame (marker-based capture, thesis
    §6.4.1.1, :mod:`app.markers.detector`): ``points`` (Q, 2) float32, the blobs' centroids
    in the camera's calibrated pixels, unlabelled; ``cameras`` the frame set (see
    :class:`Frame`: a pose worker in marker mode waits for every camera of it).
    ``worker`` names the sender (a markers worker, or a segmentation worker that also
    detects them)."""

    TYPE_ID: ClassVar[int] = 13
    ARRAYS: ClassVar[tuple[str, ...]] = ("points",)
    MAX_POINTS: ClassVar[int] = 4096
    worker: str = ""
    camera: str = ""
    cameras: list = field(default_factory=list)
    points: np.ndarray = None

    def validate(self) -> None:
        super().validate()
        _name(self, "worker")
        _name(self, "camera")
        _names(self, "cameras")
        p = _array(self, "points", "<f4", (None, 2), allow_empty=True)
        if len(p) > self.MAX_POINTS:
            raise MessageError(f"Markers: {len(p)} detections (at most {self.MAX_POINTS})")
        if p.size and (not np.all(np.isfinite(p)) or np.abs(p).max() > _MAX_SIDE):
            raise MessageError("Markers: a detection outside every image")
