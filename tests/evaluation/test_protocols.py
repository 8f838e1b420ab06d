"""Evaluation protocols, method registry, reports and the ``evaluate`` command (issue #5).

Everything runs on the synthetic utterances of tests/toydata.py with tiny model settings;
the GP families are exercised once (module fixture) to keep the file well under a minute.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from toydata import PHONES, make_utterances

from bayes_talk.app import cli
from bayes_talk.corpus import Corpus
from bayes_talk.estimators.baselines import REGISTRY
from bayes_talk.evaluation import harness as H
from bayes_talk.evaluation import metrics as M
from bayes_talk.evaluation import protocols as P
from bayes_talk.evaluation import splits as SP
from bayes_talk.evaluation import systems as S

# min_frames_per_state > max_frames_per_state: only the fallback SGPDM of each switching
# model is trained (the harness, not the switching models, is under test here)
TINY_GP = S.SystemConfig(
    latent_dim=2, synth_max_iter=3,
    models={"ssgpdm": {"max_frames_per_state": 30, "min_frames_per_state": 50, "min_count": 5, "max_iter": 5,
                       "fallback_frames": 40},
            "sgplvm": {"max_frames": 40, "max_iter": 5}, "voice-puppetry": {"n_states": 4, "n_iter": 5},
            "slds": {"n_iter": 5}, "dpds": {"max_iter": 20},
            "sparse-sgpdm": {"n_inducing": 8, "max_iter": 5, "synth_max_iter": 3}},
    synthesis={"sgplvm": {"max_iter": 3}})
METRIC_KEYS = ("mse", "rms", "l1", "linf", "nmse", "corr")
CAL_KEYS = ("coverage_50", "coverage_90", "crps", "nlpd")
CEILING = ("zero", "oracle")  # bayes_talk.evaluation.ceiling, tested in tests/evaluation/test_ceiling.py


def tiny(scheme: str = "kfold", methods=("hmm-mean",), **kw) -> P.Protocol:
    base = {"name": "tiny", "paper": "test", "scheme": scheme, "headline": (("AMSE", "mse"), ("ACC", "corr")),
            "default_methods": tuple(methods), "system": TINY_GP, "n_folds": 3 if scheme == "kfold" else None}
    base.update(kw)
    return P.Protocol(**base)


@pytest.fixture(scope="module")
def utts():
    return make_utterances(9, seed=3)


# ------------------------------------------------------------------------------ registry
def test_method_registry_complete_and_families_shared():
    assert set(S.METHODS) == {
        "ssgpdm-vlmm-optimise", "ssgpdm-vlmm-predict", "ssgpdm-phone-optimise", "ssgpdm-phone-predict",
        "ssgpdm-vlmm-posterior", "ssgpdm-phone-posterior",
        "ssgpdm-vlmm-rc-posterior", "ssgpdm-phone-rc-posterior", "ssgpdm-vlmm-rc-optimise",
        "ssgpdm-phone-rc-optimise", "ssgpdm-phone-ctx-posterior", "ssgpdm-phone-ctx-mean-posterior",
        "sgplvm-a", "sgplvm-b", "voice-puppetry", "slds", "dpds", "hmm-mean",
        "context-ridge", "context-mlp", "zero", "oracle", "sparse-sgpdm"}
    fam = S.group_by_family(["sgplvm-a", "hmm-mean", "sgplvm-b", "ssgpdm-vlmm-predict", "ssgpdm-vlmm-optimise"])
    assert fam == {"sgplvm": ["sgplvm-a", "sgplvm-b"], "hmm-mean": ["hmm-mean"],
                   "ssgpdm-vlmm": ["ssgpdm-vlmm-predict", "ssgpdm-vlmm-optimise"]}


def test_unknown_method_lists_valid_names():
    with pytest.raises(ValueError) as exc:
        S.resolve_methods("hmm-mean,not-a-method")
    msg = str(exc.value)
    assert "not-a-method" in msg
    for name in S.METHODS:
        assert name in msg
    with pytest.raises(ValueError, match="valid protocols"):
        P.get_protocol("deena2011")


def test_bad_settings_are_value_errors():
    with pytest.raises(ValueError, match="latent_dim"):
        S.SystemConfig(latent_dim=0)
    with pytest.raises(ValueError, match="unknown system setting"):
        P.get_protocol("deena2010", bogus=1)
    with pytest.raises(ValueError, match="seed"):
        P.get_protocol("deena2010", seed=-1)
    with pytest.raises(ValueError, match="unknown model 'vp'"):
        S.SystemConfig(models={"vp": {"n_states": 4}})
    with pytest.raises(ValueError, match=r"unknown setting\(s\) \['n_state'\]"):
        P.get_protocol("deena2010", models={"voice-puppetry": {"n_state": 4}})
    with pytest.raises(ValueError, match="shared by every model"):
        S.SystemConfig(models={"ssgpdm": {"latent_dim": 3}})
    with pytest.raises(ValueError, match="shared by every model"):
        S.SystemConfig(models={"voice-puppetry": {"random_state": 3}})
    with pytest.raises(ValueError, match="unknown setting"):       # fixed by the family name
        S.SystemConfig(models={"ssgpdm": {"states": "phone"}})
    with pytest.raises(ValueError, match="validation_frames"):     # the estimator's own validation
        S.SystemConfig(models={"sgplvm": {"validation_frames": -1}})
    with pytest.raises(ValueError, match="set by the methods"):    # Algorithm 1-2's is synth_max_iter
        S.SystemConfig(synthesis={"ssgpdm": {"max_iter": 3}})
    with pytest.raises(ValueError, match="not keyword arguments"):
        S.SystemConfig(synthesis={"sparse-sgpdm": {"max_iter": 3}})
    with pytest.raises(ValueError, match="n_folds"):
        tiny(n_folds=1)


# ------------------------------------------------------------------------------ splits
@pytest.mark.parametrize("n_items,k", [(23, 10), (40, 4), (10, 10)])
def test_kfold_partitions_every_utterance_tested_once(n_items, k):
    splits = SP.make_splits(tiny(n_folds=k), n_items)
    assert len(splits) == k
    tested = np.concatenate([s.test for s in splits])
    assert sorted(tested.tolist()) == list(range(n_items))          # each exactly once
    for s in splits:
        assert not set(s.train) & set(s.test)
        assert sorted(s.train + s.test) == list(range(n_items))
        assert abs(len(s.test) - n_items / k) < 1


def test_quick_kfold_uses_seeded_subset():
    p = P.get_protocol("englebienne2008", quick=True)
    splits = SP.make_splits(p, 120)
    used = sorted(np.concatenate([s.test for s in splits]).tolist())
    assert len(used) == p.n_use == len(set(used))
    assert all(sorted(s.train + s.test) == used for s in splits)


def test_repeats_and_holdout_splits():
    p = P.get_protocol("deena2009")
    splits = SP.make_splits(p, 100)
    assert len(splits) == 10
    for s in splits:
        assert len(s.train) == 50 and len(s.test) == 20 and not set(s.train) & set(s.test)
        assert max(s.train + s.test) < 100
    assert len({s.test for s in splits}) == 10                     # the repeats differ
    h = SP.make_splits(P.get_protocol("deena2010"), 300)
    assert len(h) == 1 and len(h[0].train) == 250 and len(h[0].test) == 28
    with pytest.raises(ValueError, match="needs at least 278"):
        SP.make_splits(P.get_protocol("deena2010"), 277)


@pytest.mark.parametrize("name", ["deena2009", "deena2010", "englebienne2008"])
def test_same_seed_same_split_other_seed_other_split(name):
    n = 300
    a = SP.make_splits(P.get_protocol(name), n)
    b = SP.make_splits(P.get_protocol(name), n)
    c = SP.make_splits(P.get_protocol(name, seed=7), n)
    assert a == b
    assert [s.test for s in a] != [s.test for s in c]


def test_quick_variants_are_labelled_and_smaller():
    for name in P.PROTOCOLS:
        full, quick = P.get_protocol(name), P.get_protocol(name, quick=True)
        assert quick.quick and not full.quick
        assert quick.n_needed <= full.n_needed or full.scheme == "kfold"
        assert "quick" in quick.describe()
    assert P.get_protocol("deena2009").system.latent_dim == 8
    assert P.get_protocol("deena2010").system.latent_dim == 6


def test_a_protocol_sets_a_models_constructor_arguments_by_name():
    """Per-model settings reach every family of the model, with the shared latent_dim and seed;
    an override changes one argument and keeps the rest of the quick variant's."""
    p = P.get_protocol("englebienne2008", quick=True, seed=3, models={"voice-puppetry": {"n_states": 4}})
    vp = S.build_family("voice-puppetry", p.system).get_params()
    assert (vp["n_states"], vp["n_iter"], vp["random_state"]) == (4, 20, 3)
    for fam in ("ssgpdm-vlmm", "ssgpdm-phone-ctx-mean"):
        sw = S.build_family(fam, p.system).get_params()
        assert (sw["max_iter"], sw["min_frames_per_state"], sw["latent_dim"], sw["seed"]) == (40, 30, 6, 3)
    assert S.build_family("sgplvm", p.system).get_params()["max_iter"] == 40
    assert p.system.synthesis == {"sgplvm": {"max_iter": 30}}
    assert P.PROTOCOLS["englebienne2008"].system.models == S.DEFAULT_MODELS     # nothing leaked back
    full = S.build_family("voice-puppetry", P.get_protocol("englebienne2008").system).get_params()
    assert full["n_states"] != 4 and full["n_iter"] != 20


