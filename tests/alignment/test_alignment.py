"""Alignment and recognition (issue 13): Viterbi against brute force, accuracy on built
utterances held out of training, named errors for bad transcripts, the commands."""
from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from bayes_talk.alignment import (
    AlignmentModel,
    EmptyTranscriptError,
    MissingAlignmentModelError,
    TranscriptTooLongError,
    UnpronounceableWordError,
)
from bayes_talk.alignment.scoring import edit_alignment, score_segmentation, summarise_scores
from bayes_talk.alignment.transcript import check_transcript
from bayes_talk.alignment.viterbi import viterbi_chain, viterbi_phone_loop
from bayes_talk.app.cli import main
from bayes_talk.data.labels import read_labels

N_TRAIN = 10


# ------------------------------------------------------------------ Viterbi vs brute force
def _chain_brute(logb, stay, move):
    T, S = logb.shape
    best = -np.inf
    for steps in itertools.product((0, 1), repeat=T - 1):
        if sum(steps) != S - 1:
            continue
        s, score = 0, logb[0, 0]
        for t, m in enumerate(steps, 1):
            score += move[s] if m else stay[s]
            s += m
            score += logb[t, s]
        best = max(best, score)
    return best


def test_viterbi_chain_matches_brute_force_and_is_a_valid_path():
    rng = np.random.default_rng(0)
    T, S = 8, 4
    logb = rng.normal(size=(T, S)) * 3
    stay, move = np.log(rng.uniform(0.2, 0.8, S)), np.log(rng.uniform(0.2, 0.8, S))
    path, score = viterbi_chain(logb, stay, move)
    assert score == pytest.approx(_chain_brute(logb, stay, move))
    assert path[0] == 0 and path[-1] == S - 1 and set(np.diff(path)) <= {0, 1}
    rescored = logb[0, 0] + sum((move if b > a else stay)[a] + logb[t + 1, b]
                                for t, (a, b) in enumerate(itertools.pairwise(path)))
    assert rescored == pytest.approx(score)
    assert viterbi_chain(logb[:3], stay, move)[1] == -np.inf        # fewer frames than states


def test_viterbi_phone_loop_matches_brute_force():
    rng = np.random.default_rng(1)
    P, N, T = 2, 2, 7
    logb = rng.normal(size=(T, P * N)) * 2
    stay = np.log(rng.uniform(0.2, 0.8, (P, N)))
    move = np.log1p(-np.exp(stay))
    big = np.log(rng.dirichlet(np.ones(P), size=P))
    start = np.log(rng.dirichlet(np.ones(P)))
    w, ins = 1.7, -0.9
    segs, score = viterbi_phone_loop(logb, stay, move, big, start, w, ins)
    best = -np.inf
    for states in itertools.product(range(P * N), repeat=T):     # every state sequence
        p, k = divmod(states[0], N)
        if k != 0 or states[-1] % N != N - 1:
            continue
        sc, ok = w * start[p] + ins + logb[0, states[0]], True
        for t in range(1, T):
            (p0, k0), (p1, k1) = divmod(states[t - 1], N), divmod(states[t], N)
            if (p1, k1) == (p0, k0):
                sc += stay[p0, k0]
            elif p1 == p0 and k1 == k0 + 1:
                sc += move[p0, k0]
            elif k0 == N - 1 and k1 == 0:
                sc += move[p0, k0] + w * big[p0, p1] + ins
            else:
                ok = False
                break
            sc += logb[t, states[t]]
        if ok:
            best = max(best, sc)
    assert score == pytest.approx(best)
    assert segs[0][1] == 0 and segs[-1][2] == T and all(a[2] == b[1] for a, b in itertools.pairwise(segs))


def test_edit_alignment_counts_edits_and_hits():
    d, hits = edit_alignment(list("sabcs"), list("sbxcs"))
    assert d == 2 and [(i, j) for i, j in hits] == [(0, 0), (2, 1), (3, 3), (4, 4)]
    r = score_segmentation([(0, 1, "a"), (1, 2, "b")], [(0, 1.01, "a"), (1.01, 2, "b")])
    assert r["edits"] == 0 and r["boundary_errors"] == [pytest.approx(0.01)]


# ------------------------------------------------------------------ transcripts
@pytest.mark.parametrize("text", ["", "   ", " ... !? "])
def test_empty_transcript_is_a_named_error(text):
    with pytest.raises(EmptyTranscriptError, match="empty transcript"):
        check_transcript(text)


