"""The learnt behaviour model (Caillette, Galata and Howard, CVIU 2007, §3.2, §4): the
Gaussian clusters of the feature vectors ``X_t = (x_t, dx_t)`` (the body model's joint
angles, :data:`FEATURE_DOFS`, the six global parameters left out, and their change since
the previous frame) and the VLMM over the cluster labels of training sequences.

One departure, said: the angles are first projected on their ``components`` principal
axes (the same basis for ``x`` and ``dx``, so ``dx`` stays the change of ``x``), and the
clusters live in that space. With the 21 angles whole, a full-covariance cluster has
945 parameters and Figueiredo and Jain's criterion, which asks each cluster to be
supported by half its parameters' worth of frames, kept one cluster of the 1400 frames
of two random scenes; with 8 axes (152 parameters) the motion's structure shows.

Training data (:func:`training_states`): the simulator's people, posed by our body model
(:func:`app.markers.tracking.fit_state`, least squares on the true joints, each frame
started from the one before), one sequence per person and scene. The model is a JSON
file (:data:`DEFAULT_PATH`, written by ``smartroom train behaviour``; no pickles).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.behaviour.clusters import GaussianClusters, fit_clusters, significant
from app.behaviour.vlmm import Vlmm, learn_vlmm
from app.pose.model import N_DOF

__all__ = ["FEATURE_DOFS", "BehaviourModel", "Subspace", "features", "training_states", "train_behaviour",
           "DEFAULT_PATH"]

FEATURE_DOFS = np.arange(6, N_DOF)      # the joint angles: not x, y, z, yaw, pitch, roll
DEFAULT_PATH = Path(__file__).with_name("behaviour.json")
FORMAT = "smartroom-behaviour/1"


@dataclass
class Subspace:
    """The angles' principal axes: ``x ~ mean + basis @ p`` (basis (21, D), orthonormal)."""

    mean: np.ndarray
    basis: np.ndarray

    @classmethod
    def of(cls, angles: np.ndarray, components: int) -> "Subspace":
        mean = angles.mean(axis=0)
        _, _, vt = np.linalg.svd(angles - mean, full_matrices=False)
        return cls(mean, vt[:components].T.copy())

    def reduce(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, float) - self.mean) @ self.basis

    def reduce_change(self, dx: np.ndarray) -> np.ndarray:
        return np.asarray(dx, float) @ self.basis


def features(states: np.ndarray, subspace: Subspace) -> np.ndarray:
    """Feature vectors (T - 1, 2 D) of a sequence of states (T, 27): the joint angles of
    frames 1.. and their change from the frame before (per frame), on the principal axes."""
    x = np.asarray(states, float)[:, FEATURE_DOFS]
    return np.concatenate([subspace.reduce(x[1:]), subspace.reduce_change(np.diff(x, axis=0))], axis=1)


@dataclass
class BehaviourModel:
    clusters: GaussianClusters
    vlmm: Vlmm
    subspace: Subspace
    fps: float = 25.0
    info: dict | None = None

    @property
    def dims(self) -> int:
        return self.subspace.basis.shape[1]

    def labels(self, states: np.ndarray) -> np.ndarray:
        """The cluster of each frame (1..) of a sequence of states."""
        return self.clusters.label(features(states, self.subspace))

    def to_json(self) -> str:
        sub = {"mean": significant(self.subspace.mean), "basis": significant(self.subspace.basis)}
        return json.dumps({"format": FORMAT, "fps": self.fps, "dofs": FEATURE_DOFS.tolist(), "subspace": sub,
                           "clusters": self.clusters.to_dict(), "vlmm": self.vlmm.to_dict(),
                           "info": self.info or {}}, separators=(",", ":"))

    @classmethod
    def load(cls, path=DEFAULT_PATH) -> "BehaviourModel":
        from app.errors import InputError
        try:
            d = json.loads(Path(path).read_text())
            if d.get("format") != FORMAT or d.get("dofs") != FEATURE_DOFS.tolist():
                raise ValueError("another format")
            sub = Subspace(np.asarray(d["subspace"]["mean"], float), np.asarray(d["subspace"]["basis"], float))
            if sub.mean.shape != (len(FEATURE_DOFS),) or sub.basis.ndim != 2 or sub.basis.shape[0] != len(FEATURE_DOFS):
                raise ValueError("a subspace of other angles")
            model = cls(GaussianClusters.from_dict(d["clusters"]), Vlmm.from_dict(d["vlmm"]), sub, float(d["fps"]),
                        d.get("info") or {})
        except (OSError, ValueError, KeyError, TypeError, np.linalg.LinAlgError) as exc:
            raise InputError(f"behaviour model {path}: not readable ({exc})") from None
        if model.vlmm.labels != model.clusters.k or model.clusters.means.shape[1] != 2 * model.dims:
            raise InputError(f"behaviour model {path}: its VLMM and clusters do not match")
        return model


def training_states(seeds, seconds: float = 12.0, fps: float = 25.0, progress=None) -> list[np.ndarray]:
    """Our body model's states (T, 27) of every person of the random scenes ``seeds``, one
    array per person and scene (the frames they are in the room, a gap ends a sequence)."""
    from app.markers.tracking import fit_state
    from app.messages import JOINTS
    from app.simulation.simulator import RANDOM, Simulator

    out = []
    for n, seed in enumerate(seeds):
        sim = Simulator(RANDOM, seed=int(seed), fps=fps, seconds=seconds)
        runs: dict[int, list] = {}
        last: dict[int, tuple] = {}
        for i in range(sim.frame_count()):
            for p in sim.groundtruth(i)["people"]:
                X = np.array([p["joints"][j] for j in JOINTS], float)
                prev = last.get(p["id"])
                fresh = prev is None or prev[0] != i - 1
                state = fit_state(p["height"], X, None if fresh else prev[1])
                if fresh:
                    runs.setdefault(p["id"], []).append([])
                runs[p["id"]][-1].append(state)
                last[p["id"]] = (i, state)
        out += [np.array(r) for rs in runs.values() for r in rs if len(r) >= 3]
        if progress:
            progress(n + 1, len(seeds))
    return out


def train_behaviour(sequences, k_max: int = 30, memory: int = 10, epsilon: float = 1e-4, p_min: float = 1e-3,
                    g_min: float = 1e-3, components: int = 8, fps: float = 25.0, seed: int = 0) -> BehaviourModel:
    """The angles' principal axes, the clusters of the sequences' feature vectors on them
    (Figueiredo and Jain), then the VLMM of their label sequences."""
    sequences = [np.asarray(s, float) for s in sequences if len(s) >= 3]
    subspace = Subspace.of(np.concatenate([s[:, FEATURE_DOFS] for s in sequences]), components)
    feats = [features(s, subspace) for s in sequences]
    clusters = fit_clusters(np.concatenate(feats), k_max=k_max, rng=np.random.default_rng(seed))
    labels = [clusters.label(f) for f in feats]
    vlmm = learn_vlmm(labels, clusters.k, memory=memory, epsilon=epsilon, p_min=p_min, g_min=g_min)
    return BehaviourModel(clusters, vlmm, subspace, fps,
                          {"frames": int(sum(len(f) for f in feats)), "k_max": k_max, "memory": memory,
                           "epsilon": epsilon, "components": components})
