"""Junk on the bus (issue 25). From outside a room on one host (over its TCP endpoint) the
hub lets nothing be published in the room, so junk reaches no worker. From inside (a
session connected as the room's workers are: a worker gone wrong), stats under names that
are not workers of the layout, sent as fast as one process can while a real run goes on,
change nothing in the run, in its stats.json or on the monitor (the launcher once crashed
on them: its stats table was read and written from two threads), and junk on every key is
refused by the workers' own checks before it is queued."""
import json
import subprocess
import sys
import threading
import time

import pytest
import yaml

from app.benchmarks.flood import flood, inside_endpoint, room_keys
from app.bus import BusConfig, Keys, free_port, open_session
from app.messages import Stats
from tests.conftest import ROOT
from tests.runs import write_layout

pytestmark = pytest.mark.integration


def _flood(endpoint: str, room: str, stop: threading.Event, sent: list) -> None:
    session = open_session(BusConfig(listen=[], connect=[endpoint]), mode="client")
    keys = Keys(room)
    try:
        publishers = {}
        i = 0
        while not stop.is_set():
            name = f"zz{i % 400}"   # a few hundred stages that do not exist, over and over
            pub = publishers.get(name) or publishers.setdefault(name, session.declare_publisher(keys.stats(name)))
            pub.put(Stats(worker=name, stage="zz", figures={"frames_in": 10 ** 6, "frames_out": 10 ** 6,
                                                               "fps": 25.0, "order": 9}).to_bytes())
            i += 1
        sent.append(i)
    finally:
        session.close()


def _run_beside(flood, recording, tmp_path, extra_workers=(), delay=2.0, inside=True):
    """A real run of ``recording`` (its hub on a known port) with ``flood(endpoint, room,
    stop, sent)`` publishing from another session from ``delay`` s in, connected as the
    room's workers are (``inside``) or over the hub's TCP endpoint; ``(out, stdout, stderr,
    exit code, messages sent)``."""
    port = free_port()
    path = write_layout(tmp_path / "layout.yaml", extra_workers=list(extra_workers))
    doc = yaml.safe_load(path.read_text())
    doc["bus"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    path.write_text(yaml.safe_dump(doc))
    out = tmp_path / "out"
    run = subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--layout", str(path), "--recording",
                            str(recording), "--headless", "--out", str(out)], cwd=ROOT,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stop, sent, thread = threading.Event(), [], None
    try:
        time.sleep(delay)      # the hub is up
        endpoint = inside_endpoint(out / "layout.yaml", 60.0) if inside else f"tcp/127.0.0.1:{port}"
        assert endpoint is not None, "the run wrote no layout.yaml"
        thread = threading.Thread(target=flood, args=(endpoint, doc["room"], stop, sent), daemon=True)
        thread.start()
        shown, err = run.communicate(timeout=240)
    finally:
        stop.set()
        if thread is not None:
            thread.join(timeout=30)
        if run.poll() is None:
            run.kill()
    return out, shown, err, run.returncode, (sent or [0])[0]   # (sent: what the flood says it sent)


def test_stats_from_workers_outside_the_layout_change_nothing(long_recording, tmp_path):
    out, shown, err, rc, sent = _run_beside(_flood, long_recording, tmp_path, extra_workers=[
        {"name": "monitor", "kind": "monitor", "params": {"line_period": 2.0}}])
    assert sent > 1000, sent
    assert rc == 0, err[-2000:]
    stats = json.loads((out / "stats.json").read_text())
    assert stats["complete"] and stats["frames"] == 250
    assert not [n for n in (*stats["workers"], *stats["stages"]) if n.startswith("zz")]
    assert stats["stages"]["recorder"]["frames_in"] == 250
    # the monitor (a worker that reads every stats message) refused them and never showed them
    assert stats["workers"]["monitor"]["bad_messages"] > 100
    assert stats["workers"]["monitor"]["frames_missing"] == 0   # it takes no frames, so misses none
    lines = [ln for ln in (shown + err).splitlines() if "not a worker of the layout" not in ln]   # (refusals)
    assert any("rtf=" in ln for ln in lines) and not any("zz" in ln for ln in lines)   # real stages only


JUNK_RATE = 20000   # messages a second (issue 25's figure)


def _junk(endpoint: str, room: str, stop: threading.Event, sent: list) -> None:
    """Junk on every key the spine's workers and the launcher listen on (masks, frames,
    voxels, tracks, poses, stats, acks, heartbeats, ends of stream...) at JUNK_RATE."""
    cams = ["cam0", "cam1"]   # the recording's
    workers = ["grabber", "segmentation", "reconstruction", "recorder"]
    got = flood(endpoint, room_keys(room, cams, workers), JUNK_RATE, 1e9, stop=stop.is_set)
    sent.append(got)


