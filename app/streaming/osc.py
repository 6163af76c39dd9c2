"""OSC packets of one frame's poses: the VMC protocol (one avatar per receiver) and a
plain OSC mode (every person's joint positions). Built with ``python-osc``; one OSC
bundle per frame and receiver, so a receiver applies a frame at once (one UDP datagram). python-osc builds each message's
address and type tags once (:func:`_head`); a frame only packs its float32 values after
them (a frame of 6 people took 1-3 ms with a builder per message, the frame's budget at
60 fps being 16 ms for every stage).

VMC (Virtual Motion Capture protocol, performer to marionette), per person:

- ``/VMC/Ext/Root/Pos`` ``"root"`` px py pz qx qy qz qw: the point of the floor under the
  pelvis, identity rotation;
- ``/VMC/Ext/Bone/Pos`` ``<HumanBodyBones name>`` px py pz qx qy qz qw per humanoid bone
  (:mod:`app.streaming.humanoid`: local positions and rotations of a normalised VRM
  avatar, Unity axes: y up, left-handed, metres);
- ``/VMC/Ext/T`` time (s, the recording time of the frame) and ``/VMC/Ext/OK 1``
  (loaded; calibration state and tracking are VMC 2.5's optional arguments, not sent).

Plain OSC (for TouchDesigner, Max/MSP, Pure Data, SuperCollider):

- ``/smartroom/frame`` frame (int), t (float, s), people (int);
- ``/smartroom/person/<track>/<joint>`` x y z (float, metres) per active joint, in the
  room's axes (z up) or y up (``up: y``: ``(x, y, z) -> (x, z, -y)``, as the exports).
"""
from __future__ import annotations

import struct
from functools import lru_cache

import numpy as np
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder

from app.export.axes import to_axes
from app.messages import JOINTS
from app.streaming.humanoid import BONES, HumanoidPose, quaternions

__all__ = ["vmc_packets", "joints_packet", "VMC_ROOT", "VMC_BONE", "FRAME_ADDRESS", "joint_address"]

VMC_ROOT = "/VMC/Ext/Root/Pos"
VMC_BONE = "/VMC/Ext/Bone/Pos"
VMC_TIME = "/VMC/Ext/T"
VMC_OK = "/VMC/Ext/OK"
FRAME_ADDRESS = "/smartroom/frame"


def joint_address(track: int, joint: str) -> str:
    return f"/smartroom/person/{int(track)}/{joint}"


def _message(address: str, *args) -> bytes:
    m = OscMessageBuilder(address)
    for a in args:
        m.add_arg(a, "s" if isinstance(a, str) else ("i" if isinstance(a, int) else "f"))
    return m.build().dgram


@lru_cache(maxsize=4096)
def _head(address: str, name: str | None, floats: int) -> bytes:
    """A message's bytes before its ``floats`` float32 arguments (address, type tags, the
    leading string): python-osc builds it once; each frame only packs the floats after it."""
    args = ((name,) if name is not None else ()) + (0.0,) * floats
    return _message(address, *args)[:-4 * floats]


_BUNDLE_HEAD = OscBundleBuilder(IMMEDIATELY).build().dgram   # "#bundle", the "immediately" time tag


def _bundle(messages: list[bytes]) -> bytes:
    return _BUNDLE_HEAD + b"".join(struct.pack(">i", len(m)) + m for m in messages)


def _with_floats(head: bytes, values: np.ndarray) -> bytes:
    return head + np.asarray(values, ">f4").tobytes()


def vmc_packets(avatar: HumanoidPose, t: float) -> list[bytes]:
    """Each person's VMC bundle (the people of ``avatar`` in order)."""
    values = np.concatenate([avatar.positions, quaternions(avatar.rotations)], axis=-1).astype(">f4")  # (N, B, 7)
    root = np.concatenate([avatar.root, np.tile([0.0, 0.0, 0.0, 1.0], (len(avatar.root), 1))], axis=1)
    tail = [_with_floats(_head(VMC_TIME, None, 1), [t]), _message(VMC_OK, 1)]
    packets = []
    for k in range(len(values)):
        msgs = [_with_floats(_head(VMC_ROOT, "root", 7), root[k])]
        msgs += [_head(VMC_BONE, bone, 7) + values[k, i].tobytes() for i, bone in enumerate(BONES)]
        packets.append(_bundle(msgs + tail))
    return packets


def joints_packet(frame: int, t: float, tracks, joints: np.ndarray, active: np.ndarray, up: str = "z") -> bytes:
    """Every person's active joints of one frame as one bundle (plain OSC)."""
    msgs = [_message(FRAME_ADDRESS, int(frame), float(t), len(tracks))]
    pts = to_axes(np.asarray(joints, float).reshape(-1, len(JOINTS), 3), up).astype(">f4")
    for k, track in enumerate(tracks):
        for n, joint in enumerate(JOINTS):
            if active[k, n]:
                msgs.append(_head(joint_address(track, joint), None, 3) + pts[k, n].tobytes())
    return _bundle(msgs)
