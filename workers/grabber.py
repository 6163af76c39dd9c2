"""Camera grabber: publishes every camera's frame with its index, capture time, epoch
and frame set (the cameras sent for that index).

Reads a recording folder as if live, or live cameras through ``cv2.VideoCapture``.
Before the first frame it waits until every worker of the layout is alive, so no
stage misses the start of the stream.

Offline (a recording) the grabber never runs ahead of the pipeline: it holds frame
``i`` until every stage that is alive has put out frame ``i - window`` (paced runs
also keep the recording's clock), so no stage ever drops a frame and the results do
not depend on machine load. A stage that has left the bus (crashed) is not waited
for until it is back. A restarted grabber carries on after the last frame it sent,
in a new epoch. Live cameras are paced by the cameras themselves.
"""
from __future__ import annotations

import threading
import time

from app.admission import EPOCH_QUIET_S
from app.errors import InputError
from app.messages import Frame
from app.recording import Recording
from app.sources import LiveSource, RecordingSource
from calibration import load_calibration
from workers.base import Worker
from workers.restarts import REPLAY_DELAY_S

MISSING_WAIT_S = 60.0   # offline: how long a crashed stage is waited for before frames go on without it
RESUME_HOLD_S = 4 * REPLAY_DELAY_S   # offline: new frames wait this long after a worker is back from a crash
AGAIN_QUIET_S = 4 * EPOCH_QUIET_S    # offline, restarted: the new epoch waits this long after the last frame sent again


