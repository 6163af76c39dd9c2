"""The ground prior (app.pose.coverage.ground_penalty, issue 11 round 2): no ankle below
its standing height. A standing body costs nothing, the same body sunk into the floor
costs both ankles, a raised foot nothing; leg_penalties adds it to the floor prior."""
import numpy as np

from app.messages import JOINTS
from app.pose.coverage import ground_penalty, leg_penalties
from app.pose.model import DOF, BodyModel, neutral_state

H = 1.75
ANKLES = [JOINTS.index("l_ankle"), JOINTS.index("r_ankle")]


def _states():
    stand = neutral_state(H, (1.0, 1.0, None))
    rest = 0.039 * H
    z = BodyModel(H).joints(stand)[ANKLES, 2]
    stand[DOF["z"]] += rest - z.min()                   # both ankles at their standing height
    sunk = stand.copy()
    sunk[DOF["z"]] -= 0.03                              # 3 cm into the floor
    step = stand.copy()
    step[DOF["r_hip_flex"]] = 0.4                       # the right foot lifted (swing leg)
    step[DOF["r_knee"]] = 0.8
    return np.array([stand, sunk, step])


def test_ground_penalty_holds_the_ankles_up_only():
    states = _states()
    z = np.array([BodyModel(H).joints(s)[ANKLES, 2] for s in states])
    pen = ground_penalty(states, H, 0.01)
    assert pen[0] < 1e-6                                 # standing: free
    expected = 0.5 * ((np.maximum(0.039 * H - z[1], 0) / 0.01) ** 2).sum()
    assert abs(pen[1] - expected) < 1e-9 and pen[1] > 8  # both ankles 3 cm under: 2 x 0.5 x 3^2
    assert z[2, 1] > z[0, 1] + 0.05 and pen[2] < 1e-6    # a lifted foot costs nothing


def test_leg_penalties_add_the_ground_prior_to_the_floor_prior():
    states = _states()
    without, _ = leg_penalties(states, H, 0.02)
    with_ground, _ = leg_penalties(states, H, 0.02, ground=0.01)
    assert np.allclose(with_ground, without + ground_penalty(states, H, 0.01))


def test_anchor_penalty_keeps_the_root_near_its_track_only_beyond_the_free_radius():
    from app.pose.coverage import anchor_penalty
    states = np.array([neutral_state(H, (1.0, 1.0, None)), neutral_state(H, (1.2, 1.0, None)),
                       neutral_state(H, (1.0, 1.35, None))])
    pen = anchor_penalty(states, 1.0, 1.0, 0.25, 0.05)
    assert pen[0] == 0 and pen[1] == 0                   # within 0.25 m of the track: free
    assert abs(pen[2] - 0.5 * (0.10 / 0.05) ** 2) < 1e-9  # 0.35 m away: 0.1 m beyond, 2 deviations
