"""The pose priors for visual hulls beyond the thesis (app.pose.coverage): the stance
prior (a person standing still has the feet under the hips) on its own and on a clip
whose right foot is missing from the voxels, as gesture1's k = 0 hull lacks it; the
crown (the head under the top of the person's voxels) on its own and on a hull whose
chest the masks lost."""
import numpy as np
import pytest

from app.messages import JOINTS
from app.pose.coverage import CROWN_FREE, STANCE_FREE, crown_expectation, crown_penalty, stance_penalty
from app.pose.estimator import PoseSettings
from app.pose.model import DOF, LIMITS_HI, LIMITS_LO, BodyModel, neutral_state
from app.pose.offline import clip_errors, run_clip, simulated_clip

J = {n: i for i, n in enumerate(JOINTS)}
H = 1.75


def test_stance_penalty_holds_upright_legs_only():
    stand = neutral_state(H, (1.0, 2.0, None))
    wide = stand.copy()
    wide[DOF["r_hip_abd"]] = 0.5                # the right foot 0.4 m out to the side
    sit = stand.copy()
    sit[2] -= 0.45                              # the pelvis down to a chair
    for side in "lr":
        sit[DOF[f"{side}_hip_flex"]] = 1.5      # thighs forward, shins down: feet 0.45 m ahead
        sit[DOF[f"{side}_knee"]] = 1.5
    joints = BodyModel(H).joints(sit)
    assert np.hypot(*(joints[J["r_ankle"], :2] - joints[J["r_hip"], :2])) > 0.3   # far from under the hip
    pen = stance_penalty(np.stack([stand, wide, sit]), H, 0.03)
    assert pen[0] == 0.0                        # standing straight: within STANCE_FREE
    assert pen[2] == 0.0                        # sitting: not an upright leg, not held
    d = np.hypot(*(BodyModel(H).joints(wide)[J["r_ankle"], :2] - BodyModel(H).joints(wide)[J["r_hip"], :2]))
    assert pen[1] == pytest.approx(0.5 * ((d - STANCE_FREE) / 0.03) ** 2)


def _posed_errors(clip, cal, voxel_size, **settings):
    """Joint errors ``(T - 5, 15)`` of a one-person clip posed with ``settings`` (the
    first 5 frames, lock-on, left out); every frame has a pose."""
    s = PoseSettings(voxel_size=voxel_size, density=2, room_lo=tuple(cal.room_min), room_hi=tuple(cal.room_max),
                     **settings)
    E = clip_errors(clip, run_clip(clip, s)["estimates"])[5:]
    assert not np.isnan(E).any()
    return E


@pytest.fixture(scope="module")
def footless_clip():
    """gesture1 (standing, waving), 1 s at 2 cm, the visual hull (k = 0) of the true
    silhouettes: one camera sees the feet behind furniture, so the hull has no right foot
    (docs/history/pose-likelihood.md, the thesis's likelihood on a visual hull)."""
    return simulated_clip("gesture1", range(0, 25), 0.02, source="hull", tolerance=0)


def test_stance_prior_keeps_the_footless_leg_under_the_hip(footless_clip):
    clip, cal = footless_clip
    within = {}
    for stance in (0.0, 0.03):
        E = _posed_errors(clip, cal, 0.02, stance=stance)
        within[stance] = float((E[:, J["r_ankle"]] <= 0.1).mean())
        print(f"stance {stance}: right ankle within 100 mm in {within[stance]:.2f} of the frames, "
              f"median {1e3 * np.median(E[:, J['r_ankle']]):.0f} mm, MPJPE {1e3 * E.mean():.0f} mm")
    assert within[0.03] >= 0.9, within


def _numpy_torso_frames(states, height):
    """The arms' torso frames as numpy operations (the earlier code of detections.py)."""
    from app.pose.detections import _TORSO_JOINTS, _TORSO_NEED
    from app.pose.model import joints_subset
    j = joints_subset(states, height, _TORSO_JOINTS, _TORSO_NEED)
    ls, rs = j[:, 0], j[:, 1]
    up = j[:, 2] - j[:, 3]
    up /= np.maximum(np.linalg.norm(up, axis=1, keepdims=True), 1e-9)
    left = ls - rs
    left -= np.sum(left * up, axis=1, keepdims=True) * up
    left /= np.maximum(np.linalg.norm(left, axis=1, keepdims=True), 1e-9)
    return {"l": ls, "r": rs}, np.stack([np.cross(left, up), left, up], axis=2)


