"""Context-window regressions (bayes_talk.estimators.baselines.context, context_mlp) on synthetic data."""
from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.stats
from sklearn.linear_model import Ridge
from sklearn.model_selection import GroupKFold
from toydata import make_utterances

import bayes_talk.estimators.baselines.context as C
from bayes_talk.base.bundle import write_bundle_manifest
from bayes_talk.base.errors import NotFittedError
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.base import ESTIMATOR_FILE, FORMAT_VERSION
from bayes_talk.estimators.baselines import REGISTRY
from bayes_talk.estimators.baselines.context import ContextRidge, grouped_ridge_cv
from bayes_talk.estimators.baselines.context_mlp import ContextMLP
from bayes_talk.estimators.registry import load_estimator
from bayes_talk.evaluation import systems as S
from bayes_talk.features.context_window import ContextFeatures, stack_context

PH = sorted(["sil", "aa", "m", "iy", "s", "uw"])   # LabelEncoder order
Z90 = scipy.stats.norm.ppf(0.95)
NOISE = 0.1


def random_labels(rng, T):
    labs = ["sil"] * 3
    while len(labs) < T - 3:
        labs += [str(rng.choice([p for p in PH if p != "sil"]))] * int(rng.integers(1, 5))
    return (labs + ["sil"] * 3)[:T]


def one_hot_window(labels, L):
    """x_t of (CTX) written out by hand: one-hot of π_{t+k}, k = -L..L, 'sil' beyond the ends."""
    T = len(labels)
    X = np.zeros((T, (2 * L + 1) * len(PH)))
    for t in range(T):
        for j, k in enumerate(range(-L, L + 1)):
            lab = labels[t + k] if 0 <= t + k < T else "sil"
            X[t, j * len(PH) + PH.index(lab)] = 1.0
    return X


@pytest.fixture(scope="module")
def linear_world():
    """A source linear in the one-hot label context t-2..t+2 plus N(0, NOISE²) noise."""
    rng = np.random.default_rng(0)
    L, D = 2, 3
    W = rng.normal(size=(D, 2 * L + 1, len(PH)))
    W -= W.mean(axis=2, keepdims=True)         # identifiable part: each block sums to zero
    W = W.reshape(D, -1)
    b = rng.normal(size=D)

    def utts(n, prefix, seed):
        r = np.random.default_rng(seed)
        out = []
        for i in range(n):
            labs = random_labels(r, int(r.integers(30, 50)))
            z = one_hot_window(labs, L) @ W.T + b + NOISE * r.normal(size=(len(labs), D))
            out.append(Utterance(f"{prefix}{i}", r.normal(size=(len(labs), 3)), z, labs))
        return out

    return W, b, utts(60, "tr", 1), utts(20, "te", 2)


@pytest.fixture(scope="module")
def ridge_fit(linear_world):
    train = linear_world[2]
    return ContextRidge(label_window=2, mfcc_window=None).fit(train)


def test_ridge_recovers_linear_context_coefficients(linear_world, ridge_fit):
    W, test = linear_world[0], linear_world[3]
    m = ridge_fit
    assert m.windows_ == (2, None)
    assert m.features_.encoder.classes_ == PH
    # one-hot blocks are collinear with the intercept: compare the block-centred coefficients
    P = len(PH)
    est = m.coef_.reshape(W.shape[0], 5, P)
    est = (est - est.mean(axis=2, keepdims=True)).reshape(W.shape)
    np.testing.assert_allclose(est, W, atol=0.05)
    err = np.concatenate([s.aam - m.predict(s) for s in test])
    assert np.mean(err**2) < 1.2 * NOISE**2                       # at the noise floor
    np.testing.assert_allclose(m.residual_var_, NOISE**2, rtol=0.25)


def test_ridge_cv_picks_the_true_window(linear_world):
    train = linear_world[2]
    m = ContextRidge(label_window=(0, 1, 2), mfcc_window=(None, 1)).fit(train)
    assert m.windows_[0] == 2
    rows = {(r["label_window"], r["mfcc_window"]): r["cv_mse"] for r in m.cv_table_}
    assert rows[(2, None)] < 0.5 * rows[(1, None)] < 0.5 * rows[(0, None)]


def test_ridge_90_band_covers_90_percent_of_held_out_frames(linear_world, ridge_fit):
    test = linear_world[3]
    m = ridge_fit
    inside = np.concatenate([np.abs(s.aam - m.predict(s)) <= Z90 * np.sqrt(m.predict_var(s)) for s in test])
    assert 0.86 <= inside.mean() <= 0.94


