"""Reconstruction worker: shape from silhouette, voxel colouring and surface voxels
(thesis §2.2.4) from every camera's mask of one frame.

Masks arrive per camera and are assembled by frame index. Each mask carries the frame
set (the cameras the grabber sent for that index), so the worker knows which views a
frame has. A frame is reconstructed, in frame order, once every camera of its set has
delivered or is not worth waiting for (:mod:`app.reconstruction.assembly`):

- offline (a recording) a view is waited for while its segmentation worker is away
  (restarting, on a host whose link is down), so two runs give the same voxels on an
  idle and on a loaded machine; one still missing 30 s (``STALL_S``) after the frame's first
  mask with its producer on the bus is given up and counted (``frames_stalled``: the run
  is not complete);
- live, a view may also be given up after ``wait_ms`` (a camera is waited for from its
  first mask on, and stops being waited for after ``camera_timeout_s`` of its own
  silence); every view given up is counted per camera (``late``).

A frame with fewer than ``min_views`` cameras is dropped and counted, never published
empty. Each published frame names the cameras it was built from (``Voxels.cameras``).
Several reconstruction workers may take the frames in turn (``share: [k, n]``,
:mod:`app.frame_shares`): the stage holds no state from frame to frame (except learnt
occluders, which are refused with a share).
The projection tables are built at start-up for the mask and colour sizes the
layout's segmentation workers produce, so the first frame is as fast as the others.
"""
from __future__ import annotations

import time
from collections import deque

import numpy as np

from app.errors import InputError
from app.messages import MAX_GRID_CELLS, Mask, Voxels
from app.reconstruction.assembly import FrameAssembly
from app.reconstruction.grid import VoxelGrid
from app.reconstruction.reconstructor import PIPELINE_CARVING
from app.segmentation import SILHOUETTE_FACTOR, reduce_mask, working_size
from workers.base import RECENT_FRAMES, Worker


