"""What a worker carries across a restart (the :class:`Restarts` part of the one worker base,
:class:`workers.base.Worker`).

A worker's ledger (frames seen and put out, counts) and the stage's JSON state are saved
to ``<out>/state/<name>.json`` every ``STATE_PERIOD_S``, with an append-only journal of the
frames in between (``<name>.frames``), so a worker killed at any moment is restarted with
exact counts. A stage whose outputs depend on the frames before (a tracker, a filter)
saves its state as named arrays (:meth:`Restarts.state_arrays`, ``<name>.npz``, no pickles),
and its restarted incarnation advances that state through the frames its earlier
incarnation put out after the snapshot (:meth:`Restarts.catch_up`, fed from what is sent
again) instead of skipping them.

Offline, every worker keeps its outputs of the last :data:`REPLAY_FRAMES` frames and sends
them again when a consumer of them comes back from a crash (what was in its inbox died
with it); every worker skips an input (key, sender, epoch, frame) it has handled already.
The newest frame a restarted worker's earlier incarnation put out is put out again: the
journal says "out" when ``put()`` returns, and a worker killed then may not have sent it.
It is worked on anew or, where the snapshot is of that very frame, sent from the outputs
kept with the snapshot; consumers skip it if it had arrived.

A restarted source (the grabber) carries on after the newest frame it put out
(:attr:`Restarts.resume_at`), in a new epoch, so results never hold one frame number twice.
Offline it first puts that frame out again in its earlier incarnation's epoch
(:meth:`Restarts.put_out_again`), for the same reason, and its new epoch waits
:data:`AGAIN_QUIET_S`: the stages follow a new epoch once the old one is quiet.
"""
from __future__ import annotations

import json
import os
import time
from collections import deque
from pathlib import Path

from app.admission import EPOCH_QUIET_S
from app.files import json_entry, read_json_entry, write_atomic, write_json
from app.messages import Message
from app.stats import FrameSet

REPLAY_FRAMES = 16       # offline: a stage's outputs of its last frames, sent again to a consumer that restarted
REPLAY_BYTES = 64 << 20  # ... at most this much of them (HD frames)
REPLAY_DELAY_S = 0.2     # after a restarted consumer's token appears (its subscriptions are declared before)
AGAIN_QUIET_S = 4 * EPOCH_QUIET_S   # a restarted source: its new epoch waits this long after the frame put out again
#: tests only, ``<worker>:<frame>[,...]``: the first incarnation of ``<worker>`` keeps its output of
#: ``<frame>`` off the bus (as if killed between ``put()`` and zenoh sending it) and is killed
#: (SIGKILL) once it has handled that input
FAILPOINT_ENV = "SMARTROOM_LOSE_OUTPUT"


