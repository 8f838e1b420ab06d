"""The field's landmark metrics (LVE, mouth opening, FDD, diversity, mean-of-samples and best-of-N
errors): hand-computed values on tiny tracks (bayes_talk.evaluation.metrics), the face regions
they use, and their path through the harness, the JSON and the Markdown report."""
from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path

import numpy as np
import pytest
from toydata import PHONES, make_utterances

from bayes_talk.data import face
from bayes_talk.evaluation import harness as H
from bayes_talk.evaluation import metrics as M
from bayes_talk.evaluation import protocols as P
from bayes_talk.evaluation import report
from bayes_talk.evaluation import scoring as SC
from bayes_talk.evaluation import systems as S
from bayes_talk.synthesis.result import SynthesisResult

# two frames, four landmarks; lips = {0, 1}, mouth pair (0, 1), upper face = {2, 3}
TRUTH = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]],
                  [[0.0, 0.0], [0.0, 3.0], [0.0, 1.0], [1.0, 3.0]]])
ERR = np.array([[[3.0, 4.0], [1.0, 0.0], [10.0, 0.0], [0.0, 0.0]],
                [[0.0, 0.0], [0.0, 2.0], [0.0, 0.0], [0.0, -2.0]]])
PRED = TRUTH + ERR
LIPS, PAIR, UPPER = np.array([0, 1]), (0, 1), np.array([2, 3])
REF = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])

# three draws of a two-frame, two-landmark track, and a truth at the origin
DRAWS = np.array([[[[1.0, 0.0], [0.0, 0.0]], [[0.0, 3.0], [0.0, 0.0]]],     # lip errors: 1, 9  -> 5
                  [[[0.0, 2.0], [0.0, 0.0]], [[0.0, 0.0], [0.0, 1.0]]],     # 4, 1 -> 2.5
                  [[[0.0, 0.0], [0.0, 0.0]], [[4.0, 0.0], [0.0, 0.0]]]])    # 0, 16 -> 8
ORIGIN = np.zeros((2, 2, 2))


def test_lip_vertex_error_by_hand():
    # frame 0: squared errors of the lips 25, 1 (landmark 2's 100 is not a lip) -> 25; frame 1: 0, 4 -> 4
    assert M.lip_vertex_error([TRUTH], [PRED], LIPS)[0] == pytest.approx((25 + 4) / 2, abs=1e-14)
    # every landmark a lip: frame 0's maximum is landmark 2's 100
    assert M.lip_vertex_error(TRUTH, PRED, np.arange(4))[0] == pytest.approx((100 + 4) / 2, abs=1e-14)


def test_mouth_opening_error_by_hand():
    # openings: truth 1, 3; prediction |(3,4) - (2,0)| = sqrt(17), |(0,0) - (0,5)| = 5
    np.testing.assert_allclose(M.mouth_opening(PRED, PAIR), [np.sqrt(17.0), 5.0], rtol=1e-15)
    assert M.mouth_opening_error([TRUTH], [PRED], PAIR)[0] == pytest.approx((np.sqrt(17) - 1 + 2) / 2, abs=1e-14)


def test_upper_face_dynamics_deviation_by_hand():
    # squared displacements from REF: landmark 2 truth (0, 0), prediction (100, 0): sds 0, 50;
    # landmark 3 truth (0, 4), prediction (0, 0): sds 2, 0  ->  (|50 - 0| + |0 - 2|) / 2
    assert M.upper_face_dynamics_deviation([TRUTH], [PRED], UPPER, [REF])[0] == pytest.approx(26.0, abs=1e-13)
    # the too-lively landmark does not cancel the too-still one (the signed region mean would give -24)
    assert M.upper_face_dynamics_deviation([TRUTH], [TRUTH], UPPER, [REF])[0] == 0.0


def test_sample_metrics_by_hand():
    # pairs (per frame and landmark distances, mean of 4): (1,2) (sqrt5 + 0 + 3 + 1)/4,
    # (1,3) (1 + 0 + 5 + 0)/4, (2,3) (2 + 0 + 4 + 1)/4
    want = ((4 + np.sqrt(5)) / 4 + 6 / 4 + 7 / 4) / 3
    assert M.sample_diversity([DRAWS])[0] == pytest.approx(want, abs=1e-14)
    # the whole draw with the smallest mean lip error (2.5), not the best frame of each (0.5)
    assert M.best_of_n_error([ORIGIN], [DRAWS], np.arange(2))[0] == pytest.approx(2.5, abs=1e-14)
    # average draw: frame 0 (1/3, 2/3), (0, 0) -> 5/9; frame 1 (4/3, 1), (0, 1/3) -> 25/9
    assert M.mean_of_samples_error([ORIGIN], [DRAWS], np.arange(2))[0] == pytest.approx(5 / 3, abs=1e-14)
    # identical draws have no diversity
    assert M.sample_diversity([np.repeat(DRAWS[:1], 4, axis=0)])[0] == 0.0


