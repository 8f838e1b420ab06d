"""Simulation-based calibration and predictive checks (DESIGN.md §6): SBC passes for an exact
posterior and fails for a deliberately wrong one; prior/posterior predictive checks through
pyro.infer.Predictive on the synthesis model."""
from __future__ import annotations

import inspect
import json

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.evaluation.sbc import (
    default_bins,
    holm,
    ranks,
    run_sbc,
    sampler_posterior,
    scaled_laplace,
    synthesis_sbc,
    uniformity_test,
)
from bayes_talk.evaluation.sbc_power import combined_verdict
from bayes_talk.posterior.predictive_checks import (
    posterior_predictive,
    predictive_check,
    prior_predictive,
)
from bayes_talk.posterior.sampling import sample_synthesis
from bayes_talk.synthesis.joint import make_plan

# conjugate Gaussian: θ ~ N(0, I_K), y = θ + N(0, s² I): posterior N(y/(1+s²), s²/(1+s²) I)
K, S2 = 4, 0.5


def _simulate(rng):
    theta = rng.standard_normal(K)
    return theta, theta + np.sqrt(S2) * rng.standard_normal(K)


def _posterior(var_scale):
    def post(y, seed):
        rng = np.random.default_rng(seed)
        m, v = y / (1 + S2), S2 / (1 + S2) * var_scale
        return m + np.sqrt(v) * rng.standard_normal((99, K))
    return post


def test_holm_matches_its_definition():
    p = np.array([0.01, 0.04, 0.03, 0.2])
    # sorted 0.01, 0.03, 0.04, 0.2 -> 4·0.01, max(·, 3·0.03), max(·, 2·0.04), max(·, 0.2)
    np.testing.assert_allclose(holm(p), [0.04, 0.09, 0.09, 0.2])


def test_ranks_count_draws_below_the_truth():
    draws = np.array([[[0.0], [1.0], [2.0], [3.0]]])
    assert ranks(np.array([[2.5]]), draws).tolist() == [[3]]
    assert ranks(np.array([[-1.0]]), draws).tolist() == [[0]]


def test_sbc_passes_for_the_exact_posterior_of_a_gaussian():
    res = run_sbc(_simulate, _posterior(1.0), n_sims=400, n_draws=19, seed=0)
    assert res.ranks.shape == (400, K) and res.ranks.min() >= 0 and res.ranks.max() <= 19
    assert res.passed, res.to_dict()
    assert abs(res.extreme_fraction - res.extreme_expected) < 0.03


@pytest.mark.parametrize("scale", [0.5, 2.0])
def test_sbc_fails_for_a_wrong_posterior_variance(scale):
    res = run_sbc(_simulate, _posterior(scale), n_sims=400, n_draws=19, seed=0)
    assert not res.passed and res.n_rejected == K, res.to_dict()
    # too narrow: the truth falls at the extremes; too wide: in the middle
    assert (res.extreme_fraction > 2 * res.extreme_expected) == (scale < 1)


def test_to_dict_reports_the_combined_verdict_which_rejects_a_0_85_spread_that_chi2_misses():
    # 200 simulations, 4 coordinates: the χ²-Holm test alone passes a posterior with 0.85× the
    # true spread (this seed); the pooled dispersion test of the combined verdict rejects it
    bad = run_sbc(_simulate, _posterior(0.85 ** 2), n_sims=200, n_draws=19, seed=0)
    d = bad.to_dict()
    assert d["passed"] and not d["verdict"]["passed"], d["verdict"]
    assert d["verdict"]["rejected"]["dispersion"] and d["verdict"]["dispersion_t"] > 0
    assert d["verdict"] == combined_verdict(bad.ranks, 19, bad.p_adjusted)
    ok = run_sbc(_simulate, _posterior(1.0), n_sims=200, n_draws=19, seed=0).to_dict()
    assert ok["verdict"]["passed"], ok["verdict"]
    json.dumps(d)   # JSON-ready


def test_synthesis_sbc_defaults_to_200_simulations():
    assert inspect.signature(synthesis_sbc).parameters["n_sims"].default == 200


def test_uniformity_test_rejects_unequal_bins():
    with pytest.raises(ValueError, match="divide"):
        uniformity_test(np.zeros((50, 2), int), 19, bins=3)
    assert default_bins(19, 400) == 20 and default_bins(19, 40) == 5
    with pytest.raises(ValueError, match="3 or more"):
        default_bins(9, 10)   # only 2 bins would fit: blind to a ∪-shaped histogram


@pytest.mark.parametrize("n_sims, bins, match", [(10, None, "3 or more"), (50, 3, "divide")])
def test_sbc_refuses_a_binning_it_cannot_do_before_it_runs_the_sampler(n_sims, bins, match):
    """10 simulations cannot fill 3+ bins of 20 ranks, and 3 bins do not divide 20: said
    before the first posterior run (a 20-frame NUTS SBC took 7.5 min to say it after)."""
    calls = []

    def posterior(y, seed):
        calls.append(seed)
        return np.zeros((19, 1))

    with pytest.raises(ValueError, match=match):
        run_sbc(lambda rng: (np.zeros(1), None), posterior, n_sims, 19, bins=bins)
    assert calls == []


