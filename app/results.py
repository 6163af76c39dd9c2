"""Result files beyond the contract's JSON lines: the optional voxel stream.

``voxels.bin`` (written by the recorder when asked, for evaluation and replay) is a
sequence of records, each an 8-byte little-endian length followed by one encoded
:class:`~app.messages.Voxels` message (the bus codec, so it is read back with the
same decoder), in frame order. Like every result file it is written as ``.partial``
and renamed when complete (sorted first if a restart made frames come out of order).
"""
from __future__ import annotations

import os
import struct
from pathlib import Path

from app.errors import InputError
from app.files import append_record, partial_path
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
        self.ordered, self.last_frame = True, -1
        keep = 0
        if self.tmp.exists():   # an earlier incarnation's records: keep every complete one
            for frame, offset, size in _records(self.tmp):
                self.frames.add(frame)
                self.ordered = self.ordered and frame > self.last_frame
                self.last_frame = max(self.last_frame, frame)
                keep = offset + size
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
        # a crash cuts at most this record; a full disk leaves the file at its last whole one
        self.size = append_record(self.fh, record, self.size, self.tmp)
        self.frames.add(msg.frame)
        self.ordered = self.ordered and msg.frame > self.last_frame
        self.last_frame = max(self.last_frame, msg.frame)
        return True

    def close(self, final: bool = True) -> None:
        self.fh.close()
        if not final:
            return
        if not self.ordered:   # frames sent again to a restarted recorder came after newer ones
            self._sort()
        os.replace(self.tmp, self.path)

    def _sort(self) -> None:
        """Rewrite the records in frame order, one record in memory at a time."""
        index = sorted(_records(self.tmp))
        sorted_tmp = self.tmp.with_name(self.tmp.name + ".sorted")
        with open(self.tmp, "rb") as src, open(sorted_tmp, "wb") as dst:
            for _, offset, size in index:
                src.seek(offset)
                dst.write(_LEN.pack(size) + src.read(size))
        os.replace(sorted_tmp, self.tmp)


def _records(path):
    """``(frame, payload offset, payload size)`` of each complete record, up to the first
    one cut short or unreadable (a crash while writing)."""
    with open(path, "rb") as fh:
        while True:
            head = fh.read(_LEN.size)
            if len(head) < _LEN.size:
                return
            (size,) = _LEN.unpack(head)
            payload = fh.read(size)
            if len(payload) < size:
                return
            try:
                frame = peek_frame(payload)
            except MessageError:
                return
            yield frame, fh.tell() - size, size


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