class Grabber(Worker):
    KIND = "grabber"
    ORDER = 0
    PRODUCES = ("frame",)
    DEFAULTS = {
        "cameras": "all",        # cameras this grabber reads (a list, or all)
        "start": 0,              # first frame of a recording
        "ready_timeout": 60.0,   # live: seconds to wait for the other workers before starting anyway (a recording
                                 # waits for all of them, saying so every this many seconds)
        "window": 2,             # offline: frames in flight beyond the slowest stage's last one
        "open_timeout": 10.0,    # live: seconds for a camera to deliver its first image
        "lost_timeout": 30.0,    # live: seconds with no camera delivering before the stream ends
        "skip_bad_frames": False,  # a recording's undecodable frames: stop with an error, or skip them
        "scale": 0,              # send frames at 1/scale (0: as small as the segmentation allows; 1: full size)
        "catch_up_s": 1.0,       # paced recording: a lag up to this (warm-up, a hiccup) is caught up; longer moves the clock
    }
    RANGES = {"start": (0, 1 << 40), "ready_timeout": (0.0, 3600.0), "window": (1, 64),
              "open_timeout": (0.5, 600.0), "lost_timeout": (0.5, 86400.0), "scale": (0, 16),
              "catch_up_s": (0.0, 10.0)}

    def setup(self) -> None:
        run = self.layout.run
        cams = self.cameras()
        self.epoch = time.time_ns() // 1_000_000     # a new epoch per incarnation
        self.scale = 1
        self._epoch = self.epoch
        self.lost: dict[str, int] = {}
        if run.live:
            if not run.calibration:
                raise InputError("live cameras need a calibration file (--calibration)")
            live = {c: s for c, s in run.live.items() if cams is None or c in cams}
            left = None if run.frames is None else max(0, run.frames - (self._resume or 0))
            self.source = LiveSource(live, load_calibration(run.calibration), frames=left,
                                     stop=self.stop_event, open_timeout=self.params["open_timeout"],
                                     lost_timeout=self.params["lost_timeout"], start=self._resume or 0)
            self.first = 0
        else:
            if not run.recording:
                raise InputError("the grabber has no recording and no live cameras")
            first = self.params["start"]
            resume = max(first, self._resume) if self._resume is not None else first
            total = RecordingSource(run.recording, cams, start=first, frames=run.frames).stop
            self.scale = self._send_scale(Recording(run.recording).calibration)
            self.source = RecordingSource(run.recording, cams, start=min(resume, total - 1),
                                          frames=max(0, total - resume), skip_bad=self.params["skip_bad_frames"],
                                          lost=self.lost, transform=self._reduce if self.scale > 1 else None)
            self.first = first
            self.total = total - first
            if resume >= total:
                self.source = None   # everything was sent before the restart
        self._frames = None
        self._acks: dict[str, int] = {}   # worker -> newest frame it finished
        self._outs: dict[str, int] = {}   # worker -> newest frame it put out
        self._ack_cond = threading.Condition()
        self.t0 = None

    def _send_scale(self, calib) -> int:
        """How much smaller than the camera the frames may travel: the largest power of two
        that divides every mask and colour scale of the layout's segmentation workers and
        every camera's size (HD frames are 25 MB a set; the segmentation reduces them anyway)."""
        from math import gcd

        from workers import worker_class
        from workers.segmentation import scales

        if self.params["scale"]:
            return int(self.params["scale"])
        need = 0
        for w in self.layout.workers:
            if "mask" in worker_class(w.kind).PRODUCES:
                mask, colour = scales(w, self.layout, calib)
                need = gcd(need, mask)
                if colour:
                    need = gcd(need, colour)
        scale = 1
        while need and need % (scale * 2) == 0 and all(
                c.width % (scale * 2) == 0 and c.height % (scale * 2) == 0 for c in calib.cameras):
            scale *= 2
        return scale

    def _reduce(self, camera: str, image):
        from app.segmentation import shrink
        return shrink(image, self.scale)

    # -- across restarts -------------------------------------------------------------
    _resume: int | None = None

    _out_epoch: int | None = None   # the epoch of the newest frame sent
    _sent_again = False

    def extra_state(self) -> dict:
        return {"out_epoch": self._out_epoch}

    def restore_state(self, state: dict) -> None:
        """A restarted grabber carries on after the last frame it sent (its ledger, with
        the journal, knows it exactly): a recording from there, live cameras with the
        next frame number, so results never hold one frame number twice. On a recording
        it first sends that last frame again in its own epoch (a grabber killed right after
        handing it to the bus may not have sent it; the stages that had it skip it)."""
        if self.ledger.newest_out >= 0:
            self._resume = self.ledger.newest_out + 1
            epoch = state.get("out_epoch")
            if isinstance(epoch, int) and not isinstance(epoch, bool):
                self._out_epoch = epoch

    def _send_again(self) -> None:
        """The last frame the earlier incarnation sent, in that incarnation's epoch."""
        index = self.ledger.newest_out
        again = RecordingSource(self.layout.run.recording, self.cameras(), start=index, frames=1,
                                skip_bad=self.params["skip_bad_frames"],
                                transform=self._reduce if self.scale > 1 else None)
        for i, images in again.frames():
            cameras = sorted(images)
            for cam, image in images.items():
                self.publish(self.keys.frame(cam), Frame(frame=i, stamp=time.time(), t=i / again.fps, camera=cam,
                                                         cameras=cameras, image=image, epoch=self._out_epoch,
                                                         scale=self.scale), counts=False)

    @property
    def produced(self) -> int:
        return self.ledger.done.count

    # -- frames ------------------------------------------------------------------------
    def _wait_until_ready(self) -> None:
        """Live: until every other worker is on the bus, at most ``ready_timeout``. On a
        recording nothing may be sent past a stage (the results would depend on how fast
        the machine loads it): until every worker is on the bus, said every ``ready_timeout``."""
        timeout = self.params["ready_timeout"]
        missing = self.wait_for_others(timeout)
        while missing and self.lossless and not self.stopping:
            self.log.warning("frame %d waits for %s to be on the bus (%s)", self.source.start,
                             ", ".join(sorted(missing)), "still loading, or not started on its host")
            missing = self.wait_for_others(max(timeout, 10.0))
        if missing:
            self.log.warning("starting without %s (not alive after %.0f s)", ", ".join(sorted(missing)), timeout)

    def produce(self) -> bool:
        if self.incarnation > 0 and self._out_epoch is not None and self.lossless and not self._sent_again:
            self._sent_again = True
            self._send_again()
            self.sleep(AGAIN_QUIET_S)   # the stages follow the new epoch once the old one is quiet
        if self.source is None:
            return False
        if self._frames is None:
            self._frames = iter(self.source.frames())
            if self.incarnation == 0:
                t0 = time.perf_counter()
                self._wait_until_ready()
                self._idle += time.perf_counter() - t0
        try:
            index, images = next(self._frames)
        except StopIteration:
            return False
        if self.lossless:
            self._wait_for_acks(index)
            if self.layout.run.pace:
                self._pace(index)
        if self.stopping:
            return False
        stamp = time.time()
        self.ledger.received(index, stamp)
        t = index / self.source.fps
        cameras = sorted(images)
        for cam, image in images.items():
            self.publish(self.keys.frame(cam), Frame(frame=index, stamp=stamp, t=t, camera=cam, cameras=cameras,
                                                     image=image, epoch=self.epoch, scale=self.scale), counts=False)
        self.ledger.emitted(index, stamp)   # sent once every camera's image is: a restart sends it again
        self._out_epoch = self.epoch
        return True

    def _filters(self) -> list[str]:
        """The workers that acknowledge frames (the stages, and sinks that keep results)."""
        from workers import worker_class
        return [w.name for w in self.layout.workers
                if w.name != self.name and worker_class(w.kind).acknowledges(w, self.layout)
                and not (self.layout.run.headless and worker_class(w.kind).DISPLAY)]

    def _upstream_stages(self) -> dict[str, list[str]]:
        """For each acknowledging worker, the acknowledging stages it takes its input from."""
        from workers import upstream_of
        return {n: [u for u in upstream_of(self.layout, self.layout.worker(n)) if u in self._ack_names]
                for n in self._ack_names}

    def _required(self, name: str, need: int) -> int:
        """The frame ``name`` must have finished: ``need``, or less when a stage before it
        has put out nothing that recent (it gave those frames up, e.g. too few cameras)."""
        for u in self._upstream.get(name, ()):
            need = min(need, self._outs.get(u, -1))
        return need

    def _keepers_of_results(self) -> list[str]:
        """Sinks that keep results: waited for (alive) while they restart, not acknowledged."""
        from workers import worker_class
        return [w.name for w in self.layout.workers
                if worker_class(w.kind).KEEPS_RESULTS and w.name not in self._ack_names]

    def _on_ack(self, sample) -> None:
        from app.bus import decode_sample
        from app.messages import Ack, MessageError
        try:
            msg = decode_sample(sample)
            msg.validate()
        except MessageError:
            self.reject(str(sample.key_expr), "malformed")
            return
        if not isinstance(msg, Ack) or msg.worker not in self._ack_names or msg.epoch != self.epoch:
            self.reject(str(sample.key_expr), "acknowledgement of another stream")
            return
        with self._ack_cond:
            self._acks[msg.worker] = max(msg.frame, self._acks.get(msg.worker, -1))
            self._outs[msg.worker] = max(msg.out, self._outs.get(msg.worker, -1))
            self._ack_cond.notify_all()

    def _wait_for_acks(self, index: int) -> None:
        """Hold frame ``index`` until every acknowledging worker has finished frame
        ``index - window``. A worker that has left the bus (crashed) is waited for while
        the launcher restarts it (at most ``MISSING_WAIT_S``), so no frame goes past it
        meanwhile; the frames that were in flight to it (its inbox, lost with it) are sent
        to it again by the workers before it when it is back (``Worker._resend``), and the
        stream waits for it to catch up on them as for any stage (at most ``MISSING_WAIT_S``
        more, in case its upstream restarted with it and nothing comes again)."""
        if not hasattr(self, "_ack_sub"):
            self._ack_names = self._filters()
            self._keepers = self._keepers_of_results()
            self._ack_sub = self.session.declare_subscriber(self.keys.ack(), self._on_ack)
            self._was_alive = set(self.alive)
            # nothing of this epoch is in flight yet (frames an earlier incarnation sent were
            # acknowledged in its epoch)
            self._acks = {n: index - 1 for n in self._ack_names}
            self._outs = {n: index - 1 for n in self._ack_names}
            self._missing_since: dict[str, float] = {}
            self._back_since: dict[str, float] = {}   # workers back from a crash, catching up
            self._hold_until = 0.0
            self._upstream = self._upstream_stages()
        need = index - self.params["window"]
        t0 = time.perf_counter()
        next_note = time.monotonic() + 10.0
        with self._ack_cond:
            while not self.stopping:
                alive = set(self.alive)
                now = time.monotonic()
                for n in alive - self._was_alive:
                    self._back_since[n] = now   # back after a crash: catching up on what is sent again
                    # hold new frames until the kept ones were sent again (``REPLAY_DELAY_S``):
                    # a sink that keeps results acknowledges nothing, and would get them after
                    # newer frames, or not at all once they had left the workers' replay buffers
                    self._hold_until = max(self._hold_until, now + RESUME_HOLD_S)
                self._was_alive = alive
                for n, since in list(self._back_since.items()):
                    if self._acks.get(n, -1) >= self._required(n, need):
                        del self._back_since[n]
                    elif now - since > MISSING_WAIT_S:
                        # what it missed never came again (its upstream restarted with it):
                        # go on from here; the frames it lacks are counted as missing
                        self.log.warning("%s has not caught up %.0f s after its restart; going on without "
                                         "the frames it missed", n, MISSING_WAIT_S)
                        del self._back_since[n]
                        for m in self._ack_names:
                            self._acks[m] = max(self._acks.get(m, -1), index - 1)
                            self._outs[m] = max(self._outs.get(m, -1), index - 1)
                for n in self._ack_names + self._keepers:
                    if n in alive:
                        self._missing_since.pop(n, None)
                    else:
                        self._missing_since.setdefault(n, now)
                waiting = [n for n in self._ack_names if n in alive and self._acks.get(n, -1) < self._required(n, need)]
                waiting += [n for n in self._ack_names + self._keepers
                            if n not in alive and now - self._missing_since[n] < MISSING_WAIT_S]
                if now < self._hold_until:
                    waiting.append("workers sending frames again")
                if not waiting:
                    break
                if time.monotonic() > next_note:
                    next_note = time.monotonic() + 10.0
                    self.log.warning("frame %d waits for %s to finish frame %d", index, ", ".join(waiting), need)
                self._ack_cond.wait(0.05)
        self._idle += time.perf_counter() - t0

    def _pace(self, index: int) -> None:
        """Sleep until the frame's time on the recording's clock. A lag of up to
        ``catch_up_s`` (the stages' warm-up on the first frames: look-up tables, kernels;
        or a moment's hiccup of a loaded machine) is caught up by sending the next frames
        without waiting, so a pipeline that keeps up plays the recording at its rate
        (before, a start-up lag of ~0.5 s moved the clock for good: paced RTF 0.97 for a
        pipeline that runs 2.6x real time unpaced); a frame later than that (and than one
        period) moves the clock instead of causing a long burst (as a camera that skipped
        would)."""
        now = time.monotonic()
        period = 1.0 / self.source.fps
        if self.t0 is None:
            self.t0 = now - (index - self.source.start) * period
        due = self.t0 + (index - self.source.start) * period
        if now - due > max(period, float(self.params["catch_up_s"])):
            self.t0 += now - due
        elif due > now:
            self.sleep(due - now)

    def stream_info(self) -> tuple[int, int, float]:
        fps = self.source.fps if self.source is not None else (self.layout.run.fps or 0.0)
        return self.produced, self.first, fps

    def extra_figures(self) -> dict:
        figures = {"fps_recording": self.stream_info()[2], "epoch": getattr(self, "epoch", 0)}
        source = getattr(self, "source", None)
        if source is not None:
            figures["expected_frames"] = getattr(self, "total", source.expected)
            failed = getattr(source, "failed", None)
            if failed:
                figures["cameras_failed"] = sorted(failed)
            if getattr(source, "failure", None):
                figures["stream_error"] = source.failure   # the stream ended, but not as it should
        if getattr(self, "lost", None):
            figures["views_lost"] = dict(self.lost)
        return figures

    def close(self) -> None:
        if getattr(self, "source", None) is not None:
            self.source.close()
