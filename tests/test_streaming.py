"""The streamer: VMC / OSC, Lab Streaming Layer and the JSON zenoh feed, received by real
receivers in the test (python-osc's packet parser on UDP sockets, a pylsl inlet, the
example zenoh client), against the run's poses.jsonl.

Unit tests check the humanoid bones (forward kinematics of what VMC carries gives back
the joints; a T-pose is the identity), the slots and the LSL sample layout.
"""
import json
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from app.bus import free_port
from app.messages import JOINTS
from app.streaming.humanoid import (B, BONES, HingeMemory, forward_kinematics, humanoid_poses, quaternions,
                                    rotation_matrices, to_unity)
from app.streaming.lsl import CHANNELS_PER_SLOT, channel_labels, lsl_sample
from app.streaming.receiver import UdpReceiver
from app.streaming.slots import Slots
from tests.conftest import ROOT, start_smartroom
from tests.test_export import groundtruth_records

FPS = 25.0
#: the humanoid bone sitting at each joint (forward kinematics gives the joint back)
AT = {"pelvis": "Hips", "neck": "Neck", "head": "Head", "l_shoulder": "LeftUpperArm", "l_elbow": "LeftLowerArm",
      "l_wrist": "LeftHand", "r_shoulder": "RightUpperArm", "r_elbow": "RightLowerArm", "r_wrist": "RightHand",
      "l_hip": "LeftUpperLeg", "l_knee": "LeftLowerLeg", "l_ankle": "LeftFoot", "r_hip": "RightUpperLeg",
      "r_knee": "RightLowerLeg", "r_ankle": "RightFoot"}


def _arrays(rec):
    tracks = np.array([p["track"] for p in rec["poses"]], np.int64)
    joints = np.array([[p["joints"][j] for j in JOINTS] for p in rec["poses"]], float).reshape(-1, 15, 3)
    active = np.array([[p["active"][j] for j in JOINTS] for p in rec["poses"]], bool).reshape(-1, 15)
    return tracks, joints, active


def _t_pose() -> np.ndarray:
    j = {"pelvis": (0, 0, 1.0), "neck": (0, 0, 1.5), "head": (0, 0, 1.7),
         "l_shoulder": (-0.2, 0, 1.45), "l_elbow": (-0.5, 0, 1.45), "l_wrist": (-0.75, 0, 1.45),
         "r_shoulder": (0.2, 0, 1.45), "r_elbow": (0.5, 0, 1.45), "r_wrist": (0.75, 0, 1.45),
         "l_hip": (-0.1, 0, 0.95), "l_knee": (-0.1, 0, 0.5), "l_ankle": (-0.1, 0, 0.08),
         "r_hip": (0.1, 0, 0.95), "r_knee": (0.1, 0, 0.5), "r_ankle": (0.1, 0, 0.08)}
    return np.array([[j[n] for n in JOINTS]], float)


def test_a_t_pose_facing_forward_is_every_bone_at_rest():
    """Room +y is the avatar's forward (Unity +z): a T-pose there is all identity rotations,
    and an elbow bent forward turns the forearm about Unity's +y by 90 degrees."""
    avatar = humanoid_poses(_t_pose())
    assert np.abs(avatar.rotations - np.eye(3)).max() < 1e-12
    P = _t_pose()
    P[0, JOINTS.index("l_wrist")] = (-0.5, 0.25, 1.45)
    q = quaternions(humanoid_poses(P).rotations[0, B["LeftLowerArm"]])
    assert np.allclose(q, [0.0, np.sqrt(0.5), 0.0, np.sqrt(0.5)])


def test_forward_kinematics_of_the_vmc_bones_gives_back_every_joint():
    """Simulated people walking, sitting and gesturing: root, local positions and
    quaternions (what a VMC receiver gets) rebuild all 15 joints; rotations are proper."""
    memory = HingeMemory()
    worst = 0.0
    for rec in groundtruth_records("gesture1", 3.0, FPS) + groundtruth_records("meeting3", 2.0, FPS):
        tracks, joints, _ = _arrays(rec)
        if not len(tracks):
            continue
        avatar = humanoid_poses(joints, tracks, memory)
        R = rotation_matrices(quaternions(avatar.rotations))
        assert np.allclose(np.linalg.det(avatar.rotations), 1.0)
        bones = forward_kinematics(avatar.root, avatar.positions, R)
        for j, bone in AT.items():
            worst = max(worst, np.abs(bones[:, B[bone]] - to_unity(joints[:, JOINTS.index(j)])).max())
        assert np.allclose(avatar.root[:, 1], 0.0)   # the root on the floor, the hips above it
    assert worst < 1e-9, worst


