"""Per-voxel camera misses (app.reconstruction.consensus): against a brute-force count
from ``Camera.project`` of every voxel centre into every mask, and the ``misses == 0``
subset of a ``k = 1`` hull against a ``k = 0`` carving of the same masks."""
from __future__ import annotations

import numpy as np
import pytest

from app.reconstruction import Reconstructor
from app.reconstruction.footprint import accept_map
from app.reconstruction.synthetic import Scene, person
from tests.synthetic import tiny_calibration

VOXEL = 0.05


@pytest.fixture(scope="module")
def calib():
    return tiny_calibration(5, 160, 120)


@pytest.fixture(scope="module")
def masks(calib):
    """Two people, salt-and-pepper noise, one camera without a mask this frame."""
    scene = Scene([person(1.5, 2.0, facing_deg=0.0, arm_raise=0.35), person(2.7, 2.2, facing_deg=90.0)])
    m, _ = scene.frame(calib.cameras)
    rng = np.random.default_rng(7)
    out = {n: a ^ (rng.random(a.shape) < 0.02) for n, a in m.items()}
    out["cam3"] = None
    return out


def brute_misses(calib, grid, idx, masks, footprint=0.0):
    """Cameras with a mask that see the voxel's centre on a background pixel."""
    centres = grid.centres(idx)
    miss = np.zeros(len(idx), dtype=np.int64)
    for cam in calib.cameras:
        m = masks.get(cam.name)
        if m is None:
            continue
        m01 = m.astype(np.uint8)
        if footprint > 0:
            m01 = accept_map(m01, footprint, 1)
        seen = cam.sees(centres)
        uv = cam.project(centres)
        with np.errstate(invalid="ignore"):
            u = np.floor(uv[:, 0] + 0.5)
            v = np.floor(uv[:, 1] + 0.5)
        ok = seen & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        bg = np.zeros(len(idx), dtype=bool)
        bg[ok] = m01[v[ok].astype(np.int64), u[ok].astype(np.int64)] == 0
        miss += bg
    return miss


@pytest.mark.parametrize("method,footprint", [("hierarchical", 0.0), ("flat", 0.0), ("hierarchical", 0.5)])
def test_misses_match_brute_force_and_k0(calib, masks, method, footprint):
    r = Reconstructor(calib, VOXEL, tolerance=1, method=method, colouring="none", misses=True, footprint=footprint)
    idx, _, _, timings = r.reconstruct(masks)
    misses = r.misses
    assert misses.dtype == np.uint8 and misses.shape == (len(idx),) and len(idx) > 1000
    assert "misses" in timings
    ref = brute_misses(calib, r.grid, idx, masks, footprint)
    # exact but for centres within rounding of a pixel border (the table's own maths)
    assert np.mean(misses == ref) > 0.999
    assert misses.max() <= 1 and (misses == 1).sum() > 0.3 * len(idx)   # k = 1: every voxel <= 1 miss
    k0 = Reconstructor(calib, VOXEL, tolerance=0, method=method, colouring="none", footprint=footprint).carve(masks)
    np.testing.assert_array_equal(idx[misses == 0], k0)


def test_misses_follow_the_floor_filter_and_are_off_by_default(calib, masks):
    r = Reconstructor(calib, VOXEL, tolerance=2, colouring="none", misses=True, min_top=0.5)
    idx, _, _, _ = r.reconstruct(masks)
    ref = brute_misses(calib, r.grid, idx, masks)
    assert np.mean(r.misses == ref) > 0.999 and r.misses.max() == 2
    off = Reconstructor(calib, VOXEL, colouring="none")
    off.reconstruct(masks)
    assert off.misses.size == 0