# ------------------------------------------------------------------------------ test corpus
def test_mismatched_test_corpus_refused():
    train = make_utterances(3, seed=0)
    with pytest.raises(ValueError, match=r"visual feature dimension.*D_z = 5.*test has 4"):
        SP.check_test_set(train, make_utterances(2, seed=1, Dz=4))
    with pytest.raises(ValueError, match=r"audio feature dimension.*D_y = 8.*test has 6"):
        SP.check_test_set(train, make_utterances(2, seed=1, Dy=6))
    with pytest.raises(ValueError, match=r"phone set.*only in test \['zz'\]"):
        SP.check_test_set(train, make_utterances(2, seed=1), list(PHONES), list(PHONES) + ["zz"])
    odd = make_utterances(1, seed=1)[0]
    odd = dataclasses.replace(odd, labels=["zz"] + odd.labels[1:])
    with pytest.raises(ValueError, match=r"phone set.*\['zz'\]"):
        SP.check_test_set(train, [odd])
    SP.check_test_set(train, make_utterances(2, seed=1), list(PHONES), list(PHONES))   # compatible: fine
    with pytest.raises(ValueError, match="visual feature dimension"):
        H.run_protocol(tiny(), train, ["hmm-mean"], test_sequences=make_utterances(2, seed=1, Dz=4))


