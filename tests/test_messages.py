"""The message codec: round trips without copies, and clear rejection of bad payloads."""
import json
import struct

import numpy as np
import pytest

from app.messages import (JOINTS, EndOfStream, Frame, Heartbeat, Mask, MessageError, Poses, Stats, Tracks,
                          Voxels, decode, encode)


def _samples():
    rng = np.random.default_rng(3)
    mask = rng.random((48, 61)) > 0.5
    return [
        Frame(frame=7, stamp=123.5, t=0.28, camera="cam0", image=rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)),
        Mask.pack(mask, frame=8, stamp=1.0, t=0.32, camera="cam1", colour=rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)),
        Mask.pack(mask, frame=9, camera="cam1", colour=None),
        Voxels(frame=9, voxel_size=0.02, origin=[0, 0, 0], dims=[250, 200, 125], cameras=["cam0"],
               indices=rng.integers(0, 200, (1000, 3)).astype(np.uint16),
               colours=rng.integers(0, 255, (1000, 3), dtype=np.uint8), surface=rng.random(1000) > 0.5),
        Tracks(frame=10, ids=np.array([1, 4], np.int32), positions=rng.random((2, 3)).astype(np.float32)),
        Poses(frame=11, tracks=np.array([1], np.int32), joints=rng.random((1, len(JOINTS), 3)).astype(np.float32),
              active=np.ones((1, len(JOINTS)), bool)),
        Stats(frame=12, worker="seg", stage="segmentation", figures={"frames_in": 3, "latency_ms": {"p50": 1.0}}),
        EndOfStream(frame=13, worker="grabber", stage="grabber", frames=50, fps=25.0, figures={"frames_out": 50}),
        Heartbeat(stamp=2.0, worker="pose", pid=4321, loop_age=0.25, pending=3, busy="compiling"),
    ]


@pytest.mark.parametrize("msg", _samples(), ids=lambda m: type(m).__name__)
def test_round_trip(msg):
    payload = encode(msg)
    back = decode(payload)
    assert type(back) is type(msg)
    for name in ("frame", "stamp", "t"):
        assert getattr(back, name) == getattr(msg, name)
    for name in msg.ARRAYS:
        a, b = getattr(msg, name), getattr(back, name)
        if a is None:
            assert b.size == 0
        else:
            np.testing.assert_array_equal(a, b)
            assert b.dtype == np.asarray(a).dtype
            assert not b.flags.owndata and not b.flags.writeable  # a view of the payload, no copy


@pytest.mark.parametrize("change", [{"worker": "a/b"}, {"pid": -1}, {"pending": -2}, {"loop_age": float("nan")},
                                    {"loop_age": -1.0}, {"busy": "asleep"}])
def test_bad_heartbeats_are_refused(change):
    hb = Heartbeat(stamp=2.0, worker="pose", pid=4321, loop_age=0.25, pending=3)
    hb.validate()
    for k, v in change.items():
        setattr(hb, k, v)
    with pytest.raises(MessageError):
        decode(encode(hb)).validate()


def test_mask_unpacks_to_the_same_mask():
    mask = np.random.default_rng(0).random((37, 53)) > 0.3
    back = decode(encode(Mask.pack(mask, camera="c")))
    np.testing.assert_array_equal(back.unpack(), mask)


def test_arrays_are_aligned():
    back = decode(encode(_samples()[3]))
    for name in back.ARRAYS:
        assert getattr(back, name).ctypes.data % 8 == 0 or getattr(back, name).size == 0


def test_every_truncation_is_rejected():
    payload = encode(_samples()[1])
    for n in range(len(payload)):
        with pytest.raises(MessageError):
            decode(payload[:n])


def test_corruptions_raise_message_error_only():
    payload = bytearray(encode(_samples()[3]))
    rng = np.random.default_rng(5)
    for _ in range(2000):
        bad = bytearray(payload)
        for i in rng.integers(0, 120, rng.integers(1, 4)):
            bad[i] = rng.integers(0, 256)
        try:
            decode(bytes(bad))
        except MessageError:
            pass


def _rebuild(msg, meta_fn=None, header_fn=None):
    payload = encode(msg)
    head = list(struct.unpack_from("<3sBBBHqddI", payload, 0))
    size = struct.calcsize("<3sBBBHqddI")
    meta = json.loads(payload[size:size + head[-1]])
    rest = payload[size + head[-1]:]
    if meta_fn:
        meta = meta_fn(meta)
    mb = json.dumps(meta).encode()
    head[-1] = len(mb)
    if header_fn:
        head = header_fn(head)
    return struct.pack("<3sBBBHqddI", *head) + mb + rest


@pytest.mark.parametrize("payload, message", [
    (b"XYZ" + bytes(60), "magic"),
    (_rebuild(_samples()[0], header_fn=lambda h: h[:1] + [9] + h[2:]), "version 9"),
    (_rebuild(_samples()[0], header_fn=lambda h: h[:2] + [200] + h[3:]), "unknown message type 200"),
    (_rebuild(_samples()[0], meta_fn=lambda m: {**m, "a": [["|O", [2]]]}), "bad array descriptor"),
    (_rebuild(_samples()[6], meta_fn=lambda m: {**m, "m": {"nonsense": 1}}), "unknown fields"),
    (encode(_samples()[0]) + b"\0" * 8, "trailing bytes"),
])
def test_specific_rejections(payload, message):
    with pytest.raises(MessageError, match=message):
        decode(payload)
