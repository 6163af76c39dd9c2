"""The restart bookkeeping's repeats (workers/restarts.py): an input (key, sender, epoch,
frame) is skipped when it was handled already or when an earlier incarnation of the
worker put its frame out, never because this incarnation put the frame out."""
import time

import numpy as np

from app.config import parse_layout
from app.messages import Tracks, Voxels, decode
from workers.base import Worker


class FirstPartOut(Worker):
    """A worker that puts a frame out on its first input of the frame (as a display does),
    before the frame's other input has come."""

    KIND = "first_part_out"
    CONSUMES = ("voxels", "tracks")
    ACCEPTS = (Voxels, Tracks)

    def setup(self) -> None:
        self.handled = []

    def handle(self, key, msg) -> None:
        self.handled.append((type(msg).__name__, msg.frame))
        self.ledger.emitted(msg.frame, msg.stamp)


def _parts(frame):
    now = time.time()
    return [("smartroom/voxels/reconstruction",
             Voxels(frame=frame, stamp=now, voxel_size=0.1, origin=[0, 0, 0], dims=[10, 10, 10],
                    indices=np.zeros((1, 3), np.int32), colours=np.zeros((0, 3), np.uint8), surface=np.zeros(0, bool))),
            ("smartroom/tracks/tracking", Tracks(frame=frame, stamp=now, ids=np.array([1]),
                                                 positions=np.array([[1.0, 1.0, 0.9]])))]


def _feed(w, key, msg) -> bool:
    """``msg`` off the bus as the worker loop hands it over; whether it was handled."""
    msg = decode(msg.to_bytes())
    if w._repeated(key, msg):
        return False
    w._follow_epoch(msg)
    w.ledger.received(msg.frame, msg.stamp)
    w.handle(key, msg)
    return True


def test_a_frame_this_incarnation_put_out_is_not_a_repeat(tmp_path):
    layout = parse_layout({"workers": [{"name": "grabber", "kind": "grabber"},
                                       {"name": "w", "kind": "tests.test_repeats:FirstPartOut"}]})
    layout.run.out = str(tmp_path)

    def incarnation(frames):
        w = FirstPartOut(layout.worker("w"), layout)
        w._restore_state()
        w.setup()
        got = [_feed(w, key, msg) for f in frames for key, msg in _parts(f)]
        w._save_state()
        return w, got

    first, got = incarnation(range(0, 5))
    assert first.incarnation == 0 and all(got)
    w, got = incarnation(range(5, 10))      # restarted: its own frames' second inputs are handled
    assert w.incarnation == 1 and all(got), w.handled
    assert w.handled == [(kind, f) for f in range(5, 10) for kind in ("Voxels", "Tracks")]
    assert w.repeats_skipped == 0
    for key, msg in _parts(3):              # the earlier incarnation's frames are repeats (sent again)
        assert not _feed(w, key, msg)
    assert w.repeats_skipped == 2
