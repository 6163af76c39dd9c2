"""A person's limb lengths read from their own voxels (issue 22).

The thesis sets every segment "proportionally to the height of the subject" (§6.3.4):
one person's legs and arms are Drillis & Contini's fractions of the stature. People's
differ: at 1.75 m, legs 5 % longer than the average put the hips (and, with the trunk
shorter, nothing above them) 4 cm higher, arms 6 % longer the wrists 3.5 cm farther.

:class:`ProportionFit` weighs a few candidate bodies (:class:`app.pose.model.Proportions`,
legs or arms stretched by the factors of :data:`FACTORS`, the average among them) on the
person's first posed frames once the stature is settled. Each frame the filter's
estimate is moved onto each candidate body (:func:`on_body`: the same angles, the root
raised or lowered so that the lower ankle stays where it was: a longer-legged body on the
same floor); its limbs get :data:`TRIES` random nudges of their angles (the filter's
propagation noise, so that a bent knee or elbow can meet the voxels with the candidate's
bones), and the best of them scores the candidate on the parts it changes (legs and
pelvis, or arms) with the person's likelihood and that body's flesh. The scores add up
over :attr:`ProportionFit.frames` frames; the best legs and the best arms are the
person's from then on.

Measured, it is not good enough to be the default (``pose.proportions: average``;
docs/benchmarks.md, "Limb lengths of the person's own"): on true-body voxels it finds
which way the legs differ from the average, on the pipeline's visual hulls it takes the
longest legs it may for almost everyone, whatever their own.
"""
from __future__ import annotations

import numpy as np

from app.messages import JOINTS
from app.pose.flesh import PARTS
from app.pose.model import AVERAGE, DOF, LIMITS_HI, LIMITS_LO, SIGMA0, Proportions, joints_subset, segments_needed

__all__ = ["FACTORS", "TRIES", "ProportionFit", "on_body"]

#: the stretches of legs and of arms weighed against the average (1.0)
FACTORS = (0.92, 0.96, 1.0, 1.04, 1.08)
#: the nudged limb angles scored per candidate and frame (and the estimate itself)
TRIES = 24

_ANKLES = np.array([JOINTS.index("l_ankle"), JOINTS.index("r_ankle")], dtype=np.int64)
_ANKLE_NEED = segments_needed(_ANKLES)
_GROUPS = {
    "legs": (("pelvis", "l_thigh", "l_shin", "r_thigh", "r_shin"),
             tuple(f"{s}_{d}" for s in "lr" for d in ("hip_flex", "hip_abd", "hip_rot", "knee"))),
    "arms": (("l_upper_arm", "l_forearm", "r_upper_arm", "r_forearm"),
             tuple(f"{s}_{d}" for s in "lr" for d in ("sh_flex", "sh_abd", "sh_rot", "elbow"))),
}


def on_body(state: np.ndarray, height: float, now: Proportions, other: Proportions) -> np.ndarray:
    """``state`` (27,) of a body of ``now`` proportions moved onto one of ``other``: the
    same angles, the root raised or lowered by what keeps the lower ankle's height."""
    y = np.asarray(state, dtype=np.float64)[None]
    low_now = joints_subset(y, height, _ANKLES, _ANKLE_NEED, now)[0, :, 2].min()
    low_other = joints_subset(y, height, _ANKLES, _ANKLE_NEED, other)[0, :, 2].min()
    out = y[0].copy()
    out[2] += low_now - low_other
    return out


class ProportionFit:
    """The running scores of one person's candidate legs and arms; ``frames`` frames
    weighed, :meth:`choice` gives the proportions (the average until then)."""

    def __init__(self, frames: int):
        self.frames = int(frames)
        self.sums = np.zeros((2, len(FACTORS)))   # legs, arms
        self.seen = 0

    @property
    def done(self) -> bool:
        return self.seen >= self.frames

    @staticmethod
    def body(group: int, factor: float) -> Proportions:
        return Proportions(legs=factor) if group == 0 else Proportions(arms=factor)

    def weigh(self, est: np.ndarray, height: float, now: Proportions, score, rng: np.random.Generator) -> None:
        """One frame: ``score(states, proportions, active) -> log-weights`` is the person's
        likelihood of this frame with a candidate's body; ``rng`` draws the nudges."""
        out = np.zeros_like(self.sums)
        for g, (parts, dofs) in enumerate(_GROUPS.values()):
            active = np.isin(np.array(PARTS), parts)
            idx = np.array([DOF[d] for d in dofs])
            nudges = rng.normal(0.0, 1.0, (TRIES, len(idx))) * SIGMA0[idx]
            for c, factor in enumerate(FACTORS):
                body = self.body(g, factor)
                states = np.repeat(on_body(est, height, now, body)[None], TRIES + 1, axis=0)
                states[1:, idx] = np.clip(states[1:, idx] + nudges, LIMITS_LO[idx], LIMITS_HI[idx])
                out[g, c] = np.max(score(states, body, active))
        if np.all(np.isfinite(out)):   # a frame a candidate cannot score says nothing
            self.sums += out
            self.seen += 1

    def choice(self) -> Proportions:
        """The best-scoring legs and arms (the average until :attr:`frames` are weighed)."""
        if not self.done:
            return AVERAGE
        return Proportions(legs=FACTORS[int(np.argmax(self.sums[0]))], arms=FACTORS[int(np.argmax(self.sums[1]))])