# ------------------------------------------------------------------------------ harness
def _check_summary(s, n):
    assert set(s) == {"mean", "std", "ci95", "n"} and s["n"] == n
    assert s["ci95"][0] <= s["mean"] <= s["ci95"][1]


def test_harness_baselines_schema_and_values(utts):
    proto = tiny(n_folds=3)
    methods = ["hmm-mean", "dpds", "slds", "voice-puppetry"]
    res, traj = H.run_protocol(proto, utts, methods)
    json.dumps(res, allow_nan=False)
    assert res["protocol"] == "tiny" and res["quick"] is False
    assert res["n_splits"] == 3 and res["n_scored"] == 9 and res["n_test"] == 3 and res["n_train"] == 6
    tested = [n for s in res["splits"] for n in s["test"]]
    assert sorted(tested) == sorted(u.name for u in utts)
    assert list(res["methods"]) == methods
    for name, e in res["methods"].items():
        for k in METRIC_KEYS:
            _check_summary(e[k], 9)
        assert ("log_likelihood_per_frame" in e) == REGISTRY[name].has_log_likelihood
        # a baseline with a predictive variance (hmm-mean) is scored for calibration too
        assert all(k in e for k in CAL_KEYS) == S.METHODS[name].has_variance
        assert any(k in e for k in CAL_KEYS) == S.METHODS[name].has_variance
        assert e["train_seconds"] > 0 and e["synth_frames_per_second"] > 0
        assert e["headline"]["AMSE"] == e["mse"]["mean"]
        assert len(e["per_split"]) == 3
        assert e["rms"]["mean"] <= np.sqrt(e["mse"]["mean"]) + 1e-12          # Jensen
    # the numbers are the metrics of the real predictions: recompute hmm-mean by hand
    by_name = {u.name: u for u in utts}
    mses, lls = [], []
    for s in res["splits"]:
        model = REGISTRY["hmm-mean"]().fit([by_name[n] for n in s["train"]])
        for n in s["test"]:
            u = by_name[n]
            mses.append(M.mse([u.aam], [model.predict(u)])[0])
            lls.append(model.log_likelihood(u) / u.n_frames)
    hm = res["methods"]["hmm-mean"]
    assert hm["mse"]["mean"] == pytest.approx(np.mean(mses), rel=1e-10)
    assert hm["log_likelihood_per_frame"]["mean"] == pytest.approx(np.mean(lls), rel=1e-10)
    assert traj.utterance == res["splits"][0]["test"][0] and set(traj.predictions) == set(methods)