def test_arm_proposal_kernels_give_numpys_numbers():
    """The IAPF arm proposals' loops (torso frames, the wrist target's look-up cell and
    the table's range for it) against the numpy operations they replace, bit for bit, on
    random states inside the joint limits and random hand candidates."""
    from app.pose.annealing import propagate
    from app.pose.detections import _ARM_DOFS, _ik_assign, _ik_cells, _ik_keys, _torso_frames, arm_table
    from app.pose.filters import SIGMA0
    from app.pose.model import LIMITS_HI, LIMITS_LO

    rng = np.random.default_rng(3)
    states = propagate(np.tile(neutral_state(H, (1.0, 2.0, None)), (3000, 1)), 3 * SIGMA0, LIMITS_LO, LIMITS_HI, rng)
    shoulders, frames = _torso_frames(states, H)
    ref_shoulders, ref_frames = _numpy_torso_frames(states, H)
    assert np.array_equal(frames, ref_frames)
    for side in "lr":
        assert np.array_equal(shoulders[side], ref_shoulders[side])
        keys = arm_table(side)[2]
        use = np.flatnonzero(rng.random(len(states)) < 0.5)
        target = np.array([1.0, 2.0, 1.2]) + rng.normal(0, 0.4, (len(use), 3))
        rel = np.einsum("nij,ni->nj", ref_frames[use], target - ref_shoulders[side][use]) / H
        norm = np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1e-9)
        rel *= np.clip(norm - 0.04, 0.02, 0.325) / norm
        k = _ik_keys(rel)
        lo, hi = np.empty(len(use), np.int64), np.empty(len(use), np.int64)
        _ik_cells(frames, shoulders[side], use, target, H, keys, lo, hi)
        assert np.array_equal(lo, np.searchsorted(keys, k, side="left"))
        assert np.array_equal(hi, np.searchsorted(keys, k, side="right"))
        assert (hi > lo).mean() > 0.5     # most targets fall in a cell of the table
        # the drawn configurations: lo + int(u (hi - lo)) plus noise, on some of the arm's DoFs
        cfg, d, ok = arm_table(side)[0], _ARM_DOFS[side], hi > lo
        for cols in (np.arange(4), np.array([1, 3])):
            u, noise = rng.random(int(ok.sum())), rng.normal(0, 0.05, (int(ok.sum()), len(cols)))
            ref, got = states.copy(), states.copy()
            pick = lo[ok] + (u * (hi[ok] - lo[ok])).astype(np.int64)
            ref[np.ix_(use[ok], d[cols])] = cfg[pick][:, cols] + noise
            _ik_assign(got, use, lo, hi, u, cfg, d, cols, noise)
            assert np.array_equal(got, ref)


def _numpy_detect(c, height):
    """Head, top, centroid, shoulder-band matrix and extremity candidates as numpy
    operations (the earlier code of detections.detect)."""
    trunk = c[(c[:, 2] > 0.50 * height) & (c[:, 2] < 0.70 * height)]
    axis = np.median(trunk[:, :2], axis=0) if len(trunk) >= 10 else np.median(c[:, :2], axis=0)
    near_axis = c[np.hypot(c[:, 0] - axis[0], c[:, 1] - axis[1]) < 0.18]
    if len(near_axis) < 10:
        near_axis = c
    top = float(near_axis[:, 2].max())
    head = near_axis[near_axis[:, 2] >= top - 0.08].mean(axis=0)
    head[2] = top - 0.066 * height
    band = c[(c[:, 2] > top - 0.30 * height) & (c[:, 2] < top - 0.12 * height)]
    xy = band[:, :2] - band[:, :2].mean(axis=0)
    upper = c[(c[:, 2] > top - 0.55 * height)]
    chest = np.array([head[0], head[1], head[2] - 0.125 * height])
    d = np.hypot(upper[:, 0] - head[0], upper[:, 1] - head[1])
    r = np.linalg.norm(upper - chest, axis=1)
    pick = (d > 0.30) | (upper[:, 2] > top + 0.04) | ((r > 0.32 * height) & (upper[:, 2] > top - 0.42 * height))
    pick &= r < 0.50 * height
    return head, top, c.mean(axis=0), xy.T @ xy, upper[pick], r[pick]


