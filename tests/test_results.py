"""voxels.bin across a crash of its writer and frames that come out of order."""
import numpy as np

from app.files import partial_path
from app.messages import Voxels
from app.results import VoxelWriter, iter_voxels


def _voxels(frame: int) -> Voxels:
    idx = np.arange(frame + 1, dtype=np.int32)
    return Voxels(frame=frame, stamp=0.0, t=frame / 25, voxel_size=0.04, origin=[0.0, 0.0, 0.0], dims=[10, 10, 10],
                  indices=idx, colours=np.full((len(idx), 3), frame, np.uint8), surface=np.zeros(0, bool))


def test_a_resumed_writer_keeps_complete_records_and_sorts_frames_sent_again(tmp_path):
    path = tmp_path / "voxels.bin"
    w = VoxelWriter(path)
    for f in (0, 1, 2):
        w.write(_voxels(f))
    w.close(final=False)                                  # the recorder dies ...
    with open(partial_path(path), "ab") as fh:            # ... in the middle of a record
        fh.write(b"\x40\x00\x00\x00\x00\x00\x00\x00half")
    w = VoxelWriter(path)
    assert w.count == 3
    assert w.write(_voxels(5)) and w.write(_voxels(3)) and w.write(_voxels(4))   # resent frames after a newer one
    assert not w.write(_voxels(1))                        # already in the file
    w.close(final=True)
    got = list(iter_voxels(path))
    assert [m.frame for m in got] == [0, 1, 2, 3, 4, 5]
    assert all(len(m.indices) == m.frame + 1 and int(m.colours[0, 0]) == m.frame for m in got)
    assert not partial_path(path).exists()
