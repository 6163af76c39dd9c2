"""The types of a process layout: which workers run, with which parameters, where, and
what the launcher was asked to do.

Plain dataclasses with no loader and no worker in them, so that both the config loader
(:mod:`app.config`, which reads and validates a layout against the worker kinds) and the
worker base (:mod:`workers.base`, which is handed one) import them without importing each
other.
"""
from __future__ import annotations

import copy
import os
from dataclasses import asdict, dataclass, field

import yaml

from app.bus import BusConfig
from app.errors import InputError
from app.files import write_atomic

__all__ = ["LayoutError", "WorkerSpec", "RunSpec", "Layout"]


class LayoutError(InputError):
    """A layout or parameter file is missing or malformed."""


@dataclass
class WorkerSpec:
    name: str
    kind: str
    params: dict = field(default_factory=dict)
    host: str = "local"
    restart: bool = True

    @property
    def local(self) -> bool:
        return self.host in ("local", "localhost", "127.0.0.1", os.uname().nodename)


@dataclass
class RunSpec:
    """What the launcher was asked to do (not part of a layout file's own text)."""

    recording: str | None = None
    recording_id: str | None = None            # fingerprint of the recording (app.recording.fingerprint)
    calibration: str | None = None             # calibration file (live cameras)
    fps: float | None = None                   # the source's frame rate
    out: str | None = None
    frames: int | None = None
    pace: bool = True
    headless: bool = False
    live: dict = field(default_factory=dict)   # live camera sources {camera: device or URL}
    trace: bool = False                        # workers write per-frame timings to <out>/trace/
    started_ms: int | None = None              # the hub's launcher's start, ms since 1970: the sources' epochs
                                               # (their start, the same clock) are not older (app.admission)


@dataclass
class Layout:
    room: str
    bus: BusConfig
    workers: list[WorkerSpec]
    run: RunSpec = field(default_factory=RunSpec)
    path: str = "layout.yaml"
    restarts: dict = field(default_factory=dict)   # the launcher's restart policy (app.config._restarts)

    @property
    def names(self) -> set[str]:
        """The names of the layout's workers (the only ones whose stats and ends count)."""
        return {w.name for w in self.workers}

    def worker(self, name: str) -> WorkerSpec:
        for w in self.workers:
            if w.name == name:
                return w
        raise LayoutError(f"{self.path}: no worker named {name!r} (have {', '.join(w.name for w in self.workers)})")

    def to_dict(self) -> dict:
        return {
            "room": self.room,
            "bus": asdict(self.bus),
            "workers": [asdict(w) for w in self.workers],
            "run": asdict(self.run),
            **({"restarts": dict(self.restarts)} if self.restarts else {}),
        }

    def save(self, path) -> None:
        write_atomic(path, yaml.safe_dump(self.to_dict(), sort_keys=False))

    def copy(self) -> "Layout":
        return copy.deepcopy(self)
