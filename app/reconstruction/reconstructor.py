"""The reconstruction of one frame: shape from silhouette, voxel colouring, surface
(thesis §2.2.4; coarse-to-fine after Caillette et al. §6.1).

:class:`Reconstructor` builds everything that does not change between frames in its
constructor (the voxel grid, the projection tables of every camera, the numba kernels),
so the first frame costs what the others do; :meth:`Reconstructor.reconstruct` then
turns one frame's masks and images into occupied voxels, colours and surface flags.
"""
from __future__ import annotations

import time
from collections.abc import Mapping

import cv2
import numpy as np

from app.components import Labeller
from calibration import Calibration

from .carving import (MAX_CAMERAS, carve_cells, carve_cells_occluded, classify_cells, dissent_cells, fill_cells,
                      mask_votes, occluded_votes)
from .colouring import COLOURINGS, VoxelColourer
from .consensus import count_misses, select_misses
from .floor import FloorBlobFilter
from .footprint import GhostFilter, accept_map
from .ghosts import ExplainedFilter
from .fused import chi2_thresholds, classify_cells_fused
from .grid import BrickLayout, VoxelGrid, keys_to_indices, radix_sort
from .occlusion import OccluderModel
from .occlusion_cells import MISSES_SHIFT, CellOccluders, select_and_learn
from .projection import ProjectionTable

__all__ = ["Reconstructor", "METHODS", "OCCLUSIONS", "PIPELINE_CARVING"]

METHODS = ("hierarchical", "flat", "fused")
OCCLUSIONS = ("none", "learnt", "cells")

#: The occupancy test the pipeline's reconstruction worker uses by default, and the tools
#: that stand in for it offline (the person classifier's training voxels): tolerance 1
#: (§2.2.4), never on fewer than 2 cameras, and a voxel a camera misses needs 3 others
#: (``miss_support``; issue 22, measured on the random tuning scenes, docs/benchmarks.md).
PIPELINE_CARVING = {"tolerance": 1, "min_views": 2, "miss_support": 3}


