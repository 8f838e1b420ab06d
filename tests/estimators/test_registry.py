"""One vocabulary (issue 26, item 1): a method is a registered estimator, and ``evaluate``
and ``train`` / ``synth`` run whatever the registry holds through ``fit`` / ``predict_dist``
/ ``save`` / ``load`` with no branch on a family name. A dummy estimator registered with one
line runs through the harness and through train + synth."""
from __future__ import annotations

import json
from typing import ClassVar

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.base.bundle import ESTIMATOR_DIR
from bayes_talk.estimators import registry
from bayes_talk.estimators.base import Estimator
from bayes_talk.evaluation import harness as H
from bayes_talk.evaluation import metrics as M
from bayes_talk.evaluation import protocols as P
from bayes_talk.evaluation import systems as S


class PhoneMean(Estimator):
    """A dummy method: each frame's prediction is its phone's training mean, the variance its
    phone's training variance plus ``extra_var`` (a constructor argument, stored as given)."""

    name: ClassVar[str] = "dummy-phone-mean"

    def __init__(self, extra_var: float = 0.5) -> None:
        self.extra_var = extra_var

    def fit(self, train):
        z = np.concatenate([u.aam for u in train])
        labels = np.concatenate([np.asarray(u.labels) for u in train])
        self.phones_ = sorted(set(labels.tolist()))
        self.means_ = np.stack([z[labels == p].mean(0) for p in self.phones_])
        self.vars_ = np.stack([z[labels == p].var(0) for p in self.phones_]) + self.extra_var
        self.global_ = z.mean(0)
        return self

    def _rows(self, utt):
        index = {p: i for i, p in enumerate(self.phones_)}
        return np.array([index.get(p, -1) for p in utt.labels])

    def predict(self, utt):
        self._require_fitted()
        rows = self._rows(utt)
        return np.where(rows[:, None] >= 0, self.means_[rows], self.global_)

    def predict_var(self, utt):
        rows = self._rows(utt)
        return np.where(rows[:, None] >= 0, self.vars_[rows], self.vars_.mean(0))

    def _get_state(self):
        return {"phones": self.phones_}, {"means": self.means_, "vars": self.vars_, "global": self.global_}

    def _set_state(self, meta, arrays):
        self.phones_ = list(meta["phones"])
        self.means_, self.vars_, self.global_ = arrays["means"], arrays["vars"], arrays["global"]


@pytest.fixture
def registered(monkeypatch):
    """PhoneMean registered with one line, as a new method would be."""
    monkeypatch.setitem(registry.ESTIMATORS, PhoneMean.name, (PhoneMean, {}))
    return PhoneMean.name


def test_every_method_names_a_registered_family():
    for name, m in registry.METHODS.items():
        assert m.family in registry.ESTIMATORS, name
    for fam in ("zero", "oracle", "sparse-sgpdm", registry.DEFAULT_MODEL, "voice-puppetry", "context-mlp"):
        assert fam in registry.ESTIMATORS
        assert issubclass(registry.ESTIMATORS[fam][0], Estimator), fam


def test_a_method_is_scored_with_a_variance_exactly_when_its_estimator_has_a_distribution():
    """``has_variance`` of every method agrees with its family's estimator (e.g. ``hmm-mean``,
    whose per-phone variance is a predictive distribution, is scored as one)."""
    for name, m in registry.METHODS.items():
        assert m.has_variance == registry.ESTIMATORS[m.family][0].has_distribution(), name


def test_a_method_unknown_to_the_registry_is_refused_and_a_registered_one_is_known(registered):
    assert registered not in registry.METHODS            # the import-time table does not know it ...
    assert S.resolve_methods([registered]) == [registered]   # ... evaluate reads the registry afresh
    assert S.group_by_family([registered, "hmm-mean"]) == {registered: [registered], "hmm-mean": ["hmm-mean"]}
    m = S.get_method(registered)
    assert m.family == registered and m.has_variance and m.options == {}
    with pytest.raises(ValueError, match="unknown method.*'not-registered'"):
        S.resolve_methods(["not-registered"])


