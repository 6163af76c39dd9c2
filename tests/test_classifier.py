"""The person / no-person decision tree: the shipped JSON file, its numpy reader and training."""
import json
import subprocess
import sys

import numpy as np
import pytest

from app.errors import InputError
from app.tracking.blobs import CLASSIFIER_FEATURES
from app.tracking.classifier import DEFAULT_TREE, DecisionTree, load_tree
from tests.conftest import ROOT


def test_tree_loads_without_scikit_learn():
    """The pipeline's reader imports nothing from scikit-learn (blocked in a fresh interpreter)."""
    code = ("import sys; sys.modules['sklearn'] = None\n"
            "from app.tracking.classifier import load_tree\n"
            "from app.tracking.blobs import ComponentAnalysis\n"
            "import workers.cca, workers.tracking\n"
            "t = load_tree()\n"
            "print(len(t.feature), t.predict([[300.0, 0.85, 1.75, 1.7, 0.9, 0.7]])[0])\n"
            "assert not any(m.startswith('sklearn') for m in sys.modules if sys.modules[m] is not None)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    n, verdict = r.stdout.split()
    assert int(n) >= 3 and verdict == "True"


def test_shipped_tree_is_small_json_with_its_scores():
    data = json.loads(DEFAULT_TREE.read_text())
    assert data["features"] == list(CLASSIFIER_FEATURES)
    assert len(data["nodes"]) < 200
    cv = data["training"]["cross_validated"]
    assert cv["f_measure"] > 0.95 and data["training"]["held_out"]["f_measure"] > 0.9


def test_shipped_tree_on_typical_components():
    """Persons (standing, seated) kept; a floor shadow, a small phantom, a table rejected."""
    t = load_tree()
    # weight kg, z-centroid, top, height, extents (m): the shapes of today's visual hull
    standing = [330.0, 0.85, 1.74, 1.72, 1.1, 0.8]
    floor = [25.0, 0.08, 0.18, 0.16, 0.7, 0.5]
    phantom = [40.0, 1.1, 1.5, 0.7, 0.4, 0.3]
    table = [900.0, 0.4, 0.75, 0.74, 1.6, 0.8]
    assert t.predict([standing, floor, phantom, table]).tolist() == [True, False, False, False]


def test_bad_tree_files(tmp_path):
    p = tmp_path / "t.json"
    p.write_text("{")
    with pytest.raises(InputError, match="not a JSON classifier"):
        load_tree(p)
    p.write_text(json.dumps({"format": "smartroom-decision-tree", "features": ["a"], "nodes": [[0, 1.0, 5, 6, 0.0]]}))
    with pytest.raises(InputError, match="bad tree"):
        load_tree(p)
    with pytest.raises(InputError, match="not found"):
        load_tree(tmp_path / "missing.json")


def test_training_round_trip_matches_scikit_learn():
    """A pruned tree trained on synthetic components predicts like scikit-learn's own."""
    pytest.importorskip("sklearn")
    from app.tracking.training import train_tree

    rng = np.random.default_rng(0)
    n = 600
    person = rng.random(n) < 0.3
    x = np.column_stack([
        np.where(person, rng.normal(300, 60, n), rng.gamma(2, 15, n)),    # weight
        rng.uniform(0.1, 1.2, n), np.where(person, rng.normal(1.6, 0.15, n), rng.uniform(0.1, 1.6, n)),
        rng.uniform(0.1, 1.7, n), rng.uniform(0.1, 1.5, n), rng.uniform(0.1, 1.0, n)])
    tree, report = train_tree(x, person, folds=3)
    assert report["cross_validated"]["f_measure"] > 0.9
    again = DecisionTree(**{k: v for k, v in [("features", tree.features)]}, nodes=tree.to_json()["nodes"])
    assert np.array_equal(again.predict(x), tree.predict(x))
    assert (tree.predict(x) == person).mean() > 0.95
