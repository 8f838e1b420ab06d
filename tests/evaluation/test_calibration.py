"""Calibration metrics (coverage, PIT, mixture NLPD, CRPS) against closed forms, and the
band recalibration (fit on a mis-scaled synthetic case, apply, save/load)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.integrate
import scipy.stats

from bayes_talk.calibration.bands import (
    CALIBRATION_FILE,
    BandCalibration,
    min_scales,
    split_for_calibration,
)
from bayes_talk.evaluation.calibration import (
    PIT_BINS,
    markdown_calibration,
    plot_calibration,
    ratio_se,
    score_utterance,
    summarise_calibration,
)
from bayes_talk.synthesis.result import SynthesisResult


def _gauss(mean, var):
    return SynthesisResult.gaussian(mean, var, method="test")


def _mixture(means, vars_):
    """A result with K = len(means) components (C = 1 chain)."""
    return SynthesisResult("test", None, np.asarray(means)[None], np.asarray(vars_)[None])


def test_gaussian_scores_match_closed_forms():
    rng = np.random.default_rng(0)
    T, D = 30, 3
    mu, sd = rng.normal(size=(T, D)), rng.uniform(0.5, 2.0, size=(T, D))
    z = mu + sd * rng.normal(size=(T, D)) * 1.3
    sc = score_utterance(_gauss(mu, sd**2), z, levels=(0.5, 0.9))
    w = (z - mu) / sd
    for j, q in enumerate((0.5, 0.9)):
        want = np.sum(np.abs(w) <= scipy.stats.norm.ppf(0.5 + q / 2), axis=0)
        np.testing.assert_array_equal(sc.inside[j], want)
        np.testing.assert_allclose(sc.width[j], np.sum(2 * scipy.stats.norm.ppf(0.5 + q / 2) * sd, axis=0))
    nlpd = -scipy.stats.norm.logpdf(z, mu, sd).sum(0)
    np.testing.assert_allclose(sc.nlpd, nlpd, rtol=1e-12)
    crps = sd * (w * (2 * scipy.stats.norm.cdf(w) - 1) + 2 * scipy.stats.norm.pdf(w) - 1 / np.sqrt(np.pi))
    np.testing.assert_allclose(sc.crps, crps.sum(0), rtol=1e-12)
    pit = scipy.stats.norm.cdf(w)
    want_counts = np.stack([np.histogram(pit[:, d], bins=PIT_BINS, range=(0, 1))[0] for d in range(D)], 1)
    np.testing.assert_array_equal(sc.pit_counts, want_counts)


def test_mixture_nlpd_is_the_mixture_density_and_crps_its_integral():
    # one entry, two well separated components: a moment-matched Gaussian would be wrong
    means, vars_ = np.array([[[-2.0]], [[2.0]]]), np.array([[[0.25]], [[1.0]]])
    res = _mixture(means, vars_)
    z = np.array([[0.3]])
    sc = score_utterance(res, z, crps_samples=40000, seed=1)
    dens = 0.5 * scipy.stats.norm.pdf(0.3, -2, 0.5) + 0.5 * scipy.stats.norm.pdf(0.3, 2, 1.0)
    assert sc.nlpd[0] == pytest.approx(-np.log(dens), rel=1e-12)
    moment_matched = -scipy.stats.norm.logpdf(0.3, 0.0, np.sqrt(res.var[0, 0]))
    assert abs(sc.nlpd[0] - moment_matched) > 0.1

    def F(x):
        return 0.5 * scipy.stats.norm.cdf(x, -2, 0.5) + 0.5 * scipy.stats.norm.cdf(x, 2, 1.0)

    crps = scipy.integrate.quad(lambda x: F(x) ** 2, -np.inf, 0.3)[0] + \
        scipy.integrate.quad(lambda x: (1 - F(x)) ** 2, 0.3, np.inf)[0]
    assert sc.crps[0] == pytest.approx(crps, rel=0.02)
    # PIT of the truth is F(z): z = 0.3 lies in the bin of F(0.3)
    assert sc.pit_counts[int(F(0.3) * PIT_BINS), 0] == 1


def test_ratio_se_by_hand():
    a, b = np.array([3.0, 5.0, 9.0]), np.array([10.0, 10.0, 20.0])
    r = 17.0 / 40.0
    se = np.sqrt(3 / 2 * np.sum((a - r * b) ** 2)) / 40.0
    assert ratio_se(a, b) == pytest.approx((r, se), rel=1e-14)
    assert np.isnan(ratio_se(a[:1], b[:1])[1])


def _scores(scale_truth, n=40, T=25, D=4, seed=0):
    rng = np.random.default_rng(seed)
    out, res, truths = [], [], []
    for _ in range(n):
        mu, sd = rng.normal(size=(T, D)), rng.uniform(0.5, 1.5, size=(T, D))
        z = mu + np.asarray(scale_truth) * sd * rng.normal(size=(T, D))
        r = _gauss(mu, sd**2)
        out.append(score_utterance(r, z))
        res.append(r)
        truths.append(z)
    return out, res, truths


def test_summary_detects_calibrated_and_too_narrow_bands():
    good = summarise_calibration(_scores(1.0)[0])
    for q in (0.5, 0.8, 0.9, 0.95):
        c = good["coverage"][f"{q:g}"]
        assert abs(c["pooled"] - q) < 4 * c["pooled_se"] + 1e-3, (q, c)
        assert len(c["per_param"]) == 4
    assert good["params_in_range_90"] == 1.0
    assert good["pit"]["ks"] < 0.03
    bad = summarise_calibration(_scores(2.0)[0])
    c90 = bad["coverage"]["0.9"]
    assert c90["pooled"] < 0.65                        # 2σ truth in a ±1.645σ band: P ≈ 0.59
    assert c90["pooled"] == pytest.approx(2 * scipy.stats.norm.cdf(1.645 / 2) - 1, abs=4 * c90["pooled_se"])
    assert bad["params_in_range_90"] == 0.0
    counts = np.asarray(bad["pit"]["counts"])
    assert counts[0] > 2 * counts[PIT_BINS // 2] and counts[-1] > 2 * counts[PIT_BINS // 2]  # U shape
    assert bad["nlpd"]["mean"] > good["nlpd"]["mean"] and bad["crps"]["mean"] > good["crps"]["mean"]
    md = markdown_calibration({"good": {"calibration": good}, "bad": {"calibration": bad, "calibration_raw": good}})
    assert md.count("\n| ") == 4 and "bad (raw)" in md and "cov90" in md


def test_plot_calibration_writes_png(tmp_path):
    s = summarise_calibration(_scores(1.0, n=3)[0])
    p = plot_calibration({"a": s, "b": s}, tmp_path / "cal.png", title="t")
    assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_recalibration_recovers_the_mis_scale():
    scale_truth = np.array([2.0, 0.5, 1.0, 3.0])
    _, res, truths = _scores(scale_truth, n=30, seed=1)
    cal = BandCalibration.fit(res, truths, method="test")
    np.testing.assert_allclose(cal.scale, scale_truth, rtol=0.08)
    assert cal.coverage_raw["0.9"] < 0.8
    for q in ("0.5", "0.8", "0.9", "0.95"):
        assert cal.coverage_calibrated[q] == pytest.approx(float(q), abs=0.02)
    # on fresh data from the same mis-scaling, the calibrated bands cover as nominal
    fresh = _scores(scale_truth, n=30, seed=2)
    scored = summarise_calibration([score_utterance(cal.apply(r), z) for r, z in zip(fresh[1], fresh[2])])
    for q in (0.5, 0.9):
        c = scored["coverage"][f"{q:g}"]
        assert abs(c["pooled"] - q) < 4 * c["pooled_se"] + 0.01, (q, c)
    pooled = BandCalibration.fit(res, truths, method="test", per_parameter=False)
    assert np.ptp(pooled.scale) == 0 and 0.5 < pooled.scale[0] < 3.0


def test_apply_is_an_affine_map_of_the_mixture():
    rng = np.random.default_rng(3)
    means, vars_ = rng.normal(size=(6, 5, 3)), rng.uniform(0.1, 1.0, size=(6, 5, 3))
    res = _mixture(means, vars_)
    cal = BandCalibration(np.array([2.0, 0.5, 1.0]), "test")
    out = cal.apply(res)
    np.testing.assert_allclose(out.mean, res.mean, atol=1e-12)
    np.testing.assert_allclose(out.var, res.var * cal.scale**2, rtol=1e-10)
    lo, hi = res.interval(0.9)
    lo2, hi2 = out.interval(0.9)
    m = res.mean
    np.testing.assert_allclose(hi2 - m, cal.scale * (hi - m), rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(m - lo2, cal.scale * (m - lo), rtol=1e-7, atol=1e-9)
    assert out.diagnostics["band_calibration"]["scale_max"] == 2.0
    # min_scales: the truth at the scaled band's edge needs exactly that scale
    z = m + cal.scale * (hi - m)
    np.testing.assert_allclose(min_scales(res, z, (0.9,))[0], np.broadcast_to(cal.scale, m.shape), rtol=1e-8)
    with pytest.raises(ValueError, match="3 factors but the prediction has 2"):
        BandCalibration(np.ones(3), "test").apply(_gauss(np.zeros((4, 2)), np.ones((4, 2))))


def test_save_load_round_trip_and_bad_files(tmp_path):
    cal = BandCalibration(np.array([1.5, 0.7]), "laplace", n_utterances=3, n_frames=90,
                          coverage_raw={"0.9": 0.7}, coverage_calibrated={"0.9": 0.9}, held_out=["a", "b", "c"],
                          info={"holdout": 0.2})
    assert BandCalibration.load(tmp_path) is None
    cal.save(tmp_path)
    back = BandCalibration.load(tmp_path)
    np.testing.assert_array_equal(back.scale, cal.scale)
    assert (back.method, back.held_out, back.coverage_raw, back.info) == ("laplace", ["a", "b", "c"],
                                                                          {"0.9": 0.7}, {"holdout": 0.2})
    p = tmp_path / CALIBRATION_FILE
    d = json.loads(p.read_text())
    d["scale"] = [1.0, -1.0]
    p.write_text(json.dumps(d))
    with pytest.raises(ValueError, match="band_calibration.json.*factors > 0"):
        BandCalibration.load(tmp_path)
    d["version"] = 99
    p.write_text(json.dumps(d))
    with pytest.raises(ValueError, match="version 99"):
        BandCalibration.load(tmp_path)
    p.write_text("{")
    with pytest.raises(ValueError, match="unreadable"):
        BandCalibration.load(tmp_path)


def test_split_for_calibration_is_seeded_and_disjoint():
    fit, held = split_for_calibration(20, 0.2, seed=4)
    assert len(held) == 4 and sorted(fit + held) == list(range(20))
    assert split_for_calibration(20, 0.2, seed=4) == (fit, held)
    assert split_for_calibration(20, 0.2, seed=5) != (fit, held)
    with pytest.raises(ValueError, match="at least 3"):
        split_for_calibration(2, 0.2)
    with pytest.raises(ValueError, match="fraction"):
        split_for_calibration(10, 1.5)


def test_per_state_coverage_pools_each_state_models_frames():
    """Frames synthesised by a state whose bands are too narrow show up in that state's 90 %
    coverage and not in the other's; the fraction in range counts states with enough entries."""
    from bayes_talk.evaluation.calibration import MIN_STATE_ENTRIES
    from bayes_talk.models.vlmm import Segment

    rng = np.random.default_rng(0)
    T, D = 200, 3
    truth = rng.standard_normal((T, D))
    truth[100:] *= 3.0   # the second state's frames are 3σ wide: its ±1.645σ bands cover ≈ 0.41
    res = SynthesisResult.gaussian(np.zeros((T, D)), np.ones((T, D)), method="test",
                                   segments=[Segment(("a",), 0, 100), Segment(("b", "c"), 100, 200)],
                                   model_states=[("a",), ("c",)])
    summ = summarise_calibration([score_utterance(res, truth), score_utterance(res, truth)])
    st = summ["per_state_90"]["states"]
    assert set(st) == {"a", "c"} and st["a"]["entries"] == 2 * 100 * D
    assert abs(st["a"]["coverage_90"] - 0.9) < 0.05 and st["c"]["coverage_90"] < 0.55
    assert 2 * 100 * D >= MIN_STATE_ENTRIES and summ["per_state_90"]["states_in_range_90"] == 0.5
    plain = summarise_calibration([score_utterance(_gauss(np.zeros((T, D)), np.ones((T, D))), truth)])
    assert "per_state_90" not in plain
    assert "states in [0.80, 0.97]" in markdown_calibration({"m": {"calibration": summ}})