def test_a_straight_limb_keeps_the_persons_last_hinge():
    P = _t_pose()
    P[0, JOINTS.index("l_wrist")] = (-0.5, 0.25, 1.45)    # bent: the hinge is measured
    memory = HingeMemory()
    humanoid_poses(P, [7], memory)
    P[0, JOINTS.index("l_wrist")] = (-0.8, 0.0, 1.45)     # straight
    bent_before = humanoid_poses(P, [7], memory).rotations[0, B["LeftUpperArm"]]
    fresh = humanoid_poses(P, [8], memory).rotations[0, B["LeftUpperArm"]]
    assert np.allclose(bent_before, fresh)   # same hinge as the rest one here: no spurious roll
    memory.keep([8])
    assert all(k[0] == 8 for k in memory.axes)


def test_slots_keep_people_and_reuse_freed_slots():
    s = Slots(2)
    assert s.assign([5, 9]) == [(0, 0), (1, 1)]
    assert s.assign([9, 5, 11]) == [(0, 1), (1, 0)] and s.left_out == 1
    assert s.assign([11, 9]) == [(0, 0), (1, 1)]       # 5 left: 11 takes its slot, 9 keeps its own


def test_an_lsl_sample_has_each_slot_track_and_joints_nan_when_inactive():
    tracks = np.array([4, 2])
    joints = np.arange(2 * 45, dtype=float).reshape(2, 15, 3)
    active = np.ones((2, 15), bool)
    active[1, 5] = False
    sample = lsl_sample(3, [(0, 1), (2, 0)], joints, active, tracks).reshape(3, CHANNELS_PER_SLOT)
    assert sample[0, 0] == 2 and np.isnan(sample[0, 1 + 15]) and sample[0, 1] == 45
    assert np.isnan(sample[1]).all()
    assert sample[2, 0] == 4 and np.array_equal(sample[2, 1:], joints[0].reshape(-1))
    labels = channel_labels(3)
    assert len(labels) == 3 * CHANNELS_PER_SLOT and labels[1] == "p0_pelvis_x" and labels[-1] == "p2_r_ankle_z"


# -- a real run --------------------------------------------------------------------------


def _vmc_frames(bundles) -> list[dict]:
    """Per bundle: t, root and bone (position, quaternion)."""
    out = []
    for msgs in bundles:
        got = {"bones": {}}
        for address, params in msgs:
            if address == "/VMC/Ext/Root/Pos":
                got["root"] = np.array(params[1:4])
            elif address == "/VMC/Ext/Bone/Pos":
                got["bones"][params[0]] = (np.array(params[1:4]), np.array(params[4:8]))
            elif address == "/VMC/Ext/T":
                got["t"] = params[0]
        out.append(got)
    return out


def _bones_to_joints(got) -> np.ndarray:
    pos = np.array([got["bones"][b][0] for b in BONES])[None]
    rot = rotation_matrices(np.array([got["bones"][b][1] for b in BONES]))[None]
    world = forward_kinematics(got["root"][None], pos, rot)[0]
    return np.array([world[B[AT[j]]] for j in JOINTS])


