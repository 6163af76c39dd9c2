"""The Lab Streaming Layer stream of a room: one outlet, a fixed number of person slots
(:class:`app.streaming.slots.Slots`), per slot the track id and the 15 joints' x, y, z.

Channels (float32), slot ``s`` = 0 .. slots-1: ``p<s>_track`` (the track id; NaN while
the slot is empty), then ``p<s>_<joint>_x``, ``_y``, ``_z`` for the joints in the
contract's order (metres, the room's axes: right-handed, z up, the floor at z = 0; NaN
for a joint the pose stage marks inactive and for an empty slot). The stream
description says so (``<channels>`` with label, type, unit per channel; ``<setup>``
with the joints, slots and axes; ``<acquisition>``), as the XDF metadata conventions
for motion capture ask. Sample times are the frames' capture times on LSL's clock:
the capture wall-clock time minus the offset between the wall clock and
``pylsl.local_clock()``, measured when the outlet opens and again each minute.

``pylsl``'s wheels (PyPI, Linux x86_64 manylinux_2_35, macOS, Windows) bring liblsl;
elsewhere install liblsl (e.g. conda-forge ``liblsl``) and set ``PYLSL_LIB``.
"""
from __future__ import annotations

import time

import numpy as np

from app.errors import InputError
from app.messages import JOINTS

__all__ = ["channel_labels", "lsl_sample", "open_outlet", "LslClock", "pylsl_module", "CHANNELS_PER_SLOT"]

CHANNELS_PER_SLOT = 1 + 3 * len(JOINTS)
AXES_TEXT = "room: x, y horizontal, z up (right-handed), metres, floor at z = 0"


def pylsl_module():
    """``pylsl``, or an :class:`InputError` saying how to install it."""
    try:
        import pylsl
    except (ImportError, RuntimeError) as exc:   # RuntimeError: the wheel's liblsl does not load
        raise InputError(f"the LSL streamer needs pylsl with liblsl: pip install 'smartroom[stream]' ({exc})") from None
    return pylsl


def channel_labels(slots: int) -> list[str]:
    labels = []
    for s in range(slots):
        labels.append(f"p{s}_track")
        labels += [f"p{s}_{j}_{a}" for j in JOINTS for a in "xyz"]
    return labels


def lsl_sample(slots: int, assignment, joints: np.ndarray, active: np.ndarray, tracks) -> np.ndarray:
    """One sample (float32, ``slots * CHANNELS_PER_SLOT``) from a frame's poses and the
    slots of its people (``(slot, index)`` pairs)."""
    out = np.full((slots, CHANNELS_PER_SLOT), np.nan, np.float32)
    for slot, k in assignment:
        out[slot, 0] = float(tracks[k])
        pts = np.asarray(joints[k], np.float64).copy()
        pts[~np.asarray(active[k], bool)] = np.nan
        out[slot, 1:] = pts.reshape(-1)
    return out.reshape(-1)


def open_outlet(name: str, source_id: str, slots: int, fps: float, room: str):
    """An LSL outlet (type ``MoCap``) with the channel metadata of the module docstring."""
    pylsl = pylsl_module()
    info = pylsl.StreamInfo(name, "MoCap", slots * CHANNELS_PER_SLOT, float(fps or 0.0), "float32", source_id)
    desc = info.desc()
    desc.append_child_value("manufacturer", "smartroom")
    chans = desc.append_child("channels")
    for label in channel_labels(slots):
        ch = chans.append_child("channel")
        ch.append_child_value("label", label)
        if label.endswith("_track"):
            ch.append_child_value("type", "TrackID")
            ch.append_child_value("unit", "none")
        else:
            ch.append_child_value("type", "Position" + label[-1].upper())
            ch.append_child_value("unit", "meters")
    setup = desc.append_child("setup")
    setup.append_child_value("room", room)
    setup.append_child_value("slots", str(slots))
    setup.append_child_value("joints", " ".join(JOINTS))
    setup.append_child_value("axes", AXES_TEXT)
    acq = desc.append_child("acquisition")
    acq.append_child_value("manufacturer", "smartroom")
    acq.append_child_value("model", "markerless multi-camera")
    return pylsl.StreamOutlet(info, chunk_size=1, max_buffered=60)


class LslClock:
    """Wall-clock seconds to ``pylsl.local_clock()`` seconds (the offset re-measured each minute)."""

    PERIOD_S = 60.0

    def __init__(self, pylsl):
        self._local_clock = pylsl.local_clock
        self._measured = -1e9
        self.offset = 0.0

    def __call__(self, wall: float) -> float:
        now = time.monotonic()
        if now - self._measured > self.PERIOD_S:
            a = time.time()
            lsl = self._local_clock()
            b = time.time()
            self.offset = 0.5 * (a + b) - lsl
            self._measured = now
        return wall - self.offset
