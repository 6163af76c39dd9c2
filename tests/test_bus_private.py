"""A room on one host (issue 25): its hub takes the room's workers in through a private Unix
socket and lets whatever connects over TCP subscribe but publish nothing in the room
(zenoh's access control, app.bus_acl.outsiders_read_only). Real zenoh sessions: a hub and
three clients on loopback."""
from __future__ import annotations

import threading
import time

from app.bus import BusConfig, Keys, free_port, open_session
from app.bus_acl import outsiders_read_only

WAIT = 1.0     # s: a delivery on loopback takes a few ms


def test_outsiders_subscribe_to_the_room_but_what_they_publish_in_it_reaches_no_one(tmp_path):
    keys = Keys("solo")
    port = free_port()
    private = f"unixsock-stream/{tmp_path}/hub.sock"
    hub = open_session(BusConfig(listen=[f"tcp/127.0.0.1:{port}", private]), mode="router",
                       access_control=outsiders_read_only("solo"))
    inside = open_session(BusConfig(listen=[], connect=[private]), mode="client")        # a worker
    outside = open_session(BusConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"]), mode="client")
    viewer = open_session(BusConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"]), mode="client")
    got = {"inside": [], "viewer": []}
    lock = threading.Lock()

    def take(who):
        def handler(sample):
            with lock:
                got[who].append((str(sample.key_expr), sample.payload.to_bytes()))
        return handler

    subs = [inside.declare_subscriber("**", take("inside")), viewer.declare_subscriber("**", take("viewer"))]
    token = outside.liveliness().declare_token(keys.alive("grabber"))    # a forged "worker alive"
    try:
        time.sleep(0.3)
        for i in range(20):
            inside.put(keys.tracks(), b"real %d" % i)
            outside.put(keys.tracks(), b"junk %d" % i)
            outside.put(keys.stats("pose"), b"junk")
            outside.put("elsewhere/chat", b"not the room's")
        deadline = time.monotonic() + WAIT
        while time.monotonic() < deadline and len(got["viewer"]) < 40:
            time.sleep(0.02)
        time.sleep(0.2)
        alive = [r for r in inside.liveliness().get(keys.alive(), timeout=0.5) if r.ok]
    finally:
        token.undeclare()
        for s in subs:
            s.undeclare()
        for session in (outside, viewer, inside, hub):
            session.close()
    with lock:
        viewer_got, inside_got = list(got["viewer"]), list(got["inside"])
    real = [(keys.tracks(), b"real %d" % i) for i in range(20)]
    assert [m for m in viewer_got if m[0].startswith("smartroom/")] == real       # outsiders still read the room
    assert [m for m in inside_got if m[0].startswith("smartroom/")] == real        # the junk reached no one
    assert ("elsewhere/chat", b"not the room's") in inside_got                   # other keys are not the room's
    assert alive == []                                                            # nor a forged liveliness token


def test_a_new_launcher_sweeps_the_private_sockets_killed_launchers_left(tmp_path):
    """A launcher killed outright (SIGKILL, a power cut) cannot remove its socket's folder;
    the next one removes those of this user that are a minute old and where nothing
    listens, and leaves a live run's, a folder just made and anything else alone."""
    import os
    import socket

    from app.launcher import PRIVATE_PREFIX, sweep_private_sockets

    def folder(name, listening=None, socket_file=True, age=120.0):
        d = tmp_path / name
        d.mkdir()
        if socket_file:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.bind(str(d / "hub.sock"))
            if listening is not None:
                s.listen(1)
                listening.append(s)
            else:
                s.close()          # the file stays, nobody listens: a dead hub's
        old = time.time() - age
        os.utime(d, (old, old))
        return d

    live = []
    dead = folder(f"{PRIVATE_PREFIX}dead")
    empty = folder(f"{PRIVATE_PREFIX}empty", socket_file=False)
    alive = folder(f"{PRIVATE_PREFIX}alive", listening=live)
    fresh = folder(f"{PRIVATE_PREFIX}fresh", age=0.0)
    other = folder("someone-else", socket_file=False)
    try:
        assert sweep_private_sockets(str(tmp_path)) == 2
    finally:
        for s in live:
            s.close()
    assert not dead.exists() and not empty.exists()
    assert alive.exists() and fresh.exists() and other.exists()