@pytest.mark.integration
def test_vmc_osc_lsl_and_json_receivers_get_the_runs_poses(tiny_recording, tmp_path):
    """One paced run of a replayed meeting (3 people, one entering late) with four
    streamers. VMC: three avatar slots, the second receiver down for the first part of
    the run; every bundle's root and bones rebuild its person's joints within 1 mm,
    every frame reaches a receiver that is up. Plain OSC: every frame's joints. LSL: a
    pylsl inlet's samples are poses.jsonl's. JSON: the example client prints the records.
    The pipeline's own result, poses.jsonl, has every frame."""
    import pylsl

    recs = groundtruth_records("meeting3", 3.0, FPS)
    for r in recs:
        for p in r["poses"]:
            if p["track"] == 1 and 20 <= r["frame"] < 30:
                p["active"]["r_wrist"] = False
    poses = tmp_path / "poses.jsonl"
    poses.write_text("".join(json.dumps(r) + "\n" for r in recs))
    vmc_port, osc_port, hub = free_port(), free_port(), free_port()
    stream_name = f"smartroom-test-{hub}"
    layout = {"room": "smartroom", "bus": {"listen": [f"tcp/127.0.0.1:{hub}"]},
              "workers": [{"name": "pose", "kind": "tests.replay_poses:ReplayPoses",
                           "params": {"file": str(poses), "rate": 25.0}},
                          {"name": "recorder", "kind": "recorder"},
                          {"name": "vmc", "kind": "streamer", "params": {"protocol": "vmc", "port": vmc_port,
                                                                         "people": 3}},
                          {"name": "osc", "kind": "streamer", "params": {"protocol": "osc", "port": osc_port}},
                          {"name": "lsl", "kind": "streamer", "params": {"protocol": "lsl", "people": 4,
                                                                         "name": stream_name}},
                          {"name": "json", "kind": "streamer", "params": {"protocol": "json"}}]}
    (tmp_path / "layout.yaml").write_text(yaml.safe_dump(layout))
    vmc = [UdpReceiver(vmc_port), None, UdpReceiver(vmc_port + 2)]
    osc = UdpReceiver(osc_port)
    out = tmp_path / "out"
    fed = tmp_path / "client.out"    # a file, not a pipe: a full pipe would hold the client back
    client = subprocess.Popen([sys.executable, str(ROOT / "examples" / "zenoh_poses.py"), "--connect",
                               f"tcp/127.0.0.1:{hub}", "--seconds", "60"], stdout=fed.open("w"))
    run = start_smartroom("run", "--recording", tiny_recording, "--layout", tmp_path / "layout.yaml",
                          "--headless", "--out", out)
    lsl_samples, lsl_times = [], []
    try:
        found = pylsl.resolve_byprop("name", stream_name, timeout=30)
        assert found, "no LSL stream"
        inlet = pylsl.StreamInlet(found[0])
        inlet.open_stream(timeout=10)
        meta = inlet.info()
        labels = []
        ch = meta.desc().child("channels").child("channel")
        while not ch.empty():
            labels.append(ch.child_value("label"))
            ch = ch.next_sibling()
        assert labels == channel_labels(4)
        assert meta.desc().child("setup").child_value("joints") == " ".join(JOINTS)
        deadline = time.monotonic() + 120
        while run.poll() is None and time.monotonic() < deadline:
            chunk, ts = inlet.pull_chunk(timeout=0.2)
            lsl_samples += chunk
            lsl_times += ts
            if vmc[1] is None and len(vmc[0].got) >= 25:
                vmc[1] = UdpReceiver(vmc_port + 1)   # the second avatar's receiver comes up late
        chunk, ts = inlet.pull_chunk(timeout=1.0)
        lsl_samples += chunk
        lsl_times += ts
        assert run.wait(10) == 0, run.stderr.read()[-3000:]
        time.sleep(0.5)
    finally:
        if run.poll() is None:
            run.kill()
        client.terminate()
        client.wait(20)
        for r in [*vmc, osc]:
            if r is not None:
                r.close()
    written = [json.loads(ln) for ln in (out / "poses.jsonl").read_text().splitlines()]
    assert [w["frame"] for w in written] == [r["frame"] for r in recs]   # the pipeline lost nothing
    by_t = {round(r["t"], 4): r for r in written}

    # VMC: every bundle is one person of one frame, rebuilt within 1 mm
    first_late = None
    for slot, receiver in enumerate(vmc):
        frames = _vmc_frames(receiver.messages())
        assert frames, f"slot {slot}: nothing received"
        seen = []
        for got in frames:
            rec = by_t[round(got["t"], 4)]
            _, joints, _ = _arrays(rec)
            pelvis = to_unity(joints[:, 0])
            hips = got["root"] + got["bones"]["Hips"][0]
            k = int(np.argmin(np.abs(pelvis - hips).max(axis=1)))
            assert np.abs(pelvis[k] - hips).max() < 1e-3, (slot, rec["frame"])
            assert np.abs(_bones_to_joints(got) - to_unity(joints[k])).max() < 1e-3, (slot, rec["frame"])
            seen.append(rec["frame"])
        assert seen == sorted(seen)
        present = [r["frame"] for r in written if len(r["poses"]) > slot]
        if slot == 1:
            first_late = seen[0]
            present = [f for f in present if f >= first_late]
        assert seen == present, (slot, sorted(set(present) - set(seen))[:10])
    assert first_late > written[0]["frame"] + 20    # it really was down for part of the run

    # plain OSC: every frame, its active joints
    frames = {}
    for msgs in osc.messages():
        head = dict(msgs)["/smartroom/frame"]
        frames[head[0]] = {a: p for a, p in msgs[1:]}
    assert sorted(frames) == [r["frame"] for r in written]
    for rec in written:
        got = frames[rec["frame"]]
        want = {f"/smartroom/person/{p['track']}/{j}": p["joints"][j]
                for p in rec["poses"] for j in JOINTS if p["active"][j]}
        assert set(got) == set(want)
        assert all(np.abs(np.array(got[a]) - want[a]).max() < 1e-5 for a in want)

    # LSL: from the inlet's connection on (it may join after the first frames), one sample a
    # frame, in order, equal to poses.jsonl (float32), times increasing
    slots = Slots(4)
    want = []
    for rec in written:
        tracks, joints, active = _arrays(rec)
        want.append(lsl_sample(4, slots.assign(tracks), joints, active, tracks))
    assert lsl_samples, "no LSL sample"
    first = next(k for k, w in enumerate(want) if np.allclose(np.nan_to_num(lsl_samples[0]), np.nan_to_num(w)))
    assert first < len(written) // 2 and len(lsl_samples) == len(written) - first, (first, len(lsl_samples))
    assert np.all(np.diff(lsl_times) > 0)
    for sample, w in zip(lsl_samples, want[first:]):
        assert np.array_equal(np.isnan(w), np.isnan(sample))
        assert np.allclose(np.nan_to_num(sample), np.nan_to_num(w), atol=1e-6)

    # JSON on zenoh, read by the example client (it joined once the run was under way)
    printed = [json.loads(ln) for ln in fed.read_text().splitlines() if ln.strip()]
    assert len(printed) >= len(written) - 10
    assert printed == written[-len(printed):]