class Reconstruction(Worker):
    KIND = "reconstruction"
    ORDER = 2
    CONSUMES = ("mask",)
    PRODUCES = ("voxels",)
    ACCEPTS = (Mask,)
    INBOX_DEPTH = 4   # per camera: a few frames to assemble complete sets
    ACK_ON_HANDLE = False   # a frame is finished when reconstructed or given up
    FRAME_SHARES = True     # share: [k, n]: several workers take the frames in turn (app.frame_shares)
    DEFAULTS = {
        "voxel_size": 0.04,          # metres (0.02 .. 0.15)
        "tolerance": PIPELINE_CARVING["tolerance"],   # k: cameras that may miss an occupied voxel (§2.2.4)
        "min_views": PIPELINE_CARVING["min_views"],   # cameras that must see a voxel as foreground
        "miss_support": PIPELINE_CARVING["miss_support"],  # cameras that must see a voxel as foreground when one
                                     # misses it (issue 22: phantoms where few cameras see); 0 = §2.2.4
        "method": "hierarchical",    # hierarchical (coarse-to-fine, Caillette §6.1) or flat
        "colouring": "visibility",   # visibility (depth buffers), raymarch, naive, or none
        "wait_ms": 80.0,             # longest wait for the cameras of one frame
        "camera_timeout_s": 1.0,     # a camera silent this long is not waited for
        "cache": False,              # keep projection tables on disk between runs (~140 MB at 2 cm)
        "min_top": 0.25,             # drop blobs lower than this (m): floor shadows; 0 = thesis (keep all)
        "occlusion": "none",         # none (§2.2.4), learnt: occluder masks learnt over the run (Guan et al. 2006),
                                     # or cells: occlusion learnt per voxel cell and camera (occlusion_cells.py)
        "learn_every": 1,            # learnt occluders: learn from every n-th frame (0: stop learning)
        "occlusion_evidence": 0,     # learnt occluders: frames of evidence that make a pixel (cell) an occluder;
                                     # 0: the model's default (learnt 4, cells 1)
        "occlusion_ratio": 0.0,      # evidence / (evidence + seen) needed; 0: the model's default (learnt 0.6, cells 0.4)
        "occlusion_cell": 0.08,      # cells: side of a cell (m)
        "occlusion_top": 0.0,        # learnt occluders: only below this height (m; furniture is low); 0 = no limit
        "footprint": 0.0,            # silhouette-edge test: accept a voxel when this fraction of the 3x3 pixels
                                     # around its centre pixel is foreground; 0 = the centre pixel (§2.2.4)
        "min_component": 0,          # drop connected components of fewer voxels (ghosts); 0 = keep all
        "ghost_share": 0.0,          # drop components no camera needs (share of their pixels no other component
                                     # covers, in every camera, under this; app/reconstruction/ghosts.py); 0 = keep all
        "misses": True,              # per voxel, the cameras that call it background (Voxels.misses; the
                                     # k = 0 subset of the hull for the pose stage, app.reconstruction.consensus)
        "share": None,               # [k, n]: this worker reconstructs the frames with frame % n == k, other
                                     # workers the others (a many-core host, issue 26; app.frame_shares)
        "silhouettes": SILHOUETTE_FACTOR,  # 2: the frame's masks go with the voxels, reduced by this factor (the
                                     # pose stage's silhouette term, app.pose.silhouette; 160x120 at 2 cm, 80x60 at
                                     # 4 cm from 640x480 cameras: 2.4 / 0.6 kB a camera); 0 = not sent
    }

    RANGES = {"voxel_size": (0.005, 0.5), "tolerance": (0, 8), "min_views": (1, 64), "miss_support": (0, 64),
              "wait_ms": (1.0, 10000.0), "camera_timeout_s": (0.05, 600.0), "min_top": (0.0, 3.0),
              "occlusion_top": (0.0, 10.0),
              "occlusion_evidence": (0, 100000), "occlusion_ratio": (0.0, 1.0), "occlusion_cell": (0.01, 1.0),
              "ghost_share": (0.0, 1.0),
              "footprint": (0.0, 1.0), "min_component": (0, 1_000_000), "silhouettes": (0, 64)}
    CHOICES = {"colouring": ("visibility", "raymarch", "naive", "none"), "occlusion": ("none", "learnt", "cells")}

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
        if self.frame_share is not None and p["occlusion"] != "none":
            raise InputError(f"reconstruction: occlusion {p['occlusion']} learns over every frame of the run: "
                             "not with share (each worker sees only its frames)")
        if not 0.005 <= p["voxel_size"] <= 0.5:
            raise InputError(f"reconstruction: voxel_size {p['voxel_size']} m is outside 0.005 .. 0.5 m")
        cells = VoxelGrid.from_room(calib.room_min, calib.room_max, p["voxel_size"]).n_voxels
        if cells > MAX_GRID_CELLS:   # tables, messages and grids of that size do not fit
            size = np.asarray(calib.room_max) - np.asarray(calib.room_min)
            raise InputError(f"reconstruction: the room ({' x '.join(f'{v:.3g}' for v in size)} m) at "
                             f"{p['voxel_size'] * 100:g} cm voxels is {float(cells):.3g} cells, more than "
                             f"{MAX_GRID_CELLS:.3g}: a larger voxel_size, or a smaller room in the calibration")
        mask_sizes, colour_sizes = self._expected_sizes(calib)
        self.status(f"building projection tables at {p['voxel_size'] * 100:g} cm "
                    "(the first run also compiles the kernels, ~15 s)")
        if p["method"] == "fused":   # needs distance maps, which the segmentation worker does not send yet
            raise InputError("reconstruction: method fused is offline only (smartroom bench reconstruction --hull)")
        try:
            self.reconstructor = Reconstructor(
                calib, p["voxel_size"], mask_sizes=mask_sizes, colour_sizes=colour_sizes,
                tolerance=p["tolerance"], min_views=p["min_views"], miss_support=p["miss_support"],
                method=p["method"],
                colouring=p["colouring"], cache=p["cache"], min_top=p["min_top"],
                occlusion=p["occlusion"], learn_every=p["learn_every"], occlusion_top=p["occlusion_top"],
                occlusion_evidence=p["occlusion_evidence"] or None, occlusion_ratio=p["occlusion_ratio"] or None,
                occlusion_cell=p["occlusion_cell"], ghost_share=p["ghost_share"],
                footprint=p["footprint"], min_component=p["min_component"], misses=bool(p["misses"]))
        except ValueError as exc:
            raise InputError(f"reconstruction: {exc}") from None
        self.calibration = calib
        self.names = list(calib.names)
        self.mask_sizes, self.colour_sizes = mask_sizes, colour_sizes
        self.assembly = FrameAssembly(self.names, self._producers(), self.lossless, wait_s=p["wait_ms"] / 1e3,
                                      camera_timeout_s=p["camera_timeout_s"])
        self.too_few_views = 0                   # frames dropped for fewer than min_views cameras
        self.partial_frames = 0                  # frames built without a camera of their set
        self.timings: dict[str, deque] = {}   # the last RECENT_FRAMES frames' step times
        self.occupied: deque = deque(maxlen=RECENT_FRAMES)
        self.log.info("grid %s at %.3f m, tables %.0f MB built in %.0f ms", self.reconstructor.grid.dims,
                      p["voxel_size"], self.reconstructor.table_bytes / 1e6, self.reconstructor.build_ms)

    def _producers(self) -> dict[str, set]:
        """Camera -> the workers of the layout that publish its masks."""
        from workers import worker_class

        out: dict[str, set] = {n: set() for n in self.names}
        for w in self.layout.workers:
            if "mask" not in worker_class(w.kind).produces(w):
                continue
            cams = w.params.get("cameras")
            for n in self.names:
                if cams in (None, "all") or n in cams:
                    out[n].add(w.name)
        return out

    def _expected_sizes(self, calib):
        """Mask and colour sizes per camera, from the segmentation workers of the layout."""
        from workers.segmentation import scales

        from workers import worker_class

        masks, colours = {}, {}
        for w in self.layout.workers:
            if "mask" not in worker_class(w.kind).produces(w):
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
    def admit(self, key: str, msg: Mask) -> str | None:
        if msg.camera not in self.assembly.late:
            return "unknown camera"
        if (msg.width, msg.height) != self.mask_sizes.get(msg.camera):
            return f"mask {msg.width}x{msg.height} does not match the tables {self.mask_sizes.get(msg.camera)}"
        return None

    def new_epoch(self, epoch: int) -> None:
        n = self.assembly.reset()
        if n:
            self.log.warning("%d unfinished frames of the old epoch given up", n)

    def handle(self, key: str, msg: Mask) -> None:
        now = time.monotonic()
        if self.assembly.add(msg.camera, msg.frame, msg.cameras, msg, now):
            self._decide(now)

    def _decide(self, now: float, final: bool = False) -> None:
        """Reconstruct the frames that are ready, in order (app.reconstruction.assembly)."""
        for r in self.assembly.ready(now, self.alive, self._ended_upstream, final=final):
            if r.stalled:
                self.log.warning("frame %d: no mask from %s after %.0f s; going on without (the run is not "
                                 "complete)", r.frame, ", ".join(sorted(r.stalled)), r.waited)
            self._reconstruct(r.frame, r.masks, r.partial)

    def tick(self) -> None:
        if self.assembly.pending:
            self._decide(time.monotonic())

    def flush(self) -> None:
        self._decide(time.monotonic(), final=True)

    # -- one frame ----------------------------------------------------------------------
    def _reconstruct(self, frame: int, masks: dict, partial: set) -> None:
        try:
            self._build(frame, masks, partial)
        finally:
            self.finished(frame)

    def _build(self, frame: int, masks: dict, partial: set) -> None:
        if len(masks) < self.params["min_views"]:
            self.too_few_views += 1
            if self.too_few_views in (1, 10, 100) or self.too_few_views % 1000 == 0:
                self.log.warning("frame %d: only %d camera(s) (%s), fewer than min_views %d; dropped (%d so far)",
                                 frame, len(masks), ", ".join(sorted(masks)) or "none", self.params["min_views"],
                                 self.too_few_views)
            return
        if partial:
            self.partial_frames += 1
        mask_arrays, images = {}, {}
        for cam, m in masks.items():
            mask_arrays[cam] = m.unpack()
            if m.colour is not None and m.colour.size and cam in self.colour_sizes:
                images[cam] = m.colour
        indices, colours, surface, timings = self.reconstructor.reconstruct(mask_arrays, images)
        for k, v in timings.items():
            self.timings.setdefault(k, deque(maxlen=RECENT_FRAMES)).append(v)
        self.occupied.append(len(indices))
        any_mask = next(iter(masks.values()))
        grid = self.reconstructor.grid
        cameras = sorted(mask_arrays)
        vox = Voxels(frame=frame, stamp=any_mask.stamp, t=any_mask.t, voxel_size=float(grid.voxel_size),
                     origin=[float(v) for v in grid.origin], dims=[int(v) for v in grid.dims],
                     cameras=cameras, indices=indices, colours=colours, surface=surface,
                     misses=self.reconstructor.misses)
        factor = int(self.params["silhouettes"])
        if factor > 0:
            vox.with_silhouettes([reduce_mask(mask_arrays[c], factor) for c in cameras])
        self.publish(self.keys.voxels(), vox)

    def extra_figures(self) -> dict:
        recent = getattr(self, "timings", {})
        occ = getattr(self, "occupied", ())
        assembly = getattr(self, "assembly", None)
        return {"step_ms": {k: round(float(np.mean(v)), 3) for k, v in recent.items() if v},
                "occupied_voxels": int(np.mean(occ)) if occ else 0,
                "late_views": {c: n for c, n in (assembly.late if assembly else {}).items() if n},
                # offline: frames built without a view waited for in vain (the run is not complete)
                "frames_stalled": assembly.stalled if assembly else 0,
                "frames_too_few_views": getattr(self, "too_few_views", 0),
                "frames_partial": getattr(self, "partial_frames", 0)}
