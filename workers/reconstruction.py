"""Reconstruction worker: shape from silhouette, voxel colouring and surface voxels
(thesis §2.2.4) from every camera's mask of one frame.

Masks arrive per camera; the worker assembles them by frame index and reconstructs a
frame once every live camera's mask is in, or after ``wait_ms`` with what it has (the
tolerance of shape from silhouette covers a missing view: it lowers ``N_visible``),
or as soon as a newer frame is complete (older incomplete frames are dropped and
counted). A camera silent for ``camera_timeout_s`` is not waited for until it is back.
The projection tables are built at start-up for the mask and colour sizes the
layout's segmentation workers produce, so the first frame is as fast as the others.
"""
from __future__ import annotations

import time

import numpy as np

from app.errors import InputError
from app.messages import Mask, Voxels
from app.segmentation import working_size
from workers.base import Worker

MAX_BACKLOG = 3   # frames ready at once beyond which the stage is behind and skips to the newest


class Reconstruction(Worker):
    KIND = "reconstruction"
    ORDER = 2
    CONSUMES = ("mask",)
    PRODUCES = ("voxels",)
    ACCEPTS = (Mask,)
    INBOX_DEPTH = 4   # per camera: a few frames to assemble complete sets
    DEFAULTS = {
        "voxel_size": 0.04,          # metres (0.02 .. 0.15)
        "tolerance": 1,              # k: cameras that may miss an occupied voxel (§2.2.4)
        "min_views": 2,              # cameras that must see a voxel as foreground
        "method": "hierarchical",    # hierarchical (coarse-to-fine, Caillette §6.1) or flat
        "colouring": "visibility",   # visibility (depth buffers), raymarch, naive, or none
        "wait_ms": 80.0,             # longest wait for the cameras of one frame
        "camera_timeout_s": 1.0,     # a camera silent this long is not waited for
        "cache": False,              # keep projection tables on disk between runs (~140 MB at 2 cm)
        "min_top": 0.25,             # drop blobs lower than this (m): floor shadows; 0 = thesis (keep all)
    }

    def setup(self) -> None:
        from app.reconstruction import Reconstructor
        from app.recording import Recording
        from calibration import load_calibration

        run = self.layout.run
        if run.recording:
            calib = Recording(run.recording).calibration
        elif run.calibration:
            calib = load_calibration(run.calibration)
        else:
            raise InputError("reconstruction needs a recording or a calibration")
        p = self.params
        if not 0.005 <= p["voxel_size"] <= 0.5:
            raise InputError(f"reconstruction: voxel_size {p['voxel_size']} m is outside 0.005 .. 0.5 m")
        mask_sizes, colour_sizes = self._expected_sizes(calib)
        try:
            self.reconstructor = Reconstructor(
                calib, p["voxel_size"], mask_sizes=mask_sizes, colour_sizes=colour_sizes,
                tolerance=p["tolerance"], min_views=p["min_views"], method=p["method"],
                colouring=p["colouring"], cache=p["cache"], min_top=p["min_top"])
        except ValueError as exc:
            raise InputError(f"reconstruction: {exc}") from None
        self.calibration = calib
        self.names = list(calib.names)
        self.mask_sizes, self.colour_sizes = mask_sizes, colour_sizes
        self.pending: dict[int, dict] = {}     # frame -> {"first": t, "masks": {cam: Mask}}
        self.last_seen = {n: time.monotonic() for n in self.names}
        self.newest_done = -1
        self.timings: dict[str, list] = {}
        self.occupied: list[int] = []
        self.log.info("grid %s at %.3f m, tables %.0f MB built in %.0f ms", self.reconstructor.grid.dims,
                      p["voxel_size"], self.reconstructor.table_bytes / 1e6, self.reconstructor.build_ms)

    def _expected_sizes(self, calib):
        """Mask and colour sizes per camera, from the segmentation workers of the layout."""
        from workers.segmentation import scales

        masks, colours = {}, {}
        for w in self.layout.workers:
            if w.kind != "segmentation":
                continue
            mask_scale, colour_scale = scales(w, self.layout, calib)
            cams = w.params.get("cameras")
            for cam in calib.cameras:
                if cams not in (None, "all") and cam.name not in cams:
                    continue
                masks[cam.name] = working_size(cam.width, cam.height, mask_scale)
                if colour_scale:
                    colours[cam.name] = working_size(cam.width, cam.height, colour_scale)
        return masks, colours

    # -- assembly ---------------------------------------------------------------------
    def handle(self, key: str, msg: Mask) -> None:
        if msg.camera not in self.last_seen:
            self.log.warning("ignoring a mask of unknown camera %r", getattr(msg, "camera", None))
            return
        now = time.monotonic()
        self.last_seen[msg.camera] = now
        if msg.frame <= self.newest_done:
            return  # late: that frame was already reconstructed or given up
        entry = self.pending.setdefault(msg.frame, {"first": now, "masks": {}})
        entry["masks"][msg.camera] = msg
        self._decide(now)

    def _live_cameras(self, now: float) -> set[str]:
        timeout = self.params["camera_timeout_s"]
        return {n for n, t in self.last_seen.items() if now - t <= timeout}

    def _decide(self, now: float, final: bool = False) -> None:
        """Reconstruct the frames that are complete or waited long enough, and the older
        ones still pending, oldest first; when more than ``MAX_BACKLOG`` are ready the
        stage is behind: only the newest is reconstructed and the older ones are dropped
        (counted by the ledger)."""
        if not self.pending:
            return
        live = self._live_cameras(now)
        wait = self.params["wait_ms"] / 1e3
        complete = [f for f, e in self.pending.items()
                    if final or set(e["masks"]) >= live or now - e["first"] >= wait]
        if not complete:
            return
        # frames older than a ready one will not get more masks in time: take them too,
        # in order (a missing view only lowers N_visible)
        ready = sorted(f for f in self.pending if f <= max(complete))
        if len(ready) > MAX_BACKLOG and not final:
            for f in ready[:-1]:
                del self.pending[f]   # behind: only the newest (the others count as dropped)
            ready = ready[-1:]
        for frame in ready:
            self._reconstruct(frame, self.pending.pop(frame)["masks"])

    def tick(self) -> None:
        if self.pending:
            self._decide(time.monotonic())

    def flush(self) -> None:
        self._decide(time.monotonic(), final=True)

    # -- one frame ----------------------------------------------------------------------
    def _reconstruct(self, frame: int, masks: dict) -> None:
        self.newest_done = max(self.newest_done, frame)
        mask_arrays, images = {}, {}
        for cam, m in masks.items():
            arr = m.unpack()
            if (arr.shape[1], arr.shape[0]) != self.mask_sizes.get(cam, (m.width, m.height)):
                self.log.warning("camera %s: mask %dx%d does not match the tables %s; skipped",
                                 cam, arr.shape[1], arr.shape[0], self.mask_sizes.get(cam))
                continue
            mask_arrays[cam] = arr
            if m.colour is not None and m.colour.size and cam in self.colour_sizes:
                images[cam] = m.colour
        indices, colours, surface, timings = self.reconstructor.reconstruct(mask_arrays, images)
        for k, v in timings.items():
            self.timings.setdefault(k, []).append(v)
        self.occupied.append(len(indices))
        any_mask = next(iter(masks.values()))
        grid = self.reconstructor.grid
        self.publish(self.keys.voxels(), Voxels(
            frame=frame, stamp=any_mask.stamp, t=any_mask.t, voxel_size=float(grid.voxel_size),
            origin=[float(v) for v in grid.origin], dims=[int(v) for v in grid.dims],
            cameras=sorted(mask_arrays), indices=indices, colours=colours, surface=surface))

    def extra_figures(self) -> dict:
        recent = {k: v[-50:] for k, v in getattr(self, "timings", {}).items()}
        occ = getattr(self, "occupied", [])[-50:]
        return {"step_ms": {k: round(float(np.mean(v)), 3) for k, v in recent.items() if v},
                "occupied_voxels": int(np.mean(occ)) if occ else 0}
