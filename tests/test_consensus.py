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


def test_misses_with_learnt_occluders_count_no_abstention(calib):
    """A static occluder hides the legs from cam0 frame after frame: once learnt, cam0
    abstains there, so the k = 0 carving keeps the legs and none of its voxels has a
    miss (an abstention is no miss); with k = 1 no voxel has more than one."""
    k0 = Reconstructor(calib, VOXEL, tolerance=0, colouring="none", misses=True, occlusion="learnt",
                       occlusion_evidence=2)
    k1 = Reconstructor(calib, VOXEL, tolerance=1, colouring="none", misses=True, occlusion="learnt",
                       occlusion_evidence=2)
    counts = []
    for f in range(10):
        m, _ = Scene([person(1.5 + 0.05 * f, 2.0, facing_deg=0.0)]).frame(calib.cameras)
        m = dict(m)
        m["cam0"] = m["cam0"].copy()
        m["cam0"][m["cam0"].shape[0] // 2:, :] = False
        idx, _, _, _ = k0.reconstruct(m)
        k1.reconstruct(m)
        assert len(k0.misses) == len(idx) and not k0.misses.any()
        assert k1.misses.max() <= 1
        counts.append(len(idx))
    assert k0.occluder_share()["cam0"] > 0.005 and counts[-1] > 1.05 * counts[0]   # the legs came back


# -- the pose stage on the consensus subset ------------------------------------------------
POSE_FRAMES = range(0, 24)


@pytest.fixture(scope="module")
def hull_clip():
    """meeting3 (2 people in these frames, 4 cameras) at 4 cm: the k = 1 hull of the true silhouettes at
    the pipeline's mask size (160x120), with misses, true centroids as tracks."""
    import cv2

    from app.messages import JOINTS
    from app.simulation.simulator import Simulator

    sim = Simulator("meeting3", seed=0, seconds=(max(POSE_FRAMES) + 2) / 25.0, width=320, height=240)
    cal = sim.calibration
    sizes = {c.name: (160, 120) for c in cal.cameras}
    rec = Reconstructor(cal, 0.04, mask_sizes=sizes, colouring="none", min_top=0.25, tolerance=1, misses=True)
    frames = []
    for i in POSE_FRAMES:
        people = sim.people(i)
        _, labels, gt = sim.render_people(i, people, noise=False)
        masks = {c: cv2.resize((labels[c] >= 0).astype(np.float32), sizes[c], interpolation=cv2.INTER_AREA) >= 0.5
                 for c in labels}
        idx, _, _, _ = rec.reconstruct(masks)
        frames.append({"frame": i, "indices": idx, "misses": rec.misses.copy(),
                       "ids": [p["id"] for p in gt["people"]],
                       "positions": np.array([p["centroid"] for p in gt["people"]], float).reshape(-1, 3),
                       "truth": {p["id"]: np.array([p["joints"][n] for n in JOINTS]) for p in gt["people"]}})
    return frames, rec.grid


def _mmta(errors):
    """Share of joints within 100 mm, ``errors`` ``[(frame, (15,) errors)]``, after the
    first frames (lock-on)."""
    E = np.array([e for f, e in errors if f >= min(POSE_FRAMES) + 2])
    return float((E <= 0.1).mean())


@pytest.mark.integration
def test_pose_worker_on_the_consensus_beats_the_whole_hull(hull_clip, tiny_recording, tmp_path):
    """The pose worker over the bus, fed the k = 1 hull with misses (default ``voxels:
    consensus``), against the same estimator on the whole hull (``voxels: all``)."""
    from app.messages import JOINTS
    from app.pose.estimator import PoseEstimator, PoseSettings
    from tests.pose_source import run_clip

    frames, grid = hull_clip
    assert min(len(f["ids"]) for f in frames) == 2 and all(0.2 < (f["misses"] == 0).mean() < 0.8 for f in frames)
    settings = dict(method="shbm", density=1.0, voxel_size=grid.voxel_size, room_lo=tuple(grid.origin),
                    room_hi=tuple(grid.room_max))
    est = PoseEstimator(PoseSettings(**settings))
    whole = []
    for f in frames:
        res = est.update(grid.centres(f["indices"]), None, f["ids"], f["positions"])
        whole += [(f["frame"], np.linalg.norm(res[t][0] - f["truth"][t], axis=1)) for t in f["ids"] if t in res]
    mmta_all = _mmta(whole)

    clip = tmp_path / "clip.npz"
    np.savez(clip, voxel_size=grid.voxel_size, origin=grid.origin, dims=np.asarray(grid.dims),
             frames=np.array([f["frame"] for f in frames]),
             offsets=np.cumsum([0] + [len(f["indices"]) for f in frames]),
             indices=np.concatenate([f["indices"] for f in frames]).astype(np.int16),
             misses=np.concatenate([f["misses"] for f in frames]),
             track_offsets=np.cumsum([0] + [len(f["ids"]) for f in frames]),
             ids=np.concatenate([np.array(f["ids"]) + 10 for f in frames]),
             positions=np.concatenate([f["positions"] for f in frames]))
    records = run_clip(clip, tmp_path, tiny_recording, [{"name": "pose", "params": {"method": "shbm", "density": 1}}])
    assert len(records) >= len(frames) // 2
    by_frame = {f["frame"]: f for f in frames}
    consensus = []
    for rec in records:
        f = by_frame[rec["frame"]]
        assert {p["track"] for p in rec["poses"]} == {i + 10 for i in f["ids"]}   # everyone, every frame
        for p in rec["poses"]:
            est_j = np.array([p["joints"][n] for n in JOINTS])
            consensus.append((f["frame"], np.linalg.norm(est_j - f["truth"][p["track"] - 10], axis=1)))
    mmta_cons = _mmta(consensus)
    print(f"meeting3 k=1 hull at 4 cm: MMTA whole hull {mmta_all:.3f}, consensus (pose worker) {mmta_cons:.3f}")
    assert mmta_cons >= 0.6 and mmta_cons >= mmta_all + 0.15
