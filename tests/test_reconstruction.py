"""Voxel reconstruction core: grid, projection tables, shape from silhouette (flat and
coarse-to-fine), colouring with visibility (thesis §2.2.4, Caillette et al. §6.1).

Scenes are unions of spheres rendered exactly into cameras with lens distortion
(:mod:`app.reconstruction.synthetic`); the truth is "the voxel centre lies inside a sphere".
"""
from __future__ import annotations

import numpy as np
import pytest

from app.reconstruction import Reconstructor, VoxelColourer, VoxelGrid, boundary_voxels
from app.reconstruction.grid import BrickLayout, radix_sort
from app.reconstruction.projection import ProjectionTable, camera_params, fold_radius2, project_points
from app.reconstruction.synthetic import R_ARM, TORSO, Scene, meeting_scene, person, room_calibration
from tests.synthetic import tiny_calibration

VOXEL = 0.04


@pytest.fixture(scope="module")
def calib():
    """5 cameras 160x120 with barrel distortion around a 4 x 4 x 2.5 m room."""
    return tiny_calibration(5, 160, 120)


@pytest.fixture(scope="module")
def scene():
    """One person in the middle of the room, facing +x, right arm raised sideways."""
    return Scene([person(2.0, 2.0, facing_deg=0.0, arm_raise=0.35)])


@pytest.fixture(scope="module")
def frame(calib, scene):
    return scene.frame(calib.cameras)


@pytest.fixture(scope="module")
def recon(calib):
    return Reconstructor(calib, VOXEL)


def truth_indices(grid: VoxelGrid, scene: Scene) -> np.ndarray:
    """Voxels whose centre lies inside the true shape."""
    lo = grid.index_of(scene.spheres[:, :3].min(axis=0) - 0.3)[0].clip(0)
    hi = np.minimum(grid.index_of(scene.spheres[:, :3].max(axis=0) + 0.3)[0], np.asarray(grid.dims) - 1)
    ii, jj, kk = np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi)], indexing="ij")
    idx = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], axis=1)
    return idx[scene.inside(grid.centres(idx))]


def as_set(grid, idx) -> set:
    return set(grid.flat(idx).tolist())


# -- grid and layout ------------------------------------------------------------------
def test_grid_flat_ids_and_centres():
    g = VoxelGrid.from_room([0, 0, 0], [5, 4, 2.5], 0.03)
    assert g.dims == (167, 134, 84)
    idx = np.array([[0, 0, 0], [166, 133, 83], [5, 7, 9]])
    f = g.flat(idx)
    assert f[1] == g.n_voxels - 1
    np.testing.assert_array_equal(g.unflat(f), idx)
    np.testing.assert_allclose(g.centres(idx)[2], (np.array([5, 7, 9]) + 0.5) * 0.03)
    np.testing.assert_array_equal(g.index_of(g.centres(idx)), idx)


def test_brick_layout_round_trip_and_sort_keys():
    g = VoxelGrid.from_room([0, 0, 0], [1.0, 0.7, 0.5], 0.05)        # 20 x 14 x 10: padded bricks
    lay = BrickLayout(g, 8)
    rng = np.random.default_rng(0)
    idx = np.stack([rng.integers(0, d, 500) for d in g.dims], axis=1)
    pos = lay.indices_to_positions(idx)
    np.testing.assert_array_equal(lay.positions_to_indices(pos), idx)
    # the sort key of a voxel: brick key + local key; its order is the flat-id order
    keys = lay.brick_key[pos >> 9] + lay.local_key[pos & 511]
    np.testing.assert_array_equal(lay.keys_to_indices(keys, np.int64), idx)
    sorted_keys = keys.copy()
    radix_sort(sorted_keys, lay.key_bits, np.empty_like(keys))
    np.testing.assert_array_equal(sorted_keys, np.sort(keys))
    np.testing.assert_array_equal(g.flat(lay.keys_to_indices(sorted_keys, np.int64)), np.sort(g.flat(idx)))


