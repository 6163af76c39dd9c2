"""``smartroom eval``'s pose breakdown: where the MMTA goes (people without a pose, and
each joint posed too far), consistent with the MMTA itself."""
import numpy as np

from app.evaluation.pose import pose_breakdown, pose_report
from app.messages import JOINTS

J = {n: i for i, n in enumerate(JOINTS)}


def test_breakdown_accounts_for_every_joint_the_mmta_loses():
    rng = np.random.default_rng(0)
    a = rng.normal(0, 0.3, (15, 3)) + [1.0, 1.0, 1.0]
    b = rng.normal(0, 0.3, (15, 3)) + [3.0, 2.0, 1.0]
    frames = []
    for f in range(6):
        est = {7: a + 0.01}                      # person 1 posed 17 mm off everywhere
        if f >= 2:                               # person 2 posed from frame 2 (a track confirmed late)
            e = b.copy()
            if f == 4:
                e[J["r_wrist"]] += [0.3, 0.0, 0.0]   # one wrist lost for one frame
            est[9] = e
        frames.append((f, {1: a, 2: b}, est))
    out = pose_breakdown(frames, epsilon=0.1)
    assert out["joints"] == 6 * 2 * 15
    assert out["unposed"] == {"2": [[0, 1]]}
    assert out["unposed_share"] == round(2 * 15 / 180, 4)
    assert out["joint_loss"]["r_wrist"] == round(1 / 180, 4) and sum(out["joint_loss"].values()) == out["joint_loss"]["r_wrist"]
    assert out["bad_frames"] == {"2": {"r_wrist": [[4, 4]]}}
    assert out["worst"] == [{"frame": 4, "person": 2, "joints_off": 1}]
    mmta = pose_report([(t, e, {}) for _, t, e in frames], epsilon=0.1)["mmta"]
    assert abs(1 - mmta - out["unposed_share"] - sum(out["joint_loss"].values())) < 1e-3
