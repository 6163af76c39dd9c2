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
    # gone for longer than a restart takes (a host whose link is down): still waited for
    assert fc.blockers(1, EVERYONE - {"recorder"}, 100.0 + 10 * MISSING_WAIT_S) == ["recorder"]


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


def test_a_worker_that_never_comes_back_is_a_stall():
    """Waited for until the stall timeout, however long that is, never gone on without."""
    for stall in (30.0, MISSING_WAIT_S + 30):
        fc = control(stall=stall, clock=Clock(step=1.0))
        fc.start(0, EVERYONE)
        with pytest.raises(Stalled, match=r"recorder \(not on the bus"):
            fc.wait(0, lambda: EVERYONE - {"recorder"}, lambda: False)


def test_a_stop_request_ends_the_wait_at_once():
    fc = control(stall=5.0, clock=Clock(step=1.0))
    fc.start(0, EVERYONE)
    assert fc.wait(5, lambda: EVERYONE, lambda: True) < 5.0


def test_frames_that_go_on_without_a_stage_are_counted():
    """A stage back from a crash that never catches up (what it lacks never comes again):
    after MISSING_WAIT_S the frames go on, and what it lacks is counted per worker (the
    launcher reports such an offline run incomplete)."""
    fc = control()
    fc.start(0, EVERYONE)
    for name in fc.stages:
        fc.acknowledge(name, 9, 9)
    fc.blockers(11, EVERYONE - {"reconstruction"}, 100.0)
    fc.acknowledge("segmentation", 12, 12)
    fc.acknowledge("reconstruction", 7, 7)
    assert fc.blockers(14, EVERYONE, 110.0) != []
    assert fc.went_without == {}
    assert fc.blockers(14, EVERYONE, 110.0 + MISSING_WAIT_S + 1) == []
    assert fc.went_without == {"reconstruction": 3}


def test_an_outage_of_the_hub_link_is_waited_out_not_a_stall():
    """Nobody at all on the bus (this host's link to the hub is down): the stall clock
    stands still, so an outage longer than stall_timeout_s is waited out."""
    clock = Clock(step=1.0)
    fc = control(stall=5.0, clock=clock)
    fc.start(0, EVERYONE)
    for name in fc.stages:
        fc.acknowledge(name, 0, 0)
    seen = iter([set()] * 60 + [EVERYONE] * 1000)
    assert fc.wait(2, lambda: next(seen), lambda: False) >= 60   # 60 s with nobody there, then at once
