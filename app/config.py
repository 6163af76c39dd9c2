"""The one config loader: process layouts (which workers, with which parameters, where)
and parameter overrides, validated at start with one-line errors.

A layout is YAML::

    room: smartroom                 # key prefix: smartroom/<room>/...
    bus:                            # zenoh endpoints of the hub (the launcher's session)
      listen: [tcp/127.0.0.1:0]     # port 0: a free port is chosen at start
      multicast: false
    workers:
      - name: segmentation          # unique; `smartroom worker NAME` starts it alone
        kind: segmentation          # which worker class (see workers.KINDS)
        host: local                 # `smartroom run` starts only local workers
        params: {history: 300}      # checked against the kind's DEFAULTS

The launcher adds a ``run`` section (recording, out, frames, pace, headless) and
writes the resolved layout next to the results, so every worker and every later
reader sees exactly what ran.

The types it returns (:class:`Layout`, :class:`WorkerSpec`, :class:`RunSpec`,
:class:`LayoutError`) are :mod:`app.layout`'s, which the worker base imports too: the
loader imports the worker registry and the workers, never the other way round.
"""
from __future__ import annotations

import copy
from dataclasses import MISSING, fields
from pathlib import Path

import yaml

from app.bus import BusConfig
from app.bus_section import parse_bus
from app.files import read_yaml
from app.frame_shares import stage_shares
from app.layout import Layout, LayoutError, RunSpec, WorkerSpec

__all__ = ["LayoutError", "WorkerSpec", "RunSpec", "Layout", "load_layout", "parse_layout",
           "default_layout_path", "load_overrides", "apply_overrides", "parse_assignment"]

LAYOUTS_DIR = Path(__file__).resolve().parent.parent / "deploy" / "layouts"


def default_layout_path() -> Path:
    return LAYOUTS_DIR / "local.yaml"


def _check_params(kind_cls, params: dict, where: str) -> dict:
    """Merge ``params`` over the kind's defaults, rejecting unknown names, wrong types,
    numbers outside the kind's ``RANGES`` and words outside its ``CHOICES``."""
    defaults = kind_cls.DEFAULTS
    merged = copy.deepcopy(defaults)
    for key, value in (params or {}).items():
        if key not in defaults:
            known = ", ".join(sorted(defaults)) or "none"
            raise LayoutError(f"{where}: unknown parameter {key!r} (known: {known})")
        merged[key] = _coerce(value, defaults[key], f"{where}: parameter {key}")
    for key, (lo, hi) in getattr(kind_cls, "RANGES", {}).items():
        v = merged.get(key)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and not lo <= v <= hi:
            raise LayoutError(f"{where}: parameter {key} = {v} is outside {lo} .. {hi}")
    for key, choices in getattr(kind_cls, "CHOICES", {}).items():
        v = merged.get(key)
        if v is not None and v not in choices:
            raise LayoutError(f"{where}: parameter {key} = {v!r} is not one of {', '.join(map(str, choices))}")
    return merged


def _coerce(value, default, where: str):
    if default is None or value is None:
        return value
    if default == "all":  # a set of cameras: all, or a list of names
        if value == "all" or (isinstance(value, list) and value and all(isinstance(v, str) for v in value)):
            return value
        raise LayoutError(f"{where} must be all or a list of camera names, got {value!r}")
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
        raise LayoutError(f"{where} must be true or false, got {value!r}")
    if isinstance(default, int):
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise LayoutError(f"{where} must be an integer, got {value!r}")
    if isinstance(default, float):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise LayoutError(f"{where} must be a number, got {value!r}")
    if isinstance(default, str):
        if isinstance(value, str):
            return value
        raise LayoutError(f"{where} must be a string, got {value!r}")
    if isinstance(default, (list, tuple)):
        if isinstance(value, (list, tuple)):
            return list(value)
        raise LayoutError(f"{where} must be a list, got {value!r}")
    if isinstance(default, dict):
        if isinstance(value, dict):
            return value
        raise LayoutError(f"{where} must be a mapping, got {value!r}")
    return value


