"""The pose stage's silhouette term (app.pose.silhouette): the masks travel with the
voxels, each camera's silhouette pixels are split between the tracks, and the model
that covers a person's silhouettes scores better than one that folds a limb away; on a
clip of the pipeline's own kind of voxels (MOG2 masks, k = 0 hull) it poses better."""
import cv2
import numpy as np
import pytest

from app.messages import MessageError, Voxels, decode, encode
from app.pose.estimator import PoseSettings
from app.pose.flesh import PARTS, build_flesh
from app.pose.likelihood import kernel_lut
from app.pose.model import DOF, BodyModel, neutral_state
from app.pose.offline import clip_errors, run_clip, simulated_clip
from app.pose.silhouette import SilhouetteView, silhouette_coverage
from app.segmentation import reduce_mask
from tests.payloads import older_payload

HEIGHT = 1.75


@pytest.fixture(scope="module")
def calibration():
    from app.simulation.simulator import Simulator
    return Simulator("walk1", seconds=0.2, zenithal=True).calibration


def _voxels(n=1000, cameras=("cam0", "cam1")):
    rng = np.random.default_rng(1)
    return Voxels(frame=3, voxel_size=0.02, origin=[0.0, 0.0, 0.0], dims=[250, 200, 125], cameras=list(cameras),
                  indices=rng.integers(0, 120, (n, 3)).astype(np.uint16), misses=np.zeros(n, np.uint8))


def test_silhouettes_travel_with_the_voxels():
    rng = np.random.default_rng(2)
    masks = [rng.random((60, 80)) > 0.5, rng.random((45, 61)) > 0.5]   # cameras may differ in size
    back = decode(encode(_voxels().with_silhouettes(masks)))
    back.validate()
    assert back.silhouette_sizes == [[80, 60], [61, 45]]
    for a, b in zip(masks, back.silhouette_masks()):
        np.testing.assert_array_equal(a, b)


def test_voxels_of_an_older_build_decode_without_silhouettes():
    """A payload without the added array (four arrays, the earlier Voxels) still decodes."""
    msg = _voxels()
    back = decode(older_payload(msg, "silhouette_sizes"))
    back.validate()
    assert back.silhouette_masks() == [] and back.silhouette_sizes == []
    np.testing.assert_array_equal(back.indices, msg.indices)


@pytest.mark.parametrize("change, message", [
    (lambda v: setattr(v, "silhouette_sizes", [[80, 60]]), "one \\[width, height\\] per camera"),
    (lambda v: setattr(v, "silhouette_sizes", [[80, 60], [80, 61]]), "their sizes need"),
    (lambda v: setattr(v, "silhouettes", np.zeros(0, np.uint8)), "silhouette_sizes without silhouettes"),
])
def test_malformed_silhouettes_are_rejected(change, message):
    msg = _voxels().with_silhouettes([np.ones((60, 80), bool), np.ones((60, 80), bool)])
    change(msg)
    with pytest.raises(MessageError, match=message):
        decode(encode(msg)).validate()


def _posed_points(state, spacing=0.01):
    flesh = build_flesh(HEIGHT, spacing, 1.0)
    R, O = BodyModel(HEIGHT).forward(state)
    return O[flesh.segment] + np.einsum("nij,nj->ni", R[flesh.segment], flesh.points)


def _render(calibration, states, factor=8):
    """Each camera's silhouette of the bodies in ``states``, drawn with the lens model at
    full size (dense model points, closed) and reduced as the reconstruction sends it."""
    out = []
    for cam in calibration.cameras:
        mask = np.zeros((cam.height, cam.width), np.uint8)
        for state in states:
            uv = cam.project(_posed_points(state))
            ok = np.isfinite(uv).all(axis=1)
            px = np.rint(uv[ok]).astype(int)
            inside = (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] < cam.height)
            mask[px[inside, 1], px[inside, 0]] = 1
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
        out.append(reduce_mask(mask.astype(bool), factor))
    return out


def _arms_out(position):
    y = neutral_state(HEIGHT, position)
    y[DOF["l_sh_abd"]] = y[DOF["r_sh_abd"]] = 1.3
    return y


def test_the_model_that_covers_the_silhouettes_scores_best(calibration):
    position = (2.5, 2.0, None)
    true = _arms_out(position)
    view = SilhouetteView(_render(calibration, [true]), calibration.cameras, reach=0.6)
    person = view.people(np.array([[true[0], true[1], 1.0]]))[0]
    assert (person.counts > 0).all()
    folded = true.copy()
    folded[DOF["l_sh_abd"]] = folded[DOF["r_sh_abd"]] = 0.0     # arms down along the trunk
    bent = true.copy()
    bent[DOF["r_elbow"]] = 2.0                                  # one forearm bent away
    shifted = true.copy()
    shifted[0] += 0.15
    lut = kernel_lut(build_flesh(HEIGHT, 0.08, 1.0))
    stamp = np.zeros(person.grids.shape, np.int64)
    rho = silhouette_coverage(np.array([true, folded, bent, shifted]), HEIGHT, lut, np.ones(len(PARTS), bool),
                              person, stamp, 1)
    print("rho true / folded / bent / shifted:", np.round(rho, 3))
    assert rho[0] > 0.5   # 8-cm points on ~8-cm pixels: not every pixel is hit
    assert rho[0] > rho[1] + 0.05 and rho[0] > rho[2] + 0.01 and rho[0] > rho[3] + 0.05
    # a part switched off covers nothing
    off = np.ones(len(PARTS), bool)
    off[PARTS.index("r_forearm")] = False
    rho_off = silhouette_coverage(true[None], HEIGHT, lut, off, person, stamp, 10)
    assert rho_off[0] < rho[0]


