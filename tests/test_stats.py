"""Stage accounting and the pipeline summary (RTF, Eq. 4.27)."""
import json

from app.stats import KEPT_MS, FrameSet, StageLedger, summarise
from workers.base import Inbox


class Clock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self):
        return self.now


def test_ledger_counts_drops_and_missing_frames():
    clock = Clock()
    led = StageLedger(clock)
    for f in range(10):
        if f == 3:
            continue  # never arrives
        led.received(f, stamp=clock.now)
        clock.now += 0.01
        if f != 6:  # received but skipped
            led.emitted(f, stamp=clock.now - 0.01)
        clock.now += 0.03
    fig = led.figures(final=True, expected=10)
    assert (fig["frames_in"], fig["frames_out"], fig["frames_dropped"], fig["frames_missing"]) == (9, 8, 1, 1)
    assert fig["missing_frames"] == [3] and fig["dropped_frames"] == [6]
    assert abs(fig["latency_ms"]["p50"] - 10.0) < 1e-6
    assert fig["frames_in"] + fig["frames_missing"] == 10


def _live_ledger(frames: int) -> StageLedger:
    """A live stage's ledger after ``frames`` frames: every 7th never arrives, every 3rd
    arriving one is dropped (fragmented frame sets, the worst case for their runs)."""
    clock = Clock()
    led = StageLedger(clock)
    for f in range(frames):
        clock.now += 0.04
        if f % 7 == 3:
            continue
        led.received(f, stamp=clock.now)
        led.processed(0.001, f)
        if f % 3:
            led.emitted(f, stamp=clock.now)
    return led


def test_a_ledger_state_costs_the_same_after_a_million_frames():
    """Saving a worker's state twice a second must not grow with uptime (a day at 25 fps
    is 2.2 million frames): what is saved after 10^6 frames is within 2x of what is saved
    after 10^3, its memory too, and the counts stay exact."""
    small, large = _live_ledger(1000), _live_ledger(1_000_000)
    size = {n: len(json.dumps(led.state())) for n, led in (("small", small), ("large", large))}
    assert size["large"] <= 2 * size["small"], size
    assert len(large.seen.bits) + len(large.done.bits) <= 2 * 1536 + 2048
    # the latencies and processing times behind the final percentiles are bounded too
    assert len(large.latency_ms) <= 2 * KEPT_MS and len(large.process_ms) <= 2 * KEPT_MS
    assert min(len(large.latency_ms), len(large.process_ms)) >= KEPT_MS   # (at least the run's last KEPT_MS)
    fig = large.figures(final=True, expected=1_000_000)
    arrived = 1_000_000 - sum(1 for f in range(1_000_000) if f % 7 == 3)
    kept = sum(1 for f in range(1_000_000) if f % 7 != 3 and f % 3)
    assert (fig["frames_in"], fig["frames_out"], fig["frames_missing"]) == (arrived, kept, 1_000_000 - arrived)
    assert fig["frames_dropped"] == arrived - kept
    assert fig["missing_frames"][:3] == [3, 10, 17]
    # a restarted incarnation carries on from the saved state with the same counts
    again = StageLedger(Clock())
    again.restore(json.loads(json.dumps(large.state())))
    assert (again.seen.count, again.done.count) == (large.seen.count, large.done.count)
    assert again.figures(final=True, expected=1_000_000)["frames_dropped"] == arrived - kept
    assert 999_999 in again.seen and 999_995 not in again.seen and 3 not in again.seen and 4 in again.seen


def test_a_frame_set_saved_before_frames_were_folded_still_loads():
    s = FrameSet.from_state([[0, 5], [7, 9]], horizon=1024)
    assert (s.count, 6 in s, 8 in s) == (7, False, True)


def test_busy_counts_from_the_first_frame():
    """A stage that waited for its first frame (start-up) and works flat out since is busy 1.0,
    so the monitor does not name a faster stage ahead of it the bottleneck."""
    clock = Clock()
    led = StageLedger(clock)
    clock.now += 1.8            # waiting for frames
    for f in range(2):
        led.received(f, stamp=clock.now)
        clock.now += 0.1
        led.processed(0.1, f)
        led.emitted(f, stamp=clock.now - 0.1)
    assert led.figures()["busy"] == 1.0
    idle = StageLedger(clock)
    assert idle.figures()["busy"] == 0.0


def test_summary_rtf_is_fps_over_recording_fps():
    stages = {
        "grabber": {"stage": "grabber", "order": 0, "figures": {"frames_out": 100, "fps": 25.0}},
        "segmentation": {"stage": "segmentation", "order": 1,
                         "figures": {"frames_in": 100, "frames_out": 90, "frames_dropped": 10, "fps": 12.5,
                                     "latency_ms": {"mean": 30.0, "p50": 25.0, "p95": 60.0}}},
        "recorder": {"stage": "recorder", "order": None, "figures": {}},
    }
    s = summarise(stages, 25.0, 100)
    assert s["final_stage"] == "segmentation" and s["rtf"] == 0.5
    assert s["stages"]["segmentation"]["latency_p95_ms"] == 60.0


def test_inbox_keeps_the_newest_per_key_in_arrival_order():
    drops = []
    box = Inbox(depth=1, on_drop=lambda: drops.append(1))
    box.put("cam0", 1)
    box.put("cam1", 2)
    box.put("cam0", 3)  # pushes out 1
    assert box.get(0) == ("cam1", 2)
    assert box.get(0) == ("cam0", 3)
    assert box.get(0.01) is None and len(drops) == 1
    deep = Inbox(depth=3)
    for i in range(5):
        deep.put("k", i)
    assert [deep.get(0)[1] for _ in range(3)] == [2, 3, 4]


def test_the_end_of_run_table_writes_milliseconds_as_ms():
    from app.report import summary_table
    stages = {"grabber": {"stage": "grabber", "order": 0,
                          "figures": {"frames_in": 100, "frames_out": 100, "fps": 25.0,
                                      "latency_ms": {"p50": 0.5, "p95": 0.7}, "process_ms": {"mean": 3.3}}}}
    lines = summary_table(summarise(stages, 25.0, 100)).splitlines()
    head, row = lines[0], lines[2]
    assert row.split()[-4:] == ["0.5ms", "0.7ms", "3.3ms", "0"]          # as the live table writes them
    assert head.index("lat p50") + len("lat p50") == row.index("0.5ms") + len("0.5ms")   # under its column