def parse_layout(data, path: str = "layout.yaml") -> Layout:
    """Validate a parsed layout document against the registered worker kinds."""
    from workers import KINDS, is_kind, worker_class
    from workers.base import Worker

    if not isinstance(data, dict):
        raise LayoutError(f"{path}: expected a mapping with room, bus and workers")
    unknown = set(data) - {"room", "bus", "workers", "run", "restarts"}
    if unknown:
        raise LayoutError(f"{path}: unknown section {str(sorted(map(str, unknown))[0])!r} (known: room, bus, workers)")
    room = data.get("room", "smartroom")
    if not isinstance(room, str) or not room or any(c in room for c in "/*$?# "):
        raise LayoutError(f"{path}: room must be a plain word, got {room!r}")
    bus = BusConfig(**parse_bus(data.get("bus"), path, LayoutError))   # endpoints, TLS, user/password
    entries = data.get("workers")
    if not isinstance(entries, list) or not entries:
        raise LayoutError(f"{path}: workers must be a non-empty list")
    workers, names = [], set()
    for i, e in enumerate(entries):
        if not isinstance(e, dict):
            raise LayoutError(f"{path}: workers[{i}] is not a mapping")
        extra = set(e) - {"name", "kind", "params", "host", "restart"}
        if extra:
            raise LayoutError(f"{path}: workers[{i}]: unknown key {sorted(extra)[0]!r}")
        kind = e.get("kind")
        name = e.get("name", kind)
        if not isinstance(name, str) or not name or "/" in name or "*" in name:
            raise LayoutError(f"{path}: workers[{i}]: name must be a plain word")
        if not is_kind(kind):
            raise LayoutError(f"{path}: worker {name}: unknown kind {kind!r} (known: {', '.join(sorted(KINDS))}, "
                              "or module:Class)")
        try:
            cls = worker_class(kind)
        except (ImportError, AttributeError, ValueError, TypeError) as exc:
            raise LayoutError(f"{path}: worker {name}: cannot load kind {kind!r} ({exc})") from None
        if not (isinstance(cls, type) and issubclass(cls, Worker)):
            raise LayoutError(f"{path}: worker {name}: kind {kind!r} is not a worker (a subclass of "
                              "workers.base.Worker)")

        if name in names:
            raise LayoutError(f"{path}: worker name {name} appears more than once")
        names.add(name)
        params = e.get("params") or {}
        if not isinstance(params, dict):
            raise LayoutError(f"{path}: worker {name}: params must be a mapping")
        merged = _check_params(cls, params, f"{path}: worker {name}")
        workers.append(WorkerSpec(name=name, kind=kind, params=merged, host=str(e.get("host", "local")),
                                  restart=bool(e.get("restart", True))))
    if not any(not worker_class(w.kind).CONSUMES for w in workers):
        raise LayoutError(f"{path}: no source: the layout needs a worker that produces frames (kind: grabber)")
    _check_frame_shares(workers, path)
    return Layout(room=room, bus=bus, workers=workers, run=_run_spec(data.get("run"), path), path=path,
                  restarts=_restarts(data.get("restarts"), path))


def _check_frame_shares(workers, where: str) -> None:
    """The workers of a stage that scales out by frame: every frame has exactly one of them."""
    from workers import worker_class

    for kind in sorted({w.kind for w in workers if worker_class(w.kind).FRAME_SHARES}):
        try:
            stage_shares([w for w in workers if w.kind == kind], where)
        except ValueError as exc:
            raise LayoutError(str(exc)) from None


RESTART_KEYS = {"window_s": (1.0, 86400.0), "storm": (2, 1000), "first_delay_s": (0.0, 60.0),
                "max_delay_s": (0.0, 600.0), "watchdog_s": (2.0, 86400.0), "peer_timeout_s": (1.0, 30 * 86400.0)}