def test_detections_give_numpys_numbers(footless_clip):
    """The detections' passes over the voxel list (body axis, head, centroid, shoulder
    band, extremities) against the numpy operations they replace, bit for bit, on a hull
    clip's frames, on random subsets of them and moved off the grid."""
    from app.pose.detections import _body_axis_head, _extremities, detect

    rng = np.random.default_rng(5)
    frames, _ = footless_clip
    hands = 0
    for fr in frames:
        for c in (fr.centres, fr.centres[rng.random(len(fr.centres)) < 0.3] + rng.normal(0, 0.01, 3),
                  fr.centres[fr.centres[:, 2] < 0.9]):
            c = np.ascontiguousarray(c)
            head, top, centroid, band, far, r = _numpy_detect(c, H)
            axis, top2, head2, centroid2, xy = _body_axis_head(c, H)
            far2, r2 = _extremities(c, H, top2, head2)
            assert top2 == top and np.array_equal(head2, head) and np.array_equal(centroid2, centroid)
            assert np.array_equal(xy.T @ xy, band) and np.array_equal(far2, far) and np.array_equal(r2, r)
            det = detect(c, H)
            assert np.array_equal(det.head, head) and (det.hands is None) == (len(far) == 0)
            hands += len(far)
    assert hands > 100   # the waving arm's candidates were compared too


def test_importance_draws_are_the_sequential_draws():
    """The importance function's normal draws taken in one call are the numbers of the
    one-call-per-DoF draws it replaced (same generator state, same order)."""
    from app.pose.detections import Detections, Importance
    from app.pose.model import standing_root_height

    det = Detections(head=np.array([1.0, 2.0, 1.6]), top=1.70, centroid=np.array([1.0, 2.0, 0.9]),
                     headings=[0.3, 0.3 + np.pi], hands=None)
    for n in (1, 37):
        got = Importance(det, H)._draw(n, np.random.default_rng(n))
        rng = np.random.default_rng(n)
        ref = np.tile(neutral_state(H), (n, 1))
        stand = standing_root_height(H)
        yaw = np.array(det.headings)[rng.integers(2, size=n)] + rng.normal(0, 0.15, n)
        ref[:, DOF["yaw"]] = yaw
        ref[:, DOF["z"]] = np.clip(min(stand, det.top - (H - stand)) + rng.normal(0, 0.02, n), 0.25 * H, stand + 0.02)
        flex = np.clip(max(0.0, (H - det.top) / H) * 2.5, 0.0, 1.0) * rng.random(n)
        ref[:, DOF["torso_flex"]] = flex
        back = np.sin(flex) * 0.295 * H
        ref[:, DOF["x"]] = det.head[0] - np.cos(yaw) * back + rng.normal(0, 0.03, n)
        ref[:, DOF["y"]] = det.head[1] - np.sin(yaw) * back + rng.normal(0, 0.03, n)
        for name in ("pitch", "roll", "torso_twist", "torso_lat", "neck_lat", "neck_flex"):
            ref[:, DOF[name]] = rng.normal(0, 0.05, n)
        for side in "lr":
            ref[:, DOF[f"{side}_hip_flex"]] = rng.normal(0.05, 0.15, n)
            ref[:, DOF[f"{side}_hip_abd"]] = rng.normal(0.0, 0.05, n)
            ref[:, DOF[f"{side}_hip_rot"]] = rng.normal(0.0, 0.05, n)
            ref[:, DOF[f"{side}_knee"]] = np.abs(rng.normal(0.1, 0.2, n))
            ref[:, DOF[f"{side}_sh_flex"]] = rng.normal(0.0, 0.2, n)
            ref[:, DOF[f"{side}_sh_abd"]] = np.abs(rng.normal(0.1, 0.2, n))
            ref[:, DOF[f"{side}_sh_rot"]] = rng.normal(0.0, 0.2, n)
            ref[:, DOF[f"{side}_elbow"]] = np.abs(rng.normal(0.2, 0.3, n))
        assert np.array_equal(got, ref)


