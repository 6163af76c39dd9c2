"""Worker kinds (thin shells over the algorithm cores) and how they connect.

Kinds are imported lazily so that the launcher and the CLI start fast. A layout may
also name a worker class of its own as ``kind: package.module:ClassName`` (a plugin:
any subclass of :class:`workers.base.Worker` importable where the worker runs).

The registry names kinds by their entry (``module:Class``) and imports no worker itself:
the worker base and its parts use :func:`upstream_of` and :func:`worker_class`, and the
config loader, which imports both, checks that a kind is a worker.
"""
from __future__ import annotations

import importlib

__all__ = ["KINDS", "worker_class", "upstream_of", "producers_of"]

KINDS = {
    "grabber": "workers.grabber:Grabber",
    "segmentation": "workers.segmentation:Segmentation",
    "reconstruction": "workers.reconstruction:Reconstruction",
    "cca": "workers.cca:ComponentAnalysis",
    "tracking": "workers.tracking:Tracking",
    "pose": "workers.pose:Pose",
    "keypoints": "workers.keypoints:KeypointsWorker",
    "markers": "workers.markers:MarkersWorker",
    "recorder": "workers.recorder:Recorder",
    "viewer": "workers.viewer:Viewer",
    "monitor": "workers.monitor:Monitor",
    "exporter": "workers.exporter:Exporter",
    "streamer": "workers.streamer:Streamer",
}


def is_kind(kind) -> bool:
    """A registered kind, or a ``module:Class`` plugin path."""
    return isinstance(kind, str) and (kind in KINDS or (":" in kind and all(kind.partition(":")[::2])))


def worker_class(kind: str):
    """The worker class of a kind (``ImportError``/``AttributeError`` for a plugin that is
    not there; that it is a worker is checked when the layout is loaded,
    :func:`app.config.parse_layout`)."""
    module, _, name = KINDS.get(kind, kind).partition(":")
    return getattr(importlib.import_module(module), name)


def cameras_of(spec) -> set[str] | None:
    """The cameras a worker's ``cameras`` parameter names (None: all)."""
    cams = spec.params.get("cameras")
    return None if cams in (None, "all") else set(cams)


def upstream_of(layout, spec) -> list[str]:
    """Workers of ``layout`` whose end of stream ``spec`` waits for: those producing a
    stage it consumes (per-camera stages only where the camera sets meet) and, for a
    worker that consumes ``stats``, every worker that is not a sink."""
    me = worker_class(spec.kind)
    mine = cameras_of(spec)
    names = []
    for other in layout.workers:
        if other.name == spec.name:
            continue
        produced = worker_class(other.kind).produces(other)
        if not produced:
            continue  # sinks are nobody's upstream
        if "stats" in me.CONSUMES:
            names.append(other.name)
            continue
        for stage in produced & me.consumes(spec):
            theirs = cameras_of(other)
            if stage in me.PER_CAMERA and mine is not None and theirs is not None and not (mine & theirs):
                continue
            names.append(other.name)
            break
    return names


def producers_of(layout, stage: str) -> list[str]:
    """Names of the workers of ``layout`` that publish ``stage`` (e.g. the pose workers
    sharing a frame's tracks)."""
    return [w.name for w in layout.workers if stage in worker_class(w.kind).produces(w)]
