"""The reconstruction worker's assembly of masks into frames (app.reconstruction.assembly):
which frames are built when, over plain sets and a clock, no bus."""
from app.reconstruction.assembly import STALL_S, FrameAssembly

CAMS = ["cam0", "cam1"]
PRODUCERS = {"cam0": {"seg0"}, "cam1": {"seg1"}}
BOTH = {"seg0", "seg1"}


def _assembly(lossless=True):
    return FrameAssembly(CAMS, PRODUCERS, lossless, wait_s=0.08, camera_timeout_s=1.0)


def _built(ready):
    return [(r.frame, sorted(r.masks), sorted(r.partial), sorted(r.stalled)) for r in ready]


def test_a_frame_is_built_once_every_camera_of_its_set_has_delivered():
    a = _assembly()
    assert a.add("cam0", 0, CAMS, "m00", 0.0)
    assert a.ready(0.0, BOTH, set()) == []
    a.add("cam1", 0, CAMS, "m01", 0.1)
    assert _built(a.ready(0.1, BOTH, set())) == [(0, CAMS, [], [])]
    assert not a.add("cam1", 0, CAMS, "again", 0.2)    # already built: counted late
    assert a.late == {"cam0": 0, "cam1": 1}


def test_offline_a_link_cut_between_two_cameras_masks_of_a_frame_loses_nothing():
    """Issue 25: cam0's mask of frame 138 crossed before a 90-s link cut, cam1's did not.
    The frame used to be given up 30 s into the cut (and the run still said complete);
    it now waits while cam1's producer is away, and for its mask once it is back."""
    a = _assembly()
    a.add("cam0", 138, CAMS, "m0", 0.0)
    for t in range(0, 91, 5):                        # seg1 off the bus (the cut) for 90 s
        assert a.ready(float(t), {"seg0"}, set()) == []
    assert a.ready(91.0, BOTH, set()) == []           # back: it sends the frame again
    assert a.ready(90.0 + STALL_S - 1, BOTH, set()) == []   # the stall counts from when it was last away
    a.add("cam1", 138, CAMS, "m1", 95.0)
    assert _built(a.ready(95.0, BOTH, set())) == [(138, CAMS, [], [])]
    assert a.stalled == 0 and a.late == {"cam0": 0, "cam1": 0}


def test_offline_a_producer_on_the_bus_that_sends_nothing_is_given_up_and_counted():
    a = _assembly()
    a.add("cam0", 5, CAMS, "m0", 0.0)
    assert a.ready(STALL_S - 0.5, BOTH, set()) == []
    ready = a.ready(STALL_S, BOTH, set())
    assert _built(ready) == [(5, ["cam0"], ["cam1"], ["cam1"])] and ready[0].waited == STALL_S
    assert a.stalled == 1 and a.late["cam1"] == 1


def test_offline_a_producer_that_ended_its_stream_is_not_waited_for():
    a = _assembly()
    a.add("cam0", 7, CAMS, "m0", 0.0)
    assert _built(a.ready(0.0, {"seg0"}, {"seg1"})) == [(7, ["cam0"], ["cam1"], [])]
    assert a.stalled == 0


def test_a_camera_that_sent_a_later_frame_is_not_waited_for():
    a = _assembly()
    a.add("cam0", 3, CAMS, "m0", 0.0)
    a.add("cam1", 4, CAMS, "m1", 0.0)                 # cam1 skipped frame 3 (its frame set)
    assert [r.frame for r in a.ready(0.0, BOTH, set())] == [3]


def test_live_a_view_is_given_up_after_wait_and_a_silent_camera_is_not_waited_for():
    a = _assembly(lossless=False)
    a.add("cam0", 0, CAMS, "m0", 0.0)
    assert a.ready(0.05, BOTH, set()) == []
    assert _built(a.ready(0.09, BOTH, set())) == [(0, ["cam0"], ["cam1"], [])]
    assert a.stalled == 0                            # live: not a stall
    a.add("cam1", 1, CAMS, "m1", 0.1)
    a.add("cam0", 2, CAMS, "m0", 2.0)                # cam1 silent for 1.9 s: not waited for
    assert [r.frame for r in a.ready(2.0, BOTH, set())] == [1, 2]


def test_live_a_stage_behind_skips_to_the_newest_complete_frame():
    a = _assembly(lossless=False)
    for f in range(6):
        a.add("cam0", f, CAMS, "m0", 0.0)
    a.add("cam1", 5, CAMS, "m1", 0.0)
    assert [r.frame for r in a.ready(0.0, BOTH, set())] == [2, 3, 4, 5]


def test_a_new_stream_gives_up_the_frames_of_the_old_one():
    a = _assembly()
    a.add("cam0", 9, CAMS, "m0", 0.0)
    assert a.reset() == 1 and a.pending == {}
    a.add("cam0", 0, CAMS, "m0", 1.0)                 # frame numbers start again
    assert 0 in a.pending