def test_bad_landmark_inputs_are_named():
    with pytest.raises(ValueError, match="indices must lie in"):
        M.lip_vertex_error([TRUTH], [PRED], np.array([0, 4]))
    with pytest.raises(ValueError, match="shape"):
        M.lip_vertex_error([TRUTH], [PRED[:1]], LIPS)
    with pytest.raises(ValueError, match=r"2-D landmarks"):
        M.lip_vertex_error([TRUTH[..., :1]], [PRED[..., :1]], LIPS)
    with pytest.raises(ValueError, match="two different"):
        M.mouth_opening_error([TRUTH], [PRED], (1, 1))
    with pytest.raises(ValueError, match="reference"):
        M.upper_face_dynamics_deviation([TRUTH], [PRED], UPPER, [REF[:3]])
    with pytest.raises(ValueError, match="at least 2 draws"):
        M.sample_diversity([DRAWS[:1]])
    with pytest.raises(ValueError, match="samples have shape"):
        M.best_of_n_error([TRUTH], [DRAWS], LIPS)
    with pytest.raises(ValueError, match="NaN"):
        M.lip_vertex_error([TRUTH], [np.where(PRED > 5, np.nan, PRED)], LIPS)


def test_face_regions_are_the_lips_the_midline_pair_and_the_still_upper_face():
    G = face.LANDMARK_GROUPS
    assert sorted(face.LIP_LANDMARKS) == sorted([*G["outer_lip"], *G["inner_lip"]])
    a, b = face.MOUTH_OPENING_PAIR
    assert not set(face.UPPER_FACE_LANDMARKS) & ({*face.LIP_LANDMARKS} | {*G["jaw"]})
    assert len(face.UPPER_FACE_LANDMARKS) + len(face.LIP_LANDMARKS) + len(G["jaw"]) == face.N_LANDMARKS
    # articulators: jaw 6, aperture 9 (an open mouth) against the rest face
    rest = face.shape_from_articulators(np.zeros((1, 6)))[0]
    open_ = face.shape_from_articulators(np.array([[6.0, 9.0, 0.0, 0.0, 0.0, 0.0]]))[0]
    moved = np.linalg.norm(open_ - rest, axis=1) > 1e-9
    assert not moved[face.UPPER_FACE_LANDMARKS].any() and moved[list(face.MOUTH_OPENING_PAIR)].all()
    # the pair is the inner-lip midline: same x, distance = the aperture (9 design units)
    assert open_[a, 0] == pytest.approx(open_[b, 0], abs=1e-12)
    assert np.linalg.norm(open_[a] - open_[b]) == pytest.approx(9.0 * 128 / face.DESIGN_SIZE, rel=1e-12)
    assert np.linalg.norm(rest[a] - rest[b]) == pytest.approx(0.0, abs=1e-12)


