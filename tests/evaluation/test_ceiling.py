"""Methods zero and oracle, the oracle's bias correction and the achievable-gain fraction
(bayes_talk.evaluation.ceiling, issue 9 part 3)."""
from __future__ import annotations

import numpy as np
import pytest

from bayes_talk.corpus import FORMAT_VERSION, render, renderer_settings
from bayes_talk.data import face
from bayes_talk.data.face import random_phone_intervals
from bayes_talk.data.labels import frame_labels
from bayes_talk.data.phones import PHONES
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.ceiling import OracleModel, ZeroModel
from bayes_talk.evaluation.ceiling import add_gain_fractions, gain_fraction
from bayes_talk.evaluation.harness import run_protocol
from bayes_talk.evaluation.protocols import get_protocol
from bayes_talk.evaluation.scoring import utterance_metrics
from bayes_talk.evaluation.systems import Prediction, SystemConfig, predict
from bayes_talk.features.aam import AAM

SIZE, T, N_UTT = 64, 30, 4


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A tiny 'built corpus' without speech: random timings, the corpus's face draws and
    renderer at 64 px, an AAM fitted and saved, mean-removed projections as the truth."""
    rng = np.random.default_rng(5)
    ivs = [random_phone_intervals(rng, T) for _ in range(N_UTT)]
    lms = [face.face_landmarks(iv, T, image_size=SIZE, rng=np.random.default_rng([0, i, 1]))
           for i, iv in enumerate(ivs)]
    cam = renderer_settings(FORMAT_VERSION)
    frames = [render.render_frames(lm, image_size=SIZE, **cam) for lm in lms]
    aam = AAM.fit(np.concatenate(frames), np.concatenate(lms), variance=0.99, texture_inset=1.0)
    path = tmp_path_factory.mktemp("ceiling") / "aam.npz"
    aam.save(path)
    seqs = []
    for i, (iv, lm, fr) in enumerate(zip(ivs, lms, frames)):
        z = aam.project(fr, lm)
        meta = {"corpus_kind": "built", "intervals": iv, "aam_path": str(path), "image_size": SIZE,
                "renderer": cam, "mean_removed": True}
        seqs.append(Utterance(f"utt{i:04d}", np.zeros((T, 20)), z - z.mean(axis=0), frame_labels(iv, T),
                             landmarks=lm, meta=meta))
    return seqs


def test_zero_predicts_zeros_with_the_training_variance(built):
    cfg = SystemConfig()
    model = ZeroModel().fit(built[:2])
    p = predict("zero", model, built[3], cfg)
    assert p.mean.shape == built[3].aam.shape and np.all(p.mean == 0)
    want = np.concatenate([s.aam for s in built[:2]]).var(axis=0)
    np.testing.assert_allclose(p.var, np.broadcast_to(want, p.var.shape))


def test_oracle_is_refused_on_a_user_corpus(built):
    s = built[0]
    user = Utterance(s.name, s.mfcc, s.aam, s.labels, meta=dict(s.meta, corpus_kind="user"))
    with pytest.raises(ValueError, match="oracle.*built by `bayes-talk corpus build`.*'user' corpus"):
        predict("oracle", OracleModel(n_draws=2).fit(built[:2]), user, SystemConfig())


def test_oracle_average_converges_and_its_bias_correction_removes_the_1_over_K_excess(built):
    """Raw MSE to the truth falls with K (by ~sigma^2 (1/2 - 1/16)); the bias-corrected
    figures of K = 2 and K = 16 estimate the same K -> inf oracle, far closer together."""
    v = np.concatenate([s.aam for s in built]).var(axis=0)
    raw, corrected = {}, {}
    for K in (2, 16):
        rows = [utterance_metrics(s.aam, Prediction(*OracleModel(n_draws=K, seed=3).moments(s)), v, None)
                for s in built]
        raw[K] = np.mean([r["mse"] for r in rows])
        corrected[K] = np.mean([r["mse_corrected"] for r in rows])
    print(f"\noracle MSE raw K=2 {raw[2]:.4f}, K=16 {raw[16]:.4f}; corrected {corrected[2]:.4f}, "
          f"{corrected[16]:.4f}")
    assert raw[16] < raw[2]
    assert corrected[16] < raw[16] and corrected[2] < raw[2]
    assert abs(corrected[2] - corrected[16]) < 0.35 * (raw[2] - raw[16])


def test_bias_correction_is_exact_on_a_gaussian_case():
    """Truth and K draws i.i.d. N(mu, sigma^2): the ideal predictor mu has MSE sigma^2; the
    K-draw mean has sigma^2 (1 + 1/K); the corrected figure recovers sigma^2."""
    rng = np.random.default_rng(0)
    Tn, D, K = 4000, 6, 4
    sigma2 = np.array([0.5, 1.0, 2.0, 3.0, 0.25, 1.5])
    mu = rng.normal(size=(Tn, D))
    draws = mu + rng.normal(size=(K, Tn, D)) * np.sqrt(sigma2)
    truth = mu + rng.normal(size=(Tn, D)) * np.sqrt(sigma2)
    s2 = draws.var(axis=0, ddof=1)
    pred = Prediction(draws.mean(axis=0), s2 * (1 + 1 / K), s2 / K)
    r = utterance_metrics(truth, pred, sigma2, None)
    assert r["mse"] == pytest.approx(sigma2.mean() * (1 + 1 / K), rel=0.03)
    assert r["mse_corrected"] == pytest.approx(sigma2.mean(), rel=0.03)
    assert r["nmse_corrected"] == pytest.approx(1.0, rel=0.03)
    # s^2 (1 + 1/K) is unbiased for the squared error of the K-draw mean
    assert np.mean((truth - pred.mean) ** 2) / np.mean(pred.var) == pytest.approx(1.0, rel=0.03)


def test_gain_fractions_zero_scores_0_oracle_1(built, tmp_path):
    proto = get_protocol("deena2010", models={"oracle": {"n_draws": 4}})
    result, _ = run_protocol(proto, built[:2], ["zero", "oracle"], test_sequences=built[2:],
                             train_phone_set=PHONES, test_phone_set=PHONES)
    g = {n: e["gain_fraction"] for n, e in result["methods"].items()}
    assert g["zero"] == {"amse": 0.0, "nmse": 0.0}
    assert g["oracle"]["amse"] == pytest.approx(1.0) and g["oracle"]["nmse"] == pytest.approx(1.0)
    o = result["methods"]["oracle"]
    assert o["mse_corrected"]["mean"] < o["mse"]["mean"] < result["methods"]["zero"]["mse"]["mean"]
    from bayes_talk.evaluation.report import gain_table, write_markdown

    table = gain_table(result)
    assert "| zero | 0.000 | 0.000 |" in table and "| oracle | 1.000 | 1.000 |" in table
    assert "bias-corrected for its 4 draws" in table
    md = write_markdown(result, tmp_path / "r.md").read_text()
    assert table in md and "AMSE (bias-corr.)" in md


def test_gain_fraction_arithmetic():
    methods = {"zero": {"mse": {"mean": 10.0}, "nmse": {"mean": 1.0}},
               "oracle": {"mse": {"mean": 4.5}, "mse_corrected": {"mean": 4.0},
                          "nmse": {"mean": 0.6}, "nmse_corrected": {"mean": 0.5}},
               "m": {"mse": {"mean": 7.0}, "nmse": {"mean": 1.1}}}
    assert add_gain_fractions(methods)
    assert methods["m"]["gain_fraction"] == {"amse": pytest.approx(0.5), "nmse": pytest.approx(-0.2)}
    assert not add_gain_fractions({"m": {"mse": {"mean": 1.0}}})
    assert gain_fraction(1.0, 0.5, 1.0) is None


def test_oracle_draws_below_two_are_refused(tmp_path):
    from bayes_talk.evaluation.harness import evaluate

    with pytest.raises(ValueError, match="oracle_draws must be >= 2"):   # before reading the corpus
        evaluate("deena2010", tmp_path / "no-corpus", tmp_path / "r.json", methods="oracle", oracle_draws=1)


def test_score_with_ceiling_for_the_demo():
    from bayes_talk.evaluation.ceiling import score_with_ceiling

    rng = np.random.default_rng(1)
    truth = [rng.normal(size=(40, 3)) for _ in range(3)]
    half = [0.5 * t for t in truth]
    bias = [np.full((40, 3), 0.01) for _ in truth]
    rows = score_with_ceiling(truth, {"zero": [np.zeros_like(t) for t in truth], "oracle": truth,
                                      "half": half}, {"oracle": bias})
    assert rows["oracle"]["amse"] == pytest.approx(-0.01)          # perfect, minus its bias
    assert rows["zero"]["gain_amse"] == 0.0 and rows["oracle"]["gain_nmse"] == 1.0
    z = rows["zero"]["amse"]
    assert rows["half"]["gain_amse"] == pytest.approx((z - 0.25 * z) / (z + 0.01))


def test_post_filter_leaves_the_ceiling_alone(built):
    """lowpass_hz filters the methods, not zero/oracle: a filtered oracle would lose its
    bias correction (mse_bias) and the generator's own fast motion."""
    plain, filt = SystemConfig(), SystemConfig(lowpass_hz=4.0)
    model = OracleModel(n_draws=2).fit(built[:2])
    a, b = predict("oracle", model, built[3], plain), predict("oracle", model, built[3], filt)
    np.testing.assert_array_equal(a.mean, b.mean)
    assert b.mse_bias is not None
