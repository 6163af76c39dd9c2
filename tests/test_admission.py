"""What a worker lets in from the bus: codec, validation, frame windows and epochs."""
import json
import struct

import numpy as np
import pytest

from app.admission import EPOCH_QUIET_S, EPOCH_SLACK_MS, FrameWindow, Rejections
from app.messages import (EndOfStream, Frame, Mask, MessageError, Poses, Stats, Tracks, Voxels, decode,
                          encode)


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_window_rejects_far_frames_and_follows_the_stream():
    w = FrameWindow(window=100, clock=Clock())
    assert w.admit(0, 5) is None
    assert w.admit(0, 6) is None
    assert w.admit(0, 10 ** 9) == "frame outside the window"
    assert w.admit(0, -1) == "negative frame"
    assert w.admit(0, 50) is None and w.newest == 50
    assert w.admit(0, 40) is None and w.newest == 50   # late but near: the stage decides


def test_live_a_stage_that_stood_still_jumps_to_the_newest_frames_and_counts_the_skipped():
    """Live (follow_ahead), after this worker stood still for longer than the window: the
    stream's frames come back far ahead; two nearby ones confirm the jump, the frames in
    between are counted as skipped. Offline, and beside a running stream, nothing jumps."""
    clock = Clock()
    w = FrameWindow(window=100, clock=clock, follow_ahead=True)
    assert w.admit(0, 10) is None
    clock.t += 0.04
    assert w.admit(0, 500) == "frame outside the window"    # a forger beside the running stream
    assert w.admit(0, 501) == "frame outside the window"
    assert w.admit(0, 11) is None
    clock.t += 100.0                                        # SIGSTOP, SIGCONT 100 s later
    assert w.admit(0, 2511) == "frame outside the window"
    assert w.admit(0, 2512) is None and w.newest == 2512
    assert w.skipped == 2500
    assert w.admit(0, 2513) is None
    offline = FrameWindow(window=100, clock=clock)
    assert offline.admit(0, 10) is None
    clock.t += 100.0
    assert offline.admit(0, 2511) == offline.admit(0, 2512) == "frame outside the window"


def test_new_epoch_is_followed_only_after_the_old_one_went_quiet():
    clock = Clock()
    w = FrameWindow(window=100, clock=clock)
    assert w.admit(1, 500) is None
    clock.t += 0.04
    assert w.admit(2, 501) == "new epoch while the current one is running"   # a forger beside the source
    assert w.admit(1, 501) is None
    clock.t += EPOCH_QUIET_S + 0.1                                            # the source restarted
    assert w.admit(2, 502) is None and w.epoch == 2                           # resumed numbering: at once
    assert w.admit(1, 503) == "old epoch"


def test_a_live_source_starting_again_at_zero_is_confirmed_by_two_frames():
    clock = Clock()
    w = FrameWindow(window=100, clock=clock)
    w.admit(1, 100000)
    clock.t += 2.0
    assert w.admit(2, 0) == "unconfirmed epoch"
    assert w.admit(2, 1) is None and w.epoch == 2 and w.newest == 1
    assert w.admit(2, 2) is None


def test_an_epoch_outside_the_run_never_sets_the_window():
    """Epochs are their sources' start times; with the run's start known, a forger's
    epoch from before the run (2^40 ms: 2004) or from the future is refused, so its
    message arriving first cannot hold the key against the real stream. Hosts' clocks
    may disagree by up to EPOCH_SLACK_MS."""
    start = 1_795_000_000_000                        # the launcher's start, ms since 1970
    now = [start + 5_000]
    w = FrameWindow(window=100, clock=Clock(), earliest_epoch=start, wall_ms=lambda: now[0])
    assert w.admit(2 ** 40, 10 ** 6) == "epoch before the run"
    assert w.admit(now[0] + EPOCH_SLACK_MS + 1, 3) == "epoch from the future"
    assert w.epoch is None
    assert w.admit(start + 800, 0) is None and w.epoch == start + 800   # the grabber's, started after the launcher
    assert w.admit(start + 800, 1) is None
    # a grabber on a host whose clock is 20 minutes behind is still this run's
    other = FrameWindow(window=100, clock=Clock(), earliest_epoch=start, wall_ms=lambda: now[0])
    assert other.admit(start - 20 * 60_000, 0) is None
    # without the run's start (a worker started by hand) the first epoch sets the window
    alone = FrameWindow(window=100, clock=Clock())
    assert alone.admit(2 ** 40, 10 ** 6) is None