def test_the_true_pose_covers_as_much_of_a_fine_view_as_of_a_coarse_one(calibration):
    """Silhouettes reduced 2x instead of 8x (a finer camera, or one nearer the person)
    leave the 8-cm model points one pixel in several: as sent, rho_Sil of the true pose
    falls with the pixel size; coarsened to the lattice at the person's depth
    (``spacing``) it stays, and each coarse pixel is the person's exactly when one of its
    fine pixels is, under intrinsics that map a point to its fine pixel's coarse one."""
    from app.pose.silhouette import coarsening

    position = (2.5, 2.0, None)
    true = _arms_out(position)
    where = np.array([[true[0], true[1], 1.0]])
    lut = kernel_lut(build_flesh(HEIGHT, 0.08, 1.0))
    act = np.ones(len(PARTS), bool)
    rho = {}
    for factor in (8, 2):
        view = SilhouetteView(_render(calibration, [true], factor=factor), calibration.cameras, reach=0.6)
        for spacing in (0.0, 0.08):
            person = view.people(where, spacing)[0]
            stamp = np.zeros(person.grids.shape, np.int64)
            rho[factor, spacing] = float(silhouette_coverage(true[None], HEIGHT, lut, act, person, stamp, 1)[0])
    print("rho of the true pose (reduction, spacing):", {k: round(v, 3) for k, v in rho.items()})
    assert rho[2, 0.0] < rho[8, 0.0] - 0.2                  # as sent: the finer view is scored far lower
    assert abs(rho[2, 0.08] - rho[8, 0.08]) < 0.12 and rho[2, 0.08] > 0.5
    view = SilhouetteView(_render(calibration, [true], factor=2), calibration.cameras, reach=0.6)
    fine, coarse = view.people(where)[0], view.people(where, 0.08)[0]
    for c, rays in enumerate(view.rays):
        f = coarsening(rays, where[0], 0.08)
        assert f >= 2
        rows, cols = np.nonzero(fine.grids[c])
        assert coarse.counts[c] == len(set(zip(rows // f, cols // f)))
        assert set(zip(*np.nonzero(coarse.grids[c]))) == set(zip(rows // f, cols // f))
        # a camera-frame point at a fine pixel's centre falls in that pixel's coarse pixel
        fx, sk, cx, fy, cy = fine.intrinsics[c]
        Fx, Sk, Cx, Fy, Cy = coarse.intrinsics[c]
        for u, v in ((0, 0), (17, 5), (41, 33)):
            y = (v - cy) / fy
            x = (u - cx - sk * y) / fx
            assert (int(Fy * y + Cy + 0.5), int(Fx * x + Sk * y + Cx + 0.5)) == (v // f, u // f)


def test_each_person_owns_only_their_own_pixels(calibration):
    a, b = _arms_out((1.5, 2.0, None)), _arms_out((3.5, 2.0, None))
    both = _render(calibration, [a, b])
    alone_a = _render(calibration, [a])
    view = SilhouetteView(both, calibration.cameras, reach=0.6)
    pa, pb = view.people(np.array([[1.5, 2.0, 1.0], [3.5, 2.0, 1.0]]))
    for c in range(len(both)):
        undistorted_a = view.rays[c].undistort(alone_a[c])
        mine_a, mine_b = pa.grids[c].astype(bool), pb.grids[c].astype(bool)
        assert not (mine_a & mine_b).any()
        if mine_a.any():   # what A owns is A's; B owns little of A's silhouette
            assert (mine_a & ~undistorted_a).sum() <= 0.1 * mine_a.sum()
        if mine_b.sum() > 20:
            assert (mine_b & undistorted_a).sum() <= 0.1 * mine_b.sum()
    assert (pa.counts > 0).sum() >= 3 and (pb.counts > 0).sum() >= 3
    # a pose shard posing B alone (issue 26) gets B's pixels as the full split gives them
    none_a, only_b = view.people(np.array([[1.5, 2.0, 1.0], [3.5, 2.0, 1.0]]), 0.0, [1])
    assert none_a is None and np.array_equal(only_b.grids, pb.grids) and np.array_equal(only_b.counts, pb.counts)


@pytest.fixture(scope="module")
def walk_hull_clip():
    """walk1 at 2 cm: the k = 0 hull of the segmentation's MOG2 masks, with the masks
    (what the pipeline's pose stage gets): the swinging forearms and shins are half
    carved away from the hull and whole in each camera's mask."""
    return simulated_clip("walk1", range(20, 56), 0.02, source="mog2", tolerance=0)


def test_silhouettes_pose_the_limbs_the_hull_carves(walk_hull_clip):
    clip, cal = walk_hull_clip
    assert all(fr.silhouettes and len(fr.silhouettes) == len(fr.cameras) for fr in clip)
    mmta = {}
    for sil in (0.0, 0.0005):
        scores = []
        for seed in (0, 1):
            settings = PoseSettings(voxel_size=0.02, density=2, room_lo=tuple(cal.room_min),
                                    room_hi=tuple(cal.room_max), importance_fraction=0.35, ground=0.01,
                                    silhouette=sil, seed=seed)
            E = clip_errors(clip, run_clip(clip, settings, calibration=cal)["estimates"])[6:]
            scores.append(float((E <= 0.1).mean()))
        mmta[sil] = float(np.mean(scores))
    print("walk1 MOG2 hull, MMTA without / with silhouettes:", mmta)
    assert mmta[0.0005] >= mmta[0.0] + 0.02
    assert mmta[0.0005] >= 0.88
