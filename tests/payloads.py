"""Payloads as earlier builds wrote them, for the decoders' compatibility tests."""
import json

import numpy as np

from app import messages as M


def older_payload(msg, field: str) -> bytes:
    """``msg`` encoded as the build before its last array (and its meta ``field``) were
    added wrote it: :func:`app.messages.encode` with one array fewer and the field absent."""
    cls = type(msg)
    arrays = [np.ascontiguousarray(np.zeros(0, np.uint8) if getattr(msg, n) is None else getattr(msg, n))
              for n in cls.ARRAYS[:-1]]
    values = {k: getattr(msg, k) for k in M._meta_fields(cls) if k != field}
    meta = json.dumps({"m": values, "a": [[a.dtype.str, list(a.shape)] for a in arrays]},
                      separators=(",", ":")).encode()
    parts = [M._HEADER.pack(M.MAGIC, M.VERSION, cls.TYPE_ID, 0, len(arrays), int(msg.frame), float(msg.stamp),
                            float(msg.t), len(meta)), meta]
    size = sum(len(p) for p in parts)
    for a in arrays:
        pad = -size % M._ALIGN
        parts.append(b"\0" * pad + (a.tobytes() if a.size else b""))
        size += pad + a.nbytes
    return b"".join(parts)