def test_rejections_are_counted_per_key_and_reason_and_logged_sparingly(caplog):
    import logging
    clock = Clock()
    r = Rejections(logging.getLogger("t"), clock=clock)
    with caplog.at_level(logging.WARNING):
        for _ in range(1000):
            r.add("mask/cam0", "malformed")
        clock.t += 10
        r.add("mask/cam0", "malformed")
    assert r.total == 1001 and r.figures() == {"mask/cam0: malformed": 1001}
    assert len(caplog.records) == 2 and "1000 such messages" in caplog.records[1].getMessage()


def _payload_with(msg, **meta_patch):
    """Re-encode ``msg`` with its meta JSON patched (descriptors a valid encoder never writes)."""
    raw = encode(msg)
    head = struct.Struct("<3sBBBHqddI")
    fields = list(head.unpack_from(raw, 0))
    old_len = fields[-1]
    meta = json.loads(raw[head.size:head.size + old_len])
    meta.update(meta_patch)
    new_meta = json.dumps(meta).encode()
    fields[-1] = len(new_meta)
    return head.pack(*fields) + new_meta + raw[head.size + old_len:]


@pytest.mark.parametrize("shape", [[2 ** 62, 2 ** 62], [10 ** 30], [-1, 3], [1.5, 3], ["a"], [True]])
def test_overflowing_or_odd_shapes_are_malformed_messages(shape):
    msg = Tracks(frame=1, ids=np.zeros(0, np.int32), positions=np.zeros((0, 3)))
    raw = _payload_with(msg, a=[["<i4", shape], ["<f8", [0, 3]]])
    with pytest.raises(MessageError):
        decode(raw)


def _mask(**kw):
    m = np.zeros((8, 16), bool)
    m[2:5, 3:9] = True
    base = dict(frame=3, camera="cam0", cameras=["cam0", "cam1"], colour=np.zeros((8, 16, 3), np.uint8))
    base.update(kw)
    return Mask.pack(m, **base)


@pytest.mark.parametrize("make,problem", [
    (lambda: _mask(camera=7), "camera"),
    (lambda: _mask(camera="a/b"), "camera"),
    (lambda: _mask(cameras="cam0"), "cameras"),
    (lambda: _mask(colour=np.zeros((8, 16), np.uint8)), "colour"),
    (lambda: _mask(stamp=float("nan")), "stamp"),
    (lambda: Frame(frame=0, camera="cam0", image=np.zeros((4, 4), np.uint8)), "image"),
    (lambda: Voxels(frame=0, voxel_size=0.04, dims=[10, 10, 10], indices=np.array([[1, 2, 30]], np.int16),
                    colours=np.zeros(0, np.uint8), surface=np.zeros(0, bool)), "outside the grid"),
    (lambda: Voxels(frame=0, voxel_size=0.04, dims=[10 ** 6, 10 ** 6, 10], indices=np.zeros((0, 3), np.int16),
                    colours=np.zeros(0, np.uint8), surface=np.zeros(0, bool)), "dims"),
    (lambda: Poses(frame=0, tracks=np.array([1], np.int32), joints=np.zeros((1, 14, 3)),
                   active=np.ones((1, 15), bool)), "joints"),
    (lambda: Stats(frame=0, worker="", figures={}), "worker"),
    (lambda: EndOfStream(frame=0, worker="grabber", frames=-5), "frames"),
])
def test_messages_that_decode_but_are_wrong_fail_validation(make, problem):
    msg = decode(encode(make()))
    with pytest.raises(MessageError, match=problem):
        msg.validate()


def test_valid_messages_pass_validation_and_keep_their_epoch():
    for msg in (_mask(epoch=7), Frame(frame=1, camera="cam0", cameras=["cam0"], image=np.zeros((4, 4, 3), np.uint8)),
                Tracks(frame=1, ids=np.array([3], np.int32), positions=np.ones((1, 3))),
                EndOfStream(frame=9, worker="grabber", frames=10, fps=25.0)):
        back = decode(encode(msg))
        back.validate()
        assert back.epoch == msg.epoch


def test_frames_reduced_by_the_grabber_give_the_segmentation_the_same_pixels():
    """The grabber sends frames at 1/scale; the segmentation finishes the reduction, and the
    result is the image it would have reduced itself (powers of two by halving)."""
    from app.segmentation import shrink
    rng = np.random.default_rng(3)
    img = rng.integers(0, 255, (1088, 1920, 3), dtype=np.uint8)
    assert np.array_equal(shrink(shrink(img, 2), 2), shrink(img, 4))
    assert np.array_equal(shrink(shrink(img, 4), 1), shrink(img, 4))