def test_junk_on_every_key_loses_no_frame(long_recording, tmp_path):
    """Junk at 20,000 messages a second on every key of the room while a recording runs:
    it is refused before it is queued, so no inbox drops a real message, the run
    completes and every frame is in voxels.bin (junk used to push real messages out of
    the bounded inbox: frames lost, or a run that waited for them)."""
    from app.results import iter_voxels

    out, _, err, rc, got = _run_beside(_junk, long_recording, tmp_path)
    assert rc == 0, err[-2000:]
    assert got["rate"] > 0.9 * JUNK_RATE and got["seconds"] > 5, got   # the flood went on at its rate
    stats = json.loads((out / "stats.json").read_text())
    assert stats["complete"]
    for name in ("segmentation", "reconstruction", "recorder"):
        assert stats["workers"][name]["items_dropped"] == 0, name
    rec = stats["workers"]["reconstruction"]
    assert sum(n for k, n in rec["rejected"].items() if k.startswith("mask/cam0: malformed")) > 1000
    assert [m.frame for m in iter_voxels(out / "voxels.bin")] == list(range(250))


def _forged_epoch(endpoint: str, room: str, stop: threading.Event, sent: list) -> None:
    """Valid masks of cam0 in a forged epoch (2^40 ms: the year 2004), frames 0-249 over
    and over, from before the grabber's first frame on."""
    import zenoh
    import numpy as np

    from app.messages import Mask

    session = open_session(BusConfig(listen=[], connect=[endpoint]), mode="client")
    try:
        pub = session.declare_publisher(Keys(room).mask("cam0"), congestion_control=zenoh.CongestionControl.BLOCK)
        m = np.zeros((15, 20), bool)
        i = 0
        while not stop.is_set():
            pub.put(Mask.pack(m, frame=i % 250, camera="cam0", cameras=["cam0"], epoch=2 ** 40).to_bytes())
            i += 1
            time.sleep(0.001)
        sent.append(i)
    finally:
        session.close()


def test_junk_from_outside_the_room_reaches_no_worker(long_recording, tmp_path):
    """The same junk at 20,000 messages a second, from a session linked to the hub over
    its TCP endpoint (where a viewer or a client of the zenoh feed connects): the hub of a
    room on one host lets nothing linked that way publish in the room, so no worker
    refuses a single message (none reaches them), and the run is complete."""
    from app.results import iter_voxels

    out, _, err, rc, got = _run_beside(_junk, long_recording, tmp_path, inside=False)
    assert rc == 0, err[-2000:]
    assert got["rate"] > 0.9 * JUNK_RATE and got["seconds"] > 5, got
    layout = yaml.safe_load((out / "layout.yaml").read_text())
    assert [ep.split("/")[0] for ep in layout["bus"]["connect"]] == ["unixsock-stream"]   # the workers' way in
    stats = json.loads((out / "stats.json").read_text())
    assert stats["complete"]
    refused = {name: sum(w.get("rejected", {}).values()) for name, w in stats["workers"].items()}
    assert not any(refused.values()), refused
    assert [m.frame for m in iter_voxels(out / "voxels.bin")] == list(range(250))


def test_a_forged_epoch_sent_before_the_stream_holds_no_key(long_recording, tmp_path):
    """Masks in an epoch no source of this run has (older than the launcher's start, which
    the resolved layout carries) sent from before the first real frame: the first of them
    used to set the reconstruction's window for mask/cam0, so the real masks were refused
    as a new epoch while the forger kept "its" one running and the run lost its frames.
    Now they are refused as before the run, and every frame is reconstructed."""
    from app.results import iter_voxels

    t0 = time.time()
    out, _, err, rc, sent = _run_beside(_forged_epoch, long_recording, tmp_path, delay=0.5)
    assert sent > 500, sent
    assert rc == 0, err[-2000:]
    started = yaml.safe_load((out / "layout.yaml").read_text())["run"]["started_ms"]
    assert t0 * 1000 <= started <= time.time() * 1000
    stats = json.loads((out / "stats.json").read_text())
    assert stats["complete"]
    rec = stats["workers"]["reconstruction"]
    assert sum(n for k, n in rec["rejected"].items() if k == "mask/cam0: epoch before the run") > 500
    assert [m.frame for m in iter_voxels(out / "voxels.bin")] == list(range(250))


def test_the_flood_s_junk_is_refused_by_the_message_codec_and_covers_every_key():
    """What `smartroom bench flood` sends: nothing a worker may accept (a payload that
    decodes is a heartbeat from a worker outside the layout), on every key of the room."""
    from app.benchmarks.flood import junk_payloads
    from app.messages import Heartbeat, MessageError, decode

    decoded = []
    for payload in junk_payloads(250):
        try:
            msg = decode(payload)
            msg.validate()
            decoded.append(msg)
        except MessageError:
            pass
    assert decoded and all(isinstance(m, Heartbeat) and m.worker.startswith("zz") for m in decoded)
    keys = Keys("r")
    got = set(room_keys("r", ["cam0"], ["pose"]))
    assert {keys.frame("cam0"), keys.mask("cam0"), keys.voxels(), keys.blobs(), keys.tracks(), keys.poses(),
            keys.stats("pose"), keys.eos("pose"), keys.ack("pose"), keys.heartbeat("pose")} <= got
