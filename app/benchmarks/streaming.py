"""Benchmark of the streamers: latency and throughput of VMC, plain OSC and LSL with
several people at a high frame rate (issue 29's targets: p95 <= 5 ms, 6 people at 60 fps
without drops).

This process opens the hub (a zenoh router, as the launcher does), starts one streamer
worker per protocol as its own process (``smartroom worker NAME --connect``, the same
code as in a run), publishes the simulated crowd6 scene's true joints as the pose stage
would (6 people; ``Poses`` at ``fps``, paced), and receives what the streamers send:
UDP sockets for OSC and for each VMC avatar slot, a pylsl inlet for LSL. Reported per
protocol: frames received of those sent (a person-frame per VMC slot), the frames of
which nothing arrived (``frames_missing``) and those the streamer dropped, behind
(``inbox_dropped``: a live streamer's inbox keeps the newest frames), and the latency
from just before the pose message is published to just after its packet is read here
(p50/p95/max: the streamer's arrival-to-send plus one zenoh hop and the loopback socket,
an upper bound of the streamer's own part); and the streamers' own ``send_ms`` (a
frame's handling to its last packet sent, their stats).
"""
from __future__ import annotations

import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import yaml

from app.bus import BusConfig, Keys, Publisher, free_port, open_session
from app.messages import JOINTS, Poses, Stats, decode
from app.streaming.receiver import UdpReceiver

PEOPLE = 6
LAST_PACKETS_S = 10.0   # how long the last packets are waited for after the last frame is sent