def test_harness_is_deterministic(utts):
    proto = tiny(n_folds=3)
    a, _ = H.run_protocol(proto, utts, ["hmm-mean", "voice-puppetry"])
    b, _ = H.run_protocol(proto, utts, ["hmm-mean", "voice-puppetry"])
    for name in a["methods"]:
        for k in METRIC_KEYS:
            assert a["methods"][name][k] == b["methods"][name][k]


def test_lowpass_filters_every_methods_mean(utts):
    from bayes_talk.synthesis.sequential import lowpass

    train, seq = utts[:8], utts[8]
    cfg4 = dataclasses.replace(TINY_GP, lowpass_hz=4.0)
    for name in ("hmm-mean", "voice-puppetry"):
        model = S.fit_family(S.METHODS[name].family, train, TINY_GP)
        raw, filt = S.predict(name, model, seq, TINY_GP), S.predict(name, model, seq, cfg4)
        np.testing.assert_allclose(filt.mean, lowpass(raw.mean, 4.0), rtol=1e-12, atol=1e-12)
        assert not np.allclose(filt.mean, raw.mean)
    with pytest.raises(ValueError, match="lowpass_hz"):
        dataclasses.replace(TINY_GP, lowpass_hz=0.0)


@pytest.fixture(scope="module")
def gp_run(utts):
    """All six GP methods (three families) on one tiny holdout split, counting trainings (a
    family with a posterior method trains once with its calibration, here the post-hoc band
    calibration whose stages the tests below check)."""
    calls = []
    orig, orig_cal = H.fit_family, H.fit_calibrated_family

    def counting(family, train, cfg, executor=None):
        calls.append(family)
        return orig(family, train, cfg, executor=executor)

    def counting_cal(family, train, cfg, method, executor=None, progress=None):
        calls.append(family)
        return orig_cal(family, train, cfg, method, executor=executor, progress=progress)

    mp = pytest.MonkeyPatch()
    mp.setattr(H, "fit_family", counting)
    mp.setattr(H, "fit_calibrated_family", counting_cal)
    try:
        methods = [m for m in S.METHODS if S.METHODS[m].has_variance and m not in CEILING]
        res, traj = H.run_protocol(tiny("holdout", n_train=5, n_test=2,
                                        system=dataclasses.replace(TINY_GP, calibration="bands")), utts, methods)
    finally:
        mp.undo()
    return res, traj, calls


def test_harness_gp_families_train_once_and_report_calibration(gp_run):
    res, traj, calls = gp_run
    assert sorted(calls) == ["context-mlp", "context-ridge", "hmm-mean", "sgplvm", "sparse-sgpdm", "ssgpdm-phone",
                             "ssgpdm-phone-ctx", "ssgpdm-phone-ctx-mean", "ssgpdm-phone-rc", "ssgpdm-vlmm",
                             "ssgpdm-vlmm-rc"]  # shared training
    m = res["methods"]
    assert set(m) == {k for k, v in S.METHODS.items() if v.has_variance and k not in CEILING}
    for e in m.values():
        for k in METRIC_KEYS + CAL_KEYS + ("log_likelihood_per_frame",):
            _check_summary(e[k], 2)
        assert 0 <= e["coverage_50"]["mean"] <= e["coverage_90"]["mean"] <= 1
        assert e["crps"]["mean"] > 0
        assert e["synth_frames_per_second"] > 0
    assert m["sgplvm-a"]["train_seconds"] == m["sgplvm-b"]["train_seconds"]
    assert m["sgplvm-a"]["train_shared_with"] == ["sgplvm-b"]
    assert m["ssgpdm-vlmm-optimise"]["train_seconds"] == m["ssgpdm-vlmm-predict"]["train_seconds"]
    for p in traj.predictions.values():
        assert p.var is not None and p.mean.shape == traj.truth.shape
    # the posterior mean is not the MAP path, and its variance adds the spread of the draws
    lap, opt = traj.predictions["ssgpdm-vlmm-posterior"], traj.predictions["ssgpdm-vlmm-optimise"]
    assert not np.allclose(lap.mean, opt.mean)
    assert "ssgpdm-vlmm-optimise" in m["ssgpdm-vlmm-posterior"]["train_shared_with"]


