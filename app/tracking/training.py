"""Training of the person / no-person classifier (thesis §4.2.3, Eq. 4.3, Table 4.2).

Components of simulated recordings are labelled by their ground truth: each true person
``x_j`` is assigned the component with the most voxels inside the region of influence
``E(x_j, (0.3, 0.3, z_j))`` (Eq. 4.2-4.3); those components are persons, every other
one is not (furniture, floor shadows, phantom blobs where silhouette cones of different
people meet). A decision tree (scikit-learn, CART with entropy) is grown on the features
of Table 4.1 and pruned by minimal cost-complexity, the pruning level chosen by k-fold
cross-validation of the F-measure; the tree is written as JSON for
:mod:`app.tracking.classifier`, which needs no scikit-learn.
"""
from __future__ import annotations

import numpy as np

from app.tracking.blobs import CLASSIFIER_FEATURES, ComponentAnalysis

__all__ = ["labelled_components", "train_tree", "scores"]

CATEGORIES = ("standing", "seated", "hidden", "phantom", "floor", "small")


def labelled_components(frames, grid: dict, truth: dict, step: int = 1, min_voxels: int = 1):
    """``(features (M, 6), person (M,) bool, category (M,) str)`` over every ``step``-th frame.

    ``truth``: ``{frame: record}`` of ``groundtruth.jsonl``. Categories: persons are
    ``seated`` (centroid below 0.8 m), ``hidden`` (some joints hidden from every camera)
    or ``standing``; others are ``floor`` (top under 0.3 m), ``small`` (under 5 kg) or
    ``phantom``.
    """
    cca = ComponentAnalysis(grid["dims"], grid["origin"], grid["voxel_size"])
    feats, labels, cats = [], [], []
    for v in frames[::step]:
        rec = truth.get(v.frame)
        if rec is None or len(v.indices) == 0:
            continue
        lab, f, _ = cca(v.indices)
        centres = np.asarray(grid["origin"]) + (v.indices.astype(np.float64) + 0.5) * grid["voxel_size"]
        person = np.zeros(len(f), dtype=bool)
        cat = np.empty(len(f), dtype=object)
        for p in rec.get("people", []):
            c = np.asarray(p["centroid"], dtype=np.float64)
            d = (centres - c) / np.array([0.3, 0.3, max(c[2], 0.1)])
            inside = (d ** 2).sum(axis=1) <= 1.0
            if not inside.any():
                continue
            k = int(np.bincount(lab[inside], minlength=len(f)).argmax())   # Eq. 4.3
            person[k] = True
            hidden = not all(p.get("visible", {}).values()) if p.get("visible") else False
            kind = "seated" if c[2] < 0.8 else "hidden" if hidden else "standing"
            if cat[k] is None or kind != "standing":
                cat[k] = kind
        for k in np.nonzero(~person)[0]:
            cat[k] = "floor" if f[k, 2] < 0.3 else "small" if f[k, 0] < 5.0 else "phantom"
        keep = f[:, 8] >= min_voxels
        feats.append(f[keep, :len(CLASSIFIER_FEATURES)])
        labels.append(person[keep])
        cats.append(cat[keep])
    if not feats:
        return np.zeros((0, len(CLASSIFIER_FEATURES))), np.zeros(0, bool), np.zeros(0, object)
    return np.concatenate(feats).astype(np.float64), np.concatenate(labels), np.concatenate(cats)


def scores(truth: np.ndarray, predicted: np.ndarray) -> dict:
    """Precision, recall and F-measure of the person class (Table 4.2)."""
    tp = int((truth & predicted).sum())
    fp = int((~truth & predicted).sum())
    fn = int((truth & ~predicted).sum())
    precision = tp / (tp + fp) if tp + fp else 1.0
    recall = tp / (tp + fn) if tp + fn else 1.0
    f = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"precision": round(precision, 4), "recall": round(recall, 4), "f_measure": round(f, 4),
            "components": int(len(truth)), "persons": int(truth.sum())}


def train_tree(x: np.ndarray, y: np.ndarray, folds: int = 5, seed: int = 0, log=print):
    """Grow, prune by cross-validated cost-complexity, refit: ``(DecisionTree, report)``."""
    try:
        from sklearn.model_selection import StratifiedKFold
        from sklearn.tree import DecisionTreeClassifier
    except ImportError:
        from app.errors import InputError
        raise InputError("training needs scikit-learn: pip install 'smartroom[train]'") from None
    from app.tracking.classifier import DecisionTree

    full = DecisionTreeClassifier(criterion="entropy", random_state=seed, min_samples_leaf=5)
    path = full.cost_complexity_pruning_path(x, y)
    alphas = np.unique(path.ccp_alphas)
    # a manageable grid of candidate alphas (geometric over the path)
    if len(alphas) > 25:
        alphas = np.unique(np.quantile(alphas, np.linspace(0, 1, 25)))
    cv = StratifiedKFold(n_splits=folds, shuffle=True, random_state=seed)
    results = []
    for a in alphas:
        pred = np.zeros(len(y), dtype=bool)
        for train, test in cv.split(x, y):
            m = DecisionTreeClassifier(criterion="entropy", random_state=seed, min_samples_leaf=5, ccp_alpha=a)
            m.fit(x[train], y[train])
            pred[test] = m.predict(x[test]).astype(bool)
        s = scores(y, pred)
        results.append((a, s))
    best_f = max(s["f_measure"] for _, s in results)
    # the simplest tree (largest alpha) within 0.002 of the best cross-validated F
    alpha, cv_scores = max((r for r in results if r[1]["f_measure"] >= best_f - 0.002), key=lambda r: r[0])
    model = DecisionTreeClassifier(criterion="entropy", random_state=seed, min_samples_leaf=5, ccp_alpha=alpha)
    model.fit(x, y)
    t = model.tree_
    classes = list(model.classes_)
    col = classes.index(True) if True in classes else 0
    nodes = []
    for i in range(t.node_count):
        v = t.value[i, 0]
        p = float(v[col] / v.sum()) if v.sum() else 0.0
        if t.children_left[i] == -1:
            nodes.append([-1, 0.0, -1, -1, p])
        else:
            nodes.append([int(t.feature[i]), float(t.threshold[i]), int(t.children_left[i]),
                          int(t.children_right[i]), p])
    report = {"ccp_alpha": float(alpha), "cross_validated": cv_scores, "folds": folds, "nodes": t.node_count,
              "depth": int(model.get_depth()), "unpruned_nodes": int(full.fit(x, y).tree_.node_count)}
    return DecisionTree(CLASSIFIER_FEATURES, nodes, {"training": report}), report
