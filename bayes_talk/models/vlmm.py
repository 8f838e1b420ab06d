r"""Variable-length Markov model (VLMM) over frame-level phone labels.

deena2010 §2.2, §4.1, §4.2.1; Ron, Singer & Tishby (1996), "The power of amnesia".
Where the paper leaves a choice, the reading taken is stated below; ``docs/vlmm.md`` is the
long-form description with worked examples.

Tokens and states
-----------------
Tokens are *frame-level* phone labels (25 Hz), e.g. ``"m"``, ``"aa"``, ``"sil"``. A VLMM
state is a context: a tuple of at most ``L = max_memory`` labels, oldest first, e.g.
``("m", "aa", "aa", "aa", "aa")``. Its memory ``M`` is its length in frames. The empty
tuple ``()`` is the start state only; it is never the state of a frame.

Prediction suffix tree (training, deena2010 §2.2)
-------------------------------------------------
Every context ``w`` with ``1 <= |w| <= L`` that occurs in the training sequences is a node.
For a sequence ``l_1..l_T`` an occurrence of ``w`` *ending at frame t* is
``l_{t-|w|+1}..l_t = w``. Counts:

* ``N(w)`` — occurrences of ``w`` (at every position, including at the end of a sequence);
* ``N(w, σ')`` — occurrences of ``w`` immediately followed by ``σ'`` (``t < T``). An
  occurrence that ends on the last frame of a sequence has no next token: it counts in
  ``N(w)`` but in no ``N(w, σ')``.

Estimates (plain relative frequencies, no smoothing)::

    P̂(σ'|w) = N(w, σ') / Σ_ρ N(w, ρ)                      (undefined if w was never followed)
    P̂(w)    = N(w) / Σ_s max(0, T_s − |w| + 1)              (frequency among windows of length |w|)

The parent of a node ``σw`` is its suffix ``w`` (the earliest label dropped). A node
``σw`` (``|σw| >= 2``) *passes* if ``N(σw) >= min_count`` and its weighted KL gain
(deena2010 eq. 13)::

    ΔH(σw, w) = P̂(σw) · Σ_σ' P̂(σ'|σw) · log( P̂(σ'|σw) / P̂(σ'|w) )        (natural log)

is ``>= epsilon``; a node that was never followed by a token (it only occurs at sequence
ends) has ``ΔH = 0``. Pruning is bottom-up as in Ron et al.: a node is kept if it passes
*or if any longer context extending it to the left is kept*, so the kept tree is suffix
closed (a node whose descendants survive is kept even when its own gain is small).
Single labels are always kept (memory >= 1).

PFSA (Ron et al.'s construction)
--------------------------------
``M = (Q, Σ, τ, γ, s)`` (deena2010 §2.2):

* ``Q`` — kept contexts, every single label of the alphabet, and the "missing" contexts
  that make the transition function exact: ``Q`` is closed under taking contiguous
  substrings (suffix closure from the bottom-up pruning, plus prefix closure: if ``vσ``
  is a state then so is ``v``). With this closure the PFSA state reached after any history
  ``h`` equals the longest suffix of ``h`` that is in ``Q`` (proof in ``docs/vlmm.md``).
* ``τ(q, σ)`` — the longest suffix of ``qσ`` that is in ``Q``.
* ``γ(q, σ) = P̂(σ|q)`` from ``q``'s own counts, unsmoothed; a transition ``q --σ-->``
  exists only if ``N(q, σ) > 0`` (σ was seen after ``q`` in training).
* ``s(σ)`` — fraction of training sequences whose first label is ``σ``; from the start
  state ``()`` the label ``σ`` leads to ``(σ,)``.

Traversal and resets (§4.2.1)
-----------------------------
From the start state, for each frame label ``l_t``: if the current state ``q`` has a
transition on ``l_t`` go to ``τ(q, l_t)``; otherwise *reset*: go back to the start state,
forget all memory, and consume ``l_t`` from there, landing in ``(l_t,)``. The first frame
is always consumed from the start state (``(l_1,)``, even if ``s(l_1) = 0``). Since
``|τ(q, σ)| <= |q| + 1`` and the start state has memory 0, the memory of the state after
frame ``t`` never exceeds the number of frames consumed since the last reset, and the
state is always a suffix of those frames. Labels never seen in training raise a
ValueError, or (``unknown="sil"``) are replaced by ``"sil"`` first.

This module stays above ~400 lines because a fifth of it is this description and the rest
is one class: fitting, traversal, segmentation, sampling and persistence all walk the same
prediction suffix tree.
"""
from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np

