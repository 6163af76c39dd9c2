"""Recorder: writes the contract's result files (CONTRACT §2).

``tracks.jsonl`` and ``poses.jsonl`` are written line by line (each line reaches the
operating system at once) into ``.partial`` files and renamed at the true end of the
run, in frame order; a file exists only when the layout has a stage that produces it.
With ``voxels: true`` the reconstruction is kept too, in ``voxels.bin`` (see
:mod:`app.results`), for evaluation and replay.

Results survive their writer (DESIGN §5): a restarted recorder appends to what its
earlier incarnation wrote, after cutting a record the crash left half-written, and
skips frames already written (a restarted source may send a frame again). The files
are renamed only when the stream has truly ended. A full disk stops the recorder
with a one-line error; its files stay valid up to the last complete record.

``stats.json`` is the launcher's (it knows about restarts and failures).
"""
from __future__ import annotations

import errno
import json
import os
from pathlib import Path

from app.errors import InputError
from app.files import append_record, partial_path
from app.messages import JOINTS, Poses, Tracks, Voxels
from app.pose_shares import SharedPoses
from app.results import VoxelWriter
from app.stats import FrameSet
from workers import producers_of, worker_class
from workers.base import Worker


def _r(v, nd=4):
    return [round(float(x), nd) for x in v]


class JsonLinesWriter:
    """Lines appended to ``<name>.partial`` (resumed after a crash), renamed, sorted by
    frame if needed, by :meth:`close` with ``final=True``."""

    def __init__(self, path: Path):
        self.path = path
        self.tmp = partial_path(path)
        self.frames = FrameSet()   # one byte a frame: days of frames stay small
        self.ordered = True
        self.last_frame = -1
        keep = 0
        if self.tmp.exists():   # an earlier incarnation's lines: keep every complete one
            with open(self.tmp, "rb") as fh:
                for line in fh:
                    if not line.endswith(b"\n"):
                        break
                    try:
                        frame = json.loads(line)["frame"]
                    except (ValueError, KeyError, TypeError):
                        break
                    self._note(frame)
                    keep += len(line)
            os.truncate(self.tmp, keep)
        self.fh = open(self.tmp, "ab", buffering=0)
        self.size = keep   # bytes of complete lines

    def _note(self, frame: int) -> None:
        if frame <= self.last_frame:
            self.ordered = False
        self.last_frame = max(self.last_frame, frame)
        self.frames.add(frame)

    def write(self, frame: int, record: dict) -> bool:
        """Append one frame's record; False when that frame is already in the file."""
        if frame in self.frames:
            return False
        line = (json.dumps(record, separators=(",", ":")) + "\n").encode()
        # straight to the operating system; a full disk leaves the file at its last whole line
        self.size = append_record(self.fh, line, self.size, self.tmp)
        self._note(frame)
        return True

    def close(self, final: bool) -> None:
        self.fh.close()
        if not final:
            return
        if not self.ordered:
            with open(self.tmp, encoding="utf-8") as fh:
                rows = {json.loads(line)["frame"]: line for line in fh if line.strip()}
            with open(self.tmp, "w", encoding="utf-8") as fh:
                fh.writelines(rows[f] for f in sorted(rows))
        os.replace(self.tmp, self.path)


class Recorder(Worker):
    KIND = "recorder"
    CONSUMES = ("tracks", "poses", "stats")
    ACCEPTS = (Tracks, Poses, Voxels)
    INBOX_DEPTH = 1000   # keep results rather than drop them (bounded all the same)
    DEFAULTS = {
        "voxels": False,   # also keep every frame's voxels in voxels.bin
    }

    KEEPS_RESULTS = True   # offline, the source waits while it restarts (see Worker.KEEPS_RESULTS)
    SKIPS_FINISHED = False  # a frame's tracks may be written and its poses not: the files know

    @classmethod
    def consumes(cls, spec) -> set[str]:
        """The result streams, and the voxels with ``voxels: true``."""
        return super().consumes(spec) | ({"voxels"} if spec.params.get("voxels") else set())

    def setup(self) -> None:
        if not self.layout.run.out:
            raise InputError("the recorder needs an output folder (--out)")
        self.out = Path(self.layout.run.out)
        self.out.mkdir(parents=True, exist_ok=True)
        produced = {s for w in self.layout.workers for s in worker_class(w.kind).produces(w)}
        self.tracks = JsonLinesWriter(self.out / "tracks.jsonl") if "tracks" in produced else None
        self.poses = JsonLinesWriter(self.out / "poses.jsonl") if "poses" in produced else None
        self.shares = SharedPoses(producers_of(self.layout, "poses"))   # several pose workers: one line a frame
        self.voxels = VoxelWriter(self.out / "voxels.bin") if self.params["voxels"] and "voxels" in produced else None
        self.duplicates = 0
        resumed = [f.path.name for f in self._files() if f.frames]
        if resumed:
            self.log.warning("carrying on %s after a restart", ", ".join(resumed))

    def _files(self):
        return [f for f in (getattr(self, "tracks", None), getattr(self, "poses", None),
                            getattr(self, "voxels", None)) if f is not None]

    def handle(self, key: str, msg) -> None:
        if isinstance(msg, Poses):
            for joined in self.shares.add(msg):
                self._record(joined)
        else:
            self._record(msg)

    def _record(self, msg) -> None:
        try:
            written = self._write(msg)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise InputError(f"{self.out}: disk full after frame {self.ledger.newest_out}; "
                                 "the result files are valid up to it") from None
            raise
        if written:
            self.ledger.emitted(msg.frame, msg.stamp)
        elif written is False:
            self.duplicates += 1

    def _write(self, msg) -> bool | None:
        if isinstance(msg, Tracks) and self.tracks is not None:
            return self.tracks.write(msg.frame, {
                "frame": int(msg.frame), "t": round(msg.t, 4),
                "tracks": [{"id": int(i), "position": _r(p)} for i, p in zip(msg.ids, msg.positions)]})
        if isinstance(msg, Poses) and self.poses is not None:
            poses = []
            for k, track in enumerate(msg.tracks):
                poses.append({
                    "track": int(track),
                    "joints": {j: _r(msg.joints[k, n]) for n, j in enumerate(JOINTS)},
                    "active": {j: bool(msg.active[k, n]) for n, j in enumerate(JOINTS)}})
            return self.poses.write(msg.frame, {"frame": int(msg.frame), "t": round(msg.t, 4), "poses": poses})
        if isinstance(msg, Voxels) and self.voxels is not None:
            return self.voxels.write(msg)
        return None

    def extra_figures(self) -> dict:
        shares = getattr(self, "shares", None)
        return {"duplicates_skipped": getattr(self, "duplicates", 0),
                "pose_frames_partial": shares.partial if shares else 0,
                "files": {f.path.name: len(f.frames) for f in self._files()}}

    def close(self) -> None:
        if getattr(self, "shares", None) is not None and self.poses is not None:
            for joined in self.shares.flush():   # what the last frames' pose workers sent
                try:
                    self._record(joined)
                except InputError as exc:
                    self.log.error("%s", exc)
                    break
        for f in self._files():
            try:
                f.close(final=self.input_ended)
            except OSError as exc:
                self.log.error("%s: %s", f.path, exc)