class Reconstructor:
    """Voxel reconstruction of a calibrated room.

    Parameters
    ----------
    calibration : the cameras and the room (its ``room_min`` / ``room_max`` bound the grid).
    voxel_size : voxel side in metres (0.02-0.15).
    mask_sizes : ``{camera: (width, height)}`` of the masks (default: the calibrated size);
        masks may be downscaled, the tables are built for these sizes.
    colour_sizes : ``{camera: (width, height)}`` of the colour images (default: the mask sizes).
    tolerance : ``k``, how many of the cameras that see a voxel may call it background (§2.2.4).
    min_views : the least number of cameras that must call a voxel foreground.
    miss_support : the least number of cameras that must call a voxel foreground when
        some camera calls it background (an addition to §2.2.4, :func:`.carving.carve_cells`;
        0, the thesis: ``tolerance`` alone decides).
    method : ``"hierarchical"`` (coarse-to-fine, default), ``"flat"`` (every voxel) or
        ``"fused"``: Caillette et al.'s fused segmentation and reconstruction
        (:mod:`.fused`, Eqs. 5-6); its "masks" are per-pixel squared Mahalanobis
        distance maps (float32, :class:`app.segmentation.YuvBackground`).
    alpha : the confidence level of the fused method's chi-square thresholds (0.99).
    samples : the fused method's samples per projected area: ``"all"`` its pixels
        (default) or ``"sqrt"``, the paper's ``sqrt(A)`` (see :mod:`.fused`).
    colouring : ``"visibility"`` (depth buffers, default), ``"raymarch"`` (the thesis's
        line-of-sight reference), ``"naive"`` (mean over all cameras, no surface) or
        ``"none"`` (no colours, no surface).
    brick : side in voxels of the coarsest cells (a power of two, default 8).
    box_levels : how many coarse levels are tested with summed-area tables before the
        voxels (cells of ``brick``, ``brick/2``, ...; default 2: 8^3 then 4^3 cells).
    splat, depth_tolerance, march : the depth buffer's footprint scale, depth tolerance (in
        voxels) and the length (in voxels) of the exact ray march of the near part of each
        line of sight (see :mod:`.colouring`).
    threads : threads for the per-camera visibility (default 1, single-threaded).
    cache : also keep the projection tables on disk (``$SMARTROOM_CACHE/lut``).
    min_top : drop connected components whose top is lower than this (m): floor shadows
        reconstructed as matter (see :mod:`.floor`); 0, the thesis's behaviour, keeps all.
    occlusion : ``"none"`` (the thesis: every camera that sees a voxel votes) or
        ``"learnt"``: occluder masks learnt over the run (:mod:`.occlusion`, Guan et al.
        2006); a camera abstains behind its occluders, so ``tolerance = 0`` keeps what
        furniture hides from one camera without the excess of ``tolerance = 1``; or
        ``"cells"``: occlusion learnt per voxel cell and camera (:mod:`.occlusion_cells`):
        a camera may be the one to miss a voxel only in cells where it has repeatedly
        been the one dissenter behind the free space it has seen.
    occlusion_cell : ``"cells"``: the side of a cell (m, default 0.08).
    occlusion_attached : ``"cells"``: keep a voxel one camera missed only in a connected
        component (26-neighbourhood) that holds a voxel no camera missed (with the floor
        filter, one at or above ``min_top``), so phantoms of the other views and floor
        shadows next to a person are not published as pieces.
    occlusion_evidence, occlusion_ratio, occlusion_support, occlusion_margin : the
        occluder test of :class:`~.occlusion.OccluderModel` (``"learnt"``; evidence and
        ratio default to 4 and 0.6) and of :class:`~.occlusion_cells.CellOccluders`
        (``"cells"``; default 1 and 0.4, the best of those measured, docs/history/reconstruction-hull.md).
    learn_every : learn occluders from every n-th reconstructed frame (0: never, the
        masks stay as they are).
    abstain_support : a voxel on which a camera abstains behind an occluder needs
        ``occlusion_support`` foreground votes (not only ``min_views``).
    footprint : the silhouette-edge test (issue 8; an addition to the thesis, whose test
        is the centre pixel, ``footprint = 0``): a camera also accepts a voxel whose
        centre pixel is background when at least this fraction of the pixel box of
        side ``2 footprint_radius + 1`` around it is foreground, so a voxel the
        silhouette's outline cuts is not lost at reduced mask sizes (see
        :func:`.footprint.accept_map`).
    footprint_radius : half side (pixels) of that box; at the matched mask scale a
        voxel's footprint is 1-3 pixels wide, so 1.
    occlusion_top : learnt occluders: cameras abstain (and occluders are learnt) only
        on voxels whose centre is lower than this (m): the furniture that hides people
        is low, while the phantoms the cones of other people leave reach head height;
        0 (default): no limit.
    min_component : drop connected components of fewer voxels than this from the
        published voxels (ghosts where silhouette cones of different people meet); 0
        (the thesis) keeps all. Applied after ``min_top``.
    ghost_share : drop the connected components that no camera needs (ghosts where the
        cones of different people meet, :mod:`.ghosts`): a component is kept when in some
        camera at least this share (and 5) of the foreground pixels it projects to are
        covered by no other component; 0 (the thesis) keeps all. Applied after
        ``min_top``, before ``min_component``.
    misses : also count, per published voxel, the cameras that call it background
        (:mod:`.consensus`; the ``k = 0`` subset of a ``k = 1`` hull is ``misses == 0``);
        after :meth:`reconstruct` they are in :attr:`misses` (N,) uint8 (empty when off).
    """

    def __init__(self, calibration: Calibration, voxel_size: float, mask_sizes: Mapping | None = None,
                 colour_sizes: Mapping | None = None, tolerance: int = 1, min_views: int = 2,
                 method: str = "hierarchical", colouring: str = "visibility", brick: int = 8,
                 box_levels: int = 2, splat: float = 1.0, depth_tolerance: float = 3.0, march: int = 6,
                 threads: int = 1, cache: bool = False, warm_up: bool = True, min_top: float = 0.0,
                 occlusion: str = "none", occlusion_evidence: int | None = None, occlusion_ratio: float | None = None,
                 occlusion_support: int = 3, occlusion_margin: float = 0.1, learn_every: int = 1,
                 abstain_support: bool = True, alpha: float = 0.99, samples: str = "all",
                 footprint: float = 0.0, footprint_radius: int = 1, min_component: int = 0,
                 occlusion_top: float = 0.0, misses: bool = False, occlusion_cell: float = 0.08,
                 occlusion_attached: bool = True, ghost_share: float = 0.0, miss_support: int = 0):
        if method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
        if colouring not in COLOURINGS:
            raise ValueError(f"colouring must be one of {', '.join(COLOURINGS)}, got {colouring!r}")
        if occlusion not in OCCLUSIONS:
            raise ValueError(f"occlusion must be one of {', '.join(OCCLUSIONS)}, got {occlusion!r}")
        if occlusion == "cells" and not occlusion_cell > 0:
            raise ValueError(f"occlusion_cell must be > 0 m, got {occlusion_cell}")
        if occlusion != "none" and method == "fused":
            raise ValueError("learnt occluders work with the hierarchical and flat methods, not with fused")
        if not 0.0 <= footprint <= 1.0 or footprint_radius < 1 or min_component < 0:
            raise ValueError("footprint must be in [0, 1], footprint_radius >= 1 and min_component >= 0")
        if footprint > 0 and method == "fused":
            raise ValueError("the footprint test works with the hierarchical and flat methods, not with fused")
        if tolerance < 0 or min_views < 1 or miss_support < 0:
            raise ValueError("tolerance must be >= 0, min_views >= 1 and miss_support >= 0")
        if miss_support > 0 and method == "fused":
            raise ValueError("miss_support works with the hierarchical and flat methods, not with fused")
        if len(calibration.cameras) > MAX_CAMERAS:
            raise ValueError(f"at most {MAX_CAMERAS} cameras, got {len(calibration.cameras)}")
        t0 = time.perf_counter()
        self.calibration = calibration
        self.names = list(calibration.names)
        self.method = method
        self.colouring = colouring
        self.tolerance = int(tolerance)
        self.min_views = int(min_views)
        self.miss_support = int(miss_support)
        self.grid = VoxelGrid.from_room(calibration.room_min, calibration.room_max, voxel_size)
        self.layout = BrickLayout(self.grid, brick)
        mask_sizes = dict(mask_sizes or {})
        colour_sizes = dict(colour_sizes or {})
        for d, what in ((mask_sizes, "mask_sizes"), (colour_sizes, "colour_sizes")):
            unknown = set(d) - set(self.names)
            if unknown:
                raise ValueError(f"{what}: unknown camera {sorted(unknown)[0]!r} (have {', '.join(self.names)})")
        self.mask_cameras = []
        self.colour_cameras = []
        for cam in calibration.cameras:
            mw, mh = mask_sizes.get(cam.name, (cam.width, cam.height))
            mc = cam if (mw, mh) == (cam.width, cam.height) else cam.scaled(mw, mh)
            cw, ch = colour_sizes.get(cam.name, (mw, mh))
            cc = cam if (cw, ch) == (cam.width, cam.height) else cam.scaled(cw, ch)
            self.mask_cameras.append(mc)
            self.colour_cameras.append(cc)
        self.table = ProjectionTable(self.layout, self.mask_cameras, box_levels=box_levels, cache=cache)
        self.build_ms = (time.perf_counter() - t0) * 1e3
        self.floor = FloorBlobFilter(voxel_size, self.grid.origin[2], self.grid.dims, min_top) if min_top > 0 else None
        self.footprint = float(footprint)
        self.footprint_radius = int(footprint_radius)
        self.ghosts = GhostFilter(self.grid.dims, min_component) if min_component > 0 else None
        if not 0.0 <= ghost_share <= 1.0:
            raise ValueError(f"ghost_share must be in [0, 1], got {ghost_share}")
        self.explained = None       # set once the projection tables exist (below)
        self.colourer = VoxelColourer(self.grid, self.colour_cameras, colouring, splat=splat,
                                      depth_tolerance=depth_tolerance, march=march, threads=threads)
        # per-frame buffers, allocated once
        t = self.table
        self._votes = np.zeros(t.mask_total + 1, dtype=np.uint8)     # + the 0 sentinel
        if ghost_share > 0:
            self.explained = ExplainedFilter(self.grid.dims, t.mask_total, ghost_share)
        self._sat = np.zeros(t.sat_total, dtype=np.int32)
        if method == "fused":
            if not 0.5 <= alpha < 1.0:
                raise ValueError(f"alpha must be in [0.5, 1), got {alpha}")
            self.alpha = float(alpha)
            self._dsat = np.zeros(t.sat_total, dtype=np.float64)
            if samples not in ("all", "sqrt"):
                raise ValueError(f"samples must be all or sqrt, got {samples!r}")
            self.samples = samples
            largest = max(w * h for w, h in t.mask_sizes)
            self.thresholds = chi2_thresholds(alpha, largest if samples == "all" else int(np.ceil(np.sqrt(largest))) + 1)
            self._fused_masks: dict = {}
        self.occluders = None
        self.cell_occluders = None
        cells = occlusion == "cells"
        if occlusion_evidence is None:
            occlusion_evidence = 1 if cells else 4
        if occlusion_ratio is None:
            occlusion_ratio = 0.4 if cells else 0.6
        # carving tolerance: "cells" carves at k + 1 and then selects (occlusion_cells)
        self._carve_tolerance = self.tolerance + (1 if occlusion == "cells" else 0)
        if occlusion == "cells":
            cell = max(1, int(round(occlusion_cell / voxel_size)))
            self.cell_occluders = CellOccluders(self.grid.dims, cell, len(self.names), t.mask_total,
                                                occlusion_evidence, occlusion_ratio, occlusion_support)
            g = self.grid
            self._depth_coef = np.array([[*(c.R[2] * g.voxel_size), float(c.R[2] @ (g.origin + 0.5 * g.voxel_size))
                                          + float(c.t[2])] for c in self.mask_cameras], dtype=np.float64)
            self._attached = Labeller(self.grid.dims) if occlusion_attached else None
        if occlusion == "learnt":
            self.occluders = OccluderModel(t.mask_total, occlusion_evidence, occlusion_ratio, occlusion_support,
                                           occlusion_margin)
            # depth (camera z, m) of voxel (i, j, k) in each mask camera: coef . (i, j, k, 1)
            g = self.grid
            self._depth_coef = np.array([[*(c.R[2] * g.voxel_size), float(c.R[2] @ (g.origin + 0.5 * g.voxel_size))
                                          + float(c.t[2])] for c in self.mask_cameras], dtype=np.float64)
            self._raw = np.zeros(t.mask_total + 1, dtype=np.uint8)     # votes with no occluder
            self._fg = np.zeros(t.mask_total, dtype=np.uint8)          # the masks, 0/1
            self._sat_fg = np.zeros(t.sat_total, dtype=np.int32)
        self.occlusion = occlusion
        self._k_top = 1 << 30
        if occlusion_top > 0:
            self._k_top = max(0, int(np.ceil((occlusion_top - self.grid.origin[2]) / voxel_size - 0.5)))
        self.abstain_support = bool(abstain_support)
        self.learn_every = int(learn_every)
        self.frames_carved = 0
        self.count_misses = bool(misses)
        self.misses = np.zeros(0, dtype=np.uint8)
        views = t.views_per_brick()
        self._root_cells = np.flatnonzero(views >= self.min_views).astype(np.int32)
        self._all_bricks = np.arange(self.layout.n_bricks, dtype=np.int32)
        self._edge = [np.empty(self.layout.n_cells(l + 1), dtype=np.int32) for l in range(t.box_levels)]
        self._full = [np.empty(self.layout.n_cells(l), dtype=np.int32) for l in range(t.box_levels)]
        # keys of the occupied voxels and the sort's scratch: room for every voxel (the
        # flat method's bound), pages touched now for the first 2^19 (4 MB each)
        self._keys = np.empty(self.layout.n_positions, dtype=np.int64)
        self._scratch = np.empty(self.layout.n_positions, dtype=np.int64)
        self._keys[: 1 << 19] = 0
        self._scratch[: 1 << 19] = 0
        self.warm_up_ms = 0.0
        if warm_up:
            t1 = time.perf_counter()
            self._warm_up()
            self.warm_up_ms = (time.perf_counter() - t1) * 1e3

    # -- properties -----------------------------------------------------------------
    @property
    def voxel_size(self) -> float:
        return self.grid.voxel_size

    @property
    def table_bytes(self) -> int:
        """Memory of the projection tables (bytes)."""
        return self.table.nbytes

    # -- one frame --------------------------------------------------------------------
    def _upload_masks(self, masks: Mapping) -> np.ndarray:
        """Write the masks as votes into the concatenated buffer (0 for a camera without a
        mask) and, for the hierarchical method, their summed-area tables; returns the
        indices of the cameras with a mask. With learnt occluders the votes abstain
        behind them, the summed-area table counts the pixels that may vote foreground
        (foreground or occluded) and a second one the foreground alone."""
        t = self.table
        occ = self.occluders
        cams = []
        for c, name in enumerate(self.names):
            m = masks.get(name)
            w, h = t.mask_sizes[c]
            o = t.mask_offset[c]
            votes = self._votes[o: o + w * h].reshape(h, w)
            if m is None:
                votes[:] = 0
                if occ is not None:
                    self._raw[o: o + w * h] = 0
                    self._fg[o: o + w * h] = 0
                continue
            if m.shape != (h, w):
                raise ValueError(f"camera {name}: mask must be {h}x{w}, got {'x'.join(map(str, m.shape))}")
            sat = self._sat[t.sat_offset[c]: t.sat_offset[c] + (w + 1) * (h + 1)].reshape(h + 1, w + 1)
            if self.method == "fused":   # m is the distance map d_M (Caillette Eq. 6)
                d = np.asarray(m, dtype=np.float32)
                fg = d > self.thresholds[1]
                self._fused_masks[name] = fg
                m01 = fg.view(np.uint8)
                mask_votes(m01.reshape(-1), votes.reshape(-1))
                dsat = self._dsat[t.sat_offset[c]: t.sat_offset[c] + (w + 1) * (h + 1)].reshape(h + 1, w + 1)
                cv2.integral(d, sum=dsat, sdepth=cv2.CV_64F)
                cv2.integral(1 - m01, sum=sat, sdepth=cv2.CV_32S)   # background-like pixels (d_M <= T_1)
                cams.append(c)
                continue
            m01 = np.ascontiguousarray(m.view(np.uint8) if m.dtype == np.bool_ else (m != 0).view(np.uint8))
            if self.footprint > 0:
                m01 = accept_map(m01, self.footprint, self.footprint_radius)
            if occ is None:
                mask_votes(m01.reshape(-1), votes.reshape(-1))
                if self.method == "hierarchical":
                    cv2.integral(m01, sum=sat, sdepth=cv2.CV_32S)
            else:
                flat = m01.reshape(-1)
                self._fg[o: o + w * h] = flat
                mask_votes(flat, self._raw[o: o + w * h])
                occluded = occ.occluded[o: o + w * h]
                occluded_votes(flat, occluded, votes.reshape(-1))
                if self.method == "hierarchical":
                    cv2.integral(m01 | occluded.reshape(h, w), sum=sat, sdepth=cv2.CV_32S)
                    sat_fg = self._sat_fg[t.sat_offset[c]: t.sat_offset[c] + (w + 1) * (h + 1)].reshape(h + 1, w + 1)
                    cv2.integral(m01, sum=sat_fg, sdepth=cv2.CV_32S)
            cams.append(c)
        return np.asarray(cams, dtype=np.int64)

    def _learn_occluders(self, cams: np.ndarray) -> None:
        """One frame's evidence for the occluder masks (:mod:`.occlusion`): the voxels
        of the hull at ``tolerance + 1`` (the occluders learnt so far abstaining) that
        exactly ``tolerance + 1`` cameras call background, found coarse-to-fine with the same
        conservative cell tests as the carving."""
        occ = self.occluders
        t, lay = self.table, self.layout
        L = lay.levels
        dissent = self.tolerance + 1
        mv = self.min_views
        if len(cams) >= max(mv, occ.support):
            if self.method == "flat":
                self._dissent(self._all_bricks, 3 * L, dissent)
            else:
                cells = self._root_cells
                last = t.box_levels - 1
                for lvl in range(t.box_levels):
                    n_edge, n_full = classify_cells(cells, t.boxes[lvl], cams, self._sat, t.sat_offset, t.sat_stride,
                                                    dissent, mv, lvl < last, self._edge[lvl], self._full[lvl],
                                                    self._sat_fg)
                    if n_full:
                        self._dissent(self._full[lvl][:n_full], 3 * (L - lvl), dissent)
                    cells = self._edge[lvl][:n_edge]
                self._dissent(cells, 3 * (L - last), dissent)
        occ.add(self._fg)

    def _dissent(self, cells, shift, dissent) -> int:
        occ, lay = self.occluders, self.layout
        return dissent_cells(cells, shift, self.table.lut, self._votes, self._raw, self._depth_coef, occ.occ_depth,
                             dissent, occ.support, lay.brick_key, lay.local_key, lay.key_shift_i, lay.key_shift_j,
                             occ.flag, occ.flag_depth, occ.free_depth, self._k_top)

    def _carve_voxels(self, cells, shift, k, mv, n, early_exit) -> int:
        """The exact per-voxel test of ``cells``, with or without occluders."""
        t, lay = self.table, self.layout
        if self.occluders is None:
            return carve_cells(cells, shift, t.lut, self._votes, k, mv, lay.brick_key, lay.local_key, self._keys, n,
                               early_exit, self.miss_support)
        return carve_cells_occluded(cells, shift, t.lut, self._votes, self._depth_coef, self.occluders.occ_depth, k, mv,
                                    lay.brick_key, lay.local_key, lay.key_shift_i, lay.key_shift_j, self._keys, n,
                                    self.occluders.support if self.abstain_support else 0, self._k_top,
                                    self.miss_support)

    def occluder_share(self) -> dict:
        """``{camera: fraction of its mask's pixels that are learnt occluder pixels}``."""
        if self.cell_occluders is not None:
            return {n: self.cell_occluders.share(c) for c, n in enumerate(self.names)}
        if self.occluders is None:
            return {}
        t = self.table
        return {n: self.occluders.share(int(t.mask_offset[c]), t.mask_sizes[c][0] * t.mask_sizes[c][1])
                for c, n in enumerate(self.names)}

    def carve(self, masks: Mapping) -> np.ndarray:
        """Occupied voxels (N, 3) uint16, sorted by flat id, from ``{camera: mask or None}``."""
        cams = self._upload_masks(masks)
        if self.cell_occluders is not None:
            indices, _ = self._select_cells(self._carve_keys(cams), cams)
        else:
            indices = self._indices(self._carve_keys(cams))
        self._after_carving(cams)
        if self.floor is not None:
            indices = self.floor(indices)
        if self.explained is not None:
            indices = self.explained(indices, self.layout, self.table.lut, self._votes)
        return self.ghosts(indices) if self.ghosts is not None else indices

    def _select_cells(self, keys: np.ndarray, cams: np.ndarray):
        """``occlusion="cells"``: from the keys of the hull carved at ``k + 1`` (unsorted),
        the voxels that are kept (at most ``k`` misses, or ``k + 1`` all behind learnt
        occlusion; sorted), their misses, and this frame's evidence
        (:mod:`.occlusion_cells`)."""
        occ, lay = self.cell_occluders, self.layout
        learn = bool(self.learn_every) and (self.frames_carved + 1) % self.learn_every == 0 \
            and len(cams) >= self.min_views
        n = select_and_learn(keys, np.int64(lay.key_shift_i), np.int64(lay.key_shift_j), np.int64(lay.levels),
                             lay.brick_dims_arr, self.table.lut, self._votes, self._depth_coef,
                             np.int64(self.tolerance), np.int64(occ.support), np.int64(self._k_top), np.int64(occ.cell),
                             occ.cell_dims, occ.occluded, learn, occ.free_depth, occ.seen_flag, occ.evidence_flag)
        if learn:
            occ.fold()
        keys = keys[:n]
        radix_sort(keys, lay.key_bits, self._scratch)     # by the low key bits: the misses ride along
        misses = (keys >> MISSES_SHIFT).astype(np.uint8)
        keys &= (np.int64(1) << MISSES_SHIFT) - 1
        indices = np.empty((n, 3), dtype=np.uint16)
        keys_to_indices(keys, lay.key_shift_i, lay.key_shift_j, indices)
        if self._attached is not None and (misses > self.tolerance).any():
            labels, count = self._attached(indices)
            agreed = misses <= self.tolerance
            if self.floor is not None:      # anchors: agreed voxels at or above the floor filter's top layer
                agreed &= indices[:, 2] > self.floor.top_layer
            anchored = np.zeros(count, dtype=np.bool_)
            anchored[labels[agreed]] = True
            attached = anchored[labels]
            if not attached.all():
                indices, misses = indices[attached], misses[attached]
        return indices, misses

    def _after_carving(self, cams) -> None:
        self.frames_carved += 1
        if self.occluders is not None and self.learn_every and self.frames_carved % self.learn_every == 0:
            self._learn_occluders(cams)

    def _carve_keys(self, cams: np.ndarray) -> np.ndarray:
        """Sort keys of the occupied voxels (unsorted), from the uploaded masks."""
        t, lay = self.table, self.layout
        L = lay.levels
        k, mv = self._carve_tolerance, self.min_views
        keys = self._keys
        if len(cams) < mv:
            return keys[:0]
        if self.method == "flat":
            n = self._carve_voxels(self._all_bricks, 3 * L, k, mv, 0, True)
            return keys[:n]
        n = 0
        cells = self._root_cells
        last = t.box_levels - 1
        if self.method == "fused":
            for lvl in range(t.box_levels):
                n_edge, n_full = classify_cells_fused(cells, t.boxes[lvl], cams, self._dsat, self._sat, t.sat_offset,
                                                      t.sat_stride, self.thresholds, k, mv, lvl < last,
                                                      self._edge[lvl], self._full[lvl], self.samples == "sqrt")
                if n_full:
                    n = fill_cells(self._full[lvl][:n_full], 3 * (L - lvl), lay.brick_key, lay.local_key, keys, n)
                cells = self._edge[lvl][:n_edge]
            return keys[:self._carve_voxels(cells, 3 * (L - last), k, mv, n, False)]
        for lvl in range(t.box_levels):
            n_edge, n_full = classify_cells(cells, t.boxes[lvl], cams, self._sat, t.sat_offset, t.sat_stride, k, mv,
                                            lvl < last, self._edge[lvl], self._full[lvl],
                                            None if self.occluders is None else self._sat_fg,
                                            self.occluders.support if self.occluders is not None
                                            and self.abstain_support else 0, self.miss_support)
            if n_full:
                n = fill_cells(self._full[lvl][:n_full], 3 * (L - lvl), lay.brick_key, lay.local_key, keys, n)
            cells = self._edge[lvl][:n_edge]
        n = self._carve_voxels(cells, 3 * (L - last), k, mv, n, False)
        return keys[:n]

    def _indices(self, keys: np.ndarray) -> np.ndarray:
        """Sort the keys (= by flat id) and decode them to (N, 3) uint16."""
        lay = self.layout
        radix_sort(keys, lay.key_bits, self._scratch)
        idx = np.empty((len(keys), 3), dtype=np.uint16)
        keys_to_indices(keys, lay.key_shift_i, lay.key_shift_j, idx)
        return idx

    def reconstruct(self, masks: Mapping, images: Mapping | None = None):
        """Reconstruct one frame.

        ``masks``: ``{camera: (h, w) bool mask or None}`` (a missing camera or ``None``
        lowers ``N_visible``); ``images``: ``{camera: (h, w, 3) BGR uint8 or None}`` at
        the colour size (needed for colours; the surface flag is geometric).

        Returns ``(indices, colours, surface, timings)``: occupied voxels (N, 3) uint16
        sorted by flat id, colours (N, 3) RGB uint8 (empty for ``colouring="none"``;
        zero on interior voxels), surface flags (N,) bool (empty for ``"none"`` and
        ``"naive"``) and ``{"carve", "floor", "surface", "colour", "total"}`` in ms (and
        ``"misses"`` with ``misses=True``; the counts are then in :attr:`misses`).
        """
        unknown = set(masks) - set(self.names)
        if unknown:
            raise ValueError(f"masks: unknown camera {sorted(unknown)[0]!r} (have {', '.join(self.names)})")
        t0 = time.perf_counter()
        cams = self._upload_masks(masks)
        if self.cell_occluders is not None:     # selection and misses in one visit
            indices, misses = self._select_cells(self._carve_keys(cams), cams)
            misses = misses if self.count_misses else None
            tm = 0.0
        else:
            indices = self._indices(self._carve_keys(cams))
            tm = time.perf_counter()
            misses = self.misses_of(indices) if self.count_misses else None   # before occluders learn
            tm = time.perf_counter() - tm
        self._after_carving(cams)
        t1 = time.perf_counter()
        timings = {"carve": (t1 - t0) * 1e3 - tm * 1e3, "floor": 0.0, "surface": 0.0, "colour": 0.0}
        if self.floor is not None or self.ghosts is not None or self.explained is not None:
            carved = indices
            if self.floor is not None:
                indices = self.floor(indices)
            if self.explained is not None:
                indices = self.explained(indices, self.layout, self.table.lut, self._votes)
            if self.ghosts is not None:
                indices = self.ghosts(indices)
            if misses is not None:
                misses = select_misses(carved, indices, misses, self.grid.dims)
            timings["floor"] = (time.perf_counter() - t1) * 1e3
        self.misses = misses if misses is not None else np.zeros(0, dtype=np.uint8)
        if misses is not None:
            timings["misses"] = tm * 1e3
        images = images or {}
        imgs = [images.get(n) for n in self.names]
        if self.method == "fused":
            masks = self._fused_masks
        colours, surface, tc = self.colourer.colour(indices, imgs, [masks.get(n) for n in self.names])
        timings.update(tc)
        timings["total"] = (time.perf_counter() - t0) * 1e3
        return indices, colours, surface, timings

    def misses_of(self, indices: np.ndarray) -> np.ndarray:
        """(N,) uint8: the cameras calling each voxel of ``indices`` background in the last
        carved frame, as the final carving level reads them."""
        occ = self.occluders
        if occ is None:
            return count_misses(indices, self.layout, self.table.lut, self._votes)
        return count_misses(indices, self.layout, self.table.lut, self._votes, self._depth_coef, occ.occ_depth,
                            self._k_top)

    def _warm_up(self) -> None:
        """Run every kernel once on an empty frame and on a tiny blob (numba compiles or
        loads its cache here, not on the first real frame)."""
        masks = {}
        for cam in self.mask_cameras:
            m = np.zeros((cam.height, cam.width), dtype=bool)
            m[cam.height // 2 - 1: cam.height // 2 + 2, cam.width // 2 - 1: cam.width // 2 + 2] = True
            masks[cam.name] = m if self.method != "fused" else m.astype(np.float32) * 1000.0
        images = {c.name: np.zeros((c.height, c.width, 3), np.uint8) for c in self.colour_cameras}
        self.reconstruct(masks, images)
        # images decoded from bus messages are read-only views: numba compiles those apart
        for img in images.values():
            img.flags.writeable = False
        self.reconstruct(masks, images)
        if self.occluders is not None:  # the warm-up frames are no evidence
            self.occluders.reset()
        if self.cell_occluders is not None:
            self.cell_occluders.reset()
        self.frames_carved = 0
        if self.floor is not None:  # the tiny blob may leave no voxel for the floor filter
            self.floor(np.zeros((2, 3), dtype=np.uint16))
        if self.ghosts is not None:
            self.ghosts(np.zeros((2, 3), dtype=np.uint16))
        if self.explained is not None:   # two components, so the kernel compiles here
            self.explained(np.array([[0, 0, 0], [0, 0, 5]], dtype=np.uint16), self.layout, self.table.lut, self._votes)
        lay = self.layout
        fill_cells(self._root_cells[:0], 0, lay.brick_key, lay.local_key, self._keys, 0)   # may not have run