from bayes_talk.base.errors import not_fitted
from bayes_talk.base.files import check_format, write_text

__all__ = ["FORMAT_VERSION", "START", "VLMM", "Segment", "State"]

State = tuple[str, ...]
#: The start state (empty context). Never the state of a frame.
START: State = ()
#: Version of the JSON save format written by :meth:`VLMM.to_dict`.
FORMAT_VERSION = 1
_FORMAT_NAME = "bayes_talk.VLMM"

UnknownPolicy = Literal["error", "sil"]
ResetScore = Literal["unigram", "forbid"]


class Segment(NamedTuple):
    """A run of frames ``start <= t < stop`` (half-open) assigned to VLMM ``state``."""

    state: State
    start: int
    stop: int


def _check_labels(labels: Any, what: str) -> list[str]:
    if isinstance(labels, str) or not isinstance(labels, Sequence):
        raise ValueError(  # noqa: TRY004 - package convention: bad input is a ValueError
            f"{what} must be a list of label strings, got {type(labels).__name__}"
        )
    out = list(labels)
    if not out:
        raise ValueError(f"{what} is empty; a label sequence needs at least one frame")
    for t, lab in enumerate(out):
        if not isinstance(lab, str) or not lab:
            raise ValueError(f"{what}: frame {t} has label {lab!r}; labels must be non-empty strings")
    return out