# ------------------------------------------------------------------------------ scoring, harness
class StubAAM:
    """A linear shape model of the built-in face's 57 landmarks: landmarks = base + params @ W."""

    def __init__(self, n_params: int, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.n_params, self.n_landmarks = n_params, face.N_LANDMARKS
        self.base = face.rest_shape().reshape(-1)
        self.W = rng.normal(size=(n_params, 2 * face.N_LANDMARKS))

    def reconstruct_landmarks(self, params):
        p = np.atleast_2d(np.asarray(params, dtype=np.float64))
        return (self.base + p @ self.W).reshape(p.shape[0], -1, 2)


def _space(D: int, offset=None, n_draws: int = 6, seed: int = 4) -> SC.LandmarkSpace:
    return SC.LandmarkSpace(StubAAM(D), np.zeros(D) if offset is None else offset, face.LIP_LANDMARKS,
                            face.MOUTH_OPENING_PAIR, face.UPPER_FACE_LANDMARKS, n_draws, seed)


def test_scoring_pushes_the_mean_and_the_seeded_draws_through_the_aam():
    rng = np.random.default_rng(1)
    T, D = 7, 3
    z = rng.normal(size=(T, D))
    offset = rng.normal(size=D)
    space = _space(D, offset)
    res = SynthesisResult("test", None, z[None, None] + rng.normal(size=(1, 3, T, D)), np.full((1, 3, T, D), 0.04))
    pred = S.Prediction(res.mean, res.var, result=res)
    got = SC.utterance_metrics(z, pred, z.var(0), None, space)
    lm = space.aam.reconstruct_landmarks
    truth, mean = lm(z + offset), lm(res.mean + offset)
    draws = lm(res.sample(6, seed=4).reshape(-1, D) + offset).reshape(6, T, -1, 2)
    ref = lm(offset[None])[0]
    want = {"lve": M.lip_vertex_error([truth], [mean], face.LIP_LANDMARKS)[0],
            "mouth_opening_mae": M.mouth_opening_error([truth], [mean], face.MOUTH_OPENING_PAIR)[0],
            "fdd": M.upper_face_dynamics_deviation([truth], [mean], face.UPPER_FACE_LANDMARKS, [ref])[0],
            "diversity": M.sample_diversity([draws])[0],
            "mean_of_samples_lve": M.mean_of_samples_error([truth], [draws], face.LIP_LANDMARKS)[0],
            "best_of_n_lve": M.best_of_n_error([truth], [draws], face.LIP_LANDMARKS)[0]}
    for k, v in want.items():
        assert got[k] == pytest.approx(v, rel=1e-12), k
    assert got["diversity"] > 0 and got["lve"] > 0
    # a point prediction, a single Gaussian and a point path's scale mixture (components with
    # one mean, as the observation term makes of a MAP path) have no sample metrics; no AAM: none
    scale_mix = SynthesisResult("map", None, np.repeat(res.draw_mean[:, :1], 3, axis=1),
                                np.full((1, 3, T, D), 0.04) * np.array([0.5, 1.0, 2.0])[None, :, None, None])
    assert SC.has_path_draws(res) and not SC.has_path_draws(scale_mix) and not SC.has_path_draws(None)
    for p in (S.Prediction(res.mean), S.Prediction(res.mean, res.var,
                                                   result=SynthesisResult.gaussian(res.mean, res.var, method="g")),
              S.Prediction(scale_mix.mean, scale_mix.var, result=scale_mix)):
        m = SC.utterance_metrics(z, p, z.var(0), None, space)
        assert m["lve"] == pytest.approx(M.lip_vertex_error([truth], [lm(p.mean + offset)], face.LIP_LANDMARKS)[0],
                                         rel=1e-12)
        assert all(np.isnan(m[k]) for k in ("diversity", "mean_of_samples_lve", "best_of_n_lve"))
    assert all(np.isnan(v) for k, v in SC.utterance_metrics(z, pred, z.var(0), None).items()
               if k in SC.LANDMARK_KEYS)


def test_landmark_space_only_for_the_built_face():
    u = make_utterances(1, seed=2)[0]
    assert SC.landmark_space(u) is None                             # no AAM (precomputed features)
    u.meta.update(aam_path="somewhere/aam.npz", corpus_kind="user")
    assert SC.landmark_space(u) is None                             # a user corpus: its own layout


TINY = S.SystemConfig(latent_dim=2, synth_max_iter=3, posterior_draws=8, band_calibration=None, sample_draws=5,
                      models={"ssgpdm": {"max_frames_per_state": 30, "min_frames_per_state": 50, "min_count": 5,
                                         "max_iter": 5, "fallback_frames": 40}})
METHODS = ["hmm-mean", "ssgpdm-phone-optimise", "ssgpdm-phone-posterior"]


def _with_aam(utts, monkeypatch):
    stub = StubAAM(utts[0].aam.shape[1], seed=5)
    monkeypatch.setattr("bayes_talk.corpus.workers.cached_aam", lambda path: stub)
    for k, u in enumerate(utts):
        u.meta.update(aam_path="stub/aam.npz", corpus_kind="built", aam_mean=np.full(stub.n_params, 0.1 * k))
    return stub


def test_harness_reports_the_landmark_metrics_of_every_method(monkeypatch, tmp_path):
    utts = make_utterances(7, seed=3)
    stub = _with_aam(utts, monkeypatch)
    proto = P.Protocol(name="tiny", paper="test", scheme="holdout", headline=(("AMSE", "mse"),),
                       default_methods=tuple(METHODS), system=TINY, n_train=5, n_test=2)
    res, _ = H.run_protocol(proto, utts, METHODS)
    json.dumps(res, allow_nan=False)
    assert res["settings"]["sample_draws"] == 5
    for name, e in res["methods"].items():
        mixture = name.endswith("posterior")
        for k in SC.LANDMARK_KEYS:
            sampled = k in ("diversity", "mean_of_samples_lve", "best_of_n_lve")
            if sampled and not mixture:
                assert e[k]["mean"] is None and e[k]["n"] == 0, (name, k)
            else:
                assert e[k]["n"] == 2 and e[k]["mean"] >= 0, (name, k)
        assert e["per_split"][0]["lve"] == pytest.approx(e["lve"]["mean"], rel=1e-12)
    # the numbers are those of the real predictions: recompute them
    by_name = {u.name: u for u in utts}
    (split,) = res["splits"]
    train, test = [by_name[n] for n in split["train"]], [by_name[n] for n in split["test"]]
    model = S.fit_family("ssgpdm-phone", train, TINY)
    lve, opening, div = [], [], []
    def landmarks(params, u):   # the utterance's own removed mean added first (the opening depends on it)
        return stub.reconstruct_landmarks(params.reshape(-1, params.shape[-1]) + u.meta["aam_mean"])

    for u in test:
        pred = S.predict("ssgpdm-phone-posterior", model, u, TINY)
        lm = functools.partial(landmarks, u=u)
        truth = lm(u.aam)
        lve.append(M.lip_vertex_error([truth], [lm(pred.mean)], face.LIP_LANDMARKS)[0])
        opening.append(M.mouth_opening_error([truth], [lm(pred.mean)], face.MOUTH_OPENING_PAIR)[0])
        draws = lm(pred.result.sample(5, seed=TINY.seed)).reshape(5, u.n_frames, -1, 2)
        div.append(M.sample_diversity([draws])[0])
    post = res["methods"]["ssgpdm-phone-posterior"]
    assert post["lve"]["mean"] == pytest.approx(np.mean(lve), rel=1e-10)
    assert post["mouth_opening_mae"]["mean"] == pytest.approx(np.mean(opening), rel=1e-10)
    assert post["diversity"]["mean"] == pytest.approx(np.mean(div), rel=1e-10)
    # the report: one row per method, "–" where a point method has no draws
    table = report.landmark_table(res)
    rows = {ln.split("|")[1].strip(): ln for ln in table.splitlines() if ln.startswith("| ") and "---" not in ln}
    assert "LVE (px²)" in rows["method"] and "best-of-N LVE (px²)" in rows["method"] and "5 seeded draws" in table
    assert rows["hmm-mean"].count("–") == 3 and rows["ssgpdm-phone-posterior"].count("–") == 0
    # a table of its own in the report, beside the main one (which stays as it was)
    assert "LVE" not in report.markdown_table(res)
    assert table in report.write_markdown(res, tmp_path / "r.md").read_text()


def test_a_corpus_without_an_aam_gets_null_landmark_metrics_and_evaluate_takes_sample_draws(monkeypatch, tmp_path):
    from bayes_talk.app import cli
    from bayes_talk.corpus import Corpus

    def fake_load(path, **kw):
        return Corpus(path=Path(path), kind="built", sequences=make_utterances(6, seed=5),
                      manifest={"phone_set": list(PHONES)})

    monkeypatch.setattr("bayes_talk.corpus.load_corpus", fake_load)
    monkeypatch.setitem(P.PROTOCOLS, "englebienne2008",
                        dataclasses.replace(P.PROTOCOLS["englebienne2008"], n_folds=2, system=TINY))
    out = tmp_path / "r.json"
    assert cli.main(["evaluate", "--protocol", "englebienne2008", "--corpus", str(tmp_path / "c"), "--methods",
                     "hmm-mean", "--sample-draws", "4", "--no-figures", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["settings"]["sample_draws"] == 4
    assert all(res["methods"]["hmm-mean"][k]["mean"] is None for k in SC.LANDMARK_KEYS)
    assert "LVE (px²)" in (tmp_path / "r.md").read_text()
    assert cli.main(["evaluate", "--protocol", "englebienne2008", "--corpus", str(tmp_path / "c"), "--methods",
                     "hmm-mean", "--sample-draws", "1", "--json", str(tmp_path / "x.json")]) == 2
    assert not (tmp_path / "x.json").exists()
