"""Tests of the variable-length Markov model (bayes_talk.models.vlmm, deena2010 §2.2, §4)."""
from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from bayes_talk.base.errors import NotFittedError
from bayes_talk.models.vlmm import START, VLMM, Segment

ALPHA = ("a", "b", "c")


# --------------------------------------------------------------------------- sources
def _source_next(h: list[str]) -> tuple[float, float, float]:
    """Known variable-order source over {a, b, c}; P(next = a, b, c | history h).

    after "b a"   -> c deterministically        after any other "a" -> uniform
    after "b"     -> (.5, .25, .25)             (order 1, all contexts alike)
    after "c c c" -> a deterministically        after any other "c" -> (.2, .4, .4)
    """
    last = h[-1]
    if last == "a":
        return (0.0, 0.0, 1.0) if h[-2:] == ["b", "a"] else (1 / 3, 1 / 3, 1 / 3)
    if last == "b":
        return (0.5, 0.25, 0.25)
    return (1.0, 0.0, 0.0) if h[-3:] == ["c", "c", "c"] else (0.2, 0.4, 0.4)


def _draw_source(n_seq: int, length: int, seed: int) -> list[list[str]]:
    """One long stationary stream (after burn-in) cut into ``n_seq`` sequences."""
    rng = np.random.default_rng(seed)
    h = ["a"]
    for _ in range(100):
        h.append(ALPHA[rng.choice(3, p=_source_next(h))])
    seqs = []
    for _ in range(n_seq):
        s = []
        for _ in range(length):
            h.append(ALPHA[rng.choice(3, p=_source_next(h))])
            s.append(h[-1])
        seqs.append(s)
    return seqs


# Contexts of length >= 2 whose next-label distribution under the source differs from that
# of their parent (suffix). Children of "a": "b a" (-> c) vs "a a", "c a" (uniform) all
# differ from P(.|a), which mixes them. Children of "c": "a c", "b c" ((.2,.4,.4)) and
# "c c" (mixture with "c c c" -> a) differ from P(.|c). Children of "c c": "c c c" (-> a)
# and "a c c", "b c c" ((.2,.4,.4)) differ from P(.|c c). Everything else predicts exactly
# like its parent ("x b a" like "b a", "x a a" like "a a", children of "b" like "b", ...).
EXPECTED_INFORMATIVE = {
    ("a", "a"), ("b", "a"), ("c", "a"),
    ("a", "c"), ("b", "c"), ("c", "c"),
    ("a", "c", "c"), ("b", "c", "c"), ("c", "c", "c"),
}


@pytest.fixture(scope="module")
def source_seqs() -> list[list[str]]:
    return _draw_source(100, 500, seed=0)


@pytest.fixture(scope="module")
def source_model(source_seqs) -> VLMM:
    # ε between the smallest true gain (~1e-3, "b c") and the largest sampling-noise gain
    # of an uninformative node (~1e-4) at 50 000 frames.
    return VLMM(max_memory=4, epsilon=3e-4, min_count=5).fit(source_seqs)


# --------------------------------------------------------------------------- 1. pruning
def test_tree_keeps_exactly_the_informative_contexts(source_model):
    kept = {q for q in source_model.states_ if len(q) >= 2 and source_model.in_tree_[q]}
    assert kept == EXPECTED_INFORMATIVE
    # the PFSA needs no extra state here (the kept set is already substring closed)
    assert {q for q in source_model.states_ if len(q) >= 2} == EXPECTED_INFORMATIVE
    assert set(source_model.states_) >= {("a",), ("b",), ("c",)}


def test_delta_h_matches_eq13_by_hand():
    # single training sequence, L = 2: contexts "a"(x3) "b"(x2) "a b"(x2) "b a"(x1) "a a"(x0)
    seq = ["a", "b", "a", "b", "a"]
    m = VLMM(max_memory=2, epsilon=0.0, min_count=1).fit([seq])
    # P̂(.|b a) = {b: 1}; P̂(.|a) = {b: 2/2} -> KL = 0
    assert m.delta_h_[("b", "a")] == pytest.approx(0.0, abs=1e-15)
    # P̂(.|a b) = {a: 1}; P̂(.|b) = {a: 1} -> 0
    assert m.delta_h_[("a", "b")] == pytest.approx(0.0, abs=1e-15)
    seq2 = ["a", "a", "b", "a", "c"]
    m2 = VLMM(max_memory=2, epsilon=0.0, min_count=1).fit([seq2])
    # "a": followed by a, b, c (once each); "a a": followed by b; P̂(a a) = 1/4 windows
    assert m2.delta_h_[("a", "a")] == pytest.approx(0.25 * math.log(1.0 / (1 / 3)), rel=1e-12)
    # "b a": followed by c; P̂(b a) = 1/4
    assert m2.delta_h_[("b", "a")] == pytest.approx(0.25 * math.log(3.0), rel=1e-12)


