"""Print a smartroom's poses live, from this host or another (needs only eclipse-zenoh).

    python examples/zenoh_poses.py --connect tcp/HUB_HOST:7447 [--room smartroom]

The layout must have a streamer with ``protocol: json``; each line printed is one frame's
record, as in poses.jsonl (docs/streaming/zenoh-feed.md)."""
import argparse
import json
import time

import zenoh

p = argparse.ArgumentParser()
p.add_argument("--connect", required=True, help="the hub's endpoint, e.g. tcp/10.0.0.1:7447")
p.add_argument("--room", default="smartroom")
p.add_argument("--seconds", type=float, default=0, help="stop after this long (0: until Ctrl-C)")
args = p.parse_args()
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
conf.insert_json5("connect/timeout_ms", "30000")   # wait for the hub to come up
with zenoh.open(conf) as session:
    sub = session.declare_subscriber(f"smartroom/{args.room}/poses/json",
                                     lambda s: print(s.payload.to_string(), flush=True))
    end = time.time() + args.seconds if args.seconds else float("inf")
    while time.time() < end:
        time.sleep(0.1)
