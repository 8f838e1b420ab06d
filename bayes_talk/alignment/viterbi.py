"""Viterbi decoding in the log domain for the two state graphs used here.

Forced alignment (:func:`viterbi_chain`): the transcript's phones p_1..p_K, each with
``N_STATES`` left-to-right states, concatenated into one chain of S = K * N_STATES
states; from state s only s (stay) and s + 1 (move; the last state of a phone moves into
the first of the next) are reachable. The path starts in state 0 and ends in state S - 1::

    delta_t(s) = log b_s(x_t) + max(delta_{t-1}(s) + log a_ss, delta_{t-1}(s-1) + log a_{s-1,s})

O(T S), vectorised over s.

Recognition (:func:`viterbi_phone_loop`): one composite HMM over all P phones. Within a
phone the same left-to-right transitions; from the last state of phone p into the first
state of phone q::

    log a(p -> q) = log(1 - a_last,p) + w log P(q | p) + ins

with the phone-bigram P(q | p) estimated from the training labels, the language-model
weight w and the insertion penalty ins (log domain, added once per phone entered; the
usual HTK ``-s``/``-p`` pair). The path starts in the first state of any phone with
``w log P(q | <s>)`` and may end in the last state of any phone. O(T (P S + P^2)).
"""
from __future__ import annotations

import numpy as np

__all__ = ["viterbi_chain", "viterbi_phone_loop"]

_NEG = -np.inf


def viterbi_chain(logb: np.ndarray, log_stay: np.ndarray, log_move: np.ndarray) -> tuple[np.ndarray, float]:
    """Best left-to-right path through a chain of S states.

    logb: (T, S) emission log-likelihoods of the chain's states; log_stay/log_move: (S,)
    (``log_move[s]`` is the log probability of s -> s + 1; the last entry is unused).
    Returns (state index per frame (T,), path log-likelihood); the log-likelihood is
    ``-inf`` when T < S (the chain cannot be traversed).
    """
    T, S = logb.shape
    if T < S:
        return np.zeros(T, dtype=np.int64), -np.inf
    delta = np.full(S, _NEG)
    delta[0] = logb[0, 0]
    moved = np.zeros((T, S), dtype=bool)
    for t in range(1, T):
        stay = delta + log_stay
        move = np.empty(S)
        move[0] = _NEG
        move[1:] = delta[:-1] + log_move[:-1]
        m = move > stay
        moved[t] = m
        delta = np.where(m, move, stay) + logb[t]
    score = float(delta[-1])
    path = np.empty(T, dtype=np.int64)
    s = S - 1
    for t in range(T - 1, -1, -1):
        path[t] = s
        if t > 0 and moved[t, s]:
            s -= 1
    return path, score


def viterbi_phone_loop(logb: np.ndarray, log_stay: np.ndarray, log_move: np.ndarray,
                       log_bigram: np.ndarray, log_start: np.ndarray, lm_weight: float,
                       insertion: float) -> tuple[list[tuple[int, int, int]], float]:
    """Best phone sequence and segmentation through the phone loop.

    logb: (T, P * N) emissions (phone-major); log_stay/log_move: (P, N); log_bigram:
    (P, P) log P(q | p); log_start: (P,) log P(q | <s>). Returns ``[(phone, first frame,
    end frame exclusive), ...]`` and the path score.
    """
    T = logb.shape[0]
    P, N = log_stay.shape
    lb = logb.reshape(T, P, N)
    trans = lm_weight * log_bigram + insertion + log_move[:, -1][:, None]  # (P from, P to)
    delta = np.full((P, N), _NEG)
    delta[:, 0] = lm_weight * log_start + insertion + lb[0, :, 0]
    # back-pointers: for state 0 of phone q at t, the phone p it came from (-1 = stayed);
    # for states k > 0, whether it moved from k - 1
    entry_from = np.full((T, P), -1, dtype=np.int64)
    moved = np.zeros((T, P, N), dtype=bool)
    for t in range(1, T):
        cand = delta[:, -1][:, None] + trans          # (P, P)
        best_p = np.argmax(cand, axis=0)
        enter = cand[best_p, np.arange(P)]
        stay = delta + log_stay
        new = np.empty((P, N))
        # state 0: stay or enter from another phone's last state
        e0 = enter > stay[:, 0]
        entry_from[t] = np.where(e0, best_p, -1)
        new[:, 0] = np.where(e0, enter, stay[:, 0])
        mv = delta[:, :-1] + log_move[:, :-1]
        m = mv > stay[:, 1:]
        moved[t, :, 1:] = m
        new[:, 1:] = np.where(m, mv, stay[:, 1:])
        delta = new + lb[t]
    q = int(np.argmax(delta[:, -1]))
    score = float(delta[q, -1])
    k = N - 1
    segs: list[tuple[int, int, int]] = []
    end = T
    for t in range(T - 1, -1, -1):
        if k == 0:
            p = entry_from[t, q] if t > 0 else -1
            if t == 0 or p >= 0:
                segs.append((q, t, end))
                end = t
                if t > 0:
                    q, k = int(p), N - 1
                continue
        elif moved[t, q, k]:
            k -= 1
    segs.reverse()
    return segs, score