# --------------------------------------------------------------------------- 2. coverage
def test_segmentation_covers_every_frame_once(source_model):
    rng = np.random.default_rng(1)
    small = VLMM(max_memory=3, epsilon=0.0, min_count=1).fit(
        [["a", "b", "c", "c", "a"], ["c", "c", "c", "b", "a"], ["b", "b", "a"]]
    )
    n_reset_seqs = 0
    for model in (source_model, small):
        for _ in range(300):
            T = int(rng.integers(1, 40))
            labels = [ALPHA[i] for i in rng.integers(0, 3, size=T)]
            states, resets = model.traverse(labels)
            n_reset_seqs += bool(resets)
            segs = model.segment(labels)
            cover = [t for s in segs for t in range(s.start, s.stop)]
            assert cover == list(range(T))  # in order, no gap, no overlap
            for s in segs:
                assert s.stop - s.start == len(s.state) >= 1
                assert tuple(labels[s.start : s.stop]) == s.state
                assert states[s.stop - 1] == s.state
    # the random sequences did exercise resets (pairs unseen after the current context)
    assert n_reset_seqs > 100


def test_memory_never_exceeds_frames_since_reset(source_model):
    rng = np.random.default_rng(2)
    small = VLMM(max_memory=4, epsilon=0.0, min_count=1).fit([["a", "a", "a", "a", "b"]])
    for model in (source_model, small):
        for _ in range(200):
            labels = [ALPHA[i] for i in rng.integers(0, 2 if model is small else 3, size=30)]
            states, resets = model.traverse(labels)
            last_reset = 0
            for t, q in enumerate(states):
                if t in resets:
                    last_reset = t
                    assert q == (labels[t],)
                assert 1 <= len(q) <= t - last_reset + 1
                assert q == tuple(labels[t - len(q) + 1 : t + 1])


# --------------------------------------------------------------------------- 3. by hand
def test_hand_worked_backtracking():
    # Training: one sequence "sil m aa aa sil", L = 3, ε = 0, min_count = 1 -> nothing pruned:
    #   Q = sil, m, aa, "sil m", "m aa", "aa aa", "aa sil", "sil m aa", "m aa aa", "aa aa sil"
    #   transitions seen: sil -m-> ; "sil m" -aa->; "sil m aa" -aa->; "m aa aa" -sil->;
    #                     aa -aa->, -sil->; "m aa" -aa->; "aa aa" -sil->; (end contexts: none)
    # Test "sil m aa aa aa sil":
    #   t0 sil: start           -> (sil)              M=1
    #   t1 m:   sil -m->        -> (sil m)            M=2
    #   t2 aa:  -aa->           -> (sil m aa)         M=3
    #   t3 aa:  -aa->  suffix of "sil m aa aa" in Q -> (m aa aa)  M=3
    #   t4 aa:  "m aa aa" was only followed by sil -> RESET, consume aa -> (aa)  M=1
    #   t5 sil: aa -sil->       -> (aa sil)           M=2
    # Backtrack: t5 claims 4..5; jump to t3, claims 1..3; jump to t0, claims 0.
    m = VLMM(max_memory=3, epsilon=0.0, min_count=1).fit([["sil", "m", "aa", "aa", "sil"]])
    assert m.n_states == 10
    labels = ["sil", "m", "aa", "aa", "aa", "sil"]
    assert m.states(labels) == [
        ("sil",), ("sil", "m"), ("sil", "m", "aa"), ("m", "aa", "aa"), ("aa",), ("aa", "sil")
    ]
    assert m.traverse(labels)[1] == [4]
    assert m.segment(labels) == [
        Segment(("sil",), 0, 1),
        Segment(("m", "aa", "aa"), 1, 4),
        Segment(("aa", "sil"), 4, 6),
    ]