# -- projection tables ------------------------------------------------------------------
def test_projection_matches_camera_project(calib):
    rng = np.random.default_rng(1)
    pts = rng.uniform([-1, -1, -0.5], [5, 5, 3], (5000, 3))
    for cam in calib.cameras:
        uv = np.empty((len(pts), 2))
        z = np.empty(len(pts))
        seen = np.empty(len(pts), dtype=np.bool_)
        project_points(camera_params(cam), pts, uv, z, seen)
        ref_uv, ref_z = cam.project(pts, return_depth=True)
        np.testing.assert_array_equal(seen, cam.sees(pts))            # no fold for these lenses
        np.testing.assert_allclose(uv[seen], ref_uv[seen], atol=1e-9)
        np.testing.assert_allclose(z, ref_z, atol=1e-12)


def test_lut_agrees_with_camera_project_at_mask_size(calib):
    """The table's pixel of every voxel in every (downscaled) mask is the rounded
    ``Camera.project`` of its centre, distortion included, -1 where ``sees`` is False."""
    g = VoxelGrid.from_room(calib.room_min, calib.room_max, 0.1)
    cams = [c.scaled(80, 60) for c in calib.cameras]
    table = ProjectionTable(BrickLayout(g, 8), cams)
    idx = g.unflat(np.arange(g.n_voxels), np.int64)
    pix = table.pixels(idx)
    centres = g.centres(idx)
    for c, cam in enumerate(cams):
        uv = cam.project(centres)
        seen = cam.sees(centres)
        with np.errstate(invalid="ignore"):
            ref = np.floor(uv[:, 1] + 0.5) * cam.width + np.floor(uv[:, 0] + 0.5)
        expected = np.where(seen, ref, -1).astype(np.int64)
        # exact but for points within 1e-6 px of a pixel border (rounding of equal maths)
        border = seen & ((np.abs((uv[:, 0] + 0.5) % 1.0 - 0.5) > 0.5 - 1e-6)
                         | (np.abs((uv[:, 1] + 0.5) % 1.0 - 0.5) > 0.5 - 1e-6))
        assert np.mean(pix[:, c] == expected) > 0.9999
        assert np.all((pix[:, c] == expected) | border)
        assert seen.sum() > 0.3 * len(seen)


def test_fold_radius_guards_non_monotonic_distortion():
    assert fold_radius2([-0.08, 0.01, 0, 0, 0]) == np.inf       # 1 - 0.24 r^2 + 0.05 r^4 > 0
    r2 = fold_radius2([-0.3, 0.0, 0, 0, 0])                      # 1 - 0.9 r^2 = 0 at r^2 = 1.11
    assert abs(r2 - 1 / 0.9) < 1e-9


def test_lut_cache_on_disk(calib, tmp_path, monkeypatch):
    monkeypatch.setenv("SMARTROOM_CACHE", str(tmp_path))
    g = VoxelGrid.from_room(calib.room_min, calib.room_max, 0.1)
    a = ProjectionTable(BrickLayout(g, 8), list(calib.cameras), cache=True)
    b = ProjectionTable(BrickLayout(g, 8), list(calib.cameras), cache=True)
    assert not a.from_cache and b.from_cache
    np.testing.assert_array_equal(a.lut, b.lut)
    for x, y in zip(a.boxes, b.boxes):
        np.testing.assert_array_equal(x, y)
    assert len(list((tmp_path / "lut").glob("*.npz"))) == 1


# -- shape from silhouette --------------------------------------------------------------
def test_recall_and_precision_against_true_volume(recon, scene, frame):
    """Every voxel whose centre is inside the body is found (recall >= 0.95); the visual
    hull of 5 views is larger than the body: precision (true / reconstructed) here ~0.6."""
    masks, _ = frame
    idx = recon.carve(masks)
    truth = as_set(recon.grid, truth_indices(recon.grid, scene))
    got = as_set(recon.grid, idx)
    recall = len(truth & got) / len(truth)
    precision = len(truth & got) / len(got)
    assert recall >= 0.95, recall
    assert precision >= 0.45, precision
    # the strict test (no tolerance) gives a tighter hull, and loses a little more of the
    # body's border, where a voxel centre inside the body falls on a background pixel
    strict = Reconstructor(recon.calibration, VOXEL, tolerance=0, colouring="none").carve(masks)
    got0 = as_set(recon.grid, strict)
    assert len(truth & got0) / len(truth) >= 0.9
    assert len(truth & got0) / len(got0) > precision


