"""The feet's vote for the way a person faces (app.pose.facing): read at the estimate's
ankles, it points the way the feet point whichever way the estimate faces, and says
nothing where the hull widened the footprint all round."""
import numpy as np

from app.pose.facing import DECAY, VOTE, FacingVote, floor_footprint, frame_vote
from app.pose.flesh import build_flesh
from app.pose.model import BodyModel, neutral_state
from app.pose.observation import observe

H = 1.75


def _body_voxels(yaw: float, position=(1.5, 1.5)) -> np.ndarray:
    """The flesh model's points of a person standing at ``position`` facing ``yaw``
    (feet included), as 2 cm voxel centres."""
    flesh = build_flesh(H, 0.02, 1.0)
    R, O = BodyModel(H).forward(neutral_state(H, (*position, None), yaw=yaw))
    return np.einsum("nij,nj->ni", R[flesh.segment], flesh.points) + O[flesh.segment]


def _vote(centres, estimate_yaw, position=(1.5, 1.5)):
    obs = observe(centres, 0.04, (0, 0, 0), (4, 4, 2.5))
    footprint = floor_footprint(obs.occ, obs.origin, obs.voxel_size)
    joints = BodyModel(H).joints(neutral_state(H, (*position, None), yaw=estimate_yaw))
    return frame_vote(joints, footprint, obs.origin, obs.voxel_size, H)


def test_the_vote_points_the_way_the_feet_point_whichever_way_the_estimate_faces():
    for true_yaw in (0.0, 2.0):
        centres = _body_voxels(true_yaw)
        facing = np.array([np.cos(true_yaw), np.sin(true_yaw)])
        for estimate_yaw in (true_yaw, true_yaw + np.pi):
            v = _vote(centres, estimate_yaw)
            assert np.hypot(*v) > 0.9, (true_yaw, estimate_yaw, v)            # both feet say so
            assert v @ facing / np.hypot(*v) > 0.9, (true_yaw, estimate_yaw, v)
        v = _vote(centres, true_yaw + 0.3)      # 17 deg off: the feet read where the estimate's are
        assert v @ facing >= 0, v               # (some or none say so; never the wrong way)


def test_a_footprint_widened_all_round_says_nothing():
    centres = _body_voxels(0.0)
    xs = np.arange(1.5 - 0.36, 1.5 + 0.37, 0.04)
    disc = np.array([(x, y, 0.02) for x in xs for y in xs if np.hypot(x - 1.5, y - 1.5) <= 0.36])
    assert np.allclose(_vote(np.vstack([centres, disc]), 0.0), 0.0)
    assert np.allclose(_vote(np.vstack([centres, disc]), np.pi), 0.0)
    raised = centres[centres[:, 2] > 0.12]             # the feet lost by the hull: no floor voxels
    assert np.allclose(_vote(raised, 0.0), 0.0)


def test_the_person_vote_needs_a_few_frames_and_decays():
    vote = FacingVote()
    assert vote.heading() is None
    vote.add(np.array([0.0, 1.0]))
    assert vote.heading() is None                      # one frame, one foot: not yet
    for _ in range(3):
        vote.add(np.array([0.0, 1.0]))
    assert np.isclose(vote.heading(), np.pi / 2)
    for _ in range(40):
        vote.add(np.zeros(2))                          # nothing said for 1.6 s: forgotten
    assert np.hypot(*vote.vector) < VOTE and vote.heading() is None
    assert np.isclose(np.hypot(*vote.vector), sum(DECAY ** k for k in range(40, 44)))


def test_the_vote_is_kept_in_the_pose_snapshot():
    from app.pose.estimator import PoseEstimator, PoseSettings
    from app.pose.snapshot import estimator_state, restore_estimator

    settings = PoseSettings(voxel_size=0.04, room_lo=(0.0, 0.0, 0.0), room_hi=(4.0, 4.0, 2.5), toes=0.8, gamma=10)
    est = PoseEstimator(settings)
    centres = _body_voxels(1.0)
    for _ in range(6):   # standing still: the feet vote
        est.update(centres, None, [7], [[1.5, 1.5, 1.0]])
    vote = est.people[7].vote.vector
    assert np.hypot(*vote) > 0 and vote @ [np.cos(1.0), np.sin(1.0)] / np.hypot(*vote) > 0.9, vote
    back = restore_estimator(settings, estimator_state(est))
    assert np.array_equal(back.people[7].vote.vector, vote)
    arrays = estimator_state(est)
    del arrays["p7.vote"]                              # a snapshot of an earlier build: no vote yet
    assert not restore_estimator(settings, arrays).people[7].vote.vector.any()
