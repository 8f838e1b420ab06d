"""The phonetic-context view (bayes_talk.features.context_view): a supervised reduction of
the label and MFCC window that joins the audio view of the switching model."""
from __future__ import annotations

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.features.context_view import ContextView

SMALL = {"latent_dim": 3, "max_iter": 30, "min_count": 4, "max_frames_per_state": 100, "fallback_frames": 120}


@pytest.fixture(scope="module")
def data():
    return make_utterances(16, seed=0), make_utterances(3, seed=5)


def test_training_frames_get_out_of_fold_values_and_new_frames_the_full_fit(data):
    """The training view is the out-of-fold prediction (it fits the training faces worse
    than the full-data fit does, and differs from it), new utterances get the full fit,
    and the view predicts held-out faces better than their mean does."""
    train, test = data
    cv = ContextView(label_window=4, mfcc_window=2)
    oof = cv.fit(train)
    assert [o.shape for o in oof] == [(s.n_frames, s.aam.shape[1]) for s in train] and cv.n_dims == 5
    full = [cv.transform(s.mfcc, s.labels) for s in train]
    err_oof = np.mean([np.mean((o - s.aam) ** 2) for o, s in zip(oof, train)])
    err_full = np.mean([np.mean((f - s.aam) ** 2) for f, s in zip(full, train)])
    assert err_full < err_oof and not np.allclose(oof[0], full[0])
    z = np.vstack([s.aam for s in test])
    pred = np.vstack([cv.transform(s.mfcc, s.labels) for s in test])
    assert np.mean((pred - z) ** 2) < 0.7 * np.mean((z - z.mean(0)) ** 2)
    assert cv.alpha_ in (1.0, 10.0, 100.0, 1000.0)


def test_off_by_default_and_bad_input_is_named(data):
    train, _ = data
    off = ContextView(0)
    assert off.fit(train)[0].shape == (train[0].n_frames, 0) and not off.enabled
    assert off.transform(train[0].mfcc, train[0].labels).shape == (train[0].n_frames, 0)
    with pytest.raises(ValueError, match="whole number of frames"):
        ContextView(-1)
    cv = ContextView(2)
    with pytest.raises(ValueError, match="before fit"):
        cv.transform(train[0].mfcc, train[0].labels)
    cv.fit(train)
    with pytest.raises(ValueError, match="one phone label per frame"):
        cv.transform(train[0].mfcc, train[0].labels[:-1])


def test_switching_model_explains_the_context_view_and_saves_it(data, tmp_path):
    """With ``context_view`` the state models' audio GPs explain [audio, context] columns;
    synthesis uses them; a saved and loaded model synthesises the same trajectory."""
    train, test = data
    m = SwitchingSGPDM(states="phone", right_context=True, context_view=3, **SMALL).fit(train)
    Dy, Dz = train[0].mfcc.shape[1], train[0].aam.shape[1]
    assert all(sm.means_["audio"].shape == (Dy + Dz,) for sm in m.models_.values())
    s = test[0]
    assert m.audio_input(s.mfcc, s.labels).shape == (s.n_frames, Dy + Dz)
    with pytest.raises(ValueError, match="one phone label per frame"):
        m.audio_input(s.mfcc)
    r = m.synthesize(s.mfcc, s.labels)
    plain = SwitchingSGPDM(states="phone", right_context=True, **SMALL).fit(train)
    assert not np.allclose(plain.synthesize(s.mfcc, s.labels).mean, r.mean)
    m.save(tmp_path / "m")
    back = SwitchingSGPDM.load(tmp_path / "m")
    np.testing.assert_array_equal(back.audio_input(s.mfcc, s.labels), m.audio_input(s.mfcc, s.labels))
    np.testing.assert_allclose(back.synthesize(s.mfcc, s.labels).mean, r.mean, atol=1e-10)