def test_output_is_sorted_unique_uint16(recon, frame):
    masks, images = frame
    idx, colours, surface, timings = recon.reconstruct(masks, images)
    assert idx.dtype == np.uint16 and idx.shape[1] == 3 and len(idx) > 1000
    f = recon.grid.flat(idx)
    assert np.all(np.diff(f) > 0)
    assert colours.shape == (len(idx), 3) and colours.dtype == np.uint8
    assert surface.shape == (len(idx),) and surface.dtype == np.bool_
    assert set(timings) >= {"carve", "surface", "colour", "total"}


def noisy_masks(masks, seed, flip=0.02):
    rng = np.random.default_rng(seed)
    out = {}
    for name, m in masks.items():
        noise = rng.random(m.shape) < flip
        out[name] = m ^ noise
    return out


@pytest.mark.parametrize("tolerance,min_views,miss_support", [(0, 1, 0), (1, 2, 0), (2, 2, 0), (1, 3, 0), (1, 2, 4),
                                                               (2, 2, 3)])
def test_hierarchical_equals_flat(calib, frame, tolerance, min_views, miss_support):
    """The coarse-to-fine carving gives exactly the flat result, also on noisy masks
    (salt and pepper), with a camera missing, and at the grid's padded edges."""
    masks, _ = frame
    opts = dict(tolerance=tolerance, min_views=min_views, miss_support=miss_support, colouring="none")
    hier = Reconstructor(calib, 0.05, **opts)
    flat = Reconstructor(calib, 0.05, method="flat", **opts)
    cases = [masks, noisy_masks(masks, 3), {**noisy_masks(masks, 4), "cam1": None},
             {n: np.ones_like(m) for n, m in masks.items()}]
    for m in cases:
        a, b = hier.carve(m), flat.carve(m)
        assert len(a) > 0
        np.testing.assert_array_equal(a, b)


