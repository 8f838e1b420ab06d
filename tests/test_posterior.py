"""The synthesis posterior (DESIGN.md §6): samplers on a known Gaussian, the mixture
predictive, reproducibility, ArviZ diagnostics and band coverage on toy data."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from toydata import make_utterances

from bayes_talk.evaluation.diagnostics import DIAGNOSTIC_KEYS, chain_diagnostics
from bayes_talk.evaluation.metrics import coverage
from bayes_talk.models.switching import SwitchingSGPDM
from bayes_talk.synthesis.posterior import sample_synthesis, segment_density
from bayes_talk.synthesis.samplers import run_emcee, run_laplace, run_nuts

SMALL = dict(latent_dim=3, max_iter=40, min_count=4, max_frames_per_state=120, fallback_frames=150)

# a correlated 2-D Gaussian with known moments
MU = np.array([1.0, -2.0])
COV = np.array([[1.0, 0.8], [0.8, 2.0]])
_P = torch.as_tensor(np.linalg.inv(COV))
_MU = torch.as_tensor(MU)


def gauss_lp(x: torch.Tensor) -> torch.Tensor:
    r = x - _MU
    return -0.5 * r @ _P @ r


@pytest.fixture(scope="module")
def gauss_draws():
    return {
        "nuts": run_nuts(gauss_lp, np.zeros(2), n_draws=400, warmup=150, chains=2, seed=3),
        "emcee": run_emcee(gauss_lp, np.zeros(2), n_draws=100, warmup=300, thin=5, seed=3),
        "laplace": run_laplace(gauss_lp, MU, n_draws=800, seed=3),
    }


@pytest.mark.parametrize("method", ["nuts", "emcee", "laplace"])
def test_samplers_recover_a_known_gaussian(gauss_draws, method):
    d = gauss_draws[method]
    flat = d.flat
    diag = chain_diagnostics(d.samples)
    # Monte-Carlo standard error of the mean from the (bulk) effective sample size
    ess = max(diag["ess_bulk_min"], 20.0)
    se = np.sqrt(np.diag(COV) / ess)
    assert np.all(np.abs(flat.mean(0) - MU) < 4 * se), (method, flat.mean(0), se)
    # variance: relative s.e. of a Gaussian sample variance ≈ sqrt(2 / ess)
    rel = np.abs(flat.var(0) / np.diag(COV) - 1)
    assert np.all(rel < 4 * np.sqrt(2 / ess) + 0.02), (method, flat.var(0))
    corr = np.corrcoef(flat.T)[0, 1]
    assert abs(corr - 0.8 / np.sqrt(2.0)) < 0.1, (method, corr)


def test_laplace_is_exact_on_a_gaussian():
    d = run_laplace(gauss_lp, MU, n_draws=10, seed=0)
    np.testing.assert_allclose(d.stats["cov"], COV, rtol=1e-8)
    np.testing.assert_allclose(d.stats["mean"], MU)


def test_diagnostics_keys_and_rhat_near_one(gauss_draws):
    for method, d in gauss_draws.items():
        diag = chain_diagnostics(d.samples)
        assert set(DIAGNOSTIC_KEYS) <= set(diag)
        assert diag["rhat_max"] < 1.05, (method, diag["rhat_max"])
        assert diag["ess_bulk_min"] > 50 and diag["ess_tail_min"] > 50, (method, diag)
    assert gauss_draws["nuts"].stats["divergences"] == [0, 0]
    assert 0.15 < gauss_draws["emcee"].stats["acceptance_fraction"] < 0.9


def test_diagnostics_flag_chains_that_disagree():
    rng = np.random.default_rng(0)
    s = rng.standard_normal((2, 200, 1))
    s[1] += 3.0  # two chains stuck in different places
    assert chain_diagnostics(s)["rhat_max"] > 1.5


def test_sampler_seeds_reproduce(gauss_draws):
    a = run_nuts(gauss_lp, np.zeros(2), n_draws=20, warmup=20, seed=5)
    b = run_nuts(gauss_lp, np.zeros(2), n_draws=20, warmup=20, seed=5)
    c = run_nuts(gauss_lp, np.zeros(2), n_draws=20, warmup=20, seed=6)
    assert np.array_equal(a.samples, b.samples) and not np.array_equal(a.samples, c.samples)
    e1 = run_emcee(gauss_lp, np.zeros(2), n_draws=10, warmup=20, seed=5)
    e2 = run_emcee(gauss_lp, np.zeros(2), n_draws=10, warmup=20, seed=5)
    assert np.array_equal(e1.samples, e2.samples)


# ------------------------------------------------------------------ toy switching model
@pytest.fixture(scope="module")
def toy():
    train = make_utterances(24, seed=0)
    test = make_utterances(3, seed=1, mean_len=20)
    return SwitchingSGPDM(states="vlmm", **SMALL).fit(train), test


def test_map_point_is_the_algorithm_1_optimum(toy):
    """The posterior's MAP path optimises the same density as Algorithm 1."""
    model, test = toy
    s = test[0]
    r = sample_synthesis(model, s.mfcc, s.labels, method="laplace", n_draws=16, smoothness="off", map_iter=60)
    m = model.synthesize(s.mfcc, s.labels, smoothness="off", max_iter=60)
    np.testing.assert_allclose(r.map_latents, m.latents)
    # and the density is sequence_log_density: finite, maximal near the MAP point
    seg = r.segments[0]
    key, sm = model.model_for(seg.state)
    dens = segment_density(sm, s.mfcc[seg.start:seg.stop], model.entry_[key], None, model.motion_var_)
    x = torch.as_tensor(r.map_latents[seg.start:seg.stop].reshape(-1))
    assert float(dens(x)) > float(dens(x + 0.05))


