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
from app.messages import MessageError, Voxels, decode, encode

__all__ = ["VoxelWriter", "iter_voxels"]

_LEN = struct.Struct("<Q")


class VoxelWriter:
    def __init__(self, path: Path):
        self.path = Path(path)
        self.tmp = partial_path(self.path)
        self.fh = open(self.tmp, "wb")
        self.count = 0

    def write(self, msg: Voxels) -> None:
        payload = encode(msg)
        self.fh.write(_LEN.pack(len(payload)))
        self.fh.write(payload)
        self.count += 1

    def close(self) -> None:
        self.fh.close()
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
