"""Stages that misbehave on purpose, for the fault tests (loaded as plugin kinds)."""
import os
import time

from app.messages import Ack
from workers.base import Worker
from workers.segmentation import Segmentation


class CrashyStage(Worker):
    """Consumes voxels; its incarnation ``n`` dies (exit 1) on frame ``crash_at[n]``, or
    at once when ``crash_on_start`` (a restart storm); with ``raises`` it dies of a Python
    exception (a bug) instead."""

    KIND = "crashy"
    ORDER = 3
    CONSUMES = ("voxels",)
    PRODUCES = ("crashy",)
    DEFAULTS = {"crash_at": [], "crash_on_start": False, "raises": False}

    def setup(self):
        if self.params["crash_on_start"]:
            os._exit(1)

    def handle(self, key, msg):
        plan = self.params["crash_at"]
        if self.incarnation < len(plan) and msg.frame >= plan[self.incarnation]:
            if self.params["raises"]:
                self.log.warning("about to fail on frame %d", msg.frame)
                raise RuntimeError(f"a bug met on frame {msg.frame}")
            os._exit(1)
        self.publish(self.keys.stage("crashy"), Ack(frame=msg.frame, stamp=msg.stamp, t=msg.t, worker=self.name))


class SlowStartSegmentation(Segmentation):
    """A segmentation worker that is slow on its first frame (a cold start on big videos)."""

    DEFAULTS = {**Segmentation.DEFAULTS, "first_delay_s": 2.0}
    RANGES = {}

    def handle(self, key, msg):
        if not getattr(self, "_slept", False):
            self._slept = True
            time.sleep(self.params["first_delay_s"])
        super().handle(key, msg)


class SlowSetupStage(Worker):
    """Consumes voxels; its setup takes ``setup_s`` (tables and kernels of a heavy stage)."""

    KIND = "slowsetup"
    ORDER = 3
    CONSUMES = ("voxels",)
    PRODUCES = ("slowsetup",)
    DEFAULTS = {"setup_s": 5.0}

    def setup(self):
        time.sleep(self.params["setup_s"])

    def handle(self, key, msg):
        self.publish(self.keys.stage("slowsetup"), Ack(frame=msg.frame, stamp=msg.stamp, t=msg.t, worker=self.name))


class MuteSegmentation(Segmentation):
    """A segmentation worker that comes on the bus, takes frames in and never finishes one
    (a camera host whose stage hangs, or whose masks go nowhere)."""

    ACK_ON_HANDLE = False

    def handle(self, key, msg):
        if not getattr(self, "_said", False):
            self._said = True
            self.log.warning("mute: took frame %d in", msg.frame)


class CompilingStage(Worker):
    """Consumes voxels; on frame ``at`` it compiles a kernel taking ``compile_s`` (numba's own
    compile event around the wait: a kernel compiled on a path first taken, on a first run)."""

    KIND = "compiling"
    ORDER = 3
    CONSUMES = ("voxels",)
    PRODUCES = ("compiling",)
    DEFAULTS = {"at": 10, "compile_s": 3.0}

    def handle(self, key, msg):
        if msg.frame == self.params["at"]:
            from numba.core import event
            with event.trigger_event("numba:compile", data={"dispatcher": None, "args": (), "return_type": None}):
                time.sleep(self.params["compile_s"])
        self.publish(self.keys.stage("compiling"), Ack(frame=msg.frame, stamp=msg.stamp, t=msg.t, worker=self.name))


class StuckStage(Worker):
    """Consumes voxels; its first incarnation gets stuck on frame ``at`` in
    :meth:`stuck_for_good` (a call that never returns, deaf to SIGTERM)."""

    KIND = "stuck"
    ORDER = 3
    CONSUMES = ("voxels",)
    PRODUCES = ("stuck",)
    DEFAULTS = {"at": 10}

    def handle(self, key, msg):
        if self.incarnation == 0 and msg.frame == self.params["at"]:
            self.stuck_for_good()
        self.publish(self.keys.stage("stuck"), Ack(frame=msg.frame, stamp=msg.stamp, t=msg.t, worker=self.name))

    def stuck_for_good(self):
        while True:
            time.sleep(0.1)