def test_a_registered_dummy_estimator_runs_through_evaluate(registered):
    utts = make_utterances(9, seed=3)
    proto = P.Protocol(name="tiny", paper="test", scheme="holdout", headline=(("AMSE", "mse"),),
                       default_methods=(registered,), system=S.SystemConfig(), n_train=6, n_test=3)
    res, traj = H.run_protocol(proto, utts, [registered, "zero"])
    e = res["methods"][registered]
    assert e["family"] == registered and e["has_variance"] is True
    # the scores are those of the dummy's own predictions, recomputed by hand
    by_name = {u.name: u for u in utts}
    split = res["splits"][0]
    model = PhoneMean().fit([by_name[n] for n in split["train"]])
    test = [by_name[n] for n in split["test"]]
    want = [M.mse([u.aam], [model.predict(u)])[0] for u in test]
    assert e["mse"]["mean"] == pytest.approx(np.mean(want), rel=1e-12)
    cover = [M.coverage([u.aam], *[[b] for b in model.predict_dist(u).interval(0.9)]) for u in test]
    assert e["coverage_90"]["mean"] == pytest.approx(np.mean(cover), rel=1e-12)
    assert "calibration" in e and "band_calibration" not in e      # no posterior method: no band calibration
    np.testing.assert_array_equal(traj.predictions[registered].mean, model.predict(test[0]))


def test_a_registered_familys_settings_are_its_constructor_arguments(registered):
    """A protocol sets a new family's constructor arguments by name, with nothing declared in
    the evaluation layer (its model is the family, registry.model_name); an argument its
    estimator does not take is refused, naming the ones it does."""
    assert registry.model_name(registered) == registered
    assert registry.model_settings(registered) == ("extra_var",)
    cfg = S.SystemConfig(models={registered: {"extra_var": 2.0}})
    assert S.build_family(registered, cfg).extra_var == 2.0
    assert S.build_family(registered, S.SystemConfig()).extra_var == PhoneMean().extra_var
    with pytest.raises(ValueError, match="constructor arguments dummy-phone-mean takes: extra_var"):
        S.SystemConfig(models={registered: {"n_states": 3}})
    assert registry.model_name("ssgpdm-phone-rc") == registry.model_name("ssgpdm-vlmm") == "ssgpdm"
    assert "states" not in registry.model_settings("ssgpdm")          # fixed by the family names


def test_a_registered_dummy_estimator_trains_and_synthesises(registered, shared_built_corpus, tmp_path):
    from bayes_talk import pipeline
    from bayes_talk.corpus import load_corpus
    from bayes_talk.pipeline.front_end import front_end as audio_front_end

    assert registered not in pipeline.MODEL_KINDS and registered in pipeline.model_kinds()
    out = pipeline.train(shared_built_corpus, registered, tmp_path / "model", alignment=False, extra_var=0.25)
    assert json.loads((out / "bayes_talk_model.json").read_text())["kind"] == registered
    assert (out / ESTIMATOR_DIR / "estimator.json").is_file()
    tm = pipeline.load_trained(out)
    assert isinstance(tm.model, PhoneMean) and tm.model.extra_var == 0.25 and tm.calibration is None
    wav = min((shared_built_corpus / "utterances").rglob("*.wav"))
    written = pipeline.synth(out, wav, wav.with_suffix(".lab"), tmp_path / "synth", video=False)
    assert "diagnostics" not in written                     # its own path ("map"): no posterior
    utt = pipeline.read_utterance(wav, wav.with_suffix(".lab"), tm.fps, **audio_front_end(tm.audio))
    want = tm.model.predict_dist(utt)
    np.testing.assert_array_equal(np.load(written["trajectory"]), want.mean)   # no post-filter for it
    np.testing.assert_array_equal(np.load(written["variance"]), want.var)
    with np.load(written["bands"]) as b:
        np.testing.assert_array_equal(b["upper90"], want.interval(0.9)[1])
    assert json.loads(written["segments"].read_text())["post_filter_hz"] is None
    assert np.load(written["landmarks"]).shape[0] == want.mean.shape[0]
    corpus = load_corpus(shared_built_corpus)
    np.testing.assert_allclose(tm.model.means_, PhoneMean().fit(corpus.sequences).means_, rtol=1e-12)
    with pytest.raises(ValueError, match="--posterior laplace needs a model with a whole-utterance posterior"):
        pipeline.synth(out, wav, wav.with_suffix(".lab"), tmp_path / "bad", video=False, posterior="laplace")
    with pytest.raises(ValueError, match="calibrate_bands: expected a fraction"):
        pipeline.train(shared_built_corpus, registered, tmp_path / "cal", alignment=False, calibrate_bands=0.2)
