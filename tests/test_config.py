"""Layouts and parameter overrides: validated at start with one-line errors."""
import pytest
import yaml

from app.config import LayoutError, apply_overrides, load_layout, parse_assignment, parse_layout
from workers import upstream_of


def test_default_layout_loads_with_defaults():
    layout = load_layout()
    kinds = [w.kind for w in layout.workers]
    assert kinds[:2] == ["grabber", "segmentation"] and "recorder" in kinds
    seg = layout.worker("segmentation")
    assert seg.params["history"] == 500 and seg.params["cameras"] == "all"


def _layout(workers, **extra):
    return {"room": "r", "workers": workers, **extra}


@pytest.mark.parametrize("doc, message", [
    (_layout([{"name": "g", "kind": "grabber"}, {"name": "g", "kind": "recorder"}]), "worker name g appears more than once"),
    (_layout([{"name": "x", "kind": "teleporter"}]), "worker x: unknown kind 'teleporter'"),
    (_layout([{"name": "s", "kind": "segmentation", "params": {"histroy": 3}}]), "worker s: unknown parameter 'histroy'"),
    (_layout([{"name": "s", "kind": "segmentation", "params": {"history": "long"}}]), "parameter history must be an integer"),
    (_layout([{"name": "s", "kind": "segmentation", "params": {"shadows": 1}}]), "parameter shadows must be true or false"),
    (_layout([]), "workers must be a non-empty list"),
    (_layout([{"name": "s", "kind": "segmentation"}], bus={"listen": "tcp/x"}), "bus.listen must be a list"),
    (_layout([{"name": "s", "kind": "segmentation"}], extra=1), "unknown section 'extra'"),
    ({"room": "a/b", "workers": [{"kind": "grabber"}]}, "room must be a plain word"),
    (_layout([{"name": "w", "kind": "app.errors:InputError"}]), "kind 'app.errors:InputError' is not a worker"),
])
def test_layout_errors(doc, message):
    with pytest.raises(LayoutError) as e:
        parse_layout(doc, "my.yaml")
    assert str(e.value).startswith("my.yaml: ") and message in str(e.value)


def test_missing_layout_file(tmp_path):
    with pytest.raises(LayoutError, match="layout file not found"):
        load_layout(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("workers: [\n")
    with pytest.raises(LayoutError, match="not valid YAML"):
        load_layout(bad)


def test_overrides_by_kind_and_name():
    layout = load_layout()
    out = apply_overrides(layout, {"segmentation": {"history": 42}, "grabber": {"start": 3}})
    assert out.worker("segmentation").params["history"] == 42
    assert out.worker("grabber").params["start"] == 3
    assert layout.worker("segmentation").params["history"] == 500  # the original is untouched
    with pytest.raises(LayoutError, match="no worker or kind named 'tracker'"):
        apply_overrides(layout, {"tracker": {"x": 1}})
    with pytest.raises(LayoutError, match="unknown parameter 'nope'"):
        apply_overrides(layout, {"segmentation": {"nope": 1}})


def test_set_assignments():
    assert parse_assignment("segmentation.history=300") == ("segmentation", "history", 300)
    assert parse_assignment("seg.cameras=[cam0, cam1]") == ("seg", "cameras", ["cam0", "cam1"])
    with pytest.raises(LayoutError):
        parse_assignment("history=3")


def test_upstream_follows_stages_and_cameras():
    layout = parse_layout(yaml.safe_load("""
room: r
workers:
  - {name: grab0, kind: grabber, params: {cameras: [cam0]}}
  - {name: grab1, kind: grabber, params: {cameras: [cam1]}}
  - {name: seg0, kind: segmentation, params: {cameras: [cam0]}}
  - {name: seg_all, kind: segmentation}
  - {name: rec, kind: recorder}
"""))
    assert upstream_of(layout, layout.worker("seg0")) == ["grab0"]
    assert upstream_of(layout, layout.worker("seg_all")) == ["grab0", "grab1"]
    assert sorted(upstream_of(layout, layout.worker("rec"))) == ["grab0", "grab1", "seg0", "seg_all"]
    assert upstream_of(layout, layout.worker("grab0")) == []


def test_every_shipped_layout_is_valid():
    from pathlib import Path

    layouts = sorted(Path("deploy/layouts").glob("*.yaml"))
    assert len(layouts) >= 3
    for path in layouts:
        layout = load_layout(path)
        assert layout.workers and any(w.kind == "grabber" for w in layout.workers), path
