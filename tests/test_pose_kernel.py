"""The pose likelihood kernel (thesis §6.5.1.1, Eqs. 6.13-6.16) against a plain numpy
reference on random particles: the fast kernel (vectorised placement, per-part boxes,
packed double-occupancy stamps, fixed-point surface sum, forward kinematics of the
needed segments with axis rotations) must give the same counts as the definition."""
import math

import numpy as np
import pytest

from app.pose.flesh import PART, PARTS, build_flesh
from app.pose.likelihood import Scorer, log_likelihood, normalise, part_variances
from app.pose.model import (DOF, DOF_AXIS, DOF_SEGMENT, LIMITS_HI, LIMITS_LO, N_DOF, N_SEG, SEG_OFFSET, SEG_PARENT,
                            SIGMA0, BodyModel, _exp_into, fk_segments, neutral_state)
from app.pose.observation import Observation, observe

ROOM_LO, ROOM_HI = np.array([0.0, 0.0, 0.0]), np.array([5.0, 4.0, 2.5])
H = 1.78


def _fk_reference(y, height):
    """Eq. 6.1 written out: every DoF's exponential map (App. A) as a full 3x3 product."""
    R, O = np.zeros((N_SEG, 3, 3)), np.zeros((N_SEG, 3))
    E = np.empty((3, 3))
    d = 3
    for s in range(N_SEG):
        p = SEG_PARENT[s]
        if p < 0:
            O[s], R[s] = y[:3], np.eye(3)
        else:
            for i in range(3):
                O[s, i] = O[p, i] + height * (R[p, i, 0] * SEG_OFFSET[s, 0] + R[p, i, 1] * SEG_OFFSET[s, 1]
                                              + R[p, i, 2] * SEG_OFFSET[s, 2])
            R[s] = R[p]
        while d < N_DOF and DOF_SEGMENT[d] == s:
            _exp_into(y[d], DOF_AXIS[d, 0], DOF_AXIS[d, 1], DOF_AXIS[d, 2], E)
            T = np.empty((3, 3))
            for i in range(3):
                for j in range(3):
                    T[i, j] = R[s, i, 0] * E[0, j] + R[s, i, 1] * E[1, j] + R[s, i, 2] * E[2, j]
            R[s] = T
            d += 1
    return R, O


def _counts_reference(states, flesh, obs, active):
    """``(P, Q, 5)`` counts by the definitions, one particle at a time in numpy."""
    Q = len(PARTS)
    out = np.zeros((len(states), Q, 5))
    pts, seg, part, surf = flesh.points, flesh.segment, flesh.part, flesh.surface
    keep = np.asarray(active)[part]
    h = flesh.spacing
    do_dims = np.array([int(np.ceil(n * obs.voxel_size / h)) + 1 for n in obs.occ.shape])
    dims = np.array(obs.occ.shape)
    for k, y in enumerate(states):
        R, O = BodyModel(flesh.height).forward(y)
        r, o = R[seg], O[seg]
        x = np.stack([o[:, i] + r[:, i, 0] * pts[:, 0] + r[:, i, 1] * pts[:, 1] + r[:, i, 2] * pts[:, 2]
                      for i in range(3)], axis=1)
        outside = np.any((x < obs.room_lo) | (x > obs.room_hi), axis=1)
        f = (x - obs.origin) * (1.0 / obs.voxel_size)
        inside = np.all((f >= 0) & (f < dims), axis=1)
        c = np.where(inside[:, None], f, 0).astype(np.int64)
        occupied = inside & (obs.occ[c[:, 0], c[:, 1], c[:, 2]] != 0)
        prox = np.where(inside, obs.prox[c[:, 0], c[:, 1], c[:, 2]].astype(np.float64), 0.0)
        g = (x - obs.origin) * (1.0 / h)
        in_do = np.all((g >= 0) & (g < do_dims), axis=1) & keep
        cell = np.where(in_do[:, None], g, 0).astype(np.int64) @ np.array([do_dims[1] * do_dims[2], do_dims[2], 1])
        # a cell is doubly occupied when points of two different parts fall in it
        pairs = np.unique(np.stack([cell[in_do], part[in_do]], axis=1), axis=0)
        cells, n_parts = np.unique(pairs[:, 0], return_counts=True)
        double = in_do & np.isin(cell, cells[n_parts > 1])
        for q in range(Q):
            if not active[q]:
                continue
            m = part == q
            out[k, q] = (outside[m].sum(), double[m].sum(), occupied[m].sum(),
                         np.sum(1.0 - prox[m & surf]), (m & surf).sum())
    return out


