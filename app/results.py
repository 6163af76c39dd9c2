"""Result files beyond the contract's JSON lines: the optional voxel stream.

``voxels.bin`` (written by the recorder when asked, for evaluation and replay) is a
sequence of records, each an 8-byte little-endian length followed by one encoded
:class:`~app.messages.Voxels` message (the bus codec, so it is read back with the
same decoder). Like every result file it is written as ``.partial`` and renamed
when complete.
"""
from __future__ import annotations

import os
import struct
from pathlib import Path

from app.errors import InputError
from app.files import partial_path
from app.messages import MessageError, Voxels, decode, encode, peek_frame
from app.stats import FrameSet

__all__ = ["VoxelWriter", "iter_voxels"]

_LEN = struct.Struct("<Q")


class VoxelWriter:
    """Records appended to ``voxels.bin.partial`` (resumed after a crash: a record cut
    short is removed), renamed by :meth:`close` with ``final=True``."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.tmp = partial_path(self.path)
        self.frames = FrameSet()
        keep = 0
        if self.tmp.exists():
            with open(self.tmp, "rb") as fh:
                while True:
                    head = fh.read(_LEN.size)
                    if len(head) < _LEN.size:
                        break
                    (size,) = _LEN.unpack(head)
                    payload = fh.read(size)
                    if len(payload) < size:
                        break
                    try:
                        self.frames.add(peek_frame(payload))
                    except MessageError:
                        break
                    keep += _LEN.size + size
            os.truncate(self.tmp, keep)
        self.fh = open(self.tmp, "ab", buffering=0)
        self.size = self.fh.tell()   # bytes of complete records

    @property
    def count(self) -> int:
        return len(self.frames)

    def write(self, msg: Voxels) -> bool:
        """Append one frame; False when that frame is already in the file."""
        if msg.frame in self.frames:
            return False
        payload = encode(msg)
        record = _LEN.pack(len(payload)) + payload
        try:
            self.fh.write(record)   # one write: a crash cuts at most this record
        except OSError:             # e.g. disk full: the file ends with its last complete record
            os.truncate(self.tmp, self.size)
            raise
        self.size += len(record)
        self.frames.add(msg.frame)
        return True

    def close(self, final: bool = True) -> None:
        self.fh.close()
        if final:
            os.replace(self.tmp, self.path)


def iter_voxels(path):
    """Yield the :class:`Voxels` messages of a ``voxels.bin`` file in order."""
    path = Path(path)
    with open(path, "rb") as fh:
        n = 0
        while True:
            head = fh.read(_LEN.size)
            if not head:
                return
            if len(head) < _LEN.size:
                raise InputError(f"{path}: truncated after record {n}")
            (size,) = _LEN.unpack(head)
            payload = fh.read(size)
            try:
                msg = decode(payload)
            except MessageError as exc:
                raise InputError(f"{path}: record {n} is not a voxel message ({exc})") from None
            if not isinstance(msg, Voxels):
                raise InputError(f"{path}: record {n} is a {type(msg).__name__}, not voxels")
            n += 1
            yield msg
