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

def _group(parts, dofs, body):
    """A candidate group: the parts it scores, its limb DoFs and its bodies (FACTORS order)."""
    return (np.isin(np.array(PARTS), parts), np.array([DOF[d] for d in dofs]), [body(f) for f in FACTORS])


#: legs, then arms
_GROUPS = (
    _group(("pelvis", "l_thigh", "l_shin", "r_thigh", "r_shin"),
           [f"{s}_{d}" for s in "lr" for d in ("hip_flex", "hip_abd", "hip_rot", "knee")],
           lambda f: Proportions(legs=f)),
    _group(("l_upper_arm", "l_forearm", "r_upper_arm", "r_forearm"),
           [f"{s}_{d}" for s in "lr" for d in ("sh_flex", "sh_abd", "sh_rot", "elbow")],
           lambda f: Proportions(arms=f)),
)


def _lower_ankle(state: np.ndarray, height: float, proportions: Proportions) -> float:
    return float(joints_subset(state[None], height, _ANKLES, _ANKLE_NEED, proportions)[0, :, 2].min())


def on_body(state: np.ndarray, height: float, now: Proportions, other: Proportions, low_now=None) -> np.ndarray:
    """``state`` (27,) of a body of ``now`` proportions moved onto one of ``other``: the
    same angles, the root raised or lowered by what keeps the lower ankle's height
    (``low_now``, when the caller has it)."""
    out = np.array(state, dtype=np.float64)
    low = _lower_ankle(out, height, now) if low_now is None else low_now
    out[2] += low - _lower_ankle(out, height, other)
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

    def weigh(self, est: np.ndarray, height: float, now: Proportions, score, rng: np.random.Generator) -> None:
        """One frame: ``score(states, proportions, active) -> log-weights`` is the person's
        likelihood of this frame with a candidate's body; ``rng`` draws the nudges."""
        out = np.zeros_like(self.sums)
        low = _lower_ankle(np.asarray(est, dtype=np.float64), height, now)
        for g, (active, idx, bodies) in enumerate(_GROUPS):
            nudges = rng.normal(0.0, 1.0, (TRIES, len(idx))) * SIGMA0[idx]
            for c, body in enumerate(bodies):
                states = np.repeat(on_body(est, height, now, body, low)[None], TRIES + 1, axis=0)
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
