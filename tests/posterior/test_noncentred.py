"""Non-centred coordinates of the synthesis density (issue 24, item 1): the density of x is
unchanged (Jacobian included), the gradient is exact, and x ↦ ε ↦ x round-trips."""
from __future__ import annotations

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.posterior.noncentred import NonCentred, WhitenedNonCentred, eps_hessian
from bayes_talk.posterior.samplers import laplace_scale
from bayes_talk.posterior.sampling import sample_synthesis
from bayes_talk.synthesis.joint import UtteranceDensity, make_plan


@pytest.fixture(scope="module")
def toy(toy_vlmm):
    return toy_vlmm, make_utterances(3, seed=1, mean_len=20)


@pytest.fixture(scope="module", params=["frame", "off"])
def case(toy, request):
    model, test = toy
    u = test[0]
    labels, mfcc = u.labels[:12], u.mfcc[:12]
    plan = make_plan(model, mfcc, labels, request.param)
    dens = UtteranceDensity(plan)
    x_map = sample_synthesis(model, mfcc, labels, method="map", smoothness=request.param,
                             log_warnings=False).map_latents
    return plan, dens, NonCentred(dens), x_map


def _points(nc, x_map, n=3):
    rng = np.random.default_rng(0)
    e0 = nc.to_eps(x_map)
    return [e0] + [e0 + 0.5 * rng.standard_normal(e0.shape) for _ in range(n - 1)]


def test_the_plan_has_stretches_entries_and_linked_blocks(case):
    _, _, nc, _ = case
    assert len(nc.levels) >= 2 and len(nc.e_idx) >= 2, "the test plan must have dynamics stretches and entries"


def test_x_to_eps_to_x_round_trips(case):
    _, _, nc, x_map = case
    for e in _points(nc, x_map):
        x = nc.to_x(e)
        np.testing.assert_allclose(nc.to_eps(x), e, rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(nc.to_x(nc.to_eps(x_map)), x_map, rtol=1e-10, atol=1e-10)


def test_density_of_x_is_unchanged_jacobian_included(case):
    """ln p_ε(ε) = ln p(x(ε)) + ln|det ∂x/∂ε| with the determinant of the finite-difference
    Jacobian of the map ε ↦ x (not the closed form (2))."""
    _, dens, nc, x_map = case
    n = nc.T * nc.d
    for e in _points(nc, x_map):
        h = 1e-6
        J = np.empty((n, n))
        for j in range(n):
            ep, em = e.reshape(-1).copy(), e.reshape(-1).copy()
            ep[j] += h
            em[j] -= h
            J[:, j] = (nc.to_x(ep) - nc.to_x(em)) / (2 * h)
        sign, logdet = np.linalg.slogdet(J)
        assert sign != 0
        x = nc.to_x(e)
        lp_eps, _ = nc(e)
        assert lp_eps == pytest.approx(dens(x)[0] + logdet, rel=1e-8, abs=1e-6)
        assert nc.log_jacobian(x) == pytest.approx(logdet, rel=1e-8, abs=1e-6)


def test_gradient_matches_finite_differences(case):
    _, _, nc, x_map = case
    rng = np.random.default_rng(1)
    for e in _points(nc, x_map):
        _, g = nc(e)
        assert g.shape == e.shape
        for _ in range(8):
            v = rng.standard_normal(e.shape)
            h = 1e-5
            fd = (nc(e + h * v)[0] - nc(e - h * v)[0]) / (2 * h)
            assert float(np.sum(g * v)) == pytest.approx(fd, rel=1e-5, abs=1e-5 * max(1.0, abs(fd)))


def test_whitened_noncentred_is_the_affine_pushforward_of_p_eps(case):
    """``WhitenedNonCentred``: u ↦ ln p_ε(ε_0 + L_ε u) with gradient L_εᵀ∇ln p_ε (against
    finite differences of the value), u ↔ x round-trips, and at ε_0 = ε(X_MAP) the whitened
    curvature −L_εᵀ H_ε L_ε is the identity (L_ε from :func:`eps_hessian`, whose rows are
    checked against second differences of the value)."""
    _, _, nc, x_map = case
    e0 = nc.to_eps(x_map).reshape(-1)
    H = eps_hessian(nc, e0)
    rng = np.random.default_rng(4)
    for _ in range(3):
        v = rng.standard_normal(e0.size)
        h = 1e-4
        fd2 = (nc(e0 + h * v)[0] - 2 * nc(e0)[0] + nc(e0 - h * v)[0]) / h ** 2
        assert v @ H @ v == pytest.approx(fd2, rel=1e-3, abs=1e-3)
    L, info = laplace_scale(H)
    assert info["n_floored"] == 0, "the test expects a negative definite Hessian at the MAP"
    np.testing.assert_allclose(-L.T @ H @ L, np.eye(e0.size), atol=1e-8)
    w = WhitenedNonCentred(nc, e0, L)
    for k in range(3):
        u = 0.7 * rng.standard_normal(e0.size)
        f, g = w(u)
        assert f == nc(e0 + L @ u)[0]
        v = rng.standard_normal(e0.size)
        h = 1e-5
        fd = (w(u + h * v)[0] - w(u - h * v)[0]) / (2 * h)
        assert float(g @ v) == pytest.approx(fd, rel=1e-5, abs=1e-5 * max(1.0, abs(fd)))
        x = w.to_x(u)
        np.testing.assert_allclose(x, nc.to_x(e0 + L @ u), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(w.to_u(x), u, rtol=1e-6, atol=1e-6)
    U = rng.standard_normal((2, 3, e0.size))
    assert w.to_x(U).shape == U.shape and w.to_u(w.to_x(U)).shape == U.shape


@pytest.mark.parametrize("coords", ["noncentred", "noncentred-whitened"])
def test_nuts_runs_in_noncentred_coordinates_and_reports_them(toy, coords):
    """``sampler_kw={"coords": "noncentred"}`` (or "noncentred-whitened"): the draws are
    latents (x(ε)), reproducible from the seed, and each recorded ln p is ln p_ε at the
    draw's ε (the whitening is affine: its log density is p_ε's at ε_0 + L_ε u).

    None of these needs a mixed chain: trees are capped at depth 3 (≤ 7 leapfrog steps, where
    unadapted step sizes grew 5–8 deep trees: 46 s for two runs) and the chains are short."""
    model, test = toy
    u = test[0]
    labels, mfcc = u.labels[:12], u.mfcc[:12]
    kw = {"method": "nuts", "n_draws": 16, "warmup": 10, "chains": 2, "seed": 3, "log_warnings": False,
          "map_restarts": 0, "sampler_kw": {"coords": coords, "max_tree_depth": 3}}
    r1 = sample_synthesis(model, mfcc, labels, **kw)
    r2 = sample_synthesis(model, mfcc, labels, **kw)
    assert r1.diagnostics["coords"] == coords and r1.latent_draws.shape == (2, 8, 12, 3)
    assert r1.diagnostics["max_tree_depth"] == 3 and r1.diagnostics["n_steps_mean"] <= 7
    assert np.array_equal(r1.latent_draws, r2.latent_draws)
    nc = NonCentred(UtteranceDensity(make_plan(model, mfcc, labels)))
    for c in range(2):
        lp = [nc(nc.to_eps(x))[0] for x in r1.latent_draws[c, -3:]]
        np.testing.assert_allclose(lp, r1.sample_stats["lp"][c, -3:], rtol=1e-9)
    with pytest.raises(ValueError, match="coords"):
        sample_synthesis(model, mfcc, labels, **{**kw, "sampler_kw": {"coords": "centred"}})
