"""Benchmark of the message codec and zenoh between two processes.

The path of a pipeline's messages: a publishing worker, the hub, a subscribing worker.
This process opens the hub (a zenoh router, as the launcher does) and a client session
of it that publishes 640x480x3 :class:`~app.messages.Frame` messages; a second process
(started here) subscribes as a client, as a worker does, and decodes them. Reported:

- codec: encode and decode time of one frame (in-process, median);
- latency: one-way, from just before encoding to just after decoding, with frames
  paced at 50 Hz so nothing queues (p50/p95);
- throughput: frames sent back to back with congestion control BLOCK (nothing
  dropped), received frames per second and MB/s.

Run with zenoh's shared-memory transport on and off to see what it buys.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np

from app.bus import BusConfig, Keys, free_port, open_session
from app.messages import Frame, decode, encode

LATENCY_BASE = 0
THROUGHPUT_BASE = 1_000_000


def _subscriber(endpoint: str, room: str, latency_n: int, throughput_n: int, shm: bool, timeout: float) -> dict:
    keys = Keys(room)
    session = open_session(BusConfig(listen=[], connect=[endpoint], shm=shm), mode="client")
    lat, thr = [], []

    def on_sample(sample):
        msg = decode(sample.payload.to_bytes())
        now = time.time()
        if msg.frame >= THROUGHPUT_BASE:
            thr.append(now)
        else:
            lat.append((now - msg.stamp) * 1e3)

    sub = session.declare_subscriber(keys.frame("bench"), on_sample)
    token = session.liveliness().declare_token(keys.alive("bench-sub"))
    deadline = time.time() + timeout
    while time.time() < deadline and (len(lat) < latency_n or len(thr) < throughput_n):
        time.sleep(0.01)
    time.sleep(0.2)
    token.undeclare()
    sub.undeclare()
    session.close()
    return {"latency_ms": lat, "throughput_times": thr}


def run(frames: int = 300, throughput_frames: int = 500, shape=(480, 640, 3), shm: bool = True) -> dict:
    """Run the two-process benchmark; returns figures (ms, fps, MB/s)."""
    room = f"bench{free_port()}"
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    keys = Keys(room)
    hub_bus = BusConfig(listen=[endpoint], shm=shm)
    hub = open_session(hub_bus, mode="router")
    session = open_session(hub_bus.for_worker(), mode="client")
    child = subprocess.Popen(
        [sys.executable, "-m", "app.benchmarks.bus", "--subscriber", endpoint, "--room", room,
         "--frames", str(frames), "--throughput-frames", str(throughput_frames)] + ([] if shm else ["--no-shm"]),
        stdout=subprocess.PIPE, text=True)
    try:
        ready = set()
        sub = session.liveliness().declare_subscriber(keys.alive(), lambda s: ready.add(str(s.key_expr)), history=True)
        t_end = time.time() + 30
        while not ready and time.time() < t_end:
            time.sleep(0.01)
        sub.undeclare()
        time.sleep(0.3)
        image = np.random.default_rng(0).integers(0, 255, shape, dtype=np.uint8)
        import zenoh
        pub = session.declare_publisher(keys.frame("bench"), congestion_control=zenoh.CongestionControl.BLOCK)
        # codec alone
        enc, dec = [], []
        for i in range(100):
            t0 = time.perf_counter()
            payload = encode(Frame(frame=i, stamp=0.0, camera="bench", image=image))
            t1 = time.perf_counter()
            decode(payload)
            dec.append((time.perf_counter() - t1) * 1e3)
            enc.append((t1 - t0) * 1e3)
        # latency, paced
        for i in range(frames):
            pub.put(encode(Frame(frame=LATENCY_BASE + i, stamp=time.time(), camera="bench", image=image)))
            time.sleep(0.02)
        # throughput, back to back
        t0 = time.time()
        for i in range(throughput_frames):
            pub.put(encode(Frame(frame=THROUGHPUT_BASE + i, stamp=time.time(), camera="bench", image=image)))
        send_s = time.time() - t0
        out, _ = child.communicate(timeout=120)
    finally:
        if child.poll() is None:
            child.kill()
        session.close()
        hub.close()
    res = json.loads(out.strip().splitlines()[-1])
    lat = np.asarray(res["latency_ms"])
    thr = np.asarray(res["throughput_times"])
    mb = image.nbytes / 1e6
    span = (thr[-1] - t0) if thr.size else float("nan")
    fps = thr.size / span if thr.size else 0.0
    return {
        "shape": list(shape), "shm": shm, "frame_mb": round(mb, 3),
        "encode_ms_p50": round(float(np.median(enc)), 3), "decode_ms_p50": round(float(np.median(dec)), 4),
        "latency_frames": int(lat.size), "latency_ms_p50": round(float(np.percentile(lat, 50)), 3) if lat.size else None,
        "latency_ms_p95": round(float(np.percentile(lat, 95)), 3) if lat.size else None,
        "throughput_frames": int(thr.size), "throughput_fps": round(fps, 1), "throughput_mb_s": round(fps * mb, 1),
        "send_fps": round(throughput_frames / send_s, 1), "throughput_sent": throughput_frames,
    }


def table(results: list[dict]) -> str:
    head = f"{'shm':<5}{'encode':>9}{'decode':>9}{'lat p50':>9}{'lat p95':>9}{'recv fps':>10}{'MB/s':>8}{'recv/sent':>12}"
    lines = [f"codec + zenoh, one {results[0]['shape'][1]}x{results[0]['shape'][0]}x{results[0]['shape'][2]} frame "
             f"({results[0]['frame_mb']} MB) between two workers through the hub", head]
    for r in results:
        lines.append(f"{'on' if r['shm'] else 'off':<5}{r['encode_ms_p50']:>7.2f}ms{r['decode_ms_p50']:>7.3f}ms"
                     f"{r['latency_ms_p50']:>7.2f}ms{r['latency_ms_p95']:>7.2f}ms{r['throughput_fps']:>10.1f}"
                     f"{r['throughput_mb_s']:>8.0f}{r['throughput_frames']:>6}/{r['throughput_sent']}")
    return "\n".join(lines)


def _main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--subscriber", required=True)
    p.add_argument("--room", required=True)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--throughput-frames", type=int, default=500)
    p.add_argument("--no-shm", dest="shm", action="store_false")
    a = p.parse_args()
    res = _subscriber(a.subscriber, a.room, a.frames, a.throughput_frames, a.shm, timeout=90)
    print(json.dumps(res))


if __name__ == "__main__":
    _main()