class VLMM:
    r"""Variable-length Markov model over frame labels, as a PFSA (deena2010 §2.2).

    Parameters
    ----------
    max_memory : ``L``, the longest context in frames (deena2010's states reach 5–6
        frames, e.g. "m aa aa aa aa"). Default 5.
    epsilon : threshold on the weighted KL gain ΔH of eq. 13 (natural log). A node with
        ``ΔH < epsilon`` is pruned unless a longer context below it survives. Default
        ``2e-4``: under the null hypothesis that ``σw`` predicts like ``w``,
        ``2·N(σw)·KL ≈ χ²_{k−1}`` (k = number of distinct next labels), so
        ``ΔH ≈ χ²_{k−1} / (2·N_windows)``; with ~250 utterances × ~75 frames
        (N ≈ 19 000 windows) and k − 1 ≈ 3 the 95 % point of that noise is ≈ 2e-4.
        Scale it by ``19000 / N`` for other corpus sizes (see docs/vlmm.md).
    min_count : minimum number of occurrences ``N(σw)`` for a context of length >= 2 to
        pass. Default 10: every state of the switching model trains an SGPDM on its
        occurrences, and fewer than ~10 subsequences do not constrain its hyperparameters.

    After :meth:`fit`, ``states_`` lists ``Q`` (start state excluded) in a fixed order
    (by memory, then lexicographically); :meth:`state_id` maps a state to its index.
    """

    def __init__(self, max_memory: int = 5, epsilon: float = 2e-4, min_count: int = 10) -> None:
        if isinstance(max_memory, bool) or not isinstance(max_memory, (int, np.integer)) or max_memory < 1:
            raise ValueError(f"max_memory must be an integer >= 1, got {max_memory!r}")
        if isinstance(epsilon, bool) or not isinstance(epsilon, (int, float, np.floating, np.integer)):
            raise ValueError(f"epsilon must be a real number >= 0, got {epsilon!r}")  # noqa: TRY004
        if not math.isfinite(float(epsilon)) or float(epsilon) < 0:
            raise ValueError(f"epsilon must be finite and >= 0, got {epsilon!r}")
        if isinstance(min_count, bool) or not isinstance(min_count, (int, np.integer)) or min_count < 1:
            raise ValueError(f"min_count must be an integer >= 1, got {min_count!r}")
        self.max_memory = int(max_memory)
        self.epsilon = float(epsilon)
        self.min_count = int(min_count)
        self._fitted = False

    # ------------------------------------------------------------------ fitting
    def fit(self, sequences: Iterable[Sequence[str]]) -> VLMM:
        """Build the prediction suffix tree, prune it (eq. 13) and convert it to a PFSA.

        ``sequences`` is a list of frame-label sequences (lists of strings). Returns self.
        """
        if isinstance(sequences, str) or not isinstance(sequences, Iterable):
            raise ValueError(  # noqa: TRY004
                "sequences must be a list of label sequences (lists of strings)"
            )
        seqs = [_check_labels(s, f"training sequence {i}") for i, s in enumerate(sequences)]
        if not seqs:
            raise ValueError("sequences is empty; fit needs at least one label sequence")
        L = self.max_memory

        # --- counts N(w) and N(w, σ') for every context 1 <= |w| <= L
        occ: Counter[State] = Counter()
        nxt: dict[State, Counter[str]] = {}
        for seq in seqs:
            T = len(seq)
            for t in range(T):
                follower = seq[t + 1] if t + 1 < T else None
                for k in range(1, min(L, t + 1) + 1):
                    w = tuple(seq[t - k + 1 : t + 1])
                    occ[w] += 1
                    if follower is not None:
                        nxt.setdefault(w, Counter())[follower] += 1
        windows = {k: sum(max(0, len(s) - k + 1) for s in seqs) for k in range(1, L + 1)}

        # --- eq. 13 gain of each node of length >= 2 over its parent (suffix)
        delta_h: dict[State, float] = {}
        for w in occ:
            if len(w) >= 2:
                delta_h[w] = self._delta_h(w, occ, nxt, windows)

        # --- bottom-up pruning: keep passing nodes and every suffix (ancestor) of them
        kept: set[State] = set()
        for w, dh in delta_h.items():
            if occ[w] >= self.min_count and dh >= self.epsilon:
                for j in range(len(w) - 1):  # w itself and its suffixes of length >= 2
                    kept.add(w[j:])

        # --- PFSA state set: substring closure of kept contexts, plus all single labels
        alphabet = sorted({lab for s in seqs for lab in s})
        Q: set[State] = {(a,) for a in alphabet}
        for w in kept:
            n = len(w)
            for i in range(n):
                for j in range(i + 1, n + 1):
                    Q.add(w[i:j])

        start_counts = Counter(s[0] for s in seqs)
        self._set_model(
            alphabet=alphabet,
            counts={q: occ[q] for q in Q},
            next_counts={q: dict(nxt.get(q, {})) for q in Q},
            in_tree={q: (len(q) == 1 or q in kept) for q in Q},
            delta_h={q: delta_h[q] for q in Q if len(q) >= 2},
            start_counts=dict(start_counts),
            windows=windows,
            n_sequences=len(seqs),
        )
        # occupancy of each state on the training data (summary(), switching-model budgets)
        occupancy: Counter[State] = Counter()
        for seq in seqs:
            occupancy.update(self._traverse(seq)[0])
        self.occupancy_ = {q: int(occupancy.get(q, 0)) for q in self.states_}
        return self

    @staticmethod
    def _delta_h(
        w: State, occ: dict[State, int], nxt: dict[State, Counter[str]], windows: dict[int, int]
    ) -> float:
        """ΔH(σw, w) of eq. 13 for node ``w`` (= σw) over its parent ``w[1:]``."""
        child = nxt.get(w)
        if not child:
            return 0.0
        parent = nxt[w[1:]]  # every follower of σw also follows w
        n_c = sum(child.values())
        n_p = sum(parent.values())
        kl = 0.0
        for sym, c in child.items():
            p_c = c / n_c
            kl += p_c * math.log(p_c / (parent[sym] / n_p))
        p_w = occ[w] / windows[len(w)]
        return max(0.0, p_w * kl)  # KL >= 0; clip round-off

    def _set_model(
        self,
        *,
        alphabet: list[str],
        counts: dict[State, int],
        next_counts: dict[State, dict[str, int]],
        in_tree: dict[State, bool],
        delta_h: dict[State, float],
        start_counts: dict[str, int],
        windows: dict[int, int],
        n_sequences: int,
    ) -> None:
        self.alphabet_: tuple[str, ...] = tuple(alphabet)
        self.states_: list[State] = sorted(counts, key=lambda q: (len(q), q))
        self._index: dict[State, int] = {q: i for i, q in enumerate(self.states_)}
        self.counts_ = counts
        self.next_counts_ = next_counts
        self.in_tree_ = in_tree
        self.delta_h_ = delta_h
        self.start_counts_ = start_counts
        self.windows_ = windows
        self.n_sequences_ = n_sequences
        self.n_frames_ = windows[1]
        Qset = set(self.states_)
        # transitions: q -> {σ: (τ(q, σ), γ(q, σ))}, only where N(q, σ) > 0
        self._trans: dict[State, dict[str, tuple[State, float]]] = {}
        for q in self.states_:
            nc = next_counts[q]
            tot = sum(nc.values())
            row: dict[str, tuple[State, float]] = {}
            for sym in sorted(nc):
                cand = q + (sym,)
                for k in range(min(len(cand), self.max_memory), 0, -1):
                    if cand[-k:] in Qset:
                        row[sym] = (cand[-k:], nc[sym] / tot)
                        break
            self._trans[q] = row
        n0 = sum(start_counts.values())
        self._start = {sym: start_counts[sym] / n0 for sym in sorted(start_counts)}
        self._unigram = {a: counts[(a,)] / self.n_frames_ for a in alphabet}
        self._fitted = True

    # ------------------------------------------------------------------ accessors
    def _require_fitted(self) -> None:
        if not self._fitted:
            raise not_fitted(self, "call fit(sequences) first")

    @property
    def n_states(self) -> int:
        """|Q|, the number of PFSA states (start state excluded)."""
        self._require_fitted()
        return len(self.states_)

    @property
    def state_index(self) -> dict[State, int]:
        """Mapping state -> integer id in ``0..n_states-1`` (order of ``states_``)."""
        self._require_fitted()
        return dict(self._index)

    def state_id(self, state: Sequence[str]) -> int:
        """Integer id of ``state``; ValueError if it is not a state of the PFSA."""
        self._require_fitted()
        q = tuple(state)
        if q not in self._index:
            raise ValueError(f"{' '.join(q)!r} is not a state of this VLMM")
        return self._index[q]

    def transition(self, state: Sequence[str], label: str) -> tuple[State, float] | None:
        """``(τ(q, σ), γ(q, σ))`` or None when σ was never seen after q.

        ``state=()`` is the start state: it moves to ``(σ,)`` with probability ``s(σ)``.
        """
        self._require_fitted()
        q = tuple(state)
        if q == START:
            return ((label,), self._start[label]) if label in self._start else None
        if q not in self._trans:
            raise ValueError(f"{' '.join(q)!r} is not a state of this VLMM")
        return self._trans[q].get(label)

    @property
    def start_distribution(self) -> dict[str, float]:
        """``s(σ)``: fraction of training sequences starting with σ."""
        self._require_fitted()
        return dict(self._start)

    # ------------------------------------------------------------------ traversal
    def _map_unknown(self, labels: Sequence[str], unknown: str) -> list[str]:
        labs = _check_labels(labels, "labels")
        if unknown not in ("error", "sil"):
            raise ValueError(f"unknown must be 'error' or 'sil', got {unknown!r}")
        known = set(self.alphabet_)
        bad = sorted({x for x in labs if x not in known})
        if not bad:
            return labs
        if unknown == "error":
            raise ValueError(
                f"labels never seen in VLMM training: {bad}; map them to known labels first "
                f"or pass unknown='sil'"
            )
        if "sil" not in known:
            raise ValueError(f"unknown='sil' but 'sil' was not in the training labels (unseen: {bad})")
        return [x if x in known else "sil" for x in labs]

    def _traverse(self, labs: list[str]) -> tuple[list[State], list[bool]]:
        """PFSA walk; returns per-frame states and per-frame 'consumed from start' flags."""
        states: list[State] = []
        from_start: list[bool] = []
        q: State = START
        for lab in labs:
            step = self._trans[q].get(lab) if q != START else None
            if step is None:  # start of sequence, or reset: forget memory
                q = (lab,)
                from_start.append(True)
            else:
                q = step[0]
                from_start.append(False)
            states.append(q)
        return states, from_start

    def traverse(
        self, labels: Sequence[str], unknown: UnknownPolicy = "error"
    ) -> tuple[list[State], list[int]]:
        """States of every frame and the frames where the walk reset to the start state.

        Returns ``(states, resets)``: ``states[t]`` is the state after consuming frame t
        (a context ending in ``l_t``); ``resets`` lists the frames ``t > 0`` at which no
        transition existed, so the walk restarted from the start state.
        """
        self._require_fitted()
        labs = self._map_unknown(labels, unknown)
        states, from_start = self._traverse(labs)
        return states, [t for t, f in enumerate(from_start) if f and t > 0]

    def states(self, labels: Sequence[str], unknown: UnknownPolicy = "error") -> list[State]:
        """State ``π_t`` after each frame (deena2010 §4.2.1 traversal, with resets)."""
        return self.traverse(labels, unknown)[0]

    def state_ids(self, labels: Sequence[str], unknown: UnknownPolicy = "error") -> list[int]:
        """Integer ids of :meth:`states`."""
        return [self._index[q] for q in self.states(labels, unknown)]

    def segment(self, labels: Sequence[str], unknown: UnknownPolicy = "error") -> list[Segment]:
        """Non-overlapping segmentation by backtracking (deena2010 §4.2.1).

        With ``t = T−1`` (0-based last frame): the state ``π_t`` claims the
        ``M = |π_t|`` frames ``t−M+1..t``; continue at ``t ← t−M`` until ``t < 0``
        (claims are clipped at frame 0, which cannot happen because memory never exceeds
        the frames since the last reset). Returned in frame order; covers every frame once.
        Each segment's labels equal its state's context.
        """
        states = self.states(labels, unknown)
        segs: list[Segment] = []
        t = len(states) - 1
        while t >= 0:
            q = states[t]
            start = max(0, t - len(q) + 1)
            segs.append(Segment(q, start, t + 1))
            t = start - 1
        segs.reverse()
        return segs

    def training_subsequences(
        self, labels: Sequence[str], unknown: UnknownPolicy = "error"
    ) -> list[Segment]:
        """One training subsequence per frame (deena2010 §4.1).

        For every frame t with state π: the ``M_π`` frames ending at t,
        ``Segment(π, t−M_π+1, t+1)``. They overlap across states by design.
        """
        states = self.states(labels, unknown)
        return [Segment(q, t - len(q) + 1, t + 1) for t, q in enumerate(states)]

    # ------------------------------------------------------------------ probability
    def log_prob(
        self,
        labels: Sequence[str],
        unknown: UnknownPolicy = "error",
        reset: ResetScore = "unigram",
    ) -> float:
        r"""Log-probability of a label sequence under the PFSA (natural log).

            ln P(l_1..l_T) = ln s(l_1) + Σ_{t≥2} ln γ(π_{t−1}, l_t)

        A frame the walk cannot take (no transition from ``π_{t−1}``, or ``s(l_1) = 0``
        at the first frame) is a reset. ``reset="unigram"`` scores it with the frame
        frequency ``P̂(l_t) = N(l_t) / N_frames`` and continues from ``(l_t,)`` — finite
        for any sequence over the alphabet, but not a normalised distribution once resets
        occur (γ already sums to one over the seen labels). ``reset="forbid"`` returns
        ``-inf`` at the first reset.
        """
        self._require_fitted()
        if reset not in ("unigram", "forbid"):
            raise ValueError(f"reset must be 'unigram' or 'forbid', got {reset!r}")
        labs = self._map_unknown(labels, unknown)
        total = 0.0
        q: State = START
        for lab in labs:
            if q == START:
                p = self._start.get(lab)
                step = ((lab,), p) if p is not None else None
            else:
                step = self._trans[q].get(lab)
            if step is None:
                if reset == "forbid":
                    return -math.inf
                total += math.log(self._unigram[lab])
                q = (lab,)
            else:
                q, p = step
                total += math.log(p)
        return total

    def sample(self, n: int, rng: np.random.Generator | int | None = None) -> list[str]:
        """Draw ``n`` frame labels from the PFSA.

        Starts with ``s``; from state q draws σ ~ γ(q, ·) and moves to τ(q, σ). A state
        with no outgoing transition (its context was only ever seen at the end of a
        training sequence) ends an utterance: the next label is drawn from ``s`` again,
        as a new utterance. ``rng`` is a numpy Generator or an integer seed.
        """
        self._require_fitted()
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"n must be an integer >= 0, got {n!r}")
        if rng is None or isinstance(rng, (int, np.integer)):
            rng = np.random.default_rng(rng)
        elif not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng must be a numpy Generator or an int seed, got {type(rng).__name__}")
        out: list[str] = []
        q: State = START
        start_syms = list(self._start)
        start_p = np.array([self._start[s] for s in start_syms])
        for _ in range(int(n)):
            row = self._trans[q] if q != START else {}
            if row:
                syms = list(row)
                p = np.array([row[s][1] for s in syms])
                sym = syms[int(rng.choice(len(syms), p=p / p.sum()))]
                q = row[sym][0]
            else:
                sym = start_syms[int(rng.choice(len(start_syms), p=start_p / start_p.sum()))]
                q = (sym,)
            out.append(sym)
        return out

    # ------------------------------------------------------------------ reporting
    def summary(self, top: int = 10) -> str:
        """Human-readable summary: states, memory histogram, most occupied states."""
        self._require_fitted()
        hist = Counter(len(q) for q in self.states_)
        n_tree = sum(1 for q in self.states_ if self.in_tree_[q])
        lines = [
            f"VLMM(max_memory={self.max_memory}, epsilon={self.epsilon:g}, min_count={self.min_count})",
            (
                f"trained on {self.n_sequences_} sequences, {self.n_frames_} frames, "
                f"{len(self.alphabet_)} labels"
            ),
            (
                f"{self.n_states} states ({n_tree} from the pruned tree, "
                f"{self.n_states - n_tree} added for closure)"
            ),
            "memory histogram: "
            + ", ".join(f"M={m}: {hist[m]}" for m in range(1, self.max_memory + 1)),
            "most frequent states (training frames in state):",
        ]
        ranked = sorted(self.states_, key=lambda q: (-self.occupancy_[q], -len(q), q))
        for q in ranked[:top]:
            lines.append(f"  {' '.join(q):<30s} {self.occupancy_[q]}")
        longest = sorted(
            (q for q in self.states_ if len(q) >= 2),
            key=lambda q: (-len(q), -self.occupancy_[q], q),
        )
        if longest:
            lines.append("longest-memory states:")
            for q in longest[:top]:
                lines.append(f"  {' '.join(q):<30s} {self.occupancy_[q]}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        fitted = f", n_states={len(self.states_)}" if self._fitted else ""
        return (
            f"VLMM(max_memory={self.max_memory}, epsilon={self.epsilon!r}, "
            f"min_count={self.min_count}{fitted})"
        )

    # ------------------------------------------------------------------ persistence
    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable description (format ``bayes_talk.VLMM`` version 1)."""
        self._require_fitted()
        return {
            "format": _FORMAT_NAME,
            "version": FORMAT_VERSION,
            "params": {
                "max_memory": self.max_memory,
                "epsilon": self.epsilon,
                "min_count": self.min_count,
            },
            "alphabet": list(self.alphabet_),
            "n_sequences": self.n_sequences_,
            "windows": [self.windows_[k] for k in range(1, self.max_memory + 1)],
            "start_counts": dict(sorted(self.start_counts_.items())),
            "states": [
                {
                    "context": list(q),
                    "count": self.counts_[q],
                    "next_counts": dict(sorted(self.next_counts_[q].items())),
                    "in_tree": self.in_tree_[q],
                    "delta_h": self.delta_h_.get(q),
                    "occupancy": self.occupancy_[q],
                }
                for q in self.states_
            ],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> VLMM:
        """Inverse of :meth:`to_dict`; ValueError on a wrong format, version or content."""
        check_format(d, _FORMAT_NAME, FORMAT_VERSION, "saved VLMM")
        try:
            p = d["params"]
            model = cls(p["max_memory"], p["epsilon"], p["min_count"])
            L = model.max_memory
            alphabet = [str(a) for a in d["alphabet"]]
            windows = {k + 1: int(v) for k, v in enumerate(d["windows"])}
            if len(windows) != L:
                raise ValueError(f"'windows' has {len(windows)} entries, expected max_memory={L}")
            counts: dict[State, int] = {}
            next_counts: dict[State, dict[str, int]] = {}
            in_tree: dict[State, bool] = {}
            delta_h: dict[State, float] = {}
            occupancy: dict[State, int] = {}
            for e in d["states"]:
                q = tuple(str(x) for x in e["context"])
                if not 1 <= len(q) <= L:
                    raise ValueError(f"state {q} has memory outside 1..{L}")
                counts[q] = int(e["count"])
                next_counts[q] = {str(k): int(v) for k, v in e["next_counts"].items()}
                in_tree[q] = bool(e["in_tree"])
                if len(q) >= 2:
                    delta_h[q] = float(e["delta_h"])
                occupancy[q] = int(e["occupancy"])
            start_counts = {str(k): int(v) for k, v in d["start_counts"].items()}
            n_sequences = int(d["n_sequences"])
        except (KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"malformed saved VLMM: {exc!r}") from exc
        missing = [a for a in alphabet if (a,) not in counts]
        if missing or not start_counts:
            raise ValueError(f"malformed saved VLMM: single-label states missing for {missing}")
        known = set(alphabet)
        for q, nc in next_counts.items():
            if any(x not in known for x in q) or any(k not in known for k in nc):
                raise ValueError(f"malformed saved VLMM: state {q} uses a label outside the alphabet")
        model._set_model(
            alphabet=alphabet,
            counts=counts,
            next_counts=next_counts,
            in_tree=in_tree,
            delta_h=delta_h,
            start_counts=start_counts,
            windows=windows,
            n_sequences=n_sequences,
        )
        model.occupancy_ = occupancy
        return model

    def save(self, path: str | Path) -> None:
        """Write :meth:`to_dict` as JSON to ``path`` (atomically: a crash never leaves half a file)."""
        write_text(path, json.dumps(self.to_dict(), indent=1))

    @classmethod
    def load(cls, path: str | Path) -> VLMM:
        """Read a model written by :meth:`save`; ValueError if truncated or the wrong version."""
        text = Path(path).read_text(encoding="utf-8")
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not a valid VLMM JSON file (truncated?): {exc}") from exc
        return cls.from_dict(d)
