"""A variable length Markov model over cluster labels (Caillette, Galata and Howard, CVIU
2007, §4.2; Ron, Singer and Tishby, Machine Learning 25, 1996, the prediction suffix tree;
the growth criterion as in Galata, Johnson and Hogg, CVIU 81, 2001).

The model is a set of contexts (label strings of length at most ``memory``, the paper's
``w_M``, the most recent label last) with each its next-label distribution. A context
``s = a s'`` (``a`` its oldest label, ``s'`` its suffix, already in the model) joins when it
was seen often enough (``P(s) >= p_min``) and predicts differently enough from ``s'``:

    dH(s) = P(s) sum_k P(k | s) log(P(k | s) / P(k | s')) >= epsilon

(the paper's threshold epsilon; Galata et al.'s weighted Kullback-Leibler gain). Every
suffix of a context is a context (the empty one, the root, always). The output
probabilities are smoothed, ``gamma(s, k) = (1 - K g_min) P(k | s) + g_min`` (Ron et al.'s
gamma_min; K the labels), so no label is impossible.

The model's state after a history is its longest suffix that is a context (the PFSA of the
paper, its states the contexts; :meth:`Vlmm.next_state` is ``tau``, :meth:`Vlmm.gamma` is
``gamma``, the root's distribution ``s``). :meth:`Vlmm.entropy` is the model entropy of Eq. 2,
``H = -(1/n) sum_i log2 gamma(q_i, k_i)`` (bits per label; the paper leaves the base open),
``q_i`` the state before label ``i``.
"""
from __future__ import annotations

from collections import Counter

import numpy as np

__all__ = ["Vlmm", "learn_vlmm"]


class Vlmm:
    """Contexts (tuples of labels, oldest first) and their smoothed next-label distributions."""

    def __init__(self, labels: int, memory: int, contexts: dict[tuple, np.ndarray]):
        self.labels = int(labels)
        self.memory = int(memory)
        self.contexts = contexts     # context -> (labels,) probabilities, each sums to 1

    def state_of(self, history) -> tuple:
        """The longest suffix of ``history`` (labels, oldest first) that is a context."""
        h = tuple(int(k) for k in history)[-self.memory:] if self.memory else ()
        for start in range(len(h) + 1):
            if h[start:] in self.contexts:
                return h[start:]
        return ()

    def next_state(self, state: tuple, label: int) -> tuple:
        """``tau(q, k)``: the state after ``label`` follows state ``state``."""
        return self.state_of(state + (int(label),))

    def gamma(self, state: tuple, label: int | None = None):
        """``gamma(q, k)``: the probability of ``label`` after state ``state`` (all labels'
        with ``label`` None)."""
        p = self.contexts[state]
        return p if label is None else float(p[int(label)])

    def entropy(self, sequences) -> float:
        """Eq. 2 over ``sequences`` (each a sequence of labels): bits per label."""
        total, n = 0.0, 0
        for seq in sequences:
            state = ()
            for k in seq:
                total -= np.log2(self.gamma(state, k))
                n += 1
                state = self.next_state(state, k)
        return total / max(n, 1)

    def to_dict(self) -> dict:
        return {"labels": self.labels, "memory": self.memory,
                "contexts": [{"context": list(c), "p": [round(float(v), 9) for v in p]}
                             for c, p in sorted(self.contexts.items(), key=lambda kv: (len(kv[0]), kv[0]))]}

    @classmethod
    def from_dict(cls, d: dict) -> "Vlmm":
        labels, memory = int(d["labels"]), int(d["memory"])
        contexts = {}
        for e in d["contexts"]:
            c = tuple(int(k) for k in e["context"])
            p = np.asarray(e["p"], float)
            if len(c) > memory or any(not 0 <= k < labels for k in c) or p.shape != (labels,) \
                    or not np.all(p > 0) or abs(p.sum() - 1) > 1e-6:
                raise ValueError(f"VLMM context {list(c)}: not a context of {labels} labels and memory {memory}")
            contexts[c] = p / p.sum()
        if () not in contexts or any(c[1:] not in contexts for c in contexts if c):
            raise ValueError("VLMM: a context without its suffix (or no root)")
        return cls(labels, memory, contexts)


def learn_vlmm(sequences, labels: int, memory: int = 10, epsilon: float = 1e-4, p_min: float = 1e-3,
               g_min: float = 1e-3) -> Vlmm:
    """The VLMM of ``sequences`` of labels ``0..labels-1`` (module docstring): contexts of
    at most ``memory`` labels, grown where the weighted KL gain is at least ``epsilon``
    (nats) and the context's probability at least ``p_min``; ``g_min`` the smoothing."""
    sequences = [[int(k) for k in s] for s in sequences]
    if any(not 0 <= k < labels for s in sequences for k in s):
        raise ValueError(f"labels outside 0..{labels - 1}")
    # counts of every string up to memory + 1 long: its occurrences followed by each label
    follow: dict[tuple, Counter] = {}
    for s in sequences:
        for i, k in enumerate(s):
            for m in range(0, min(memory, i) + 1):
                follow.setdefault(tuple(s[i - m:i]), Counter())[k] += 1
    total = sum(len(s) for s in sequences)

    def dist(c: tuple) -> np.ndarray:
        p = np.zeros(labels)
        for k, n in follow[c].items():
            p[k] = n
        return p / p.sum()

    chosen = {(): dist(())}
    frontier = [()]
    while frontier:
        grown = []
        for s_ in frontier:
            if len(s_) >= memory:
                continue
            for a in range(labels):
                s = (a,) + s_
                if s not in follow:
                    continue
                n_s = sum(follow[s].values())
                if n_s / total < p_min:
                    continue
                p, q = dist(s), dist(s_)
                on = p > 0
                gain = n_s / total * float(np.sum(p[on] * np.log(p[on] / q[on])))
                # a context that adds nothing may still lead to longer ones that do (Ron et al.
                # keep testing the longer strings); it joins only with one of them
                grown.append((s, gain >= epsilon))
        frontier = []
        for s, keep in grown:
            frontier.append(s)
            if keep:
                for m in range(len(s), -1, -1):
                    chosen.setdefault(s[len(s) - m:], dist(s[len(s) - m:]))
    smoothed = {c: (1.0 - labels * g_min) * p + g_min for c, p in chosen.items()}
    return Vlmm(labels, memory, smoothed)