def _crowd(frames: int, fps: float, people: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(tracks, joints) per frame: the crowd6 scene's true joints (no rendering)."""
    from app.simulation.simulator import Simulator
    sim = Simulator("crowd6", fps=fps, seconds=frames / fps, width=64, height=48)
    out = []
    for i in range(frames):
        gt = sim.groundtruth(i % sim.frame_count())
        ps = gt["people"][:people]
        out.append((np.array([p["id"] for p in ps], np.int64),
                    np.array([[p["joints"][j] for j in JOINTS] for p in ps], float).reshape(-1, 15, 3)))
    return out


def _osc_frame(data: bytes, fps: float, vmc: bool) -> int:
    from pythonosc.osc_packet import OscPacket
    for m in OscPacket(data).messages:
        if vmc and m.message.address == "/VMC/Ext/T":
            return int(round(m.message.params[0] * fps))
        if not vmc and m.message.address == "/smartroom/frame":
            return int(m.message.params[0])
    return -1


def _received(proto: str, udp: dict, lsl_got: list) -> int:
    """Packets received so far (a frame's bundle, for VMC a person-frame's)."""
    return len(lsl_got) if proto == "lsl" else sum(len(r.got) for r in udp[proto])


def _latency(pairs: list[float]) -> dict:
    if not pairs:
        return {}
    a = np.asarray(pairs) * 1e3
    return {"p50_ms": round(float(np.percentile(a, 50)), 3), "p95_ms": round(float(np.percentile(a, 95)), 3),
            "max_ms": round(float(a.max()), 3)}


def run(seconds: float = 10.0, fps: float = 60.0, people: int = PEOPLE, protocols=("osc", "vmc", "lsl"),
        progress=None) -> dict:
    """Run the benchmark; figures per protocol (module docstring)."""
    say = progress or (lambda line: None)
    hub = free_port()
    room = f"bench{hub}"
    keys = Keys(room)
    ports = {"osc": free_port(), "vmc": free_port()}
    lsl_name = f"smartroom-bench-{hub}"
    # the names this process publishes as (a layout needs a source): only the streamers run
    workers = [{"name": "grabber", "kind": "grabber"}, {"name": "pose", "kind": "pose"}]
    n_stand_ins = len(workers)
    for proto in protocols:
        params = {"protocol": proto}
        if proto in ("osc", "vmc"):
            params["port"] = ports[proto]
        if proto in ("vmc", "lsl"):
            params["people"] = people
        if proto == "lsl":
            params["name"] = lsl_name
        workers.append({"name": f"stream_{proto}", "kind": "streamer", "params": params})
    frames = _crowd(int(seconds * fps), fps, people)
    # packets due: a frame's; VMC a bundle per person present (crowd6's people enter in its first seconds)
    expected = {"osc": len(frames), "vmc": sum(len(tr) for tr, _ in frames), "lsl": len(frames)}
    tmp = Path(tempfile.mkdtemp(prefix="smartroom-bench-streaming-"))
    layout = tmp / "layout.yaml"
    layout.write_text(yaml.safe_dump({"room": room, "bus": {"listen": [f"tcp/127.0.0.1:{hub}"]},
                                      "run": {"fps": fps}, "workers": workers}))
    session = open_session(BusConfig(listen=[f"tcp/127.0.0.1:{hub}"]), mode="router")
    stats: dict[str, dict] = {}

    def on_stats(sample):
        try:
            msg = decode(sample.payload.to_bytes())
        except Exception:   # noqa: BLE001 - a benchmark's own bus: nothing else publishes here
            return
        if isinstance(msg, Stats):
            stats[msg.worker] = msg.figures

    subs = [session.declare_subscriber(keys.stats(), on_stats)]
    alive: set[str] = set()
    subs.append(session.liveliness().declare_subscriber(
        keys.alive(), lambda s: alive.add(Keys.last(s.key_expr)), history=True))
    udp = {}
    if "osc" in protocols:
        udp["osc"] = [UdpReceiver(ports["osc"])]
    if "vmc" in protocols:
        udp["vmc"] = [UdpReceiver(ports["vmc"] + s) for s in range(people)]
    procs = [subprocess.Popen([sys.executable, "-m", "app.cli", "worker", w["name"], "--layout", str(layout),
                               "--connect", f"tcp/127.0.0.1:{hub}"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True) for w in workers[n_stand_ins:]]
    inlet = None
    lsl_got: list[tuple[float, float]] = []
    sent: list[float] = []
    try:
        deadline = time.monotonic() + 60
        names = {w["name"] for w in workers[n_stand_ins:]}
        while not names <= alive and time.monotonic() < deadline:
            if any(p.poll() is not None for p in procs):
                raise RuntimeError("a streamer exited: " + " ".join(p.stderr.read()[-500:] for p in procs
                                                                    if p.poll() is not None))
            time.sleep(0.05)
        if not names <= alive:
            raise RuntimeError(f"streamers not on the bus after 60 s: {sorted(names - alive)}")
        if "lsl" in protocols:
            import pylsl
            found = pylsl.resolve_byprop("name", lsl_name, timeout=20)
            if not found:
                raise RuntimeError("the LSL stream was not found")
            inlet = pylsl.StreamInlet(found[0], max_buflen=60)
            inlet.open_stream(timeout=10)
            offset = time.time() - pylsl.local_clock()
            stop_lsl = threading.Event()

            def pull():
                while not stop_lsl.is_set():
                    _, ts = inlet.pull_sample(timeout=0.1)
                    if ts is not None:
                        lsl_got.append((time.time(), ts + offset))

            lsl_thread = threading.Thread(target=pull, daemon=True)
            lsl_thread.start()
            # the inlet reports itself connected as it reads the outlet's header; the outlet
            # takes it on as a consumer a moment later (its own thread, liblsl's tcp_server),
            # and a sample pushed in between never reaches it: wait for the streamer to say so
            deadline = time.monotonic() + 20
            while not stats.get("stream_lsl", {}).get("lsl_inlets") and time.monotonic() < deadline:
                time.sleep(0.05)
            if not stats.get("stream_lsl", {}).get("lsl_inlets"):
                raise RuntimeError("the LSL outlet took no inlet within 20 s")
        say(f"streamers up; publishing {len(frames)} frames of {people} people at {fps:g} fps")
        pub = Publisher(session, keys.poses(), droppable=False)
        epoch = time.time_ns() // 1_000_000
        t0 = time.perf_counter()
        for i, (tracks, joints) in enumerate(frames):
            wait = t0 + i / fps - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            stamp = time.time()
            sent.append(stamp)
            pub.put(Poses(frame=i, stamp=stamp, t=i / fps, epoch=epoch, worker="pose", tracks=tracks,
                          joints=joints, active=np.ones(joints.shape[:2], bool)))
        # the last packets (a busy machine may hold them a while), and a last second of stats
        time.sleep(1.5)
        deadline = time.monotonic() + LAST_PACKETS_S
        while time.monotonic() < deadline and any(
                _received(proto, udp, lsl_got) < expected[proto] for proto in protocols):
            time.sleep(0.1)
        if inlet is not None:
            stop_lsl.set()
            lsl_thread.join(2)
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
        for rs in udp.values():
            for r in rs:
                r.close()
        for s in subs:
            s.undeclare()
        session.close()
    sent_at = np.asarray(sent)
    result = {"seconds": seconds, "fps": fps, "people": people, "frames": len(frames), "protocols": {}}
    # frames a protocol sends a packet for (VMC: a frame with people)
    due = {proto: {i for i, (tr, _) in enumerate(frames) if len(tr) or proto != "vmc"} for proto in protocols}
    for proto in protocols:
        row: dict = {}
        lat, received, got = [], 0, set()
        if proto in udp:
            for r in udp[proto]:
                for when, data in r.got:
                    f = _osc_frame(data, fps, vmc=proto == "vmc")
                    if 0 <= f < len(sent_at):
                        lat.append(when - sent_at[f])
                        received += 1
                        got.add(f)
        else:
            for when, stamp in lsl_got:
                f = int(np.argmin(np.abs(sent_at - stamp)))
                lat.append(when - sent_at[f])
                received += 1
                got.add(f)
        # frames of which nothing arrived: each should be one the streamer counted as dropped
        row.update({"received": received, "expected": expected[proto], "frames_missing": len(due[proto] - got)})
        row.update(_latency(lat))
        figures = stats.get(f"stream_{proto}", {})
        row["streamer_send_ms"] = figures.get("send_ms", {})
        row["send_failed"] = figures.get("send_failed")
        row["inbox_dropped"] = figures.get("items_dropped")
        result["protocols"][proto] = row
    return result


def table(result: dict) -> str:
    lines = [f"streamers: {result['people']} people at {result['fps']:g} fps, {result['frames']} frames "
             f"({result['seconds']:g} s); latency from publishing the pose message to reading the packet",
             f"{'protocol':<9}{'received':>16}{'dropped':>9}{'p50 ms':>9}{'p95 ms':>9}{'max ms':>9}{'send p95 ms':>13}"]
    for proto, row in result["protocols"].items():
        got = f"{row['received']}/{row['expected']}"
        dropped = "?" if row.get("inbox_dropped") is None else row["inbox_dropped"]
        lines.append(f"{proto:<9}{got:>16}{dropped:>9}{row.get('p50_ms', float('nan')):>9.2f}"
                     f"{row.get('p95_ms', float('nan')):>9.2f}{row.get('max_ms', float('nan')):>9.2f}"
                     f"{row['streamer_send_ms'].get('p95', float('nan')):>13.2f}")
    return "\n".join(lines)