def test_a_streamer_with_a_bad_protocol_or_port_is_refused_by_the_layout(tmp_path):
    from app.config import parse_layout
    from app.errors import InputError
    base = {"room": "r", "bus": {"listen": ["tcp/127.0.0.1:0"]},
            "workers": [{"name": "grabber", "kind": "grabber"}]}
    for params, words in (({"protocol": "udp"}, "protocol"), ({"port": 70000}, "port"), ({"people": 99}, "people")):
        doc = dict(base, workers=[*base["workers"], {"name": "s", "kind": "streamer", "params": params}])
        with pytest.raises(InputError, match=words):
            parse_layout(doc, "layout.yaml")


@pytest.mark.integration
def test_the_streaming_benchmark_receives_every_frame(tmp_path):
    """``smartroom bench streaming``: streamer processes for OSC, VMC and LSL, 3 people at
    30 fps for 2 s; every frame (every person-frame for VMC) is received, latencies reported.
    Live, a streamer held up for longer than its inbox drops the oldest frames (a busy CI
    machine): then every frame missing is one it counted as dropped, and no more than a few."""
    from tests.conftest import smartroom
    r = smartroom("bench", "streaming", "--seconds", 2, "--people", 3, "--stream-fps", 30, "--out", tmp_path,
                  timeout=180)
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads((tmp_path / "bench_streaming.json").read_text())
    for proto in ("osc", "vmc", "lsl"):
        row = res["protocols"][proto]
        per_frame = row["expected"] // res["frames"]   # VMC: a bundle per person, 3 people throughout
        assert row["expected"] == per_frame * res["frames"] > 0, (proto, row)
        assert row["frames_missing"] == row["inbox_dropped"] <= 0.05 * res["frames"], (proto, row)
        assert row["received"] == row["expected"] - per_frame * row["frames_missing"], (proto, row)
        assert 0 < row["p50_ms"] <= row["p95_ms"] < 1000, (proto, row)
    assert "p95 ms" in r.stdout
