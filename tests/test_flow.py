"""Offline flow control (workers/flow.py): the rules by which a source holds a frame, over
plain sets and a clock; no bus."""
import logging

import pytest

from app.errors import Stalled
from workers.flow import MISSING_WAIT_S, RESUME_HOLD_S, SENDING_AGAIN, FlowControl


class Clock:
    def __init__(self, step=0.0):
        self.now, self.step = 100.0, step

    def __call__(self):
        self.now += self.step
        return self.now


def control(window=2, stall=120.0, clock=None, **kw):
    kw.setdefault("stages", ["segmentation", "reconstruction", "tracking"])
    kw.setdefault("upstream", {"reconstruction": ["segmentation"], "tracking": ["reconstruction"]})
    kw.setdefault("keepers", ["recorder"])
    return FlowControl(window=window, stall_timeout_s=stall, clock=clock or Clock(), log=logging.getLogger("t"), **kw)


EVERYONE = {"segmentation", "reconstruction", "tracking", "recorder"}


def test_a_source_waits_for_the_slowest_acknowledging_stage():
    fc = control()
    fc.start(0, EVERYONE)
    assert fc.blockers(1, EVERYONE, 100.0) == []                 # frames 0 and 1 in flight: the window
    # frame 2 waits for frame 0: from the first stage (the later ones have nothing of it yet)
    assert fc.blockers(2, EVERYONE, 100.0) == ["segmentation"]
    fc.acknowledge("segmentation", 0, 0)
    assert fc.blockers(2, EVERYONE, 100.0) == ["reconstruction"]
    for name in ("segmentation", "reconstruction"):
        fc.acknowledge(name, 3, 3)
    fc.acknowledge("tracking", 1, 1)
    assert fc.blockers(5, EVERYONE, 100.0) == ["tracking"]       # the slowest one holds frame 5
    fc.acknowledge("tracking", 3, 3)
    assert fc.blockers(5, EVERYONE, 100.0) == []
    assert fc.blockers(6, EVERYONE, 100.0) != []


def test_a_waiting_source_goes_on_when_the_slowest_stage_acknowledges():
    import threading
    import time

    fc = control(clock=time.monotonic)
    fc.start(0, EVERYONE)
    for name in ("segmentation", "reconstruction"):
        fc.acknowledge(name, 1, 1)
    went = threading.Event()
    source = threading.Thread(target=lambda: (fc.wait(3, lambda: EVERYONE, lambda: False), went.set()))
    source.start()
    assert not went.wait(0.3)                   # tracking has not finished frame 1
    fc.acknowledge("tracking", 1, 1)            # from the bus's thread: wakes the source
    assert went.wait(2.0)
    source.join()


def test_a_stage_that_is_away_pauses_the_source_and_is_waited_for_after_it_is_back():
    fc = control()
    fc.start(0, EVERYONE)
    for name in fc.stages:
        fc.acknowledge(name, 9, 9)
    away = EVERYONE - {"reconstruction"}
    assert fc.blockers(11, away, 100.0) == ["reconstruction"]    # crashed: the launcher restarts it
    assert fc.blockers(11, away, 100.0 + MISSING_WAIT_S - 1) == ["reconstruction"]
    # back: new frames are held while the workers before it send it again what it lost ...
    assert fc.blockers(11, EVERYONE, 110.0) == [SENDING_AGAIN]
    # ... and until it has caught up on them
    fc.acknowledge("segmentation", 10, 10)
    fc.acknowledge("tracking", 10, 10)
    fc.acknowledge("reconstruction", 7, 7)
    assert fc.blockers(12, EVERYONE, 110.0 + RESUME_HOLD_S + 0.01) == ["reconstruction"]
    fc.acknowledge("reconstruction", 10, 10)
    assert fc.blockers(12, EVERYONE, 110.0 + RESUME_HOLD_S + 0.01) == []


def test_a_sink_that_keeps_results_pauses_the_source_while_it_is_away():
    fc = control()
    fc.start(0, EVERYONE)
    assert fc.blockers(1, EVERYONE - {"recorder"}, 100.0) == ["recorder"]
    # gone for longer than a restart takes: frames go on without it (counted missing there)
    assert fc.blockers(1, EVERYONE - {"recorder"}, 100.0 + MISSING_WAIT_S + 1) == []


def test_a_stage_whose_upstream_gave_a_frame_up_does_not_block_it():
    fc = control()
    fc.start(0, EVERYONE)
    fc.acknowledge("segmentation", 5, 5)
    fc.acknowledge("reconstruction", 5, 2)      # frames 3-5 given up (too few cameras): nothing put out
    fc.acknowledge("tracking", 2, 2)            # ... so tracking has all there is up to frame 5
    assert fc.required("tracking", 5) == 2
    assert fc.blockers(7, EVERYONE, 100.0) == []


def test_a_stage_on_the_bus_that_finishes_nothing_is_a_stall_naming_it_and_the_frame():
    clock = Clock(step=1.0)
    fc = control(stall=5.0, clock=clock)
    fc.start(0, EVERYONE)
    fc.acknowledge("segmentation", 0, 0)
    fc.acknowledge("tracking", 0, 0)
    with pytest.raises(Stalled) as info:
        fc.wait(2, lambda: EVERYONE, lambda: False)
    msg = str(info.value)
    assert "\n" not in msg and "frame 2" in msg and "reconstruction" in msg and "finished frame -1" in msg
    assert "segmentation" not in msg.split(" for ", 1)[1].split(";")[0]
    assert 5.0 <= clock.now - 100.0 <= 8.0


def test_a_worker_that_never_comes_back_is_a_stall_only_while_it_is_waited_for():
    fc = control(stall=30.0, clock=Clock(step=1.0))
    fc.start(0, EVERYONE)
    with pytest.raises(Stalled, match=r"recorder \(not on the bus"):
        fc.wait(0, lambda: EVERYONE - {"recorder"}, lambda: False)
    # with a stall timeout longer than a restart's wait, the frames go on without it instead
    fc = control(stall=MISSING_WAIT_S + 30, clock=Clock(step=5.0))
    fc.start(0, EVERYONE)
    assert fc.wait(0, lambda: EVERYONE - {"recorder"}, lambda: False) >= MISSING_WAIT_S


def test_a_stop_request_ends_the_wait_at_once():
    fc = control(stall=5.0, clock=Clock(step=1.0))
    fc.start(0, EVERYONE)
    assert fc.wait(5, lambda: EVERYONE, lambda: True) < 5.0


def test_frames_that_go_on_without_a_stage_are_counted():
    """A stage away longer than MISSING_WAIT_S: the frames sent past it are counted per
    worker (the launcher reports such an offline run incomplete)."""
    clock = Clock(step=5.0)
    fc = control(window=100, stall=MISSING_WAIT_S + 60, clock=clock)
    fc.start(0, EVERYONE)
    fc.wait(0, lambda: EVERYONE, lambda: False)
    assert fc.went_without == {}
    away = EVERYONE - {"recorder"}
    assert fc.wait(1, lambda: away, lambda: False) >= MISSING_WAIT_S   # waited for, then on without it
    fc.wait(2, lambda: away, lambda: False)
    assert fc.went_without == {"recorder": 2}
