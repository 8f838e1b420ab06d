"""The one synthesis result type: mixture moments, exact quantiles, InferenceData."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.stats as st

from bayes_talk.synthesis.result import SynthesisResult


def _mixture(C=2, S=6, T=4, D=3, d=2, seed=0) -> SynthesisResult:
    rng = np.random.default_rng(seed)
    m = 2.0 * rng.normal(size=(C, S, T, D))
    v = rng.uniform(0.05, 1.0, size=(C, S, T, D))
    return SynthesisResult("laplace", rng.normal(size=(C, S, T, d)), m, v, seed=seed)


def test_mixture_moments_follow_the_law_of_total_variance():
    r = _mixture()
    m, v = r.draw_mean.reshape(-1, 4, 3), r.draw_var.reshape(-1, 4, 3)
    np.testing.assert_allclose(r.mean, m.mean(0))
    np.testing.assert_allclose(r.var, v.mean(0) + m.var(0))
    s = r.sample(100_000, seed=1)
    np.testing.assert_allclose(s.mean(0), r.mean, atol=0.03)
    np.testing.assert_allclose(s.var(0), r.var, rtol=0.03)


@pytest.mark.parametrize("q", [0.025, 0.25, 0.5, 0.75, 0.95, 0.999])
def test_mixture_quantile_inverts_the_mixture_cdf(q):
    r = _mixture()
    y = r.quantile(q)
    np.testing.assert_allclose(r.cdf(y), q, atol=1e-9)
    # the CDF against a direct sum over the components with scipy
    m, sd = r.draw_mean.reshape(-1, 4, 3), np.sqrt(r.draw_var.reshape(-1, 4, 3))
    np.testing.assert_allclose(r.cdf(y), st.norm.cdf(y[None], m, sd).mean(0), rtol=1e-12)


def test_interval_covers_its_level_of_mixture_samples():
    r = _mixture(seed=3)
    s = r.sample(40_000, seed=4)
    for level in (0.5, 0.9):
        lo, hi = r.interval(level)
        cov = np.mean((s >= lo) & (s <= hi), axis=0)
        assert np.all(np.abs(cov - level) < 0.02), cov
    q = r.quantiles((0.5, 0.9))
    assert np.all(q[0.9][0] < q[0.5][0]) and np.all(q[0.5][1] < q[0.9][1])


def test_a_single_gaussian_gives_the_exact_normal_bands_and_density():
    rng = np.random.default_rng(5)
    mean, var = rng.normal(size=(6, 2)), rng.uniform(0.1, 2.0, size=(6, 2))
    r = SynthesisResult.gaussian(mean, var, rng.normal(size=(6, 3)), method="optimise")
    assert r.is_gaussian and r.latents.shape == (6, 3) and r.latent_draws.shape == (1, 1, 6, 3)
    lo, hi = r.interval(0.9)
    np.testing.assert_allclose(lo, st.norm.ppf(0.05, mean, np.sqrt(var)), rtol=1e-12)
    np.testing.assert_allclose(hi, st.norm.ppf(0.95, mean, np.sqrt(var)), rtol=1e-12)
    y = rng.normal(size=(6, 2))
    np.testing.assert_allclose(r.logpdf(y), st.norm.logpdf(y, mean, np.sqrt(var)), rtol=1e-12)


def test_mixture_logpdf_matches_scipy():
    r = _mixture(seed=7)
    y = np.random.default_rng(8).normal(size=(4, 3))
    m, sd = r.draw_mean.reshape(-1, 4, 3), np.sqrt(r.draw_var.reshape(-1, 4, 3))
    np.testing.assert_allclose(r.logpdf(y), np.log(st.norm.pdf(y[None], m, sd).mean(0)), rtol=1e-10)


def test_shift_moves_the_bands_and_keeps_their_widths():
    r = _mixture()
    delta = np.full((4, 3), 0.7)
    lo, hi = r.interval(0.8)
    lo2, hi2 = r.shift(delta).interval(0.8)
    np.testing.assert_allclose(lo2, lo + 0.7, atol=1e-9)
    np.testing.assert_allclose(hi2 - lo2, hi - lo, atol=1e-9)
    np.testing.assert_allclose(r.interval(0.8)[0], lo)  # the original is unchanged


def test_bad_shapes_and_levels_are_refused_with_the_field_named():
    m = np.zeros((1, 2, 3, 4))
    with pytest.raises(ValueError, match="draw_var"):
        SynthesisResult("x", None, m, np.ones((1, 2, 3, 5)))
    with pytest.raises(ValueError, match="draw_var"):
        SynthesisResult("x", None, m, -np.ones_like(m))
    with pytest.raises(ValueError, match="latent_draws"):
        SynthesisResult("x", np.zeros((1, 3, 3, 2)), m, np.ones_like(m))
    r = SynthesisResult("x", None, m, np.ones_like(m))
    with pytest.raises(ValueError, match="level"):
        r.interval(1.0)
    with pytest.raises(ValueError, match=r"\(3, 4\)"):
        r.cdf(np.zeros((4, 3)))


def test_inference_data_groups_and_netcdf_round_trip(tmp_path):
    import arviz as az

    r = _mixture(C=2, S=6, T=4, D=3, d=2)
    r.sample_stats = {"diverging": np.zeros((2, 6), bool)}
    r.diagnostics = {"rhat_max": np.float64(1.02)}
    truth = np.zeros((4, 3))
    idata = r.to_inference_data(truth=truth)
    assert set(idata.groups()) == {"posterior", "posterior_predictive", "sample_stats", "observed_data"}
    assert idata.posterior["latents"].shape == (2, 6, 4, 2)
    np.testing.assert_array_equal(idata.posterior["aam_mean"].values, r.draw_mean)
    pp = idata.posterior_predictive["aam"]
    assert pp.shape[0] == 2 and pp.shape[1] * 2 >= 100 and pp.shape[2:] == (4, 3)
    path = tmp_path / "p.nc"
    idata.to_netcdf(str(path))
    back = az.from_netcdf(str(path))
    assert back.posterior.attrs["bayes_talk_method"] == "laplace"
    assert '"rhat_max": 1.02' in back.posterior.attrs["bayes_talk_diagnostics"]
    summ = az.summary(back, var_names=["latents"])
    assert len(summ) == 4 * 2 and np.all(np.isfinite(summ["r_hat"]))
    with pytest.raises(ValueError, match=r"\(4, 3\)"):
        r.to_inference_data(truth=np.zeros((3, 3)))


def test_evaluate_scores_the_bands_of_the_result_not_a_gaussian_of_its_moments():
    from bayes_talk.evaluation.scoring import utterance_metrics
    from bayes_talk.evaluation.systems import Prediction

    # two well separated modes at ±3 (sd 0.5): the mixture's 50 % band is [-3, 3], the
    # moment-matched Gaussian's (sd 3.04) only ±2.05, which misses values near the modes
    T, D = 50, 2
    m = np.stack([np.full((T, D), -3.0), np.full((T, D), 3.0)])[None]      # (1, 2, T, D)
    r = SynthesisResult("laplace", None, m, np.full_like(m, 0.25))
    z = np.where(np.arange(T)[:, None] % 2 == 0, 0.0, 2.9) * np.ones((T, D))  # half at the gap, half by a mode
    pred = Prediction(r.mean, r.var, result=r)
    out = utterance_metrics(z, pred, np.ones(D), None)
    for level in (0.5, 0.9):
        lo, hi = r.interval(level)
        assert out[f"coverage_{int(level * 100)}"] == pytest.approx(np.mean((z >= lo) & (z <= hi)))
    assert out["coverage_50"] == pytest.approx(1.0)
    gauss = utterance_metrics(z, Prediction(r.mean, r.var), np.ones(D), None)
    assert gauss["coverage_50"] == pytest.approx(0.5)  # the values by a mode lie outside ±2.05


def test_a_low_pass_post_filter_moves_the_scored_bands_with_the_mean():
    import dataclasses

    from bayes_talk.evaluation import systems as S

    rng = np.random.default_rng(2)
    T, D = 40, 2
    m = np.cumsum(rng.normal(size=(1, 3, T, D)), axis=2)
    r = SynthesisResult("optimise", None, m, np.full_like(m, 0.1))

    class _Fixed:  # stands in for a fitted switching model
        def predict_dist(self, seq, algorithm="optimise", max_iter=0):
            return r

    seq = type("U", (), {"mfcc": np.zeros((T, 3)), "labels": ["a"] * T})()
    cfg = dataclasses.replace(S.SystemConfig(), lowpass_hz=4.0)
    pred = S.predict("ssgpdm-vlmm-optimise", _Fixed(), seq, cfg)
    from bayes_talk.synthesis.sequential import lowpass

    np.testing.assert_allclose(pred.mean, lowpass(r.mean, 4.0))
    lo, hi = pred.band(0.9)
    lo0, hi0 = r.interval(0.9)
    np.testing.assert_allclose(lo - lo0, pred.mean - r.mean, atol=1e-9)
    np.testing.assert_allclose(hi - lo, hi0 - lo0, atol=1e-9)
