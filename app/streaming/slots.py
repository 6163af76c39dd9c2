"""Tracked people in a fixed number of slots (a VMC receiver per slot, an LSL stream's
channel groups): a person keeps their slot while tracked, a new one takes the lowest
free slot, and people beyond the slots are left out (counted)."""
from __future__ import annotations

__all__ = ["Slots"]


class Slots:
    def __init__(self, count: int):
        self.count = int(count)
        self.of: dict[int, int] = {}     # track -> slot
        self.left_out = 0                # person-frames that found no free slot

    def assign(self, tracks) -> list[tuple[int, int]]:
        """``(slot, index in tracks)`` for this frame's people that have a slot; the
        tracks no longer present free theirs first."""
        present = [int(t) for t in tracks]
        self.of = {t: s for t, s in self.of.items() if t in set(present)}
        taken = set(self.of.values())
        out = []
        for k, t in enumerate(present):
            if t not in self.of:
                free = next((s for s in range(self.count) if s not in taken), None)
                if free is None:
                    self.left_out += 1
                    continue
                self.of[t] = free
                taken.add(free)
            out.append((self.of[t], k))
        return sorted(out)