class Restarts:
    """The restart part of :class:`workers.base.Worker` (uses its ledger, log, keys,
    publishers and layout)."""

    def _init_restarts(self) -> None:
        self._journal_fd: int | None = None
        self.ledger.journal = self._journal
        self.incarnation = 0                 # restarts of this worker within the run
        self._replay: dict[int, list[tuple[str, bytes]]] = {}   # offline: frame -> its outputs, oldest first
        self._replay_epochs: dict[int, int] = {}   # offline: frame -> the epoch its outputs are of
        self._replay_bytes = 0
        self._replay_to: set[str] | None = None  # consumers of this worker's outputs
        self.resent = 0                          # messages sent again to restarted consumers
        self._inputs: dict[tuple[str, str, int], FrameSet] = {}  # (key, sender, epoch) -> frames handled
        self._earlier: dict | None = None        # the earlier incarnation's state arrays (earlier_arrays)
        self._snapshot_ms: deque = deque(maxlen=100)
        self._caught_up: list[int] = []         # frames the stage advanced through unpublished (catch_up)
        #: the newest frame an earlier incarnation put out: its outputs may not have left before
        #: it died, so it is put out again (worked on anew, or the outputs kept with the state arrays)
        self._redo: int | None = None
        #: the newest frame put out before this incarnation (-1: none): only frames up to it
        #: can have been put out by an earlier incarnation (this one's own are not repeats)
        self._earlier_newest = -1
        self._redo_outputs: list[tuple[str, bytes]] = []
        self._redo_epoch = 0
        lose = [f for w, _, f in (p.rpartition(":") for p in os.environ.get(FAILPOINT_ENV, "").split(","))
                if w == self.name and f.isdigit()]
        self._lose = int(lose[0]) if lose else None   # FAILPOINT_ENV
        self._killed_after_handle = False
        self.repeats_skipped = 0                 # inputs that arrived again (sent again after a restart)
        self.not_sent_again = 0                  # frames after the restored state nobody sent again (lost_after)
        self.out_epoch: int | None = None        # a source: the epoch of the newest frame it put out

    def lost_after(self, first: int, last: int) -> None:
        """Frames ``first..last`` after this incarnation's restored state never came again
        (a stage before it restarted with it: its outputs of them died with it), so the
        stage carries on without them: counted (``not_sent_again`` in the figures; on a
        recording the launcher reports the run incomplete)."""
        self.not_sent_again += max(0, last - first + 1)

    # -- the stage's state ------------------------------------------------------------
    def extra_state(self) -> dict:
        """Stage state carried to the next incarnation after a crash (JSON-able)."""
        return {}

    def restore_state(self, state: dict) -> None:
        """Take over what :meth:`extra_state` of an earlier incarnation returned."""

    def state_arrays(self) -> dict | None:
        """Stage state carried to the next incarnation as named numpy arrays (filter
        samples, particles: too big or too numeric for the JSON state), saved with the
        state every ``STATE_PERIOD_S`` and whenever the stage calls :meth:`save_arrays`;
        None: nothing new since the last save. No object arrays (loading runs no code).
        Stamped with :meth:`stamp_arrays`, taken over with :meth:`earlier_arrays`."""
        return None

    def stamp_arrays(self, arrays: dict, epoch: int, frame: int, t: float, **stream) -> dict:
        """``arrays`` marked as the state after ``frame`` (time ``t``, s) of ``epoch`` in
        ``stream`` (JSON-able facts the state depends on: grid, parameters), for
        :meth:`earlier_arrays`."""
        arrays["worker"] = json_entry({"epoch": int(epoch), "frame": int(frame), "t": float(t), "stream": stream})
        import numpy as np
        outputs = self._replay.get(int(frame), [])   # offline: put out again if they never left (_put_out_again)
        arrays["worker_outputs"] = json_entry([key for key, _ in outputs])
        for i, (_, payload) in enumerate(outputs):
            arrays[f"worker_output{i}"] = np.frombuffer(payload, dtype=np.uint8)
        return arrays

    @property
    def earlier_pending(self) -> bool:
        """The earlier incarnation's state arrays are still to be taken over."""
        return self._earlier is not None

    def earlier_arrays(self, msg: Message | None, what: str, **stream) -> tuple[dict, dict] | None:
        """The earlier incarnation's :meth:`state_arrays` (once; None after) with their stamp
        (``{"epoch", "frame", "t", "stream"}``) if they belong to ``msg``'s stream: its epoch, the
        same ``stream`` facts, and not ahead of ``msg`` unless ``msg`` was put out by that
        incarnation already. Otherwise one log line saying why and that ``what`` starts
        afresh (``msg`` None: the source restarted), and None."""
        arrays, self._earlier = self._earlier, None
        if arrays is None:
            return None
        try:
            if msg is None:
                raise ValueError("the source restarted (a new epoch)")
            try:
                mine = read_json_entry(arrays, "worker")
                epoch, frame, t, theirs = int(mine["epoch"]), int(mine["frame"]), float(mine["t"]), mine["stream"]
            except (KeyError, ValueError, TypeError, IndexError, AttributeError) as exc:
                raise ValueError(f"no readable stamp ({type(exc).__name__})") from None
            if epoch != msg.epoch or theirs != json.loads(json.dumps(stream)):
                raise ValueError(f"of epoch {epoch}, {theirs}: not this stream's")
            if msg.frame <= frame and msg.frame not in self.ledger.done:
                raise ValueError(f"of frame {frame}, ahead of frame {msg.frame}")
        except ValueError as exc:
            self.log.warning("state arrays %s: %s starts afresh", exc, what)
            return None
        return arrays, {"epoch": epoch, "frame": frame, "t": t, "stream": theirs}

    def catch_up(self, key: str, msg: Message) -> None:
        """An input of a frame an earlier incarnation of this worker put out (sent again
        after the restart): advance the stage's state through it without publishing
        (default: skip it; a stage that advances says so with :meth:`caught_up_on`).
        Called in frame order, before the frames after them."""

    def caught_up_on(self, frame: int) -> None:
        """The stage advanced its state through ``frame`` without publishing it; said in
        one line when it publishes again."""
        self._caught_up.append(frame)

    @property
    def caught_up_frames(self) -> int:
        """Frames caught up on since the stage last published."""
        return len(self._caught_up)

    # -- outputs sent again to a consumer that restarted (offline) ------------------------
    def _keep_for_replay(self, frame: int, epoch: int, key: str, payload: bytes) -> None:
        """Keep the outputs of the last :data:`REPLAY_FRAMES` frames: what was in flight to a
        consumer when it died (its inbox) is lost with it, and is sent again when it is back."""
        self._replay.setdefault(frame, []).append((key, payload))
        self._replay_epochs[frame] = int(epoch)
        self._replay_bytes += len(payload)
        while len(self._replay) > REPLAY_FRAMES or (self._replay_bytes > REPLAY_BYTES and len(self._replay) > 1):
            oldest = next(iter(self._replay))
            self._replay_epochs.pop(oldest, None)
            self._replay_bytes -= sum(len(p) for _, p in self._replay.pop(oldest))

    def _consumers(self) -> set[str]:
        """Workers of the layout that take this worker's outputs (and acknowledge or keep them)."""
        if self._replay_to is None:
            from workers import upstream_of, worker_class
            mine = self.produces(self.spec)
            self._replay_to = {w.name for w in self.layout.workers
                               if w.name != self.name and not worker_class(w.kind).DISPLAY
                               and mine & worker_class(w.kind).consumes(w)
                               and self.name in upstream_of(self.layout, w)}
        return self._replay_to

    def _resend(self, name: str) -> None:
        """``name`` is back after a crash: send the kept outputs again (it skips what its
        earlier incarnation finished; the other consumers skip them as repeats). Where they
        span a restart of the source (two epochs), the newer epoch's follow the older's
        after :data:`AGAIN_QUIET_S`, as the source itself put them out: a stage follows a
        newer epoch only once the current one is quiet (:class:`app.admission.FrameWindow`),
        and ``name``'s fresh window takes the older epoch from its first frames. Nothing is
        put out meanwhile (the lock), so no newer frame overtakes them."""
        time.sleep(REPLAY_DELAY_S)
        with self._publish_lock:
            frames = list(self._replay)
            items = [(self._replay_epochs.get(frame), k, p) for frame in frames for k, p in self._replay[frame]]
            for i, (epoch, key, payload) in enumerate(items):
                if i and epoch != items[i - 1][0]:
                    time.sleep(AGAIN_QUIET_S)
                self._publishers[key].put_payload(payload)
            frames.sort()
        self.resent += len(items)
        if items:
            self.log.info("%s is back: sent frames %d-%d again (%d messages)", name, frames[0], frames[-1], len(items))

    def _repeated(self, key: str, msg: Message) -> bool:
        """This input (key, sender, epoch, frame) was handled already: a stage sent it again
        to a consumer that restarted, and every consumer of that key receives it."""
        ident = (key, getattr(msg, "worker", "") or "", msg.epoch)   # a restarted source may send a frame again
        frames = self._inputs.get(ident)
        if frames is None:
            frames = self._inputs[ident] = FrameSet()
        if not frames.add(msg.frame):
            self.repeats_skipped += 1
            return True
        if getattr(msg, "camera", None) is not None or not self.put_out_before(msg.frame):
            return False         # per-camera inputs are handled one by one (a frame may be out for some cameras)
        self.repeats_skipped += 1
        self._follow_epoch(msg)
        if msg.frame == self._redo:
            self._put_out_again(msg)
        self.catch_up(key, msg)
        return True

    def put_out_before(self, frame: int) -> bool:
        """An earlier incarnation of this worker put ``frame`` out (its ledger comes back from
        the journal): not worked on again. Only the earlier incarnations' frames: a frame this
        incarnation put out may still have inputs to come (a sink that shows each input as it
        comes, the viewer, puts a frame out with its voxels, before its tracks and poses). Except the newest such frame when its outputs were
        not kept with the state arrays: the journal says "put out" when ``put()`` returns, and
        a worker killed then may not have sent it yet; it is worked on again and put out
        again (consumers skip repeats)."""
        return (self.SKIPS_FINISHED and self.incarnation > 0 and frame <= self._earlier_newest
                and frame in self.ledger.done and not (frame == self._redo and not self._redo_outputs))

    def _put_out_again(self, msg: Message) -> None:
        """The outputs of the newest frame put out before the restart, kept with the state
        arrays (the state is of that very frame: it cannot be worked on again)."""
        outputs, self._redo_outputs, self._redo = self._redo_outputs, [], None
        if msg.epoch != self._redo_epoch:
            return               # of another stream
        pubs = [self._publisher(key) for key, _ in outputs]
        with self._publish_lock:
            for pub, (key, payload) in zip(pubs, outputs):
                pub.put_payload(payload)
                if self.lossless:
                    self._keep_for_replay(msg.frame, msg.epoch, key, payload)
        self.log.warning("put out frame %d again from the state arrays (%d messages)", msg.frame, len(outputs))

    # -- a source that restarted ------------------------------------------------------
    @property
    def resume_at(self) -> int | None:
        """The frame a restarted source carries on from: the one after the newest it put out
        (its ledger, with the journal, knows it exactly); None: it put out nothing yet."""
        return self.ledger.newest_out + 1 if self.ledger.newest_out >= 0 else None

    def put_out_again(self, frame: int, epoch: int) -> None:
        """A source: put ``frame`` out again in ``epoch`` (its earlier incarnation's), see
        :meth:`_source_again`. Default: nothing (a source that cannot read a frame again)."""

    def _source_again(self) -> None:
        """Offline, before a restarted source's first frame: the newest frame its earlier
        incarnation put out, again in that incarnation's epoch (a source killed right after
        handing it to the bus may not have sent it; the stages that had it skip it as a
        repeat); then :data:`AGAIN_QUIET_S` for the stages to see the old epoch go quiet."""
        if self.incarnation > 0 and self.out_epoch is not None and self.lossless:
            self.put_out_again(self.ledger.newest_out, self.out_epoch)
            self.sleep(AGAIN_QUIET_S)

    # -- the state files ------------------------------------------------------------
    def _state_path(self) -> Path | None:
        out = self.layout.run.out
        return Path(out) / "state" / f"{self.name}.json" if out else None

    def _save_state(self) -> None:
        """The ledger and the stage's state, every ``STATE_PERIOD_S``; frames seen and
        done in between go to an append-only journal (``<name>.frames``), so a worker
        killed at any moment is restarted with exact frame counts."""
        path = self._state_path()
        if path is None:
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_json(path, {"incarnation": self.incarnation, "ledger": self.ledger.state(),
                              "rejected": self.rejections.figures(), "stage": self.extra_state(),
                              "out_epoch": self.out_epoch}, indent=None)
            if self._journal_fd is None:
                self._journal_fd = os.open(path.with_suffix(".frames"), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
            os.ftruncate(self._journal_fd, 0)   # everything in it is in the state now
        except OSError as exc:   # a full disk must not kill the stage; the recorder reports it
            self.log.debug("cannot save state: %s", exc)
        self.save_arrays()
        self._last_state = time.monotonic()

    def save_arrays(self) -> None:
        """Save :meth:`state_arrays` now (``<out>/state/<name>.npz``, written to a temporary
        file and renamed: a worker killed meanwhile leaves the previous snapshot whole)."""
        path = self._state_path()
        if path is None:
            return
        t0 = time.perf_counter()
        try:
            arrays = self.state_arrays()
            if arrays is None:
                return
            import io

            import numpy as np
            buf = io.BytesIO()
            np.savez(buf, **arrays)
            path.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(path.with_suffix(".npz"), buf.getvalue())
            self._snapshot_ms.append((time.perf_counter() - t0) * 1e3)
        except OSError as exc:   # a full disk must not kill the stage
            self.log.debug("cannot save state arrays: %s", exc)

    def _restore_arrays(self) -> None:
        path = self._state_path()
        path = path.with_suffix(".npz") if path is not None else None
        if path is None or not path.is_file():
            return
        import numpy as np
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except Exception as exc:  # noqa: BLE001 - a damaged file (zip, header, pickled object) of any kind
            self.log.warning("state arrays %s not readable (%s): starting afresh", path.name,
                             str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__)
            return
        self._redo_outputs = self._outputs_of(arrays)
        self._earlier = arrays   # taken over by the stage with its first input (earlier_arrays)

    def _outputs_of(self, arrays: dict) -> list[tuple[str, bytes]]:
        """The outputs kept with the state arrays (taken out of them) if the state is of the
        newest frame put out (:meth:`_put_out_again`); else none."""
        keys = [k for k in arrays if k.startswith("worker_output")]
        entries = {k: arrays.pop(k) for k in keys}
        try:
            stamp = read_json_entry(arrays, "worker")
            names = read_json_entry(entries, "worker_outputs")
            if int(stamp["frame"]) != self._redo or not isinstance(names, list):
                return []
            self._redo_epoch = int(stamp["epoch"])
            outputs = [(str(names[i]), entries[f"worker_output{i}"].tobytes()) for i in range(len(names))]
        except (KeyError, ValueError, TypeError, IndexError, AttributeError):
            return []
        produced = {self.keys.stage(stage) for stage in self.produces(self.spec)
                    if stage not in self.PER_CAMERA}
        return [(k, p) for k, p in outputs if k in produced]

    def _journal(self, kind: str, frame: int) -> None:
        if self._journal_fd is not None:
            try:
                os.write(self._journal_fd, f"{kind}{frame}\n".encode())
            except OSError:
                pass

    def _restore_state(self) -> None:
        path = self._state_path()
        if path is None or not path.is_file():
            return
        try:
            state = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return
        self.incarnation = int(state.get("incarnation", 0)) + 1
        journal = []
        try:
            for line in path.with_suffix(".frames").read_text(encoding="ascii", errors="replace").splitlines():
                if line[:1] in ("i", "o") and line[1:].isdigit():
                    journal.append((line[0], int(line[1:])))
        except OSError:
            pass
        self.ledger.restore(state.get("ledger") or {}, journal)
        self._earlier_newest = self.ledger.newest_out
        if self.ledger.newest_out >= 0 and self.PRODUCES:   # a sink's outputs are its files
            self._redo = self.ledger.newest_out
            epoch = state.get("out_epoch")
            if isinstance(epoch, int) and not isinstance(epoch, bool):
                self.out_epoch = epoch
        self.rejections.restore(state.get("rejected"))
        self.ledger.bad_messages = self.rejections.total
        self.restore_state(state.get("stage") or {})
        self._restore_arrays()
        self.log.warning("restarted (incarnation %d): carrying on from frame %d", self.incarnation,
                         self.ledger.last_frame)