def test_words_outside_the_latin_script_are_a_named_error():
    with pytest.raises(UnpronounceableWordError, match="Привет"):
        check_transcript("hello Привет world")
    assert check_transcript("Café au lait, 42 times.") == ["Café", "au", "lait,", "42", "times."]


# ------------------------------------------------------------------ trained on a small corpus
@pytest.fixture(scope="module")
def small(tmp_path_factory):
    from bayes_talk.corpus import load_corpus

    out = tmp_path_factory.mktemp("align") / "corpus"
    assert main(["corpus", "build", str(out), "--n-utterances", str(N_TRAIN + 2), "--seed", "5"]) == 0
    c = load_corpus(out)
    model = AlignmentModel(n_tune=4).fit(c.sequences[:N_TRAIN])
    mdir = tmp_path_factory.mktemp("align") / "model"
    mdir.mkdir(exist_ok=True)
    (mdir / "bayes_talk_model.json").write_text("{}")              # marks a model directory
    model.save(mdir)
    return c, model, mdir


@pytest.mark.parametrize("method", ["hmm", "dtw"])
def test_aligner_finds_espeak_boundaries_on_held_out_utterances(small, method):
    c, model, _ = small
    rows = []
    for s in c.sequences[N_TRAIN:]:
        r = model.align(s.audio_path, s.meta["text"], method=method)
        assert r.intervals[0][0] == 0 and r.intervals[-1][1] == pytest.approx(s.meta["intervals"][-1][1])
        rows.append(score_segmentation(s.meta["intervals"], r.intervals, s.n_frames))
    summary = summarise_scores(rows)
    assert summary["phone_error_rate"] == 0.0                       # the corpus's own G2P
    assert summary["boundary_error_ms_median"] <= 20.0
    assert summary["frame_label_agreement"] >= 0.8


def test_recogniser_beats_chance_and_round_trips_through_save(small):
    c, model, mdir = small
    loaded = AlignmentModel.load(mdir)
    rows = []
    for s in c.sequences[N_TRAIN:]:
        r = model.recognise(s.audio_path)
        assert loaded.recognise(s.audio_path).intervals == r.intervals
        rows.append(score_segmentation(s.meta["intervals"], r.intervals, s.n_frames))
    # chance with 40 phones is a PER near 1; ten training utterances already do far better
    assert summarise_scores(rows)["phone_error_rate"] < 0.6
    assert model.lm_weight in (2.0, 4.0, 8.0, 12.0, 16.0)


def test_transcript_much_longer_than_the_audio_is_refused(small):
    c, model, _ = small
    s = c.sequences[N_TRAIN]
    with pytest.raises(TranscriptTooLongError):
        model.align(s.audio_path, " ".join([s.meta["text"]] * 4))
    with pytest.raises(TranscriptTooLongError, match="alignment cost"):   # fits in frames, not in sound
        model.align(s.audio_path, " ".join([s.meta["text"]] * 2))


def test_align_and_recognise_commands_write_readable_labels_and_refuse_bad_input(small, tmp_path):
    c, _, mdir = small
    s = c.sequences[N_TRAIN + 1]
    lab, tg = tmp_path / "a.lab", tmp_path / "a.TextGrid"
    assert main(["align", str(s.audio_path), "--model", str(mdir), "--text", s.meta["text"], "--out", str(lab)]) == 0
    tfile = tmp_path / "t.txt"
    tfile.write_text(s.meta["text"] + "\n", encoding="utf-8")
    assert main(["align", str(s.audio_path), "--model", str(mdir), "--transcript", str(tfile),
                 "--method", "hmm", "--out", str(tg)]) == 0
    assert [p for *_, p in read_labels(lab)] == [p for *_, p in read_labels(tg)] == \
        [p for *_, p in s.meta["intervals"]]
    before = lab.read_bytes()
    assert main(["align", str(s.audio_path), "--model", str(mdir), "--text", "x", "--out", str(lab)]) == 2
    assert lab.read_bytes() == before                               # not overwritten unasked
    rec = tmp_path / "r.lab"
    assert main(["recognise", str(s.audio_path), "--model", str(mdir), "--out", str(rec)]) == 0
    assert read_labels(rec)[-1][1] == pytest.approx(s.meta["intervals"][-1][1])
    for text in ("", "Привет мир", " ".join([s.meta["text"]] * 4)):
        bad = tmp_path / "bad.lab"
        assert main(["align", str(s.audio_path), "--model", str(mdir), "--text", text, "--out", str(bad)]) == 2
        assert not bad.exists()
    with pytest.raises(MissingAlignmentModelError, match="align-train"):
        AlignmentModel.load(tmp_path)