def test_posterior_method_is_the_posterior_mixture(utts):
    from bayes_talk.posterior.sampling import sample_synthesis

    cfg = dataclasses.replace(TINY_GP, posterior_draws=16)
    model = S.fit_family("ssgpdm-phone", utts[:6], cfg)
    seq = utts[7]
    pred = S.predict("ssgpdm-phone-posterior", model, seq, cfg)
    r = sample_synthesis(model, seq.mfcc, seq.labels, method="laplace", n_draws=16, seed=cfg.seed)
    np.testing.assert_allclose(pred.mean, r.mean, rtol=1e-10)
    dm, dv = r.draw_mean[0], r.draw_var[0]
    np.testing.assert_allclose(pred.var, dv.mean(0) + dm.var(0), rtol=1e-10)


def test_report_markdown_and_figure(gp_run, tmp_path):
    from bayes_talk.evaluation import report

    res, traj, _ = gp_run
    table = report.markdown_table(res)
    lines = table.strip().splitlines()
    assert len(lines) == 2 + len(res["methods"])
    assert "cov90" in lines[0] and "AMSE" in lines[0]
    png = report.plot_trajectories(traj, tmp_path / "t.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.png"]                  # no temp left
    with pytest.raises(ValueError, match="no methods"):
        report.markdown_table({"methods": {}})


# ------------------------------------------------------------------------------ CLI
@pytest.fixture
def fake_corpora(monkeypatch, tmp_path):
    """load_corpus reads toy corpora: DIR names 'good', 'small-dz', 'odd-phones'."""
    loaded = []

    def fake_load(path, **kw):
        name = Path(path).name
        loaded.append((name, kw.get("aam")))
        seqs = {"good": lambda: make_utterances(12, seed=5), "test": lambda: make_utterances(3, seed=6),
                "small-dz": lambda: make_utterances(3, seed=6, Dz=4),
                "odd-phones": lambda: make_utterances(3, seed=6)}[name]()
        phones = list(PHONES) + (["zz"] if name == "odd-phones" else [])
        manifest = {"phone_set": phones, "aam": {"path": "aam.npz", "sha256": name}}   # each its own AAM
        return Corpus(path=Path(path), kind="built", sequences=seqs, manifest=manifest,
                      aam_path=Path(path) / "aam.npz")

    monkeypatch.setattr("bayes_talk.corpus.load_corpus", fake_load)
    tiny_eng = dataclasses.replace(P.PROTOCOLS["englebienne2008"], n_folds=3, system=TINY_GP)
    monkeypatch.setitem(P.PROTOCOLS, "englebienne2008", tiny_eng)
    return tmp_path, loaded