def test_context_mean_makes_the_view_the_visual_mean_function(data, tmp_path):
    """With ``context_mean`` the state models explain the residual face z − c (the view c
    out-of-fold), every synthesis path adds c_t back to each component, the result names
    c_t as its mean function, the band calibration's mean stage shrinks towards c_t, and
    the setting survives save/load."""
    from bayes_talk.calibration.bands import _shrunk, mean_shrinkage
    from bayes_talk.posterior.sampling import sample_synthesis

    train, test = data
    with pytest.raises(ValueError, match="context_view > 0"):
        SwitchingSGPDM(states="phone", context_mean=True, **SMALL)
    with pytest.raises(ValueError, match="True or False"):
        SwitchingSGPDM(states="phone", context_view=3, context_mean="yes", **SMALL)
    m = SwitchingSGPDM(states="phone", right_context=True, context_view=3, context_mean=True, **SMALL).fit(train)
    plain = SwitchingSGPDM(states="phone", right_context=True, context_view=3, **SMALL).fit(train)
    # the state models were trained on residuals: their visual means (per state) are small
    # beside the per-state face means the plain model's states learned
    spread = {name: np.mean([np.abs(sm.means_["visual"]).mean() for sm in mm.models_.values()])
              for name, mm in (("resid", m), ("plain", plain))}
    assert spread["resid"] < 0.5 * spread["plain"], spread
    s = test[0]
    c = m.visual_offset(m.audio_input(s.mfcc, s.labels))
    np.testing.assert_array_equal(c, m.context_.transform(s.mfcc, s.labels))
    seq = m.synthesize(s.mfcc, s.labels)
    np.testing.assert_array_equal(seq.mean_function, c)
    X = seq.latent_draws[0, 0]
    resid = np.zeros_like(c)
    for g in m.segment(s.labels):
        _, sm = m.model_for(g.state)
        resid[g.start:g.stop] = sm.predict_view("visual", X[g.start:g.stop])[0]
    np.testing.assert_allclose(seq.mean, c + resid, atol=1e-10)
    post = sample_synthesis(m, s.mfcc, s.labels, method="laplace", n_draws=8, seed=0)
    np.testing.assert_array_equal(post.mean_function, c)
    # stage 0 shrinks μ − c: a = 0 leaves the mean function, a = 1 the prediction
    np.testing.assert_allclose(_shrunk(post, np.zeros(c.shape[1])).mean, c, atol=1e-12)
    np.testing.assert_allclose(_shrunk(post, np.ones(c.shape[1])).mean, post.mean, atol=1e-12)
    # a truth equal to c_t + 0.5 (μ − c_t) gives a_d = 0.5 exactly
    half = c + 0.5 * (post.mean - c)
    np.testing.assert_allclose(mean_shrinkage([post], [half]), 0.5, atol=1e-12)
    m.save(tmp_path / "m")
    back = SwitchingSGPDM.load(tmp_path / "m")
    assert back.config.context_mean is True
    np.testing.assert_allclose(back.synthesize(s.mfcc, s.labels).mean, seq.mean, atol=1e-10)
    assert plain.synthesize(s.mfcc, s.labels).mean_function is None


def test_out_of_fold_ridge_equals_sklearns_cross_val_predict():
    """ridge_out_of_fold (the Gram matrices of the folds from the whole one, issue 29) gives
    sklearn's ``cross_val_predict(Ridge(alpha))`` for every penalty, to rounding, on one-hot
    and offset continuous columns (the centring must be the fold's, not the data's)."""
    from sklearn.linear_model import Ridge
    from sklearn.model_selection import GroupKFold, cross_val_predict

    from bayes_talk.features.context_view import ALPHAS, ridge_out_of_fold

    rng = np.random.default_rng(3)
    n = 1200
    X = np.hstack([rng.integers(0, 2, size=(n, 30)).astype(float), rng.normal(size=(n, 20)) + 3.0])
    Z = X @ rng.normal(size=(50, 4)) * 0.1 + rng.normal(size=(n, 4)) + 5.0
    groups = np.repeat(np.arange(40), n // 40)
    cv = GroupKFold(n_splits=5)
    tests = [t for _, t in cv.split(X, Z, groups)]
    for a, got in zip(ALPHAS, ridge_out_of_fold(X, Z, tests, ALPHAS)):
        want = cross_val_predict(Ridge(alpha=a), X, Z, groups=groups, cv=cv)
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11 * np.abs(want).max(), err_msg=f"alpha {a}")