def _person(flesh_fine, state):
    """Voxel centres of a body at ``state``: the fine LUT moved there and snapped to 2 cm."""
    R, O = BodyModel(H).forward(state)
    x = O[flesh_fine.segment] + np.einsum("mij,mj->mi", R[flesh_fine.segment], flesh_fine.points)
    return np.unique(np.floor(x / 0.02).astype(np.int64), axis=0) * 0.02 + 0.01


def _particles(rng, base, n, spread=2.5):
    P = np.tile(base, (n, 1)) + rng.standard_normal((n, N_DOF)) * SIGMA0 * spread
    P[: n // 4, [DOF["l_sh_flex"], DOF["r_sh_flex"]]] = rng.uniform(0.5, 1.5, (n // 4, 2))   # arms across
    P[: n // 4, [DOF["l_sh_abd"], DOF["r_sh_abd"]]] = rng.uniform(-0.3, 0.0, (n // 4, 2))    # the trunk: DO
    P[n // 4: n // 3, :2] += rng.normal(0, 0.5, (n // 3 - n // 4, 2))                        # far off
    return np.clip(P, LIMITS_LO, LIMITS_HI)


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(7)
    fine = build_flesh(H, 0.02, 1.0)
    # a person close to the wall x = 0, arm raised, so that particles reach outside the room
    truth = neutral_state(H, (0.32, 2.0, None), yaw=0.4)
    truth[DOF["r_sh_flex"]], truth[DOF["l_elbow"]] = 1.2, 1.0
    obs = observe(_person(fine, truth), 0.02, ROOM_LO, ROOM_HI)
    return rng, truth, obs


@pytest.mark.parametrize("density", [1.0, 2.0, 3.0])
def test_kernel_matches_the_reference_on_random_particles(scene, density):
    rng, truth, obs = scene
    flesh = build_flesh(H, 0.02, density)
    scorer = Scorer(flesh)
    scorer.set_observation(obs)
    states = _particles(rng, truth, 60)
    h1 = np.array([p in ("torso", "pelvis", "head") for p in PARTS])          # SHBM-APF's H1
    no_left_arm = np.ones(len(PARTS), bool)
    no_left_arm[[PART["l_upper_arm"], PART["l_forearm"]]] = False              # DDM: a limb off
    for active in (np.ones(len(PARTS), bool), h1, no_left_arm):
        got = scorer.counts(states, active)
        want = _counts_reference(states, flesh, obs, active)
        np.testing.assert_array_equal(got[..., [0, 1, 2, 4]], want[..., [0, 1, 2, 4]])
        np.testing.assert_allclose(got[..., 3], want[..., 3], rtol=0, atol=1e-9)
        assert np.all(got[:, ~active] == 0)
    # the test exercises every score: points outside the room, shared cells, data hits
    assert got[..., 0].sum() > 0 and got[..., 1].sum() > 0 and got[..., 2].sum() > 0
    # the same particles again (stamps of earlier particles left in the grid) and one by one
    np.testing.assert_array_equal(scorer.counts(states[:7], no_left_arm), got[:7])
    np.testing.assert_array_equal(np.concatenate([scorer.counts(states[i:i + 1], no_left_arm)
                                                  for i in range(7)]), got[:7])
    # another observation with another box (the stamp grid is reused, not cleared)
    small = observe(obs.centres[obs.centres[:, 2] > 1.0], 0.02, ROOM_LO, ROOM_HI)
    assert small.occ.shape != obs.occ.shape
    scorer.set_observation(small)
    np.testing.assert_array_equal(scorer.counts(states, h1)[..., [0, 1, 2, 4]],
                                  _counts_reference(states, flesh, small, h1)[..., [0, 1, 2, 4]])


def test_kernel_on_a_grid_without_an_empty_first_cell():
    """Points outside the box read a cell empty in both grids; when the box has none
    (here: every cell occupied) one is added."""
    rng = np.random.default_rng(3)
    dims = (30, 30, 50)
    occ = np.ones(dims, np.uint8)
    prox = rng.choice(np.float32([0.25, 0.5, 1.0]), size=dims)
    obs = Observation(origin=np.array([0.6, 0.7, 0.0]), voxel_size=0.04, occ=occ, prox=prox,
                      centres=np.zeros((0, 3)), surface=np.zeros(0, bool), room_lo=ROOM_LO, room_hi=ROOM_HI)
    flesh = build_flesh(H, 0.04, 1.0)
    scorer = Scorer(flesh)
    scorer.set_observation(obs)
    states = _particles(rng, neutral_state(H, (1.2, 1.3, None)), 40, spread=4.0)
    active = np.ones(len(PARTS), bool)
    got, want = scorer.counts(states, active), _counts_reference(states, flesh, obs, active)
    np.testing.assert_array_equal(got[..., [0, 1, 2, 4]], want[..., [0, 1, 2, 4]])
    np.testing.assert_allclose(got[..., 3], want[..., 3], rtol=0, atol=1e-9)
    assert 0 < got[..., 2].sum() < flesh.part_size.sum() * len(states)   # some points left the box


def test_forward_kinematics_axis_rotations_and_needed_segments():
    """The axis-rotation shortcut gives the general exponential-map product bit for bit,
    and a forward kinematics limited to some segments leaves those the same."""
    rng = np.random.default_rng(5)
    R, O = np.empty((N_SEG, 3, 3)), np.empty((N_SEG, 3))
    R2, O2 = np.empty((N_SEG, 3, 3)), np.empty((N_SEG, 3))
    need = np.zeros(N_SEG, bool)
    need[[0, 1, 2]] = True   # pelvis, torso, head
    for k in range(200):
        y = rng.uniform(np.maximum(LIMITS_LO, -4), np.minimum(LIMITS_HI, 4))
        if k < 3:
            y[3:] = (0.0, math.pi / 2, math.pi)[k]
        fk_segments(y, H, SEG_PARENT, SEG_OFFSET, DOF_SEGMENT, DOF_AXIS, R, O)
        Rr, Or = _fk_reference(y, H)
        assert np.array_equal(R, Rr) and np.array_equal(O, Or)
        fk_segments(y, H, SEG_PARENT, SEG_OFFSET, DOF_SEGMENT, DOF_AXIS, R2, O2, need)
        assert np.array_equal(R2[need], R[need]) and np.array_equal(O2[need], O[need])


def test_scores_and_partitioned_likelihood_match_their_formulas():
    """Eqs. 6.13-6.16 normalised and Eq. 6.25 (the fused loops) against numpy written out."""
    rng = np.random.default_rng(11)
    flesh = build_flesh(H, 0.02, 2.0)
    counts = rng.integers(0, 60, (300, len(PARTS), 5)).astype(float)
    counts[..., 3] = rng.random(counts.shape[:2]) * 40
    counts[:5, :, 4] = 0.0
    size = flesh.part_size[None, :]
    want = np.stack([counts[..., 0] / size, counts[..., 1] / size, 1.0 - counts[..., 2] / size,
                     counts[..., 3] / np.maximum(counts[..., 4], 1.0)], axis=-1)
    scores = normalise(counts, flesh)
    np.testing.assert_array_equal(scores, want)
    for active in (np.ones(len(PARTS), bool), rng.random(len(PARTS)) < 0.5):
        want = -0.5 * np.sum(scores[:, active, :] ** 2 / part_variances()[active][None], axis=(1, 2))
        np.testing.assert_allclose(log_likelihood(scores, flesh, active), want, rtol=1e-13, atol=0)


def test_floor_penalty_with_leg_only_kinematics_matches_the_full_joints():
    """The floor prior's heights come from the legs' forward kinematics only
    (:func:`app.pose.model.fk_joint_z_batch`): bit-identical to all 15 joints."""
    from app.messages import JOINTS
    from app.pose.coverage import floor_penalty
    from app.pose.model import JOINT_LOCAL, JOINT_SEG, fk_joints_batch
    rng = np.random.default_rng(3)
    P = 200
    lo, hi = np.maximum(LIMITS_LO, -np.pi), np.minimum(LIMITS_HI, np.pi)
    states = lo + rng.random((P, N_DOF)) * (hi - lo)
    states[:, :3] = rng.normal([2.0, 2.0, 0.9], 0.3, (P, 3))
    J = np.empty((P, len(JOINTS), 3))
    fk_joints_batch(states, H, SEG_PARENT, SEG_OFFSET, DOF_SEGMENT, DOF_AXIS, JOINT_SEG, JOINT_LOCAL, J)
    z = J[:, [JOINTS.index("l_ankle"), JOINTS.index("r_ankle")], 2]
    rest = 0.039 * H
    ref = 0.5 * (np.maximum(z.min(axis=1) - rest, 0.0) / 0.05) ** 2
    assert np.array_equal(floor_penalty(states, H, 0.05), ref)
    ref = ref + 0.5 * (np.maximum(z.max(axis=1) - rest, 0.0) / 0.03) ** 2
    assert np.array_equal(floor_penalty(states, H, 0.05, both=0.03), ref)
    assert np.count_nonzero(ref) > P // 2


def test_joint_subsets_and_torso_frames_match_all_joints():
    """:func:`app.pose.model.joints_subset` (forward kinematics of the needed segments
    only, used by the arms' inverse kinematics) gives BodyModel.joints's numbers."""
    from app.messages import JOINTS
    from app.pose.detections import _torso_frames
    from app.pose.model import joints_subset
    rng = np.random.default_rng(5)
    lo, hi = np.maximum(LIMITS_LO, -np.pi), np.minimum(LIMITS_HI, np.pi)
    states = lo + rng.random((100, N_DOF)) * (hi - lo)
    J = BodyModel(H).joints(states)
    for names in (JOINTS, ["l_ankle", "r_ankle"], ["l_wrist"], ["neck", "pelvis", "l_shoulder"]):
        idx = np.array([JOINTS.index(n) for n in names], dtype=np.int64)
        assert np.array_equal(joints_subset(states, H, idx), J[:, idx])
    shoulders, frames = _torso_frames(states, H)
    ls, rs = J[:, JOINTS.index("l_shoulder")], J[:, JOINTS.index("r_shoulder")]
    up = J[:, JOINTS.index("neck")] - J[:, JOINTS.index("pelvis")]
    up /= np.maximum(np.linalg.norm(up, axis=1, keepdims=True), 1e-9)
    left = ls - rs
    left -= np.sum(left * up, axis=1, keepdims=True) * up
    left /= np.maximum(np.linalg.norm(left, axis=1, keepdims=True), 1e-9)
    assert np.array_equal(shoulders["l"], ls) and np.array_equal(shoulders["r"], rs)
    assert np.array_equal(frames, np.stack([np.cross(left, up), left, up], axis=2))


def test_outer_surface_equals_a_fill_of_the_whole_box():
    """The outer surface (cavities are not surface) fills only the voxels' bounding box:
    the same flags as filling the holes of the whole box (scipy) on random blobs."""
    from scipy.ndimage import binary_fill_holes

    from app.pose.observation import outer_surface_flags
    rng = np.random.default_rng(3)
    for _ in range(200):
        shape = tuple(int(v) for v in rng.integers(3, 24, 3))
        occ = (rng.random(shape) < rng.uniform(0.2, 0.95)).astype(np.uint8)
        lo = rng.integers(0, shape)
        keep = np.zeros(shape, bool)
        keep[lo[0]:lo[0] + rng.integers(1, 12), lo[1]:lo[1] + rng.integers(1, 12), lo[2]:lo[2] + rng.integers(1, 12)] = True
        occ[~keep] = 0
        idx = np.argwhere(occ).astype(np.int64)
        outside = np.pad(~binary_fill_holes(occ.astype(bool)), 1, constant_values=True)
        i, j, k = (idx + 1).T
        want = (outside[i - 1, j, k] | outside[i + 1, j, k] | outside[i, j - 1, k] | outside[i, j + 1, k]
                | outside[i, j, k - 1] | outside[i, j, k + 1])
        assert np.array_equal(outer_surface_flags(idx, occ), want)