def test_cli_evaluate_writes_json_markdown_figure(fake_corpora, capsys):
    tmp, _ = fake_corpora
    out = tmp / "res.json"
    rc = cli.main(["evaluate", "--protocol", "englebienne2008", "--corpus", str(tmp / "good"),
                   "--methods", "hmm-mean,dpds", "--json", str(out)])
    assert rc == 0, capsys.readouterr().err
    res = json.loads(out.read_text())
    assert res["settings"]["lowpass_hz"] is None
    rc = cli.main(["evaluate", "--protocol", "englebienne2008", "--corpus", str(tmp / "good"),
                   "--methods", "hmm-mean", "--lowpass-hz", "4", "--json", str(tmp / "lp.json")])
    assert rc == 0, capsys.readouterr().err
    lp = json.loads((tmp / "lp.json").read_text())
    assert lp["settings"]["lowpass_hz"] == 4.0
    assert lp["methods"]["hmm-mean"]["mse"] != res["methods"]["hmm-mean"]["mse"]
    assert "low-passed at 4 Hz" in (tmp / "lp.md").read_text()
    assert "low-passed" not in (tmp / "res.md").read_text()
    for key in ("protocol", "quick", "n_train", "n_test", "methods"):
        assert key in res
    assert res["protocol"] == "englebienne2008" and res["quick"] is False
    assert res["n_scored"] == 12 and set(res["methods"]) == {"hmm-mean", "dpds"}
    assert res["methods"]["dpds"]["rms"]["n"] == 12
    md = (tmp / "res.md").read_text()
    assert "| hmm-mean |" in md and "res_trajectories.png" in md
    assert (tmp / "res_trajectories.png").read_bytes()[:4] == b"\x89PNG"
    assert not [p for p in tmp.iterdir() if p.name.startswith(".")]              # temp files gone


