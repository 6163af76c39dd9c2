"""The pipeline's IAPF share (issue 11, round 2): the pose worker draws 35 % of the first
annealing layer from the detections (0.2 before; through the pipeline 0.35 gains on
gesture1, walk1 and meeting3, docs/history/pose-likelihood.md "Round 2"): a filter
whose particles all sit in a wrong arm pose gets that share of them from the importance
function, and with it finds the arm the data shows."""
import numpy as np

from app.pose.filters import APF
from app.pose.model import DOF, LIMITS_HI, LIMITS_LO, N_DOF
from workers.pose import Pose


class _ArmScorer:
    """A likelihood with one peak: the left elbow straight (0.05 rad)."""

    def log_weights(self, states, active=None):
        return -0.5 * ((states[:, DOF["l_elbow"]] - 0.05) / 0.05) ** 2


def _hanging_arm(n, rng, base=None, dofs=None):
    out = np.array(base, dtype=np.float64)
    out[:, DOF["l_elbow"]] = np.abs(rng.normal(0.05, 0.05, n))
    return np.clip(out, LIMITS_LO, LIMITS_HI)


def test_the_worker_draws_its_share_of_the_first_layer_from_the_detections():
    share = Pose.DEFAULTS["importance_fraction"]
    assert share == 0.35
    filt = APF(particles=200, layers=1, rng=np.random.default_rng(0), importance_fraction=share)
    base = np.zeros((200, N_DOF))
    base[:, DOF["l_elbow"]] = 2.0                      # the forearm folded up: every particle
    mixed = filt._mix_importance(base.copy(), _hanging_arm)
    moved = np.abs(mixed[:, DOF["l_elbow"]] - 2.0) > 1e-9
    assert moved.sum() == round(share * 200)
    assert np.array_equal(mixed[~moved], base[~moved])  # the dynamics' particles stay


def test_a_folded_forearm_is_found_straight_within_a_frame():
    filt = APF(particles=200, layers=3, rng=np.random.default_rng(1),
               importance_fraction=Pose.DEFAULTS["importance_fraction"])
    state = np.zeros(N_DOF)
    state[DOF["z"]] = 1.0
    state[DOF["l_elbow"]] = 2.0
    filt.reset(state, spread=np.full(N_DOF, 1e-3))      # stuck: the diffusion cannot reach the peak
    est = filt.step(_ArmScorer(), importance=_hanging_arm)
    assert abs(est[DOF["l_elbow"]] - 0.05) < 0.05