def test_label_sources_relabel_the_test_utterances_only(small):
    from bayes_talk.evaluation.label_sources import parse_label_sources, relabel

    c, model, _ = small
    assert parse_label_sources("true, aligned,recognised") == ("true", "aligned", "recognised")
    with pytest.raises(ValueError, match="unknown label source"):
        parse_label_sources("true,oracle")
    tests = c.sequences[N_TRAIN:]
    same, _ = relabel(tests, "true", model)
    assert same == tests
    new, seg = relabel(tests, "recognised", model)
    assert seg["source"] == "recognised" and 0 <= seg["phone_error_rate"] < 0.6
    for a, b in zip(tests, new):
        assert np.array_equal(a.mfcc, b.mfcc) and np.array_equal(a.aam, b.aam) and len(b.labels) == a.n_frames
        assert b.meta["true_intervals"] == [tuple(iv) for iv in a.meta["intervals"]]
    assert json.dumps(seg)                                          # JSON-ready


def test_corpus_build_centres_rate_and_pitch_jitter_where_asked(tmp_path):
    out = tmp_path / "f3"
    assert main(["corpus", "build", str(out), "--n-utterances", "2", "--seed", "1", "--voice", "en+f3",
                 "--rate", "215", "--pitch", "70"]) == 0
    seqs = json.loads((out / "manifest.json").read_text())["sequences"]
    assert all(200 <= s["rate"] <= 230 and 62 <= s["pitch"] <= 78 and s["voice"] == "en+f3" for s in seqs)


def test_align_train_adds_models_to_a_model_directory_only(small, tmp_path):
    c, _, _ = small
    assert main(["align-train", str(c.path), "--model-dir", str(tmp_path)]) == 2    # not a model dir
    (tmp_path / "bayes_talk_model.json").write_text("{}")
    assert main(["align-train", str(c.path), "--model-dir", str(tmp_path)]) == 0
    meta = json.loads((tmp_path / "alignment.json").read_text())
    assert meta["info"]["n_train"] == len(c.sequences) and (tmp_path / "alignment.npz").exists()
    assert main(["align-train", str(c.path), "--model-dir", str(tmp_path)]) == 2    # no silent replace


def test_label_sources_need_one_training_set(small):
    from bayes_talk.evaluation.harness import run_protocol
    from bayes_talk.evaluation.label_sources import run_label_sources
    from bayes_talk.evaluation.protocols import get_protocol

    c, _, _ = small
    with pytest.raises(ValueError, match="needs one training set"):
        run_label_sources(run_protocol, get_protocol("englebienne2008"), c.sequences, None,
                          ["voice-puppetry"], ("true", "aligned"))


def test_aligner_fitted_in_a_worker_process_is_the_one_fitted_here(small, tmp_path):
    """``train`` fits the aligner in a worker process beside the state models
    (``Executor.submit``); the saved models are byte-identical to an in-process fit but
    for the fit's timings (``info``'s seconds)."""
    import json

    from bayes_talk.alignment.commands import fit_alignment
    from bayes_talk.base.executor import make_executor

    c, _, _ = small
    seqs = c.sequences[:4]
    with make_executor("processes", 2) as ex:
        remote = ex.submit(fit_alignment, seqs).result()
    here = fit_alignment(seqs)
    for name, model in (("remote", remote), ("here", here)):
        (tmp_path / name).mkdir()
        model.save(tmp_path / name)
    files = sorted(p.name for p in (tmp_path / "here").iterdir())
    assert files == sorted(p.name for p in (tmp_path / "remote").iterdir()) and files
    for f in files:
        a, b = (tmp_path / "here" / f).read_bytes(), (tmp_path / "remote" / f).read_bytes()
        if f.endswith(".json"):
            a, b = json.loads(a), json.loads(b)
            for d in (a["info"], b["info"]):
                assert d.pop("hmm_fit_seconds") > 0 and d.pop("tune_seconds") > 0
        assert a == b, f