def test_pruned_tree_and_closure_by_hand():
    # "x a y" twice and "z a w" twice; L = 2, min_count = 2, ε = 0.1.
    #   P̂(.|a) = {y: .5, w: .5}; P̂(.|x a) = {y: 1}: ΔH = (2/10)·ln 2 ≈ 0.139 >= 0.1 -> kept
    #   likewise "z a". "a y", "a w", "x"... are followed by nothing -> ΔH = 0 -> pruned.
    seqs = [["x", "a", "y"], ["x", "a", "y"], ["z", "a", "w"], ["z", "a", "w"]]
    m = VLMM(max_memory=2, epsilon=0.1, min_count=2).fit(seqs)
    assert {q for q in m.states_ if len(q) == 2} == {("x", "a"), ("z", "a")}
    assert m.states(["z", "a", "w"]) == [("z",), ("z", "a"), ("w",)]
    assert m.segment(["x", "a", "y"]) == [Segment(("x", "a"), 0, 2), Segment(("y",), 2, 3)]
    # raising min_count above the count (2) prunes them although ΔH is large
    m3 = VLMM(max_memory=2, epsilon=0.1, min_count=3).fit(seqs)
    assert all(len(q) == 1 for q in m3.states_)


def test_ancestors_of_kept_nodes_are_kept_and_prefixes_added():
    # L = 3, 5 copies each of "p y z A", "q y z B", "r z A", "s z B".
    #   P̂(.|z) = P̂(.|y z) = {A: .5, B: .5} -> ΔH(y z, z) = 0: fails the test on its own,
    #   P̂(.|p y z) = {A: 1}: ΔH = (5/30)·ln 2 = 0.116 >= ε = 0.05 -> passes ("q y z" alike),
    #   P̂(.|r z) = {A: 1}:   ΔH = (5/50)·ln 2 = 0.069 -> passes ("s z" alike).
    # Bottom-up pruning keeps "y z" because its children survive (Ron et al.). The PFSA
    # then needs "p y" and "q y" (prefixes of kept states) so that the walk can reach
    # "p y z": without them the state after "p y" would be "y" and "p y z" unreachable.
    seqs = (
        [["p", "y", "z", "A"]] * 5 + [["q", "y", "z", "B"]] * 5
        + [["r", "z", "A"]] * 5 + [["s", "z", "B"]] * 5
    )
    m = VLMM(max_memory=3, epsilon=0.05, min_count=2).fit(seqs)
    assert m.delta_h_[("y", "z")] == pytest.approx(0.0, abs=1e-15)
    assert m.delta_h_[("p", "y", "z")] == pytest.approx(math.log(2) / 6, rel=1e-12)
    tree = {q for q in m.states_ if len(q) >= 2 and m.in_tree_[q]}
    assert tree == {("p", "y", "z"), ("q", "y", "z"), ("y", "z"), ("r", "z"), ("s", "z")}
    assert {q for q in m.states_ if len(q) >= 2} == tree | {("p", "y"), ("q", "y")}
    assert m.states(["p", "y", "z", "A"]) == [("p",), ("p", "y"), ("p", "y", "z"), ("A",)]
    assert m.transition(("p", "y", "z"), "A") == (("A",), 1.0)
    assert m.transition(("p", "y", "z"), "B") is None


# --------------------------------------------------------------------------- 4. reset
def test_unseen_pair_resets_to_start():
    m = VLMM(max_memory=3, epsilon=0.0, min_count=1).fit([["a", "a", "b", "b"], ["b", "a", "a"]])
    # Q = all substrings of length <= 3 of the training sequences (nothing pruned).
    # "b a a" is a training path: b -a-> "b a" -a-> "b a a", no reset.
    states, resets = m.traverse(["b", "a", "a"])
    assert resets == [] and states == [("b",), ("b", "a"), ("b", "a", "a")]
    # "a b a": "a b" was only ever followed by "b" -> reset at frame 2, memory forgotten
    # (the plain pair "b a" exists, but the walk does not back off to it: it restarts).
    states, resets = m.traverse(["a", "b", "a"])
    assert resets == [2] and states == [("a",), ("a", "b"), ("a",)]
    # "a" -> "a" -> "a": "a a" was followed by "b" only, "a" by "a", "b"; so the third "a"
    # has no transition from "a a": the walk resets and restarts with memory 1.
    states, resets = m.traverse(["a", "a", "a", "a"])
    assert resets == [2]
    assert states == [("a",), ("a", "a"), ("a",), ("a", "a")]
    assert m.transition(("a", "a"), "a") is None


