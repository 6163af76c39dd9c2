"""The inlet (app.bus.Inlet): control keys drained in batches by one thread, over a real
zenoh hub on loopback. Nothing is lost or reordered, even when a subscription's FIFO
fills between two drains; a handler that raises does not stop the others."""
import threading
import time

import pytest
import zenoh

from app.bus import BusConfig, Inlet, free_port, open_session


@pytest.fixture
def bus():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    hub = open_session(BusConfig(listen=[endpoint], shm=False), mode="router")
    sender = open_session(BusConfig(listen=[], connect=[endpoint], shm=False), mode="client")
    receiver = open_session(BusConfig(listen=[], connect=[endpoint], shm=False), mode="client")
    yield sender, receiver
    for s in (sender, receiver, hub):
        s.close()


def _wait(cond, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.01)
    return cond()


def test_every_message_of_every_key_in_order_even_past_the_fifo(bus, monkeypatch):
    sender, receiver = bus
    monkeypatch.setattr(Inlet, "CAPACITY", 50)   # a full FIFO holds the sender back, drops nothing
    inlet = Inlet(receiver, period_s=0.02)
    got = {"a": [], "b": []}
    lock = threading.Lock()

    def on(name):
        def handle(sample):
            with lock:
                got[name].append(int(sample.payload.to_bytes()))
        return handle

    inlet.subscribe("t/a", on("a"))
    inlet.subscribe("t/b/*", on("b"))
    time.sleep(0.5)   # the hub knows the subscriptions
    pubs = [sender.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK) for k in ("t/a", "t/b/x")]
    n = 2000
    for i in range(n):
        pubs[i % 2].put(str(i).encode())
    assert _wait(lambda: len(got["a"]) + len(got["b"]) == n), {k: len(v) for k, v in got.items()}
    assert got["a"] == list(range(0, n, 2))
    assert got["b"] == list(range(1, n, 2))
    inlet.close()
    assert not inlet._thread.is_alive()


def test_a_handler_that_raises_stops_nothing_and_unsubscribe_stops_its_key(bus):
    sender, receiver = bus
    inlet = Inlet(receiver)
    good = []

    def bad(sample):
        raise ValueError("a bug")

    bad_sub = inlet.subscribe("t/bad", bad)
    inlet.subscribe("t/good", lambda s: good.append(s.payload.to_bytes()))
    time.sleep(0.5)
    for _ in range(5):
        sender.put("t/bad", b"x")
        sender.put("t/good", b"y")
    assert _wait(lambda: len(good) == 5)
    inlet.unsubscribe(bad_sub)
    sender.put("t/good", b"z")
    assert _wait(lambda: len(good) == 6)
    assert len(inlet._subs) == 1
    inlet.close()