def _restarts(data, path: str) -> dict:
    """The ``restarts`` section: when the launcher restarts a crashed worker (see
    :class:`app.launcher.RestartPolicy`): ``{window_s, storm, first_delay_s, max_delay_s,
    watchdog_s, peer_timeout_s}`` (``watchdog_s``: a worker whose loop stands still this long
    is restarted, :mod:`app.watchdog`; ``peer_timeout_s``: how long a launcher waits for the
    workers of another host, and a worker started by itself for the hub, before the run
    ends: an outage shorter than that is waited out)."""
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise LayoutError(f"{path}: restarts must be a mapping of {', '.join(RESTART_KEYS)}")
    for key, value in data.items():
        if key not in RESTART_KEYS:
            raise LayoutError(f"{path}: restarts: unknown key {str(key)!r} (known: {', '.join(RESTART_KEYS)})")
        lo, hi = RESTART_KEYS[key]
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not lo <= value <= hi:
            raise LayoutError(f"{path}: restarts: {key} = {value!r} is outside {lo} .. {hi}")
    return dict(data)


def _run_spec(data, path: str) -> RunSpec:
    """The ``run`` section the launcher writes (checked like the rest: any file may be edited)."""
    if data is None:
        return RunSpec()
    if not isinstance(data, dict):
        raise LayoutError(f"{path}: run must be a mapping")
    known = {f.name: f for f in fields(RunSpec)}
    for key, value in data.items():
        if key not in known:
            raise LayoutError(f"{path}: run: unknown key {str(key)!r} (known: {', '.join(known)})")
        default = known[key].default if known[key].default is not MISSING else known[key].default_factory()
        want = {"recording": str, "recording_id": str, "calibration": str, "out": str, "fps": (int, float),
                "frames": int, "started_ms": int}.get(
            key, type(default))
        if value is not None and (not isinstance(value, want) or isinstance(value, bool) != isinstance(default, bool)):
            raise LayoutError(f"{path}: run: {key} has the wrong type ({value!r})")
    return RunSpec(**data)


def load_layout(path=None) -> Layout:
    """Read and validate a layout file (default: ``deploy/layouts/local.yaml``)."""
    p = Path(path) if path else default_layout_path()
    return parse_layout(read_yaml(p, "layout file", LayoutError), str(p))


def load_overrides(path) -> dict:
    """A ``--config`` file: ``{worker name or kind: {param: value}}``."""
    data = read_yaml(path, "config file", LayoutError) or {}
    if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
        raise LayoutError(f"{path}: expected a mapping of worker name or kind to parameters")
    return data


def parse_assignment(text: str) -> tuple[str, str, object]:
    """``worker.param=value`` (value parsed as YAML) from ``--set``."""
    if "=" not in text or "." not in text.split("=", 1)[0]:
        raise LayoutError(f"--set {text}: expected WORKER.PARAM=VALUE")
    lhs, rhs = text.split("=", 1)
    target, param = lhs.rsplit(".", 1)
    try:
        value = yaml.safe_load(rhs)
    except yaml.YAMLError:
        raise LayoutError(f"--set {text}: value is not valid YAML") from None
    return target, param, value


def apply_overrides(layout: Layout, overrides: dict, source: str = "--config") -> Layout:
    """Apply ``{worker name or kind: {param: value}}`` to a layout (validated)."""
    from workers import worker_class

    out = layout.copy()
    for target, params in overrides.items():
        hits = [w for w in out.workers if w.name == target or w.kind == target]
        if not hits:
            raise LayoutError(f"{source}: no worker or kind named {target!r} in {layout.path}")
        for w in hits:
            merged = dict(w.params)
            merged.update(params)
            w.params = _check_params(worker_class(w.kind), merged, f"{source}: worker {w.name}")
    _check_frame_shares(out.workers, source)
    return out
