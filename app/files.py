"""Reading and writing the project's small files, once: YAML and JSON-lines readers
with one-line errors, and writers that write a temporary ``.partial`` file and rename
it, so a file with its final name is always complete."""
from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import yaml

from app.errors import InputError

__all__ = ["partial_path", "write_atomic", "append_record", "write_json", "read_yaml", "read_jsonl", "json_entry", "read_json_entry"]


def partial_path(path) -> Path:
    """Where ``path`` is written before it is renamed into place."""
    p = Path(path)
    return p.with_name(p.name + ".partial")


def write_atomic(path, data: str | bytes) -> None:
    """Write text or bytes to ``path`` through a ``.partial`` file and a rename; a write
    that fails (a full disk) leaves ``path`` as it was and no ``.partial`` file."""
    tmp = partial_path(path)
    try:
        if isinstance(data, bytes):
            tmp.write_bytes(data)
        else:
            tmp.write_text(data, encoding="utf-8")
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise


def append_record(fh, data: bytes, size: int, path) -> int:
    """Append one whole record to the unbuffered file ``fh`` (at ``size`` bytes of complete
    records, ``path``'s); the new size. A write may take fewer bytes than it was given (a
    disk filling up): the rest is written after it, and when the disk is full the file is
    cut back to ``size``, so it always ends with its last complete record, and ``OSError``
    is raised."""
    view = memoryview(data)
    try:
        while view:
            n = fh.write(view)
            if not n:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
            view = view[n:]
    except OSError:
        os.truncate(path, size)
        fh.seek(0, os.SEEK_END)
        raise
    return size + len(data)


def write_json(path, data, indent: int | None = 1) -> None:
    write_atomic(path, json.dumps(data, indent=indent))


def json_entry(data):
    """``data`` as JSON in a 0-d string array: an entry of a state file of named arrays
    (``numpy.savez``) that loads without pickles."""
    import numpy as np
    return np.array(json.dumps(data))


def read_json_entry(arrays, key: str):
    """What :func:`json_entry` stored under ``key``; ``ValueError`` (or ``KeyError`` when
    missing) for anything else."""
    import numpy as np
    try:
        return json.loads(str(np.asarray(arrays[key])[()]))
    except (TypeError, IndexError) as exc:
        raise ValueError(f"{key} is not a JSON entry ({type(exc).__name__})") from None


def read_yaml(path, what: str, error=InputError):
    """Parse a YAML file; ``error(message)`` names the file, and the line when malformed."""
    p = Path(path)
    if not p.is_file():
        raise error(f"{p}: {what} not found")
    try:
        with open(p, encoding="utf-8") as fh:
            return yaml.safe_load(fh)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" (line {mark.line + 1})" if mark is not None else ""
        raise error(f"{p}: not valid YAML{line}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{p}: cannot be read ({exc.__class__.__name__})") from None


def read_jsonl(path, error=InputError) -> list[dict]:
    """A JSON-lines file as a list; ``error(message)`` names the malformed line."""
    p = Path(path)
    out = []
    with open(p, encoding="utf-8") as fh:
        for n, line in enumerate(fh, 1):
            if line.strip():
                try:
                    out.append(json.loads(line))
                except json.JSONDecodeError:
                    raise error(f"{p}: line {n} is not valid JSON") from None
    return out