def test_grouped_cv_equals_brute_force_sklearn(linear_world):
    """The eigendecomposition shortcut gives the out-of-fold errors of sklearn's Ridge."""
    train = linear_world[2]
    feats = ContextFeatures.fit(train[:15], 2, 1)
    X, Z, groups = stack_context(feats, train[:15])
    sets = [feats.columns(1, None), feats.columns(2, 1)]
    alphas = [0.1, 10.0]
    sse = grouped_ridge_cv(X, Z, groups, sets, alphas, n_splits=4)
    Xd = X.toarray()
    want = np.zeros_like(sse)
    for tr, te in GroupKFold(n_splits=4).split(Xd, Z, groups):
        for c, cols in enumerate(sets):
            for a, alpha in enumerate(alphas):
                r = Ridge(alpha=alpha).fit(Xd[np.ix_(tr, cols)], Z[tr])
                want[c, a] += ((Z[te] - r.predict(Xd[np.ix_(te, cols)])) ** 2).sum(axis=0)
    np.testing.assert_allclose(sse, want, rtol=1e-7)


def test_cv_never_sees_a_test_utterance(linear_world, monkeypatch):
    """Plant a phone that only a test utterance has; record every group the CV splitter sees."""
    train, test = linear_world[2:]
    seen: list[set] = []

    class Recording(GroupKFold):
        def split(self, X, y=None, groups=None):
            seen.append(set(np.asarray(groups).tolist()))
            return super().split(X, y, groups)

    monkeypatch.setattr(C, "GroupKFold", Recording)
    planted = test[0]
    labels = list(planted.labels)
    labels[10:14] = ["zh"] * 4                  # "zh" occurs in no training utterance
    planted = Utterance("planted", planted.mfcc, planted.aam, labels)
    train = train[:20]
    m = ContextRidge(label_window=(1, 2), mfcc_window=None).fit(train)
    assert seen and all(g == {s.name for s in train} for g in seen)
    assert "zh" not in m.features_.encoder.classes_
    sub_phone = m.features_.encoder.substitute("zh")
    assert sub_phone in PH
    with pytest.warns(UserWarning, match=f"'zh'->'{sub_phone}'"):
        pred = m.predict(planted)
    sub = Utterance("sub", planted.mfcc, None, [sub_phone if p == "zh" else p for p in labels])
    np.testing.assert_array_equal(pred, m.predict(sub))


# ----------------------------------------------------------------------------- MLP
@pytest.fixture(scope="module")
def toy():
    return make_utterances(40, seed=5), make_utterances(12, seed=6)


@pytest.fixture(scope="module")
def mlp_fit(toy):
    train, _ = toy
    return ContextMLP(label_window=2, mfcc_window=1, hidden=32, l2=1e-3, learning_rate=1e-2,
                      max_epochs=80, patience=8, seed=0).fit(train)


def test_mlp_beats_a_constant_on_a_nonlinear_toy(toy, mlp_fit):
    train, test = toy
    mean = np.concatenate([s.aam for s in train]).mean(axis=0)
    const = np.mean(np.concatenate([(s.aam - mean) ** 2 for s in test]))
    mse = np.mean(np.concatenate([(s.aam - mlp_fit.predict(s)) ** 2 for s in test]))
    assert mse < 0.3 * const
    assert 1 <= mlp_fit.best_epoch_ <= 80
    assert set(mlp_fit.validation_utterances_) <= {s.name for s in train}
    inside = np.concatenate([np.abs(s.aam - mlp_fit.predict(s)) <= Z90 * np.sqrt(mlp_fit.predict_var(s))
                             for s in test])
    assert 0.8 <= inside.mean() <= 0.97


def test_mlp_is_seeded(toy, mlp_fit):
    train, test = toy
    again = ContextMLP(label_window=2, mfcc_window=1, hidden=32, l2=1e-3, learning_rate=1e-2,
                       max_epochs=80, patience=8, seed=0).fit(train)
    np.testing.assert_array_equal(again.predict(test[0]), mlp_fit.predict(test[0]))