def test_a_lowered_root_is_drawn_sitting_with_its_feet_on_the_floor():
    """With the blob's top 0.3 m below the stature (a person sitting down), the
    importance function's ``low_legs`` share of draws bends both legs so that the
    ankles stand at their height above the floor, ahead of the hips, within the limits;
    without it (0) the legs stay near standing and the ankles go into the floor."""
    from app.pose.detections import Detections, Importance
    det = Detections(head=np.array([1.0, 2.0, 1.25]), top=H - 0.3, centroid=np.array([1.0, 2.0, 0.7]),
                     headings=[0.0], hands=None)
    model = BodyModel(H)
    for share, sitting in ((0.5, True), (0.0, False)):
        draws = Importance(det, H, low_legs=share)(400, np.random.default_rng(3))
        assert ((draws >= LIMITS_LO) & (draws <= LIMITS_HI)).all()
        bent = (draws[:, DOF["l_knee"]] > 0.7) & (draws[:, DOF["l_hip_flex"]] > 0.7)
        if not sitting:
            assert not bent.any()
            assert np.median([model.joints(s)[JOINTS.index("l_ankle"), 2] for s in draws]) < 0.0
            continue
        assert 0.35 < bent.mean() < 0.65
        j = np.array([model.joints(s) for s in draws[bent]])
        for side in ("l", "r"):
            ankle, hip = j[:, JOINTS.index(f"{side}_ankle")], j[:, JOINTS.index(f"{side}_hip")]
            off = np.abs(ankle[:, 2] - 0.039 * H)          # from the ankle's standing height
            assert np.median(off) < 0.015 and np.percentile(off, 90) < 0.04
            assert (ankle[:, 0] - hip[:, 0]).mean() > 0.2      # feet ahead of the hips (heading 0: +x)


def test_observation_box_and_cells_are_numpys(footless_clip):
    """The observation's box (one pass for the bounds), cells (one pass for the index
    and the occupancy) and proximity map (flat offsets away from the box's border)
    against numpy operations, on hull frames moved off the grid."""
    from app.pose.observation import _kernel, observe

    frames, cal = footless_clip
    rng = np.random.default_rng(2)
    for fr in frames[::4]:
        # (no margin: the kernel crosses the box's border, the bounds-tested path)
        for margin in (0.35, 0.0):
            c = fr.centres + rng.normal(0, 0.004, 3)
            obs = observe(c, 0.02, cal.room_min, cal.room_max, margin=margin)
            lo, hi = c.min(axis=0) - margin, c.max(axis=0) + margin
            lo[2] = min(lo[2], cal.room_min[2])
            origin = np.floor(lo / 0.02) * 0.02
            dims = np.maximum(np.ceil((hi - origin) / 0.02).astype(np.int64) + 1, 1)
            idx = np.floor((c - origin) / 0.02).astype(np.int64)
            occ = np.zeros(tuple(dims), np.uint8)
            occ[idx[:, 0], idx[:, 1], idx[:, 2]] = 1
            assert np.array_equal(obs.origin, origin) and np.array_equal(obs.occ, occ)
            # the proximity map: the kernel stamped by maximum around every surface voxel
            offs, kern = _kernel(2, 1.0)
            prox = np.zeros(tuple(dims), np.float32)
            for o, v in zip(offs, kern):
                at = idx[obs.surface] + o
                at = at[np.all((at >= 0) & (at < dims), axis=1)]
                np.maximum.at(prox, (at[:, 0], at[:, 1], at[:, 2]), v)
            assert np.array_equal(obs.prox, prox)


def test_leg_penalties_are_the_floor_and_stance_priors():
    """The scorer's one pass over the legs gives the floor and stance priors' numbers bit
    for bit (random states inside the joint limits: standing, crouching, legs spread)."""
    from app.pose.annealing import propagate
    from app.pose.coverage import floor_penalty, leg_penalties
    from app.pose.filters import SIGMA0
    from app.pose.model import LIMITS_HI, LIMITS_LO

    rng = np.random.default_rng(4)
    states = propagate(np.tile(neutral_state(H, (1.0, 2.0, None)), (4000, 1)), 3 * SIGMA0, LIMITS_LO, LIMITS_HI, rng)
    for both, stance in ((0.0, 0.0), (0.05, 0.03)):
        fl, st = leg_penalties(states, H, 0.02, both, stance)
        assert np.array_equal(fl, floor_penalty(states, H, 0.02, both))
        assert (st is None) == (stance == 0)
        if st is not None:
            assert np.array_equal(st, stance_penalty(states, H, stance)) and (st > 0).mean() > 0.1 and (st == 0).any()
    crowned, _ = leg_penalties(states, H, 0.02, 0.05, 0.03, crown=(1.62, 0.015))   # the head in the same pass
    head = crown_penalty(states, H, 1.62, 0.015)
    assert np.array_equal(crowned, floor_penalty(states, H, 0.02, 0.05) + head) and (head > 0).mean() > 0.1


