"""Which frame the live view shows (app/viewer/frames.py): a frame's parts together."""
from types import SimpleNamespace

from app.viewer.frames import FrameAssembly


def _msg(frame, epoch=0):
    return SimpleNamespace(frame=frame, epoch=epoch)


def test_the_newest_complete_frame_is_drawn_and_older_ones_dropped():
    a = FrameAssembly(wait_s=2.0)
    for f in range(3):
        a.add("voxels", _msg(f), 0.0)
    key, parts = a.take(0.0)                  # only voxels have ever come: nothing else to wait for
    assert key == (0, 2) and set(parts) == {"voxels"}
    a.add("tracks", _msg(2), 0.1)             # late part of the frame on show: drawn with it
    key, parts = a.take(0.1)
    assert key == (0, 2) and set(parts) == {"voxels", "tracks"}
    assert a.take(0.1) is None                # nothing new
    for f in (3, 4, 5):
        a.add("voxels", _msg(f), 0.2)
    a.add("tracks", _msg(3), 0.2)
    a.add("tracks", _msg(4), 0.3)
    assert a.take(0.3)[0] == (0, 4)           # 5 waits for its tracks; 3 is older than 4
    assert sorted(a.frames) == [(0, 4), (0, 5)]
    a.add("tracks", _msg(3), 0.4)             # older than the frame on show: never drawn
    assert (0, 3) not in a.frames


def test_a_silent_stage_is_not_waited_for_and_is_again_when_back():
    a = FrameAssembly(wait_s=1.0)
    for f in range(2):
        for kind in ("voxels", "tracks", "poses"):
            a.add(kind, _msg(f), 0.0)
    assert a.take(0.0)[0] == (0, 1)
    for f in range(2, 6):                     # the pose stage crashed: its poses stop
        a.add("voxels", _msg(f), 0.2 * f)
        a.add("tracks", _msg(f), 0.2 * f)
    assert a.take(1.0) is None                # 1 s: still waited for
    key, parts = a.take(1.2)                  # silent for longer than wait_s: drawn without skeletons
    assert key == (0, 5) and set(parts) == {"voxels", "tracks"}
    a.add("voxels", _msg(6), 1.3)
    a.add("tracks", _msg(6), 1.3)
    a.add("poses", _msg(6), 1.4)              # back
    a.add("voxels", _msg(7), 1.4)
    a.add("tracks", _msg(7), 1.4)
    key, parts = a.take(1.4)
    assert key == (0, 6) and set(parts) == {"voxels", "tracks", "poses"}


def test_epochs_order_frames_and_waiting_frames_are_bounded():
    a = FrameAssembly(keep=4)
    a.add("voxels", _msg(900, epoch=1), 0.0)
    assert a.take(0.0)[0] == (1, 900)
    a.add("voxels", _msg(0, epoch=2), 0.1)    # the source restarted: its frame numbers start again
    assert a.take(0.1)[0] == (2, 0)
    for f in range(1, 20):
        a.add("voxels", _msg(f, epoch=2), 0.2)
        a.add("tracks", _msg(f - 1, epoch=2), 0.2)
    assert len(a.frames) <= 4


def test_at_the_start_a_frame_waits_for_the_kinds_of_the_layout_not_heard_of_yet():
    """The first voxels arrive before any tracks ever came: the frame waits for the
    layout's tracks and poses (a first frame drawn with voxels only was seen), but not
    for ever: a kind still missing ``first_wait_s`` after the stream began is not waited for."""
    from types import SimpleNamespace

    from app.viewer.frames import FrameAssembly

    a = FrameAssembly(wait_s=2.0, layout_kinds=("voxels", "tracks", "poses"), first_wait_s=10.0)
    part = lambda f: SimpleNamespace(frame=f, epoch=1)   # noqa: E731
    a.add("voxels", part(0), 0.0)
    assert a.take(0.5) is None and a.take(2.5) is None          # tracks and poses never came yet: it waits
    a.add("tracks", part(0), 3.0)
    a.add("poses", part(0), 3.1)
    key, parts = a.take(3.2)
    assert key == (1, 0) and sorted(parts) == ["poses", "tracks", "voxels"]
    b = FrameAssembly(wait_s=2.0, layout_kinds=("voxels", "tracks", "poses"), first_wait_s=10.0)
    b.add("voxels", part(0), 0.0)
    b.add("voxels", part(1), 10.5)
    assert b.take(10.6)[0] == (1, 1)                              # a stage that never came: drawn without it
