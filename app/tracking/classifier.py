"""The person / no-person classifier (thesis §4.2.3, Table 4.2, Fig. 4.4): a pruned binary
decision tree over the features of Table 4.1, stored as a small JSON file and evaluated
here with numpy alone (training, :mod:`app.tracking.training`, needs scikit-learn; running
does not).

File format (``app/tracking/person_tree.json``)::

    {"format": "smartroom-decision-tree", "version": 1,
     "features": ["weight", "z_centroid", ...],      # column order of the input
     "nodes": [[feature, threshold, left, right, p_person], ...],
     ...}                                             # training notes (scores, data)

Node 0 is the root; a node with ``feature == -1`` is a leaf; a sample goes left when
``x[feature] <= threshold``. A leaf says person when ``p_person > 0.5``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from app.errors import InputError

__all__ = ["DecisionTree", "DEFAULT_TREE", "load_tree"]

DEFAULT_TREE = Path(__file__).with_name("person_tree.json")
FORMAT = "smartroom-decision-tree"


class DecisionTree:
    def __init__(self, features, nodes, info: dict | None = None):
        self.features = tuple(features)
        arr = np.asarray(nodes, dtype=np.float64).reshape(-1, 5)
        self.feature = arr[:, 0].astype(np.int64)
        self.threshold = arr[:, 1]
        self.left = arr[:, 2].astype(np.int64)
        self.right = arr[:, 3].astype(np.int64)
        self.p_person = arr[:, 4]
        self.info = info or {}
        n = len(arr)
        inner = self.feature >= 0
        if n == 0 or (inner & ((self.left < 0) | (self.left >= n) | (self.right < 0) | (self.right >= n))).any() \
                or (self.feature >= len(self.features)).any():
            raise ValueError("tree nodes point outside the tree or the feature list")

    def probability(self, x: np.ndarray) -> np.ndarray:
        """P(person) (K,) of the rows of ``x`` (K, len(features))."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, len(self.features))
        node = np.zeros(len(x), dtype=np.int64)
        for _ in range(64):   # depth bound
            f = self.feature[node]
            inner = f >= 0
            if not inner.any():
                break
            rows = np.nonzero(inner)[0]
            go_left = x[rows, f[rows]] <= self.threshold[node[rows]]
            node[rows] = np.where(go_left, self.left[node[rows]], self.right[node[rows]])
        return self.p_person[node]

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Person (True) or not (K,) bool."""
        return self.probability(x) > 0.5

    def to_json(self) -> dict:
        nodes = [[int(f), float(t), int(a), int(b), round(float(p), 4)]
                 for f, t, a, b, p in zip(self.feature, self.threshold, self.left, self.right, self.p_person)]
        return {"format": FORMAT, "version": 1, "features": list(self.features), "nodes": nodes, **self.info}


def load_tree(path=DEFAULT_TREE) -> DecisionTree:
    """Read a tree file (raises :class:`InputError` naming the file and the problem)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: classifier file not found") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a JSON classifier ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"{path}: not a {FORMAT} file")
    try:
        info = {k: v for k, v in data.items() if k not in ("format", "version", "features", "nodes")}
        return DecisionTree(data["features"], data["nodes"], info)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: bad tree ({exc})") from None