def test_paired_difference_se_and_the_verdict_by_two_se():
    """difference_se is ratio_se of the per-utterance differences: by hand, and a method that
    is better on every utterance by a constant beats its control by more than 2 s.e."""
    from bayes_talk.evaluation.calibration import control_verdict, paired_difference_se

    rng = np.random.default_rng(0)
    truths = [rng.normal(size=(30 + 5 * i, 2)) for i in range(6)]
    good = [score_utterance(_gauss(np.zeros_like(t), np.ones_like(t)), t) for t in truths]
    wide = [score_utterance(_gauss(np.zeros_like(t), np.full_like(t, 9.0)), t) for t in truths]
    a, b = summarise_calibration(good), summarise_calibration(wide)
    d = np.array(a["nlpd"]["per_utterance"]) - np.array(b["nlpd"]["per_utterance"])
    n = np.array(a["nlpd"]["entries"], float)
    assert paired_difference_se(a["nlpd"], b["nlpd"]) == pytest.approx(ratio_se(d, n)[1], rel=1e-12)
    v = control_verdict({"calibration": a, "calibration_control": b})
    assert v["beats"] and v["beats_by_2se"]
    assert v["nlpd"]["difference"] < -2 * v["nlpd"]["difference_se"]
    same = control_verdict({"calibration": a, "calibration_control": a})
    assert not same["beats"] and not same["beats_by_2se"]


def test_resolution_sees_bands_that_widen_with_the_error():
    """A predictive whose s.d. tracks the error's scale has a positive Spearman correlation
    and RMS errors rising across width bins; a constant band has neither."""
    from bayes_talk.evaluation.calibration import resolution

    rng = np.random.default_rng(1)
    sd = rng.uniform(0.1, 3.0, size=(4000, 2))
    err = np.abs(rng.normal(size=sd.shape) * sd)
    r = resolution(sd, err)
    assert r["spearman_median"] > 0.4
    assert np.all(np.diff(r["rms_by_width_bin"]) > 0)
    flat = resolution(np.ones_like(sd), err)
    assert flat["spearman_median"] == 0.0
    s = summarise_calibration([score_utterance(_gauss(np.zeros((50, 2)), np.ones((50, 2))), rng.normal(size=(50, 2)))])
    assert s["resolution"]["spearman_median"] == 0.0 and s["mse"]["mean"] > 0