def test_miss_support_lies_between_the_tolerances(calib, frame):
    """``miss_support``: a voxel one camera misses is kept only with that many foreground
    views. 0 (or at most min_views) is tolerance 1 as written, the number of cameras is
    tolerance 0, and the sets in between are nested; every voxel it drops is one a camera
    misses, seen by fewer cameras than asked."""
    masks = noisy_masks(frame[0], 7, flip=0.01)
    masks["cam2"] = masks["cam2"].copy()
    masks["cam2"][:, : masks["cam2"].shape[1] // 2] = 0          # one camera loses half the body
    sets = {}
    for s in range(0, 6):
        r = Reconstructor(calib, VOXEL, miss_support=s, colouring="none")
        sets[s] = as_set(r.grid, r.carve(masks))
    k0 = as_set(r.grid, Reconstructor(calib, VOXEL, tolerance=0, colouring="none").carve(masks))
    assert sets[0] == sets[1] == sets[2]
    assert sets[5] == k0
    for s in range(2, 5):
        assert sets[s + 1] <= sets[s]
    assert len(sets[4]) < len(sets[0])      # the half-missing camera's voxels need 4 other views
    assert len(sets[5]) < len(sets[4])


@pytest.mark.parametrize("brick,box_levels", [(4, 1), (8, 1), (8, 3), (16, 2)])
def test_hierarchical_equals_flat_other_layouts(calib, frame, brick, box_levels):
    masks, _ = frame
    m = noisy_masks(masks, 5, flip=0.01)
    hier = Reconstructor(calib, 0.05, brick=brick, box_levels=box_levels, colouring="none")
    flat = Reconstructor(calib, 0.05, method="flat", colouring="none")
    np.testing.assert_array_equal(hier.carve(m), flat.carve(m))


def test_hierarchical_equals_flat_three_people_half_masks():
    calib = room_calibration(5, 320, 240)
    half = {c.name: (160, 120) for c in calib.cameras}
    masks, _ = meeting_scene(1.0).frame([c.scaled(160, 120) for c in calib.cameras])
    hier = Reconstructor(calib, 0.03, mask_sizes=half, colouring="none")
    flat = Reconstructor(calib, 0.03, mask_sizes=half, method="flat", colouring="none")
    a, b = hier.carve(masks), flat.carve(masks)
    assert len(a) > 5000
    np.testing.assert_array_equal(a, b)


def test_tolerance_keeps_a_limb_missing_in_one_view(calib, scene, recon):
    """A camera whose silhouette misses the raised arm: with k = 1 the arm is still
    reconstructed from the other views, with k = 0 it is carved away."""
    armless = Scene([person(2.0, 2.0, facing_deg=0.0, arm_raise=0.35)])
    keep = armless.part_of != R_ARM
    armless.spheres, armless.body_of, armless.part_of = (armless.spheres[keep], armless.body_of[keep],
                                                         armless.part_of[keep])
    armless.bounds[0, 5] = keep.sum()
    masks, _ = scene.frame(calib.cameras)
    # the camera where the arm covers the most pixels loses it
    lost = {c.name: int((masks[c.name] & ~armless.render(c)[0]).sum()) for c in calib.cameras}
    victim = max(lost, key=lost.get)
    assert lost[victim] > 30
    broken = dict(masks)
    broken[victim] = armless.render(calib.camera(victim))[0]

    g = recon.grid
    arm = truth_indices(g, scene)
    parts = scene.part_at(g.centres(arm))[:, 1]
    arm = as_set(g, arm[(parts == R_ARM) & (g.centres(arm)[:, 1] < 2.0 - 0.3)])   # away from the torso
    assert len(arm) > 20

    with_k1 = as_set(g, recon.carve(broken))
    strict = Reconstructor(calib, VOXEL, tolerance=0, colouring="none")
    with_k0 = as_set(g, strict.carve(broken))
    assert len(arm & with_k1) / len(arm) >= 0.9
    assert len(arm & with_k0) / len(arm) < 0.5


def test_dropped_camera_still_reconstructs(recon, scene, frame):
    masks, _ = frame
    dropped = {**masks, "cam2": None}
    del dropped["cam4"]                              # absent from the dict: also missing
    idx = recon.carve(dropped)
    truth = as_set(recon.grid, truth_indices(recon.grid, scene))
    got = as_set(recon.grid, idx)
    assert len(truth & got) / len(truth) >= 0.95
    assert len(got) > len(as_set(recon.grid, recon.carve(masks)))   # fewer views: a larger hull


def test_min_views(recon, frame):
    """A voxel seen as foreground by a single camera is never occupied."""
    masks, _ = frame
    one = {n: (m if n == "cam0" else None) for n, m in masks.items()}
    assert len(recon.carve(one)) == 0
    two = {n: (m if n in ("cam0", "cam2") else None) for n, m in masks.items()}
    assert len(recon.carve(two)) > 0


def test_bad_masks_raise(recon, frame):
    masks, _ = frame
    with pytest.raises(ValueError, match="cam0: mask must be 120x160"):
        recon.carve({**masks, "cam0": np.zeros((10, 10), bool)})
    with pytest.raises(ValueError, match="unknown camera"):
        recon.reconstruct({**masks, "camX": masks["cam0"]})


# -- colouring and visibility -------------------------------------------------------------
def torso_sides(recon, scene, idx, surface):
    """Surface voxels of the torso well in front of / behind the person's frontal plane."""
    c = recon.grid.centres(idx)
    parts = scene.part_at(c)[:, 1]
    ahead = (c[:, 0] - 2.0)                        # the person faces +x from x = 2
    torso = surface & (parts == TORSO) & (c[:, 2] > 1.05) & (c[:, 2] < 1.35) & (np.abs(c[:, 1] - 2.0) < 0.12)
    return torso & (ahead > 0.06), torso & (ahead < -0.06)


def test_visibility_colours_front_and_back(calib, scene, frame, recon):
    """Red front, blue back: with visibility the front of the shirt is red and the back
    blue; the naive mean over all cameras mixes them (thesis Fig. 2.4)."""
    masks, images = frame
    idx, colours, surface, _ = recon.reconstruct(masks, images)
    front, back = torso_sides(recon, scene, idx, surface)
    assert front.sum() > 15 and back.sum() > 15
    red, blue = np.array([220, 30, 30]), np.array([30, 40, 220])       # RGB of the BGR shirt
    col = colours.astype(float)
    assert np.median(np.abs(col[front] - red).max(axis=1)) < 20
    assert np.median(np.abs(col[back] - blue).max(axis=1)) < 20

    naive = Reconstructor(calib, VOXEL, colouring="naive")
    idx_n, col_n, surf_n, _ = naive.reconstruct(masks, images)
    np.testing.assert_array_equal(idx_n, idx)
    assert surf_n.size == 0
    col_n = col_n.astype(float)
    # naive: front voxels are much less red, back voxels much less blue
    assert col[front, 0].mean() - col_n[front, 0].mean() > 40
    assert col[back, 2].mean() - col_n[back, 2].mean() > 40
    # interior voxels carry no colour
    assert np.all(colours[~surface] == 0)


def test_depth_buffer_agrees_with_ray_march(calib, scene, frame, recon):
    """The fast visibility takes the thesis's ray-march decision for >= 98 % of the
    (boundary voxel, camera) pairs, and gives nearly the same surface set and colours."""
    masks, images = frame
    idx = recon.carve(masks)
    fast = recon.colourer
    ref = VoxelColourer(recon.grid, recon.colour_cameras, "raymarch")
    vf = fast.visible_pixels(idx) >= 0
    vr = ref.visible_pixels(idx) >= 0
    b = boundary_voxels(recon.grid, idx)
    assert (vf[b] == vr[b]).mean() >= 0.98
    sf, sr = vf.any(axis=1), vr.any(axis=1)
    assert (sf & sr).sum() / (sf | sr).sum() >= 0.93
    imgs = [images[n] for n in recon.names]
    cf, _, _ = fast.colour(idx, imgs)
    cr, _, _ = ref.colour(idx, imgs)
    both = sf & sr
    assert (np.abs(cf[both].astype(int) - cr[both].astype(int)).max(axis=1) <= 8).mean() >= 0.95
    # a pure depth buffer (no near ray march) agrees less: ~94 % of the decisions
    pure = VoxelColourer(recon.grid, recon.colour_cameras, "visibility", depth_tolerance=1.0, march=0)
    vp = pure.visible_pixels(idx) >= 0
    assert 0.9 <= (vp[b] == vr[b]).mean() < (vf[b] == vr[b]).mean()


def test_threads_give_the_same_result(calib, frame, recon):
    masks, images = frame
    a = recon.reconstruct(masks, images)
    b = Reconstructor(calib, VOXEL, threads=2).reconstruct(masks, images)
    for x, y in zip(a[:3], b[:3]):
        np.testing.assert_array_equal(x, y)


def test_ray_march_never_sees_interior_voxels(recon, frame):
    """Culling to the boundary and to camera-facing faces changes nothing for the ray march."""
    masks, _ = frame
    idx = recon.carve(masks)
    ref = VoxelColourer(recon.grid, recon.colour_cameras, "raymarch")
    np.testing.assert_array_equal(ref.visible_pixels(idx), ref.visible_pixels(idx, cull=False))


def test_three_people_surface_and_colours():
    """Three people, half-size masks and colour images: the colours on the surface are
    colours of that person (or the mean of two of them, where the cameras that see a
    voxel see different sides), not of the others nor of the background."""
    calib = room_calibration(5, 320, 240)
    half = {c.name: (160, 120) for c in calib.cameras}
    scene = meeting_scene(0.5)
    masks, images = scene.frame([c.scaled(160, 120) for c in calib.cameras])
    r = Reconstructor(calib, 0.04, mask_sizes=half, colour_sizes=half)
    idx, colours, surface, _ = r.reconstruct(masks, images)
    truth = as_set(r.grid, truth_indices(r.grid, scene))
    assert len(truth & as_set(r.grid, idx)) / len(truth) >= 0.95
    c = r.grid.centres(idx)
    body_part = scene.part_at(c)
    _, dist = scene.nearest(c)
    on_body = surface & (dist < 0.5 * r.voxel_size) & np.any(colours > 0, axis=1)
    assert on_body.sum() > 300
    palettes = []
    for b in scene.bodies:
        pal = np.concatenate([b.front, b.back])[:, ::-1].astype(int)                # RGB
        palettes.append(np.concatenate([pal, (pal[:, None] + pal[None, :]).reshape(-1, 3) // 2]))
    rows = np.flatnonzero(on_body)
    dist_to_own = np.array([np.abs(palettes[body_part[n, 0]] - colours[n].astype(int)).max(axis=1).min()
                            for n in rows])
    ok = (dist_to_own <= 30).sum()
    assert ok / on_body.sum() >= 0.95


def test_colour_images_at_another_size(calib, frame, scene):
    """Half-size masks, full-size colour images: colours sampled at full resolution."""
    masks, images = frame
    half = {c.name: (80, 60) for c in calib.cameras}
    small = {c.name: scene.render(c.scaled(80, 60))[0] for c in calib.cameras}
    r = Reconstructor(calib, VOXEL, mask_sizes=half, colour_sizes={c.name: (160, 120) for c in calib.cameras})
    idx, colours, surface, _ = r.reconstruct(small, images)
    assert len(idx) > 500 and surface.sum() > 100
    with pytest.raises(ValueError, match="colour image must be 120x160x3"):
        r.reconstruct(small, {**images, "cam0": np.zeros((60, 80, 3), np.uint8)})
    # a missing image leaves the surface (geometric) unchanged
    _, _, surface2, _ = r.reconstruct(small, {**images, "cam1": None})
    np.testing.assert_array_equal(surface, surface2)


def test_no_colouring_and_empty_frames(calib, frame):
    masks, images = frame
    r = Reconstructor(calib, VOXEL, colouring="none")
    idx, colours, surface, timings = r.reconstruct(masks, images)
    assert len(idx) > 0 and colours.shape == (0, 3) and surface.shape == (0,)
    empty = {n: np.zeros_like(m) for n, m in masks.items()}
    idx, colours, surface, _ = Reconstructor(calib, VOXEL).reconstruct(empty, images)
    assert idx.shape == (0, 3) and colours.shape == (0, 3) and surface.shape == (0,)
    idx, _, _, _ = r.reconstruct({})
    assert idx.shape == (0, 3)
    # no colour images: the surface (geometric) but no colours
    idx, colours, surface, _ = Reconstructor(calib, VOXEL).reconstruct(masks)
    assert len(idx) > 0 and colours.shape == (0, 3) and surface.shape == (len(idx),) and surface.any()


def test_floor_blob_filter_drops_low_blobs_only():
    from app.reconstruction.floor import FloorBlobFilter

    box = lambda x0, x1, z1: np.mgrid[x0:x1, 10:14, 0:z1].reshape(3, -1).T  # noqa: E731
    person = box(10, 14, 80)            # 1.6 m tall at 2 cm
    shadow = box(20, 28, 6)             # 12 cm high: a floor shadow
    foot_shadow = np.mgrid[14:18, 10:14, 0:2].reshape(3, -1).T  # joined to the person
    crouch = box(40, 50, 14)            # 28 cm: reaches min_top, kept
    voxels = np.concatenate([person, shadow, foot_shadow, crouch]).astype(np.uint16)
    f = FloorBlobFilter(0.02, 0.0, (60, 30, 100), min_top=0.25)
    kept = {tuple(v) for v in f(voxels)}
    assert kept == {tuple(v) for v in np.concatenate([person, foot_shadow, crouch])}
    assert len(FloorBlobFilter(0.02, 0.0, (60, 30, 100), min_top=0.0)(voxels)) == len(voxels)
