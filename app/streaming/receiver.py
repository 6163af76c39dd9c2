"""A UDP receiver read in a thread: what the benchmark and the tests receive from a
streamer (a real socket, as a VMC or OSC receiver has), every datagram with its arrival
wall-clock time; :meth:`UdpReceiver.messages` parses them with python-osc."""
from __future__ import annotations

import socket
import threading
import time

__all__ = ["UdpReceiver"]


class UdpReceiver:
    def __init__(self, port: int, host: str = "127.0.0.1"):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.sock.bind((host, port))
        self.sock.settimeout(0.1)
        self.got: list[tuple[float, bytes]] = []
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name=f"udp-{port}", daemon=True)
        self.thread.start()

    def _run(self):
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536)
            except OSError:
                continue
            self.got.append((time.time(), data))

    def messages(self) -> list[list[tuple[str, list]]]:
        """Per datagram (an OSC bundle or message), its messages as ``(address, arguments)``."""
        from pythonosc.osc_packet import OscPacket
        return [[(m.message.address, list(m.message.params)) for m in OscPacket(data).messages]
                for _, data in self.got]

    def close(self):
        self._stop.set()
        self.thread.join(2)
        self.sock.close()