def test_unknown_labels():
    m = VLMM(max_memory=2, epsilon=0.0, min_count=1).fit([["sil", "a", "a", "sil"]])
    with pytest.raises(ValueError, match="never seen"):
        m.states(["sil", "zz"])
    assert m.states(["sil", "zz"], unknown="sil") == m.states(["sil", "sil"])
    no_sil = VLMM(max_memory=2, epsilon=0.0, min_count=1).fit([["a", "b"]])
    with pytest.raises(ValueError, match="'sil' was not in the training labels"):
        no_sil.states(["a", "q"], unknown="sil")
    with pytest.raises(ValueError, match="unknown must be"):
        m.states(["sil"], unknown="nearest")


# --------------------------------------------------------------------------- 5. subsequences
def test_training_subsequences_carry_the_state_labels(source_model, source_seqs):
    for labels in source_seqs[:20]:
        subs = source_model.training_subsequences(labels)
        assert len(subs) == len(labels)  # one per frame
        states, resets = source_model.traverse(labels)
        assert resets == []  # training data never resets
        for t, (q, start, stop) in enumerate(subs):
            assert stop == t + 1 and stop - start == len(q) and start >= 0
            assert q == states[t]
            assert tuple(labels[start:stop]) == q
    # on the training data the traversal state is the longest suffix of the history in Q
    Q = set(source_model.states_)
    labels = source_seqs[0]
    for t, q in enumerate(source_model.states(labels)):
        longest = max(
            (tuple(labels[t - k + 1 : t + 1]) for k in range(1, min(4, t + 1) + 1)
             if tuple(labels[t - k + 1 : t + 1]) in Q),
            key=len,
        )
        assert q == longest


# --------------------------------------------------------------------------- 6. save/load
def test_save_load_round_trip(tmp_path, source_model, source_seqs):
    path = tmp_path / "vlmm.json"
    source_model.save(path)
    loaded = VLMM.load(path)
    assert loaded.states_ == source_model.states_
    assert loaded.state_index == source_model.state_index
    assert loaded.summary() == source_model.summary()
    rng = np.random.default_rng(3)
    for labels in source_seqs[:3] + [[ALPHA[i] for i in rng.integers(0, 3, 60)]]:
        assert loaded.states(labels) == source_model.states(labels)
        assert loaded.segment(labels) == source_model.segment(labels)
        assert loaded.log_prob(labels) == source_model.log_prob(labels)
    assert loaded.sample(50, rng=7) == source_model.sample(50, rng=7)


