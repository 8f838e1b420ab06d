"""bayes_talk.base.arviz_compat: the same answers from ArviZ 0.2x (Python 3.11) and 1.x (>= 3.12).

Each check compares with a value computed here from its definition, so the test runs
unchanged under either version (CI runs it on 3.11; `.ci/smoke.sh 3.13` on 3.13).
"""
from __future__ import annotations

import numpy as np
import pytest

from bayes_talk.base import arviz_compat as azc


def _ar1(rng, rho: float, chains: int, draws: int, n: int) -> np.ndarray:
    x = np.empty((chains, draws, n))
    x[:, 0] = rng.normal(size=(chains, n))
    for t in range(1, draws):
        x[:, t] = rho * x[:, t - 1] + np.sqrt(1 - rho ** 2) * rng.normal(size=(chains, n))
    return x


def test_rhat_separates_mixed_from_stuck_chains():
    rng = np.random.default_rng(0)
    good = rng.normal(size=(4, 500, 3))
    stuck = good + np.array([0.0, 0.0, 3.0, 3.0])[:, None, None]   # two chains in another mode
    r_good, r_stuck = azc.rhat(good), azc.rhat(stuck)
    assert r_good.shape == (3,) and np.all(np.abs(r_good - 1) < 0.01)
    assert np.all(r_stuck > 1.5)


def test_bulk_ess_of_an_ar1_chain_matches_its_integrated_autocorrelation():
    rho, C, S = 0.8, 4, 4000
    x = _ar1(np.random.default_rng(1), rho, C, S, 2)
    want = C * S * (1 - rho) / (1 + rho)          # N / τ, τ = (1 + ρ) / (1 − ρ) for AR(1)
    bulk = azc.ess(x, "bulk")
    assert bulk.shape == (2,) and np.all(np.abs(bulk / want - 1) < 0.15)
    tail = azc.ess(x, "tail")
    assert np.all((tail > 0.5 * want) & (tail < C * S))   # the tail indicators mix faster than x
    with pytest.raises(ValueError, match="'bulk' or 'tail'"):
        azc.ess(x, "median")


def test_mcse_of_the_mean_is_sd_over_root_ess():
    x = _ar1(np.random.default_rng(2), 0.5, 4, 2000, 2)
    m = azc.mcse(x, "mean")
    want = x.reshape(-1, 2).std(axis=0) / np.sqrt(azc.ess(x, "bulk"))
    np.testing.assert_allclose(m, want, rtol=0.1)
    sd = azc.mcse(x, "sd")
    assert sd.shape == (2,) and np.all((sd > 0) & (sd < m * 2))


def test_bfmi_is_the_energy_ratio_of_each_chain():
    e = np.cumsum(np.random.default_rng(3).normal(size=(3, 200)), axis=1)   # a slow random walk: low BFMI
    want = np.sum(np.diff(e, axis=1) ** 2, axis=1) / np.sum((e - e.mean(axis=1, keepdims=True)) ** 2, axis=1)
    np.testing.assert_allclose(azc.bfmi(e), want, rtol=1e-10)
    assert np.all(azc.bfmi(e) < 0.3)
    with pytest.raises(ValueError, match="chains, draws"):
        azc.bfmi(e[0])


def test_psis_khat_is_small_for_light_tails_and_large_for_heavy_ones():
    rng = np.random.default_rng(4)
    light = rng.normal(scale=0.3, size=2000)
    heavy = np.log(rng.pareto(1.0, size=2000) + 1.0)    # ratios with a Pareto(1) tail: k ≈ 1
    lw, k_light = azc.psislw(light)
    assert lw.shape == (2000,) and k_light < 0.5
    assert azc.psislw(heavy)[1] > 0.7
    from scipy.special import logsumexp

    assert abs(logsumexp(lw)) < 1e-9                           # normalised log weights
    flat, k_flat = azc.psislw(np.zeros(400))                   # q = p: a constant tail
    np.testing.assert_allclose(flat, -np.log(400), rtol=1e-12)
    assert k_flat == np.inf
    d = np.abs(lw - (light - logsumexp(light)))              # a light tail is barely smoothed
    assert np.median(d) < 0.01 and d.max() < 0.2


def test_from_dict_groups_attrs_and_netcdf_round_trip(tmp_path):
    rng = np.random.default_rng(5)
    post = {"x": rng.normal(size=(2, 10, 4, 3))}
    idata = azc.from_dict(post, posterior_predictive={"y": rng.normal(size=(2, 5, 4))},
                          sample_stats={"diverging": np.zeros((2, 10), bool)},
                          observed_data={"y": np.zeros(4)},
                          coords={"frame": np.arange(4)}, dims={"x": ["frame", "k"], "y": ["frame"]})
    np.testing.assert_array_equal(idata.posterior["x"].values, post["x"])
    assert idata.posterior["x"].dims[:3] == ("chain", "draw", "frame")
    assert idata.observed_data["y"].shape == (4,)
    idata.posterior.attrs.update({"bayes_talk_method": "laplace"})
    path = tmp_path / "p.nc"
    idata.to_netcdf(str(path))
    back = azc.from_netcdf(path)
    assert back.posterior.attrs["bayes_talk_method"] == "laplace"
    np.testing.assert_array_equal(back.posterior["x"].values, post["x"])
    assert bool(back.sample_stats["diverging"].values.any()) is False


def test_version_flag_matches_the_installed_arviz():
    import arviz

    assert azc.ARVIZ_VERSION == arviz.__version__
    assert azc.ARVIZ_1 == (int(arviz.__version__.split(".")[0]) >= 1)