def test_cli_test_corpus_and_refusals(fake_corpora, capsys):
    tmp, loaded = fake_corpora
    base = ["evaluate", "--protocol", "englebienne2008", "--corpus", str(tmp / "good"), "--methods", "hmm-mean"]
    out = tmp / "tc.json"
    assert cli.main(base + ["--test-corpus", str(tmp / "test"), "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["scheme"] == "test-corpus" and res["n_train"] == 12 and res["n_test"] == 3
    # the test frames are projected through the training corpus's AAM, not their own
    assert loaded == [("good", None), ("test", tmp / "good" / "aam.npz")]
    assert res["test_features"] == "projected through the training corpus's AAM"
    assert (res["corpus"], res["test_corpus"]) == (str(tmp / "good"), str(tmp / "test"))
    for bad, what in (("small-dz", "visual feature dimension"), ("odd-phones", "phone set")):
        capsys.readouterr()
        assert cli.main(base + ["--test-corpus", str(tmp / bad), "--json", str(tmp / "x.json")]) == 2
        assert what in capsys.readouterr().err
    assert not (tmp / "x.json").exists()
    # unknown method: error lists the valid names, nothing loaded
    loaded.clear()
    assert cli.main(base[:-1] + ["hmm-mean,nope", "--json", str(out)]) == 2
    err = capsys.readouterr().err
    assert "nope" in err and "ssgpdm-vlmm-optimise" in err and not loaded


def test_cli_records_the_corpora_as_given(fake_corpora, monkeypatch):
    """Relative corpus paths stay relative in the result (no machine's directory in it), even
    when the corpus directory is a symlink that resolves elsewhere."""
    tmp, _ = fake_corpora
    (tmp / "data").mkdir()
    (tmp / "data" / "good").symlink_to(tmp / "good")
    monkeypatch.chdir(tmp)
    assert cli.main(["evaluate", "--protocol", "englebienne2008", "--corpus", "data/good", "--test-corpus",
                     "test", "--methods", "hmm-mean", "--json", "rel.json"]) == 0
    res = json.loads((tmp / "rel.json").read_text())
    assert (res["corpus"], res["test_corpus"]) == ("data/good", "test")


@pytest.mark.parametrize("where", ["missing-dir/out.json", "a-directory.json", "out.txt"])
def test_cli_unwritable_json_fails_before_loading(fake_corpora, capsys, monkeypatch, where):
    tmp, loaded = fake_corpora
    (tmp / "a-directory.json").mkdir()
    trained = []
    monkeypatch.setattr(H, "fit_family", lambda *a, **k: trained.append(a) or (_ for _ in ()).throw(AssertionError))
    rc = cli.main(["evaluate", "--protocol", "englebienne2008", "--corpus", str(tmp / "good"),
                   "--methods", "hmm-mean", "--json", str(tmp / where)])
    assert rc == 2
    assert "bayes-talk: error:" in capsys.readouterr().err
    assert not loaded and not trained


def test_quick_run_is_labelled_quick_in_the_result():
    proto = P.get_protocol("englebienne2008", quick=True, models={"voice-puppetry": {"n_states": 4}})
    res, _ = H.run_protocol(proto, make_utterances(proto.n_use + 5, seed=8), ["hmm-mean"])
    assert res["quick"] is True and "quick" in res["description"]
    assert res["n_splits"] == proto.n_folds and res["n_scored"] == proto.n_use
    assert res["settings"]["models"]["voice-puppetry"] == {"n_states": 4, "n_iter": 20}
    assert res["settings"]["families"]["hmm-mean"] == S.build_family("hmm-mean", proto.system).get_params()


def test_harness_reports_calibration_and_calibrated_and_raw_posterior(gp_run):
    res, traj, _ = gp_run
    for name, e in res["methods"].items():
        c = e["calibration"]
        assert c["n_utterances"] == 2 and set(c["coverage"]) == {"0.5", "0.8", "0.9", "0.95"}
        pooled = [c["coverage"][q]["pooled"] for q in ("0.5", "0.8", "0.9", "0.95")]
        assert pooled == sorted(pooled) and 0 <= pooled[0] and pooled[-1] <= 1       # nested bands
        assert len(c["coverage"]["0.9"]["per_param"]) == traj.truth.shape[1]
        assert sum(c["pit"]["counts"]) == c["n_entries"] and np.isfinite(c["nlpd"]["mean"])
        posterior = "posterior" in name
        calibrated = any("posterior" in n for n in [name, *e["train_shared_with"]])   # one wrapper, every method
        assert ("calibration_raw" in e) == calibrated and ("band_calibration" in e) == posterior
    post = res["methods"]["ssgpdm-vlmm-posterior"]
    (bc,) = post["band_calibration"]
    assert bc["method"] == "laplace" and len(bc["scale"]) == traj.truth.shape[1] and len(bc["held_out"]) == 1
    assert post["calibration_seconds"] > 0
    # stage 0 shrinks the mean by the factors a_d; stage 1 scales the shrunk mixture about
    # it, the second maps the levels (the calibrated 90 % band is a raw band of the mapped level)
    pred = traj.predictions["ssgpdm-vlmm-posterior"]
    a = np.asarray(bc["mean_scale"])
    assert a.shape == (traj.truth.shape[1],) and np.all((a >= 0) & (a <= 1))
    np.testing.assert_allclose(pred.result.mean, a * pred.raw.mean, atol=1e-10)
    shrunk = dataclasses.replace(pred.raw, draw_mean=pred.raw.draw_mean * a)
    # stage 3 pools the level-mapped result with N(mean, control_var) by the weights pool_weight
    assert len(bc["pool_weight"]) == traj.truth.shape[1]
    np.testing.assert_array_equal(pred.result.pool_weight, bc["pool_weight"])
    staged = pred.result.base
    np.testing.assert_allclose(staged.mixture.var, shrunk.var * np.asarray(bc["scale"]) ** 2, rtol=1e-8)
    w = np.asarray(bc["pool_weight"])
    np.testing.assert_allclose(pred.result.var, (1 - w) * staged.var + w * np.asarray(bc["control_var"]), rtol=1e-10)
    np.testing.assert_allclose(pred.result.cdf(pred.result.interval(0.9)[1]), 0.95, atol=1e-8)
    assert len(bc["level_raw"]) == traj.truth.shape[1]
    assert "## Calibration" in res["markdown_sections"][0] and "ssgpdm-vlmm-posterior (raw)" in \
        res["markdown_sections"][0]
    # the constant-band control: the calibrated mean, one band per parameter over all frames
    np.testing.assert_allclose(pred.control.mean, pred.result.mean, atol=1e-12)
    lo, hi = pred.control.interval(0.9)
    np.testing.assert_allclose(hi - lo, np.broadcast_to((hi - lo)[0], lo.shape), rtol=1e-9)
    v = post["uncertainty_beats_control"]
    assert post["calibration_control"]["n_utterances"] == 2
    assert v["beats"] == (v["nlpd"]["difference"] < 0 and v["crps"]["difference"] < 0)
    assert v["nlpd"]["control"] == post["calibration_control"]["nlpd"]["mean"]
    assert "ssgpdm-vlmm-posterior (constant-band control)" in res["markdown_sections"][0]
    assert f"ssgpdm-vlmm-posterior: its uncertainty {'beats' if v['beats'] else 'does NOT beat'}" in \
        res["markdown_sections"][0]