def test_load_rejects_wrong_version_and_truncation(tmp_path, source_model):
    d = source_model.to_dict()
    d["version"] = 99
    with pytest.raises(ValueError, match="version expected 1, found 99"):
        VLMM.from_dict(d)
    with pytest.raises(ValueError, match="saved VLMM: format expected"):
        VLMM.from_dict({"format": "something else", "version": 1})
    path = tmp_path / "vlmm.json"
    source_model.save(path)
    text = path.read_text()
    path.write_text(text[: len(text) // 2])
    with pytest.raises(ValueError, match="truncated"):
        VLMM.load(path)
    d = source_model.to_dict()
    del d["states"]
    with pytest.raises(ValueError, match="malformed"):
        VLMM.from_dict(d)
    json.dumps(source_model.to_dict())  # plain JSON, no custom encoder needed


# --------------------------------------------------------------------------- 7. ε monotone
def test_larger_epsilon_never_gives_more_states(source_seqs):
    seqs = source_seqs[:30]
    counts = [
        VLMM(max_memory=4, epsilon=eps, min_count=2).fit(seqs).n_states
        for eps in (0.0, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 1e-1)
    ]
    assert all(a >= b for a, b in itertools.pairwise(counts))
    assert counts[0] > counts[-1] == 3  # the grid spans from everything to single labels


# --------------------------------------------------------------------------- probability
def test_log_prob_by_hand():
    # L = 1 (first-order): s = {a: 1/2, b: 1/2}; a -> {b: 2/3, a: 1/3}; b -> {a: 1}
    m = VLMM(max_memory=1, epsilon=0.0, min_count=1).fit([["a", "b", "a", "a"], ["b", "a", "b"]])
    expected = math.log(1 / 2) + math.log(1 / 3) + math.log(2 / 3) + math.log(1.0)
    assert m.log_prob(["a", "a", "b", "a"]) == pytest.approx(expected, rel=1e-12)
    # "b b" was never seen: the reset is scored with the frame frequency P̂(b) = 3/7
    assert m.log_prob(["b", "b"]) == pytest.approx(math.log(1 / 2) + math.log(3 / 7), rel=1e-12)
    assert m.log_prob(["b", "b"], reset="forbid") == -math.inf


def test_sample_is_seeded_and_follows_the_source(source_model):
    x = source_model.sample(5000, rng=11)
    assert x == source_model.sample(5000, rng=np.random.default_rng(11))
    assert x != source_model.sample(5000, rng=12)
    assert set(x) <= set(ALPHA)
    after_ba = [x[t + 2] for t in range(len(x) - 2) if x[t : t + 2] == ["b", "a"]]
    after_ccc = [x[t + 3] for t in range(len(x) - 3) if x[t : t + 3] == ["c", "c", "c"]]
    assert len(after_ba) > 100 and set(after_ba) == {"c"}
    assert len(after_ccc) > 30 and set(after_ccc) == {"a"}
    after_b = np.array([x[t + 1] for t in range(len(x) - 1) if x[t] == "b"])
    assert abs(np.mean(after_b == "a") - 0.5) < 0.05  # 4 σ at n ≈ 1500


# --------------------------------------------------------------------------- defaults / API
def test_default_epsilon_rejects_noise_contexts_on_a_corpus_of_the_documented_size():
    # ~250 utterances x ~75 frames, 40 phones; the next label depends only on the current
    # phone and on how long it has lasted (durations uniform), so a context is informative
    # iff it is a run of the last label possibly preceded by ONE other label (which pins
    # the run length). Any label further left is noise; the defaults must keep none.
    from bayes_talk.data.phones import PHONES, VOWELS

    rng = np.random.default_rng(5)
    ph = PHONES[1:]
    P = rng.dirichlet(np.full(len(ph), 0.3), size=len(ph))
    seqs = []
    for _ in range(250):
        labs = ["sil"] * int(rng.integers(3, 9))
        i = int(rng.integers(len(ph)))
        while len(labs) < 70:
            p = ph[i]
            labs += [p] * (int(rng.integers(3, 9)) if p in VOWELS else int(rng.integers(1, 5)))
            i = int(rng.choice(len(ph), p=P[i]))
        seqs.append(labs + ["sil"] * int(rng.integers(3, 9)))
    m = VLMM().fit(seqs)

    def informative(q):
        run = next((k for k, x in enumerate(reversed(q)) if x != q[-1]), len(q))
        return len(q) - run <= 1

    tree = [q for q in m.states_ if len(q) >= 2 and m.in_tree_[q]]
    assert len(tree) > 50  # real duration structure is found ...
    assert [q for q in tree if not informative(q)] == []  # ... and no noise context kept
    assert ("sil", "sil", "sil", "sil", "sil") in m.states_
    text = m.summary()
    assert f"{m.n_states} states" in text and "sil sil sil sil sil" in text


def test_state_ids_and_bad_input():
    m = VLMM(max_memory=2, epsilon=0.0, min_count=1).fit([["a", "b", "a"]])
    ids = m.state_ids(["a", "b", "a"])
    assert ids == [m.state_id(q) for q in m.states(["a", "b", "a"])]
    assert sorted(m.state_index.values()) == list(range(m.n_states))
    with pytest.raises(ValueError, match="not a state"):
        m.state_id(("b", "b"))
    with pytest.raises(ValueError, match="empty"):
        VLMM().fit([])
    with pytest.raises(ValueError, match="empty"):
        m.segment([])
    with pytest.raises(ValueError, match="frame 1"):
        VLMM().fit([["a", 3]])
    with pytest.raises(ValueError, match="max_memory"):
        VLMM(max_memory=0)
    with pytest.raises(ValueError, match="epsilon"):
        VLMM(epsilon=-1.0)
    with pytest.raises(ValueError, match="min_count"):
        VLMM(min_count=0)
    with pytest.raises(NotFittedError, match="not fitted"):
        VLMM().states(["a"])
    assert m.transition(START, "a") == (("a",), 1.0)