def test_laplace_synthesis_mixture_and_reproducibility(toy):
    model, test = toy
    s = test[1]
    r = sample_synthesis(model, s.mfcc, s.labels, method="laplace", n_draws=64, seed=1)
    T, Dz = s.aam.shape
    assert r.mean.shape == (T, Dz) and r.var.shape == (T, Dz) and r.latents.shape == (64, T, 3)
    # mixture variance = mean GP variance + spread of the means >= mean GP variance
    assert np.all(r.var >= r.gp_var - 1e-15) and np.mean(r.var - r.gp_var) > 0
    np.testing.assert_allclose(r.var, r.draw_var.mean(0) + r.draw_mean.var(0))
    r2 = sample_synthesis(model, s.mfcc, s.labels, method="laplace", n_draws=64, seed=1)
    r3 = sample_synthesis(model, s.mfcc, s.labels, method="laplace", n_draws=64, seed=2)
    assert np.array_equal(r.latents, r2.latents) and not np.array_equal(r.latents, r3.latents)
    q1, q2 = r.quantiles(), r2.quantiles()
    assert all(np.array_equal(q1[k][0], q2[k][0]) for k in q1)


@pytest.mark.parametrize("method", ["nuts", "emcee"])
def test_mcmc_synthesis_runs_with_diagnostics(toy, method):
    model, test = toy
    s = test[2]
    kw = dict(warmup=40, chains=2) if method == "nuts" else dict(warmup=60)
    r = sample_synthesis(model, s.mfcc[:10], s.labels[:10], method=method, n_draws=16, seed=0, **kw)
    assert r.latents.shape[:2] == (16, 10) and np.all(np.isfinite(r.mean)) and np.all(r.var > 0)
    assert len(r.diagnostics) == len(r.segments)
    for d in r.diagnostics:
        assert {"rhat_max", "ess_bulk_min", "ess_tail_min", "seconds"} <= set(d)
        assert ("divergences" in d) if method == "nuts" else ("acceptance_fraction" in d)
    assert np.all(r.var >= r.gp_var)
    r2 = sample_synthesis(model, s.mfcc[:10], s.labels[:10], method=method, n_draws=16, seed=0, **kw)
    assert np.array_equal(r.latents, r2.latents)


def test_band_coverage_on_held_out_toy_data_is_monotone(toy):
    model, test = toy
    levels = (0.5, 0.8, 0.9, 0.95)
    bands = {q: ([], []) for q in levels}
    truth = []
    for s in test[:2]:
        r = sample_synthesis(model, s.mfcc, s.labels, method="laplace", n_draws=64, seed=0)
        q = r.quantiles(levels)
        truth.append(s.aam)
        for k in levels:
            bands[k][0].append(q[k][0])
            bands[k][1].append(q[k][1])
    cov = [coverage(truth, *bands[k]) for k in levels]
    print("coverage", dict(zip(levels, cov)))
    assert all(0.0 <= c <= 1.0 for c in cov)
    assert all(a <= b for a, b in zip(cov, cov[1:])) and cov[-1] > cov[0]
    widths = [np.mean([np.mean(hi - lo) for lo, hi in zip(*bands[k])]) for k in levels]
    assert all(a < b for a, b in zip(widths, widths[1:]))
