"""A deliberately slow stage for tests (loaded as a plugin kind: ``tests.slow_stage:SlowStage``)."""
import time

from app.messages import Ack
from workers.base import Worker


class SlowStage(Worker):
    KIND = "slow"
    ORDER = 2
    CONSUMES = ("mask",)
    PRODUCES = ("slow",)
    DEFAULTS = {"delay_ms": 100.0, "flush_ms": 0.0}   # per mask; once its input has ended

    def handle(self, key, msg):
        time.sleep(self.params["delay_ms"] / 1e3)
        self.publish(self.keys.stage("slow"), Ack(frame=msg.frame, stamp=msg.stamp, t=msg.t, worker=self.name))

    def flush(self):
        time.sleep(self.params["flush_ms"] / 1e3)