# ------------------------------------------------------------------ the synthesis model
@pytest.fixture(scope="module")
def toy(toy_vlmm):
    return toy_vlmm, make_utterances(2, seed=1, mean_len=20)


def test_sbc_rejects_laplace_with_halved_variance_on_the_synthesis_model(toy):
    model, test = toy
    labels = test[0].labels[2:7]   # 5 frames across a phone change: 15 latent coordinates
    res = synthesis_sbc(model, labels, scaled_laplace(0.5, n_draws=40), n_sims=40, n_draws=19, seed=0)
    assert res.ranks.shape == (40, 15)
    assert not res.passed, res.to_dict()
    assert res.extreme_fraction > 2 * res.extreme_expected


class _PickledPool:
    """A parallel executor stand-in: every task and result goes through pickle, as in a
    process pool, but runs here, last chunk first (results are still returned in order)."""

    parallel = True
    n_workers = 2

    def __init__(self):
        self.tasks = []

    def map(self, fn, items, desc=None, unit="task"):
        import pickle

        from bayes_talk.base.executor import run_task

        items = [pickle.dumps((fn, x)) for x in items]
        self.tasks.append(len(items))
        out = {j: pickle.loads(pickle.dumps(run_task(*pickle.loads(b)))) for j, b in reversed(list(enumerate(items)))}
        return [out[j] for j in range(len(items))]


@pytest.mark.parametrize("make_posterior", [lambda: scaled_laplace(0.5, n_draws=40),
                                            lambda: sampler_posterior("laplace", n_draws=40)])
def test_sbc_through_a_parallel_executor_gives_the_serial_ranks(toy, make_posterior):
    """The simulations' posterior runs go to the executor in 8 chunks (picklable posteriors)
    and the ranks, diagnostics and verdict equal the serial run's."""
    model, test = toy
    labels = test[0].labels[2:6]
    one = synthesis_sbc(model, labels, make_posterior(), n_sims=20, n_draws=11, seed=3)
    pool = _PickledPool()
    two = synthesis_sbc(model, labels, make_posterior(), n_sims=20, n_draws=11, seed=3, executor=pool)
    assert pool.tasks == [8]
    np.testing.assert_array_equal(two.ranks, one.ranks)
    assert two.to_dict()["p_values"] == one.to_dict()["p_values"]
    assert {k: v for k, v in two.info.items() if k != "seconds"} == {k: v for k, v in one.info.items() if k != "seconds"}


def test_prior_predictive_simulates_the_synthesis_model(toy):
    model, test = toy
    labels = test[0].labels[:8]
    plan = make_plan(model, test[0].mfcc[:8], labels)
    X, Y = prior_predictive(plan, 6, seed=0)
    assert X.shape == (6, 8, 3) and Y.shape == (6, 8, model.dims_[0])
    X2, Y2 = prior_predictive(plan, 6, seed=0)
    assert np.array_equal(X, X2) and np.array_equal(Y, Y2)
    # the audio is the audio GP predictive at the simulated latents: standardised residuals ~ N(0, 1)
    z = []
    for b in plan.blocks:
        p = b.model.predictors_["audio"]
        for s in range(6):
            mu, var = b.model.predict_view("audio", X[s, b.start:b.stop])
            z.append((Y[s, b.start:b.stop] - mu) / np.sqrt(var))
    z = np.concatenate([a.ravel() for a in z])
    assert p is not None and abs(z.mean()) < 0.3 and 0.7 < z.std() < 1.3, (z.mean(), z.std())


def test_posterior_predictive_check_accepts_simulated_audio_and_flags_shifted_audio(toy):
    model, test = toy
    labels = test[1].labels[:10]
    plan = make_plan(model, test[1].mfcc[:10], labels, smoothness="off")
    _, Y = prior_predictive(plan, 1, seed=3)
    y = Y[0]
    post = sample_synthesis(model, y, labels, method="laplace", n_draws=64, seed=0, smoothness="off")
    rep = posterior_predictive(make_plan(model, y, labels, smoothness="off"), post.latent_draws, seed=1)
    assert rep.shape == (64,) + y.shape
    ok = predictive_check(y, rep)
    assert 0.75 <= ok.coverage[0.9] <= 1.0 and ok.coverage[0.5] < ok.coverage[0.9], ok.to_dict()
    shifted = y + 5 * rep.std(0).mean()
    bad = predictive_check(shifted, rep)
    assert bad.coverage[0.9] < 0.2 and bad.extreme()["mean"] == y.shape[1], bad.to_dict()