# ----------------------------------------------------------------------------- files
@pytest.mark.parametrize("which", ["ridge", "mlp"])
def test_save_load_round_trip_and_damaged_files(which, ridge_fit, mlp_fit, linear_world, toy, tmp_path):
    """The context regressions save as every estimator (issue 26): a directory, read back
    without naming the class; a damaged or foreign file is refused, naming it."""
    model, seq = (ridge_fit, linear_world[3][0]) if which == "ridge" else (mlp_fit, toy[1][0])
    cls = type(model)
    d = model.save(tmp_path / "m")
    back = load_estimator(d)
    assert type(back) is cls
    np.testing.assert_array_equal(back.predict(seq), model.predict(seq))
    np.testing.assert_array_equal(back.predict_var(seq), model.predict_var(seq))
    assert back.windows_ == model.windows_
    with pytest.raises(FileExistsError, match="overwrite"):
        model.save(d)
    model.save(d, overwrite=True)
    path = d / ESTIMATOR_FILE
    meta = json.loads(path.read_text())
    assert meta["version"] == FORMAT_VERSION

    def rewrite(text: str) -> None:       # a changed descriptor with a manifest that agrees
        path.write_text(text)
        write_bundle_manifest(d)

    # wrong version, the other regression's class, truncated JSON, arrays of another shape
    rewrite(json.dumps({**meta, "version": 99}))
    with pytest.raises(ValueError, match="version expected 2, found 99"):
        load_estimator(d)
    other = ContextMLP if cls is ContextRidge else ContextRidge
    rewrite(json.dumps(meta))
    with pytest.raises(ValueError, match=f"a saved {cls.__name__}.*not a {other.__name__}"):
        other.load(d)
    rewrite(json.dumps(meta)[:50])
    with pytest.raises(ValueError, match="truncated or not JSON"):
        load_estimator(d)
    rewrite(json.dumps({**meta, "state": {**meta["state"], "n_visual": meta["state"]["n_visual"] + 1}}))
    with pytest.raises(ValueError, match=f"{ESTIMATOR_FILE}: .*(residual_var|coef).*"):
        load_estimator(d)
    model.save(d, overwrite=True)                        # a truncated NPZ: the manifest names it
    npz = d / "arrays.npz"
    npz.write_bytes(npz.read_bytes()[:100])
    with pytest.raises(ValueError, match=r"arrays\.npz"):
        load_estimator(d)
    model.save(d, overwrite=True)
    npz.unlink()
    with pytest.raises(ValueError, match=r"arrays\.npz.*missing"):
        load_estimator(d)


def test_a_context_model_saved_by_an_earlier_version_is_refused_by_name(tmp_path):
    """Before issue 26 the context regressions saved ``<base>.json`` + ``<base>.npz`` of their
    own format; those files are refused with the file, the format and what to do."""
    (tmp_path / "m.json").write_text(json.dumps({"format": "bayes_talk.context-ridge", "version": 1}))
    with pytest.raises(ValueError, match=r"m\.json: a model of format 'bayes_talk.context-ridge' saved by an "
                                         "earlier bayes_talk.*train the model again"):
        load_estimator(tmp_path / "m")


# ----------------------------------------------------------------------------- bad input
def test_bad_input_errors(linear_world, ridge_fit):
    train, test = linear_world[2:]
    for kw, msg in (({"label_window": -1}, "label_window"), ({"mfcc_window": "4"}, "mfcc_window"),
                    ({"label_window": None, "mfcc_window": None}, "both be None"), ({"n_splits": 1}, "n_splits")):
        with pytest.raises(ValueError, match=msg):
            ContextRidge(**kw).fit(train)
    with pytest.raises(ValueError, match="validation_fraction"):
        ContextMLP(validation_fraction=1.0)
    with pytest.raises(ValueError, match="at least 2"):
        ContextRidge().fit(train[:1])
    with pytest.raises(NotFittedError, match="not fitted"):
        ContextRidge().predict(test[0])
    s = test[0]
    with pytest.raises(ValueError, match="mfcc has shape"):
        ridge_fit.predict(Utterance("wide", np.zeros((s.n_frames, 7)), None, s.labels))
    with pytest.raises(ValueError, match="qq"):
        ridge_fit.predict(Utterance("bad", s.mfcc, None, ["qq"] + s.labels[1:]))
    dup = [Utterance("same", u.mfcc, u.aam, u.labels) for u in train[:3]]
    with pytest.raises(ValueError, match="distinct names"):
        ContextRidge().fit(dup)


def test_registered_for_evaluation_with_variances(linear_world):
    train, test = linear_world[2:]
    cfg = S.SystemConfig()
    for name in ("context-ridge", "context-mlp"):
        assert REGISTRY[name].name == name and S.METHODS[name].has_variance
    model = S.fit_family("context-ridge", train[:12], cfg)
    pred = S.predict("context-ridge", model, test[0], cfg)
    assert pred.var is not None and pred.var.shape == pred.mean.shape == test[0].aam.shape
    np.testing.assert_array_equal(pred.var[0], model.residual_var_)
