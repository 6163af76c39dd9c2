"""Occluder masks learnt over a run (Guan, Franco and Pollefeys, "Visual hull
construction in the presence of partial occlusion", 3DPVT 2006).

Shape from silhouette with ``tolerance = 0`` (thesis §2.2.4) keeps a tight hull but
loses every part of a body that one camera cannot see: a leg behind the table, a
sitting person's knees under it. ``tolerance = 1`` keeps them, and pays for it
everywhere: each camera may then miss any voxel, so the hull swells where the
silhouette cones of the other cameras meet (issue 8: 5-6x the body volume).

A static occluder hides the same pixels of one camera frame after frame. So a camera
may be allowed to miss a voxel *only where something static hides it from that
camera*: pixels of camera ``c`` where, frame after frame, the other cameras
reconstruct matter (a voxel with ``support`` or more foreground votes and exactly one
background vote, ``c``'s) while ``c`` sees background. Per pixel the model counts

    ``miss(p)``: frames in which such a voxel projects to ``p`` in camera ``c``,
    ``seen(p)``: frames in which ``p`` is foreground in ``c``'s own mask,

and ``p`` is an occluder pixel once ``miss(p) >= min_evidence`` and
``miss(p) >= ratio * (miss(p) + seen(p))``: a pixel that often shows people itself
(floor, walls, a person's usual path) never becomes one; the phantom voxels where the
cones of other people meet fall on ever different pixels and rarely reach the count.
Behind an occluder pixel the camera abstains (as where it does not see the voxel), so
the carving is ``tolerance = 0`` everywhere else. Nothing about the room's furniture
is given: the masks are learnt from the masks and the reconstruction alone.

Seen free space (Guan et al.'s argument that an occluder lies in front of what it
hides): where a camera sees a person (a voxel every camera agrees on) through a pixel,
nothing static hides that pixel up to the person's depth, so a miss at or in front of
the deepest such depth is a phantom of the other views, not an occlusion, and gives no
evidence.

Depth (after Guan et al., whose occlusion is per pixel and depth): each occluder
pixel keeps the least depth (camera z) of the voxels that gave evidence for it, and
the camera abstains only on voxels at or past that depth less ``margin``; on nearer
voxels (in front of the table) it still votes background.
"""
from __future__ import annotations

import numpy as np

__all__ = ["OccluderModel"]


class OccluderModel:
    """Per-pixel occlusion evidence of every camera, in the concatenated mask layout
    of :class:`~.projection.ProjectionTable` (camera ``c`` at ``mask_offset[c]``)."""

    def __init__(self, mask_total: int, min_evidence: int = 4, ratio: float = 0.6, support: int = 3,
                 margin: float = 0.1):
        if min_evidence < 1 or not 0.0 < ratio <= 1.0 or support < 1:
            raise ValueError("occlusion: min_evidence >= 1, 0 < ratio <= 1 and support >= 1 needed")
        self.min_evidence = int(min_evidence)
        self.ratio = float(ratio)
        self.support = int(support)
        self.miss = np.zeros(mask_total, dtype=np.float32)
        self.seen = np.zeros(mask_total, dtype=np.float32)
        self.flag = np.zeros(mask_total + 1, dtype=np.uint8)     # + the "not seen" sentinel, as the votes
        self.flag_depth = np.full(mask_total + 1, np.inf, dtype=np.float32)
        self.free_depth = np.zeros(mask_total + 1, dtype=np.float32)       # seen free up to (m)
        self.depth = np.full(mask_total, np.inf, dtype=np.float32)          # least evidence depth (m)
        self.occ_depth = np.full(mask_total + 1, np.inf, dtype=np.float32)  # abstain from here on (m)
        self.margin = float(margin)
        self.occluded = np.zeros(mask_total, dtype=np.uint8)
        self.updates = 0

    def add(self, foreground: np.ndarray) -> None:
        """Fold in one frame: ``flag`` (set by :func:`.carving.dissent_cells`) and the
        concatenated 0/1 foreground masks of the cameras that had one."""
        flag = self.flag[:-1]
        self.miss += flag
        self.seen += foreground
        np.minimum(self.depth, self.flag_depth[:-1], out=self.depth)
        self.flag[:] = 0
        self.flag_depth[:] = np.inf
        self.updates += 1
        m, s = self.miss, self.seen
        self.occluded[:] = (m >= self.min_evidence) & (m >= self.ratio * (m + s))
        self.occ_depth[:-1] = self.depth - self.margin

    def share(self, offset: int, size: int) -> float:
        """Fraction of one camera's pixels that are occluder pixels."""
        return float(self.occluded[offset: offset + size].mean()) if size else 0.0

    def reset(self) -> None:
        self.miss[:] = 0
        self.seen[:] = 0
        self.flag[:] = 0
        self.flag_depth[:] = np.inf
        self.free_depth[:] = 0
        self.depth[:] = np.inf
        self.occ_depth[:] = np.inf
        self.occluded[:] = 0
        self.updates = 0