def test_coverage_is_the_masked_sum():
    """rho_Cov from the kernel's counts (whole numbers) against numpy's masked sum."""
    from app.pose.coverage import coverage

    rng = np.random.default_rng(6)
    counts = rng.integers(0, 300, (500, 11, 5)).astype(np.float64)
    active = rng.random(11) < 0.6
    for n, delta in ((5000, 2.0), (40000, 1.0), (0, 2.0)):
        ref = np.minimum(counts[:, active, 2].sum(axis=1) * delta ** 3 / max(n, 1), 1.0)
        got = coverage(counts, active, n, delta)
        assert np.array_equal(got, ref) and ((got < 1).any() or n == 0)


def test_crown_expects_the_head_under_the_top_and_pushes_only_a_lower_head():
    vs = 0.04
    standing_top = 1.015 * H - vs / 2                           # the top the stature was read from
    stand = neutral_state(H, (1.0, 2.0, None))
    head = BodyModel(H).joints(stand)[J["head"], 2]
    assert crown_expectation(standing_top, H, vs) == pytest.approx(head)
    assert crown_expectation(standing_top + 0.3, H, vs) == pytest.approx(head)   # a hand above the head: capped
    assert crown_expectation(standing_top - 0.5, H, vs) == pytest.approx(head - 0.5)   # sitting: the head lower
    squat = stand.copy()
    squat[2] -= 0.3
    pen = crown_penalty(np.stack([stand, squat]), H, head, 0.03)
    assert pen[0] == 0.0
    assert pen[1] == pytest.approx(0.5 * ((0.3 - CROWN_FREE) / 0.03) ** 2)
    assert crown_penalty(squat[None], H, head - 0.5, 0.03)[0] == 0.0          # the top says sitting: not pushed


def test_crown_keeps_a_hull_without_its_chest_standing():
    """The masks lose a grey shirt against a grey wall (random scene 10): the 4 cm hull
    (k = 0) of gesture1 has nothing between 0.95 and 1.4 m. The scores alone let the body
    sink into a crouch under the head's voxels in some runs (which ones depends on the float
    rounding of numpy's SIMD path): on an AVX-512 machine, filter seeds 0 and 3 of 0-4 sank
    (pelvis within 100 mm in 6 % and 3 % of the frames, MMTA 0.05 and 0.01); on an earlier
    machine one of seeds 0-2 did (MMTA 0.13 or 0.31). The crown holds it up in every run:
    asserted here, pelvis and neck within 100 mm in at least 95 % of the frames for each
    seed. A hull without its chest is also nearly the same from the front and from the
    back, so a standing body may be posed facing the wrong way from the first frame: two
    of the five seeds on the AVX-512 machine (pelvis and neck in place, hips 180 mm and
    wrists 1.2 m off, MMTA 0.20; app.pose.facing); the others keep MMTA 0.86-0.93, and at
    least three of the five are asserted at 0.75 or more."""
    clip, cal = simulated_clip("gesture1", range(0, 40), 0.04, source="hull", tolerance=0,
                               hide=lambda f, c: ~((c[:, 2] > 0.95) & (c[:, 2] < 1.4)))
    mmta, upright = {}, {}
    for seed in range(5):
        E = _posed_errors(clip, cal, 0.04, crown=0.03, seed=seed)
        mmta[seed] = float((E <= 0.1).mean())
        upright[seed] = float((E[:, [J["pelvis"], J["neck"]]] <= 0.1).all(axis=1).mean())
        print(f"crown 0.03, seed {seed}: MMTA {mmta[seed]:.3f}, pelvis and neck within 100 mm in "
              f"{upright[seed]:.2f} of the frames, head median {1e3 * np.median(E[:, J['head']]):.0f} mm, "
              f"pelvis median {1e3 * np.median(E[:, J['pelvis']]):.0f} mm")
    assert min(upright.values()) >= 0.95, upright
    assert sum(m >= 0.75 for m in mmta.values()) >= 3, mmta
