"""Camera grabber: publishes every camera's frame with its index and capture time.

Reads a recording folder as if live (paced at its fps, or as fast as the pipeline
takes it with ``--no-pace``) or live cameras through ``cv2.VideoCapture``. Before the
first frame it waits until every worker of the layout is alive, so no stage misses
the start of the stream.
"""
from __future__ import annotations

import threading
import time

from app.errors import InputError
from app.messages import Frame
from app.sources import LiveSource, RecordingSource
from calibration import load_calibration
from workers.base import Worker


class Grabber(Worker):
    KIND = "grabber"
    ORDER = 0
    PRODUCES = ("frame",)
    DEFAULTS = {
        "cameras": "all",        # cameras this grabber reads (a list, or all)
        "start": 0,              # first frame of a recording
        "ready_timeout": 60.0,   # seconds to wait for the other workers before starting anyway
        "window": 2,             # --no-pace: frames in flight beyond the slowest stage's last one
        "ack_timeout": 1.0,      # --no-pace: longest wait for a stage's acknowledgement
    }

    def setup(self) -> None:
        run = self.layout.run
        cams = self.cameras()
        if run.live:
            if not run.calibration:
                raise InputError("live cameras need a calibration file (--calibration)")
            live = {c: s for c, s in run.live.items() if cams is None or c in cams}
            self.source = LiveSource(live, load_calibration(run.calibration), frames=run.frames)
        else:
            if not run.recording:
                raise InputError("the grabber has no recording and no live cameras")
            self.source = RecordingSource(run.recording, cams, start=self.params["start"], frames=run.frames)
        self._frames = None
        self._acks: dict[str, int] = {}
        self._ack_cond = threading.Condition()
        self.produced = 0
        self.first = self.source.start
        self.t0 = None

    def _wait_until_ready(self) -> None:
        others = {w.name for w in self.layout.workers if w.name != self.name}
        if self.layout.run.headless:
            from workers import worker_class
            others = {n for n in others if not worker_class(self.layout.worker(n).kind).DISPLAY}
        alive: set[str] = set()

        def seen(sample):
            alive.add(self.keys.last(sample.key_expr))

        sub = self.session.liveliness().declare_subscriber(self.keys.alive(), seen, history=True)
        deadline = time.monotonic() + self.params["ready_timeout"]
        while not others <= alive and time.monotonic() < deadline and not self.stopping:
            time.sleep(0.02)
        sub.undeclare()
        if not others <= alive:
            self.log.warning("starting without %s (not alive after %.0f s)",
                             ", ".join(sorted(others - alive)), self.params["ready_timeout"])

    def produce(self) -> bool:
        if self._frames is None:
            self._frames = iter(self.source.frames())
            t0 = time.perf_counter()
            self._wait_until_ready()
            self._idle += time.perf_counter() - t0
        try:
            index, images = next(self._frames)
        except StopIteration:
            return False
        if self.source.live:
            pass
        elif self.layout.run.pace:
            self._pace(index)
        else:
            self._wait_for_acks(index)
        stamp = time.time()
        self.ledger.received(index, stamp)
        t = index / self.source.fps
        for cam, image in images.items():
            self.publish(self.keys.frame(cam), Frame(frame=index, stamp=stamp, t=t, camera=cam, image=image))
        self.produced += 1
        return True

    def _filters(self) -> list[str]:
        """Stages between this source and the sinks, which acknowledge frames."""
        from workers import worker_class
        return [w.name for w in self.layout.workers
                if worker_class(w.kind).ORDER and worker_class(w.kind).PRODUCES
                and not (self.layout.run.headless and worker_class(w.kind).DISPLAY)]

    def _on_ack(self, sample) -> None:
        from app.bus import decode_sample
        try:
            msg = decode_sample(sample)
        except Exception:  # noqa: BLE001 - flow control must not die on a bad message
            return
        with self._ack_cond:
            self._acks[msg.worker] = max(msg.frame, self._acks.get(msg.worker, -1))
            self._ack_cond.notify_all()

    def _wait_for_acks(self, index: int) -> None:
        """Unpaced reading: hold frame ``index`` until every stage has acknowledged frame
        ``index - window`` (or ``ack_timeout`` passed: a stage may have died)."""
        if not hasattr(self, "_ack_sub"):
            self._ack_names = self._filters()
            self._ack_sub = self.session.declare_subscriber(self.keys.ack(), self._on_ack)
        need = index - self.params["window"]
        t0 = time.perf_counter()
        deadline = time.monotonic() + self.params["ack_timeout"]
        with self._ack_cond:
            while not self.stopping and any(self._acks.get(n, -1) < need for n in self._ack_names):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._ack_cond.wait(left)
        self._idle += time.perf_counter() - t0

    def _pace(self, index: int) -> None:
        """Sleep until the frame's time on the recording's clock. A frame that is late by
        more than one period moves the clock instead of causing a burst (as a camera
        that skipped would)."""
        now = time.monotonic()
        if self.t0 is None:
            self.t0 = now
        due = self.t0 + (index - self.first) / self.source.fps
        if now - due > 1.0 / self.source.fps:
            self.t0 += now - due
        elif due > now:
            self.sleep(due - now)

    def stream_info(self) -> tuple[int, int, float]:
        return self.produced, self.first, self.source.fps

    def extra_figures(self) -> dict:
        return {"fps_recording": self.source.fps, "expected_frames": self.source.expected}

    def close(self) -> None:
        if getattr(self, "source", None) is not None:
            self.source.close()
