"""Stages that scale out by frame (app/frame_shares.py, issue 26): which frames a share
takes, the layout's shares checked, and the shards' outputs handed on in frame order."""
import random
from types import SimpleNamespace

import pytest

from app.config import parse_layout
from app.frame_shares import FrameOrder, count_own, last_own, owns, stage_shares
from app.layout import LayoutError, WorkerSpec
from workers.flow import FlowControl


def test_a_share_takes_every_n_th_frame():
    assert [f for f in range(10) if owns((1, 3), f)] == [1, 4, 7]
    assert owns(None, 7)
    for share in [(0, 1), (0, 2), (1, 2), (2, 3), (1, 4)]:
        for first in range(0, 7):
            for count in range(0, 13):
                want = sum(owns(share, f) for f in range(first, first + count))
                assert count_own(share, first, count) == want, (share, first, count)
    assert count_own(None, 5, 10) == 10
    assert [last_own((1, 3), f) for f in range(1, 9)] == [1, 1, 1, 4, 4, 4, 7, 7]
    assert last_own(None, 9) == 9


def _spec(name, share):
    return WorkerSpec(name=name, kind="reconstruction", params={} if share is None else {"share": share})


def test_the_shares_of_a_stage_must_cover_every_frame_once():
    assert stage_shares([_spec("a", None)]) == {}
    assert stage_shares([_spec("a", [0, 2]), _spec("b", [1, 2])]) == {"a": (0, 2), "b": (1, 2)}
    for bad, says in [([[0, 2], [0, 2]], "each once"), ([[0, 2], [1, 3]], "one n"), ([[0, 2], None], "share must be"),
                      ([[0, 3], [1, 3]], "each once"), ([[2, 2]], "share must be")]:
        with pytest.raises(ValueError, match=says):
            stage_shares([_spec(f"w{i}", s) for i, s in enumerate(bad)])


def test_a_layout_whose_shares_leave_frames_to_nobody_is_a_one_line_error():
    data = {"room": "r", "bus": {}, "workers": [
        {"name": "grabber", "kind": "grabber"},
        {"name": "rec_a", "kind": "reconstruction", "params": {"share": [0, 3]}},
        {"name": "rec_b", "kind": "reconstruction", "params": {"share": [1, 3]}}]}
    with pytest.raises(LayoutError, match=r"k = 0 \.\. 2 each once, got k = \[0, 1\]"):
        parse_layout(data, "x.yaml")
    data["workers"][2]["params"]["share"] = [1, 2]
    data["workers"][1]["params"]["share"] = [0, 2]
    assert [w.params["share"] for w in parse_layout(data, "x.yaml").workers[1:]] == [[0, 2], [1, 2]]


def _msg(frame, epoch=1):
    return SimpleNamespace(frame=frame, epoch=epoch)


def test_the_shards_outputs_are_handed_on_in_frame_order():
    """Three shards finish their frames in their own order but out of step with each
    other (each at most two frames ahead, as the flow control allows); frame 13 is given
    up by its shard (never sent). Every frame sent comes out once, in order."""
    rng = random.Random(5)
    n, frames = 3, [f for f in range(60) if f != 13]
    streams = {r: [f for f in frames if f % n == r] for r in range(n)}
    order, out, sent = FrameOrder(n), [], []
    while any(streams.values()):
        lead = min(s[0] for s in streams.values() if s)
        r = rng.choice([r for r, s in streams.items() if s and s[0] <= lead + 2 * n])
        f = streams[r].pop(0)
        sent.append(f)
        out += [m.frame for _, m in order.add("voxels", _msg(f))]
    out += [m.frame for _, m in order.flush()]
    assert sent != sorted(sent)          # they did arrive out of order
    assert out == frames and order.forced == 0


def test_a_frame_waits_for_the_frames_before_it_and_the_end_releases_the_rest():
    order = FrameOrder(2)
    assert [m.frame for _, m in order.add("k", _msg(1))] == []       # frame 0 may still come
    assert [m.frame for _, m in order.add("k", _msg(0))] == [0, 1]
    assert [m.frame for _, m in order.add("k", _msg(3))] == []
    assert [m.frame for _, m in order.flush()] == [3]                 # the end of the stream
    # a new epoch (a restarted live source numbering from 0): the old epoch's frames go first
    order = FrameOrder(2)
    order.add("k", _msg(9, epoch=1))
    assert [(m.epoch, m.frame) for _, m in order.add("k", _msg(0, epoch=2))] == [(1, 9), (2, 0)]
    # live, a shard that stays away holds nothing longer than max_pending frames
    order = FrameOrder(2, max_pending=4)
    got = [m.frame for f in (0, 2, 4, 6, 8, 10) for _, m in order.add("k", _msg(f))]
    assert got == [0, 2] and order.forced == 1


def test_the_flow_control_asks_of_a_shard_only_its_own_frames():
    flow = FlowControl(["rec_a", "rec_b", "cca"], {"cca": ["rec_a", "rec_b"]}, [], window=2, stall_timeout_s=60,
                       shares={"rec_a": (0, 2), "rec_b": (1, 2)})
    flow.start(0, {"rec_a", "rec_b", "cca"})
    for worker, frame in (("rec_a", 8), ("rec_b", 7), ("cca", 8)):
        flow.acknowledge(worker, frame, frame)
    assert flow.blockers(10, {"rec_a", "rec_b", "cca"}, 0.0) == []   # frame 8: rec_a's; rec_b's newest is 7
    assert flow.blockers(11, {"rec_a", "rec_b", "cca"}, 0.0) == ["rec_b"]   # 9 is rec_b's; cca waits for it


def test_stats_json_counts_a_shard_s_own_frames_and_its_stage_s_rate():
    """A worker with share [1, 2] of a 10-frame stream that got its 5 frames misses
    nothing; one that got 4 misses frame 7 only; summed, the two run at their stage's rate
    and are not the bottleneck."""
    from app.stats import StageLedger, summarise

    ledger = StageLedger()
    for f in (1, 3, 5, 9):
        ledger.received(f, 0.0)
        ledger.emitted(f, 0.0)
    fig = ledger.figures(final=True, expected=10, first=0, share=(1, 2))
    assert fig["frames_missing"] == 1 and fig["missing_frames"] == [7]
    ledger.received(7, 0.0)
    assert ledger.figures(final=True, expected=10, first=0, share=(1, 2))["frames_missing"] == 0

    def stage(order, fps, share=None):
        f = {"frames_in": 10, "frames_out": 10, "fps": fps}
        if share:
            f["frame_share"] = share
        return {"stage": "s", "order": order, "figures": f}

    out = summarise({"rec_a": stage(2, 12.0, [0, 2]), "rec_b": stage(2, 12.5, [1, 2]), "pose": stage(5, 20.0)}, 25.0)
    assert out["bottleneck"] == "pose" and out["stages"]["rec_a"]["frame_share"] == [0, 2]


def test_an_override_that_leaves_frames_to_nobody_is_refused_too():
    from app.config import apply_overrides, load_layout

    layout = load_layout("deploy/layouts/many_cores.yaml")
    with pytest.raises(LayoutError, match="one n"):
        apply_overrides(layout, {"reconstruction_0": {"share": [0, 3]}}, "--set")
