"""Particle Gibbs over frames (issue 24, items 2-3): the per-frame factors sum to the synthesis
density to round-off, and conditional SMC with ancestor sampling leaves a known posterior
invariant (a linear-Gaussian chain whose posterior is computed exactly)."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.special import logsumexp
from toydata import make_utterances

from bayes_talk.posterior.frame_updates import block_factor, block_mtm, dynamics_blocks
from bayes_talk.posterior.methods import NUTS_DEFAULTS, PG_NUTS_BUDGET, PG_NUTS_DEFAULTS
from bayes_talk.posterior.particle_gibbs import (
    FrameFactors,
    MixtureProposal,
    csmc_as,
    run_particle_gibbs,
)
from bayes_talk.posterior.sampling import sample_synthesis
from bayes_talk.synthesis.joint import UtteranceDensity, make_plan


@pytest.fixture(scope="module")
def toy(toy_vlmm):
    return toy_vlmm, make_utterances(1, seed=1, mean_len=20)[0]


@pytest.fixture(scope="module")
def toy20(toy):
    """The toy utterance's first 20 frames: (T, their FrameFactors, the joint MAP, the sweep's
    proposal with the MAP as an extra centre)."""
    model, u = toy
    T = 20
    plan = make_plan(model, u.mfcc[:T], u.labels[:T])
    ff = FrameFactors(UtteranceDensity(plan))
    x_map = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="map", log_warnings=False).map_latents
    return T, ff, x_map, MixtureProposal(ff, plan, rho=0.5, h=(0.005, 0.02, 0.05), extra_centres=x_map[None])


@pytest.mark.parametrize("smoothness", ["frame", "off"])
def test_frame_factors_sum_to_the_utterance_density(toy, smoothness):
    model, u = toy
    plan = make_plan(model, u.mfcc, u.labels, smoothness)
    dens = UtteranceDensity(plan)
    ff = FrameFactors(dens)
    assert ff.dyn_gp and ff.entry and (bool(ff.smooth) == (smoothness == "frame"))
    x_map = sample_synthesis(model, u.mfcc, u.labels, method="map", smoothness=smoothness,
                             log_warnings=False).map_latents
    rng = np.random.default_rng(0)
    for X in (x_map, x_map + 1e-3 * rng.standard_normal(x_map.shape), x_map + 0.2 * rng.standard_normal(x_map.shape)):
        ref = dens(X)[0]
        assert ff.total(X) == pytest.approx(ref, rel=1e-10, abs=1e-8)


class _AR1:
    """x_0 ~ N(0, 1), x_t = a x_{t−1} + N(0, s²), y_t = x_t + N(0, r²): factors and a proposal."""

    T, d, a, s, r = 5, 1, 0.8, 0.5, 0.7

    def __init__(self, y, starts=()):
        """``starts``: frames whose coupling to x_{t−1} stands for a smoothness factor, not a
        dynamics one (block starts inside a group for :func:`block_mtm`); the density is the same."""
        self.y = y
        self.dyn_gp = {t: 0 for t in range(1, self.T) if t not in starts}

    def log_f(self, t, Xprev, X):
        x = X[:, 0]
        lp = -0.5 * ((self.y[t] - x) / self.r) ** 2
        if t == 0:
            return lp - 0.5 * x * x
        return lp - 0.5 * ((x - self.a * Xprev[:, 0]) / self.s) ** 2

    def link_logf(self, t, Xprev, X):      # the terms of f_t with x_{t−1}
        return np.zeros(len(X)) if t == 0 else -0.5 * ((X[:, 0] - self.a * Xprev[:, 0]) / self.s) ** 2

    def dynamics_mean_sd(self, t, Xprev):
        return self.a * Xprev, np.full_like(Xprev, self.s)

    def dynamics_logpdf(self, t, Xprev, X):
        return -0.5 * ((X[:, 0] - self.a * Xprev[:, 0]) / self.s) ** 2 - np.log(self.s) - 0.5 * np.log(2 * np.pi)

    def sample_logq(self, t, Xprev, N, rng, X=None, ref=None, x_next=None):      # the prior transition (bootstrap)
        m = np.zeros(N) if t == 0 else self.a * Xprev[:, 0]
        sd = 1.0 if t == 0 else self.s
        if X is None:
            X = (m + sd * rng.standard_normal(N))[:, None]
        if ref is not None:
            X[-1] = ref
        return X, -0.5 * ((X[:, 0] - m) / sd) ** 2 - np.log(sd)

    def exact(self):
        cov = np.linalg.inv(_ar1_precision(self))
        return cov @ (self.y / self.r**2), np.diag(cov)


@pytest.mark.parametrize(("broken", "backward"), [(False, False), (True, False), (False, True)])
def test_csmc_with_ancestor_sampling_leaves_a_known_posterior_invariant(broken, backward):
    """Mean and variance of every coordinate within 5 Monte-Carlo s.e. of the exact posterior,
    with ancestor sampling and with backward simulation; a deliberately broken kernel (the
    reference particle's weight ignored: not invariant) fails."""
    y = np.array([0.5, 1.5, -0.3, 2.0, 1.0])
    m = _AR1(y)
    mean, var = m.exact()
    rng = np.random.default_rng(1)
    x = np.zeros((m.T, 1))
    draws = []
    for it in range(3000):
        if broken:   # the always-moving variant: never keeps the reference path
            x_new, _ = csmc_as(m, m, x, 2, rng)
            x = x_new if np.any(x_new != x) else x + 0.3
        else:
            x, _ = csmc_as(m, m, x, 8, rng, backward=backward)
        if it >= 200:
            draws.append(x[:, 0].copy())
    D = np.array(draws)
    # effective sample size of each coordinate from batch means
    B = D.reshape(28, -1, m.T).mean(1)
    se = B.std(0, ddof=1) / np.sqrt(len(B))
    ok = np.all(np.abs(D.mean(0) - mean) < 5 * se) and np.all(np.abs(D.var(0) / var - 1) < 0.15)
    assert ok != broken, (D.mean(0), mean, D.var(0), var)


@pytest.mark.parametrize(("blocks", "broken"), [([(t, t + 1) for t in range(5)], False),
                                                ([(t, t + 1) for t in range(5)], True),
                                                ([(0, 2), (2, 5)], False), ([(1, 4)], False), ([(0, 2), (2, 5)], True)])
def test_block_mtm_leaves_a_known_posterior_invariant(blocks, broken):
    """Multiple-try Metropolis updates of blocks of the AR(1) chain given their neighbours —
    single frames, and blocks whose later frames are drawn from the dynamics (so the weights
    must cancel the dynamics terms exactly) — keep the exact posterior's means and variances
    of the frames they update (5 Monte-Carlo s.e., 15 %); accepting every selected try (no
    Metropolis test) does not."""
    y = np.array([0.5, 1.5, -0.3, 2.0, 1.0])
    m = _AR1(y)
    mean, var = m.exact()
    rng = np.random.default_rng(2)
    x = np.zeros((m.T, 1))
    draws = []
    for it in range(3000):
        x, moved = block_mtm(m, m, x, blocks, 4, rng, _broken=broken)
        assert moved.shape == (len(blocks),)
        if it >= 200:
            draws.append(x[:, 0].copy())
    D = np.array(draws)
    if len(blocks) == 1:   # frames outside the block stay where they are; compare the block's conditional
        s, e = blocks[0]
        assert np.all(D[:, :s] == 0) and np.all(D[:, e:] == 0)
        cov = np.linalg.inv(_ar1_precision(m)[s:e, s:e])
        mean, var = cov @ (y[s:e] / m.r ** 2), np.diag(cov)      # x outside = 0
        D = D[:, s:e]
    B = D.reshape(28, -1, D.shape[1]).mean(1)
    se = B.std(0, ddof=1) / np.sqrt(len(B))
    ok = np.all(np.abs(D.mean(0) - mean) < 5 * se) and np.all(np.abs(D.var(0) / var - 1) < 0.15)
    assert ok != broken, (D.mean(0), mean, D.var(0), var)


def test_block_sweeps_repeat_the_block_updates_and_keep_a_known_posterior(monkeypatch):
    """``block_sweeps`` = R: after each CSMC sweep the move runs R passes of the multiple-try
    block updates (counted), and the composition keeps the AR(1) chain's exact posterior means
    and variances (5 Monte-Carlo s.e., 15 %); R < 1 is refused."""
    import bayes_talk.posterior.particle_gibbs as pg

    y = np.array([0.5, 1.5, -0.3, 2.0, 1.0])
    m = _AR1(y)
    mean, var = m.exact()
    calls = []
    real = pg.block_mtm

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(pg, "block_mtm", counted)
    move = pg.ParticleGibbsMove(m, m, lambda u: u, lambda x: x, n_particles=2, blocks=[(0, 2), (2, 3), (3, 5)],
                                frame_tries=4, block_sweeps=3)
    rng = np.random.default_rng(5)
    u = np.zeros((m.T, 1))
    draws = []
    for it in range(3000):
        u, rec = move(u, rng)
        assert len(calls) == 3 * (it + 1) and rec["pg_frame_moved"].shape == (m.T,)
        if it >= 200:
            draws.append(u[:, 0].copy())
    D = np.array(draws)
    B = D.reshape(28, -1, m.T).mean(1)
    se = B.std(0, ddof=1) / np.sqrt(len(B))
    assert np.all(np.abs(D.mean(0) - mean) < 5 * se), (D.mean(0), mean, se)
    assert np.all(np.abs(D.var(0) / var - 1) < 0.15), (D.var(0), var)
    with pytest.raises(ValueError, match="block_sweeps"):
        pg.ParticleGibbsMove(m, m, lambda u: u, lambda x: x, blocks=[(0, 2)], frame_tries=4, block_sweeps=0)


class _BroadStarts:
    """A group's joint proposal for :func:`block_mtm`: the starts iid N(0, 1.5²), state-independent."""

    def sample_starts(self, s, e, N, rng, ref=None, x_prev=None, x_next=None):
        Y = 1.5 * rng.standard_normal((N, 2, 1))
        if ref is not None:
            Y[-1] = ref
        return Y, (-0.5 * (Y / 1.5) ** 2).sum((1, 2))


@pytest.mark.parametrize(("blocks", "broken"), [([(0, 5)], False), ([(1, 5)], False), ([(0, 5)], True)])
def test_block_mtm_of_a_group_with_a_later_start_leaves_a_known_posterior_invariant(blocks, broken):
    """A group of two consecutive blocks ([s, 3) and [3, 5), frame 3 without a dynamics factor
    into it) updated at once, both starts' tries from a joint proposal and the other frames from
    the dynamics: the block's conditional means and variances are kept (5 Monte-Carlo s.e.,
    15 %); accepting every selected try does not."""
    y = np.array([0.5, 1.5, -0.3, 2.0, 1.0])
    m = _AR1(y, starts=(3,))
    rng = np.random.default_rng(5)
    x = np.zeros((m.T, 1))
    draws = []
    for it in range(3000):
        x, moved = block_mtm(m, _BroadStarts(), x, blocks, 8, rng, _broken=broken)
        assert moved.shape == (1,)
        if it >= 200:
            draws.append(x[:, 0].copy())
    s, e = blocks[0]
    D = np.array(draws)
    assert np.all(D[:, :s] == 0)
    cov = np.linalg.inv(_ar1_precision(m)[s:e, s:e])
    mean, var = cov @ (y[s:e] / m.r ** 2), np.diag(cov)
    D = D[:, s:e]
    B = D.reshape(28, -1, D.shape[1]).mean(1)
    se = B.std(0, ddof=1) / np.sqrt(len(B))
    ok = np.all(np.abs(D.mean(0) - mean) < 5 * se) and np.all(np.abs(D.var(0) / var - 1) < 0.15)
    assert ok != broken, (D.mean(0), mean, D.var(0), var)


def _ar1_precision(m):
    T, a, s, r = m.T, m.a, m.s, m.r
    P = np.zeros((T, T))
    P[0, 0] = 1.0
    for t in range(1, T):
        P[t, t] += 1 / s**2
        P[t - 1, t - 1] += a * a / s**2
        P[t, t - 1] = P[t - 1, t] = -a / s**2
    return P + np.eye(T) / r**2


def test_dynamics_blocks_partition_the_frames_into_runs(toy):
    """``dynamics_blocks(ff, 1)``: the isolated frames (no dynamics on either side: every frame
    of a block without dynamics; of a block with, none unless it is alone); with no length cap
    the blocks partition the frames, each starting where no dynamics factor enters and
    continuing through the frames that have one; a cap keeps only the shorter runs."""
    model, u = toy
    plan = make_plan(model, u.mfcc, u.labels)
    ff = FrameFactors(UtteranceDensity(plan))
    iso = [s for s, _ in dynamics_blocks(ff, 1)]
    assert iso and len(iso) < ff.T and all(e == s + 1 for s, e in dynamics_blocks(ff, 1))
    for b in plan.blocks:   # every frame of a block without dynamics; of a block with, none unless alone
        frames = set(range(b.start, b.stop))
        nxt = next((c for c in plan.blocks if c.start == b.stop), None)
        into_next = nxt is not None and nxt.linked
        if b.model.dynamics_predictor_ is None:
            assert frames <= set(iso)
        elif b.stop - b.start > 1 or b.linked or into_next:
            assert not frames & set(iso), (b.start, b.stop)
    runs = dynamics_blocks(ff, ff.T)
    assert [s for s, _ in runs] == [0] + [e for _, e in runs[:-1]] and runs[-1][1] == ff.T
    for s, e in runs:
        assert s not in ff.dyn_gp and all(v in ff.dyn_gp for v in range(s + 1, e)) and ff.run_end(s) == e
    assert max(e - s for s, e in runs) > 3
    assert dynamics_blocks(ff, 3) == [(s, e) for s, e in runs if e - s <= 3]


def test_particle_gibbs_on_the_synthesis_density_records_its_draws_and_update_rate(toy):
    model, u = toy
    T = 12
    plan = make_plan(model, u.mfcc[:T], u.labels[:T])
    dens = UtteranceDensity(plan)
    x_map = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="map", log_warnings=False).map_latents
    q = MixtureProposal(FrameFactors(dens), plan)
    assert all(abs(logsumexp(w)) < 1e-9 for w in q.logw.values())
    out = run_particle_gibbs(dens, plan, np.stack([x_map, x_map]), n_draws=10, warmup=5, seed=0, n_particles=32)
    assert out["samples"].shape == (2, 10, T, 3)
    np.testing.assert_allclose(out["lp"][0], [dens(x)[0] for x in out["samples"][0]], rtol=1e-12)
    rate = out["frame_update_rate"]
    assert rate.shape == (2, T) and np.all((rate >= 0) & (rate <= 1)) and rate.mean() > 0.1, rate


@pytest.mark.parametrize("frame_kw", [{}, {"pg_frame_tries": 4, "pg_frame_modes": True},
                                      {"pg_frame_tries": 4, "pg_frame_modes": True, "pg_block_len": 6},
                                      {"pg_frame_tries": 4, "pg_frame_modes": True, "pg_block_len": 6,
                                       "pg_neighbours": True},
                                      {"pg_frame_tries": 4, "pg_frame_modes": True, "pg_block_len": 6,
                                       "pg_pairs": True},
                                      {"pg_frame_tries": 4, "pg_frame_modes": True, "pg_block_len": 6,
                                       "pg_pairs": False},
                                      {"coords": "noncentred-whitened", "pg_frame_tries": 4, "pg_frame_modes": True}])
def test_particle_gibbs_composed_with_nuts_keeps_the_chain_state_consistent(toy, frame_kw):
    """PG ∘ NUTS in non-centred coordinates: after each sweep the sampler's cached potential
    is that of the new state (the recorded ln p_ε equals the density at the draw), the sweeps
    move the chain, and the seed reproduces the draws — also with the isolated frames (3–6
    here), or those and the dynamics runs of up to 6 frames, updated after each sweep from their
    own modes (also conditioned on their neighbours, ``pg_neighbours``), and in the whitened non-centred
    coordinates (the move maps through their ``to_x``/``to_u``). NUTS trees are capped at depth 3 (≤ 7
    leapfrog steps; unadapted step sizes after a 12-iteration warm-up grew deep ones): the
    consistency of the cached potential after a sweep does not need long trajectories."""
    from bayes_talk.posterior.noncentred import NonCentred

    model, u = toy
    T = 10
    kw = {"method": "nuts", "n_draws": 16, "warmup": 12, "chains": 2, "seed": 4, "map_restarts": 0,
          "log_warnings": False, "sampler_kw": {"coords": "noncentred", "pg_every": 1, "pg_particles": 16,
                                                "max_tree_depth": 3, **frame_kw}}
    r1 = sample_synthesis(model, u.mfcc[:T], u.labels[:T], **kw)
    r2 = sample_synthesis(model, u.mfcc[:T], u.labels[:T], **kw)
    assert np.array_equal(r1.latent_draws, r2.latent_draws)
    dens = UtteranceDensity(make_plan(model, u.mfcc[:T], u.labels[:T]))
    if frame_kw:
        blocks = dynamics_blocks(FrameFactors(dens), frame_kw.get("pg_block_len", 1))
        assert blocks, "the frame updates need isolated frames"
        assert "pg_block_len" not in frame_kw or max(e - s for s, e in blocks) > 1, "and here longer blocks"
    nc = NonCentred(dens)
    for c in range(2):
        lp = [nc(nc.to_eps(x))[0] for x in r1.latent_draws[c]]
        np.testing.assert_allclose(lp, r1.sample_stats["lp"][c], rtol=1e-9)


def test_pg_nuts_method_is_the_composition_in_noncentred_coordinates(toy):
    """``method="pg-nuts"`` (the ``synth --posterior pg-nuts`` sampler) is NUTS in non-centred
    coordinates with a particle Gibbs sweep after every iteration: the same draws as
    ``method="nuts"`` with those sampler keywords, its settings in the diagnostics, the AAM
    diagnostics computed; whitened coordinates are refused."""
    model, u = toy
    T = 6
    kw = {"n_draws": 8, "warmup": 4, "chains": 2, "seed": 1, "map_restarts": 0, "log_warnings": False}
    r = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="pg-nuts", sampler_kw={"pg_particles": 8}, **kw)
    ref = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="nuts",
                           sampler_kw={"coords": "noncentred", "pg_every": 1, "pg_particles": 8,
                                       "pg_h": (0.005, 0.02, 0.05), "pg_lookahead": True,
                                       "pg_mode_centres": True, "pg_frame_tries": 16, "pg_frame_modes": True,
                                       "pg_block_len": PG_NUTS_DEFAULTS["pg_block_len"],
                                       "pg_neighbours": PG_NUTS_DEFAULTS["pg_neighbours"],
                                       "pg_pairs": PG_NUTS_DEFAULTS["pg_pairs"],
                                       "pg_block_sweeps": PG_NUTS_DEFAULTS["pg_block_sweeps"],
                                       "pg_adapt_weights": PG_NUTS_DEFAULTS["pg_adapt_weights"],
                                       "pg_adapt_moments": PG_NUTS_DEFAULTS["pg_adapt_moments"]},
                           **kw)
    assert r.method == "pg-nuts" and r.latent_draws.shape == (2, 4, T, 3)
    assert np.array_equal(r.latent_draws, ref.latent_draws)
    d = r.diagnostics
    assert (d["coords"], d["pg_every"], d["pg_particles"]) == ("noncentred", 1, 8)
    assert (d["pg_h"], d["pg_lookahead"], d["pg_mode_centres"]) == ([0.005, 0.02, 0.05], True, True)
    assert (d["pg_frame_tries"], d["pg_frame_modes"], d["pg_block_len"]) == (16, True, PG_NUTS_DEFAULTS["pg_block_len"])
    assert (d["pg_neighbours"], d["pg_pairs"], d["pg_block_sweeps"], d["pg_adapt_moments"]) == (
        PG_NUTS_DEFAULTS["pg_neighbours"], PG_NUTS_DEFAULTS["pg_pairs"], PG_NUTS_DEFAULTS["pg_block_sweeps"],
        PG_NUTS_DEFAULTS["pg_adapt_moments"])
    assert [d[k] for k in ("pg_mode_delta", "pg_mode_scale", "pg_mode_starts")] == [
        PG_NUTS_DEFAULTS["pg_mode_delta"], list(np.atleast_1d(PG_NUTS_DEFAULTS["pg_mode_scale"])),
        PG_NUTS_DEFAULTS["pg_mode_starts"]]
    assert isinstance(d["pg_blocks_without_modes"], list)
    assert "aam_rhat_max" in d and "ebfmi_min" in d and r.sample_stats["lp"].shape == (2, 4)
    with pytest.raises(ValueError, match="non-centred"):
        sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="pg-nuts", sampler_kw={"coords": "whitened"}, **kw)


@pytest.mark.parametrize(("method", "budget"), [("pg-nuts", PG_NUTS_BUDGET), ("nuts", NUTS_DEFAULTS)])
def test_pg_nuts_runs_its_own_warmup_and_draws_by_default(toy, monkeypatch, method, budget):
    """Without ``warmup`` and ``n_draws``, pg-nuts runs ``PG_NUTS_BUDGET`` (200 warm-up + 500
    draws per chain) and NUTS in the same coordinates its own defaults (500 + 250): what the
    runner receives, and the default draws the CLI states."""
    from bayes_talk.posterior.methods import DEFAULT_DRAWS, draws_help
    from bayes_talk.posterior.methods import nuts as runner

    class Stop(Exception):
        pass

    got = {}

    def recorder(dens, mp, modes, z0, L, per_chain, warmup, chains, seed, skw, whiten=False):
        got.update(per_chain=per_chain, warmup=warmup, chains=chains,
                   rule=[type(skw.get("enough")).__name__, skw.get("min_draws"), skw.get("check_every")])
        raise Stop

    monkeypatch.setattr(runner, "nuts_noncentred", recorder)
    model, u = toy
    T = 6
    with pytest.raises(Stop):
        sample_synthesis(model, u.mfcc[:T], u.labels[:T], method=method, map_restarts=0, log_warnings=False,
                         sampler_kw={"coords": "noncentred"})
    rule = (["TargetCheck", budget["min_draws_per_chain"], budget["check_every"]] if budget.get("stop_at_targets")
            else ["NoneType", None, None])   # pg-nuts stops at the R-hat/ESS targets, NUTS draws them all
    assert got == {"per_chain": budget["draws_per_chain"], "warmup": budget["warmup"],
                   "chains": NUTS_DEFAULTS["chains"], "rule": rule}
    assert method == "nuts" or rule[0] == "TargetCheck"
    assert DEFAULT_DRAWS[method] == NUTS_DEFAULTS["chains"] * budget["draws_per_chain"]
    assert f"{method} {NUTS_DEFAULTS['chains']} x {budget['draws_per_chain']}" in draws_help()


def test_the_stopping_rule_passes_mixed_chains_and_fails_chains_apart(toy):
    """:class:`TargetCheck` on latent draws around the toy MAP: four chains of independent draws
    (800 in all) pass the R-hat ≤ 1.01 and ESS ≥ 400 checks on the latents and AAM parameters;
    one chain shifted fails R-hat, too few draws fail ESS; each check is in ``history``."""
    from bayes_talk.posterior.sampling import TargetCheck
    from bayes_talk.synthesis.joint import make_plan

    model, u = toy
    T = 6
    plan = make_plan(model, u.mfcc[:T], u.labels[:T])
    x_map = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="map", log_warnings=False).map_latents
    rng = np.random.default_rng(0)
    X = x_map.reshape(1, 1, -1) + 0.05 * rng.standard_normal((4, 200, x_map.size))
    check = TargetCheck(plan)
    assert check(X) is True
    shifted = X.copy()
    shifted[0] += 0.05
    assert check(shifted) is False
    assert check(X[:, :60]) is False
    h = check.history
    assert [c["draws_per_chain"] for c in h] == [200, 200, 60]
    assert h[0]["failed"] == [] and h[0]["aam_ess_bulk_min"] >= 400 and h[0]["aam_rhat_max"] <= 1.01
    assert f"R-hat {h[1]['rhat_max']:.4f} > 1.01" in h[1]["failed"] and h[1]["rhat_max"] > 1.01
    assert any("bulk ESS" in f for f in h[2]["failed"]) and h[2]["ess_bulk_min"] < 400


def test_pg_nuts_stops_at_the_targets_or_draws_the_most(toy):
    """pg-nuts with the stopping rule on (the default) checks after ``min_draws_per_chain`` and
    every ``check_every`` draws (``stop_checks`` in the diagnostics) and keeps the draws up to
    the first check that passed, or all ``n_draws`` if none did — a prefix of the draws of the
    same run with ``stop_at_targets`` off."""
    model, u = toy
    T = 6
    kw = {"n_draws": 2 * 40, "warmup": 10, "chains": 2, "seed": 2, "map_restarts": 0, "log_warnings": False}
    opts = {"pg_particles": 8, "min_draws_per_chain": 10, "check_every": 10}
    r = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="pg-nuts", sampler_kw=opts, **kw)
    full = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="pg-nuts",
                            sampler_kw={**opts, "stop_at_targets": False}, **kw)
    d, checks = r.diagnostics, r.diagnostics["stop_checks"]
    assert "stop_checks" not in full.diagnostics and full.latent_draws.shape[1] == 40
    n = r.latent_draws.shape[1]
    assert [c["draws_per_chain"] for c in checks] == list(range(10, n + 1 if d["stopped_early"] else n, 10))
    assert d["stopped_early"] == (checks[-1]["failed"] == []) and d["max_draws_per_chain"] == 40
    assert all(c["failed"] for c in checks[:-1])
    assert n == (checks[-1]["draws_per_chain"] if d["stopped_early"] else 40) and d["n_draws"] == n
    np.testing.assert_array_equal(r.latent_draws, full.latent_draws[:, :n])
    with pytest.raises(ValueError, match="non-centred"):
        sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="nuts", sampler_kw={"stop_at_targets": True}, **kw)


def test_pg_nuts_own_mode_settings_reach_the_proposal_and_blocks_without_modes_are_reported(toy, monkeypatch):
    """``sampler_kw`` ``pg_mode_delta``/``_scale``/``_starts``/``pg_adapt_moments``/``pg_adapt_clusters``
    are the own-mode proposal's δ, c, starts, ``moments`` and ``clusters``, and ``pg_block_sweeps`` the move's passes of block updates (recorded in the
    diagnostics), out-of-range values are refused naming the key, and a
    block whose mode search finds nothing (here the first block's, removed) is listed in
    ``pg_blocks_without_modes`` while the others are not."""
    import bayes_talk.posterior.frame_updates as fu
    import bayes_talk.posterior.particle_gibbs as pg

    model, u = toy
    T = 10
    seen, calls = [], []
    real_modes = fu.factor_modes

    class Recording(fu.BlockModeProposal):
        def __init__(self, base, blocks, **kw):
            seen.append(kw)
            super().__init__(base, blocks, **kw)

    def first_block_has_none(own, starts, **kw):
        m, S, lw = real_modes(own, starts, **kw)
        calls.append(len(m))
        return (m[:0], S[:0], lw[:0]) if len(calls) == 1 else (m, S, lw)

    sweeps = []

    class RecordingMove(pg.ParticleGibbsMove):
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            sweeps.append(self.block_sweeps)

    monkeypatch.setattr(pg, "BlockModeProposal", Recording)
    monkeypatch.setattr(pg, "ParticleGibbsMove", RecordingMove)
    monkeypatch.setattr(fu, "factor_modes", first_block_has_none)
    kw = {"n_draws": 8, "warmup": 2, "chains": 2, "seed": 1, "map_restarts": 0, "log_warnings": False}
    r = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="pg-nuts",
                         sampler_kw={"pg_particles": 8, "pg_mode_delta": 0.5, "pg_mode_scale": 2.0,
                                     "pg_mode_starts": 8, "pg_block_sweeps": 2, "pg_adapt_moments": True,
                                     "pg_adapt_clusters": True, "max_tree_depth": 3}, **kw)
    from bayes_talk.base.executor import Executor

    assert len(seen) == 1 and isinstance(seen[0].pop("executor"), Executor)   # the chains' executor
    assert seen == [{"neighbours": False, "delta": 0.5, "scale": 2.0, "n_starts": 8, "moments": True,
                     "clusters": True}]
    assert sweeps == [2]
    d = r.diagnostics
    assert (d["pg_mode_delta"], d["pg_mode_scale"], d["pg_mode_starts"]) == (0.5, [2.0], 8)
    blocks = dynamics_blocks(FrameFactors(UtteranceDensity(make_plan(model, u.mfcc[:T], u.labels[:T]))),
                             PG_NUTS_DEFAULTS["pg_block_len"])
    assert len(blocks) > 1 and calls[0] > 0 and len(calls) == len(blocks)
    assert d["pg_blocks_without_modes"] == [list(blocks[0])]
    assert d["pg_block_sweeps"] == 2 and d["pg_adapt_moments"] is True and d["pg_adapt_clusters"] is True
    for bad in ({"pg_mode_delta": 0.0}, {"pg_mode_scale": -1.0}, {"pg_mode_starts": 0}, {"pg_block_sweeps": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="pg-nuts", sampler_kw=bad, **kw)


def test_pg_nuts_reports_the_mode_weights_the_chains_warmups_taught(toy):
    """With ``pg_adapt_weights`` the diagnostics hold how far the learnt weights of every block
    with modes moved from the own ones (total variation in [0, 1], its maximum) in the one move
    frozen from all the chains' warm-ups; without it there is no such entry."""
    model, u = toy
    T = 10
    kw = {"n_draws": 8, "warmup": 4, "chains": 2, "seed": 3, "map_restarts": 0, "log_warnings": False}
    skw = {"pg_particles": 8, "max_tree_depth": 3, "pg_mode_starts": 8}
    r = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="pg-nuts",
                         sampler_kw={**skw, "pg_adapt_weights": True, "pg_adapt_moments": False}, **kw)
    ad = r.diagnostics["pg_adaptation"]
    blocks = dynamics_blocks(FrameFactors(UtteranceDensity(make_plan(model, u.mfcc[:T], u.labels[:T]))),
                             PG_NUTS_DEFAULTS["pg_block_len"])
    with_modes = {str(s) for s, _ in blocks} - {str(b[0]) for b in r.diagnostics["pg_blocks_without_modes"]}
    assert set(ad["weight_shift"]) == with_modes
    assert all(0.0 <= v <= 1.0 for v in ad["weight_shift"].values())
    assert ad["weight_shift_max"] == max(ad["weight_shift"].values())
    assert ad["modes_with_learnt_moments"] == {}
    assert ad["weight_shift_max"] > 0, "the warm-up learnt nothing"
    # with the moments: the blocks whose modes gathered enough mass in the (short) warm-ups
    rm = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="pg-nuts",
                          sampler_kw={**skw, "pg_adapt_weights": True, "pg_adapt_moments": True}, **kw)
    learnt = rm.diagnostics["pg_adaptation"]["modes_with_learnt_moments"]
    assert set(learnt) <= with_modes and all(v >= 1 for v in learnt.values())
    assert learnt, "no block gathered enough mass for its moments"
    r0 = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="pg-nuts",
                          sampler_kw={**skw, "pg_adapt_weights": False}, **kw)
    assert "pg_adaptation" not in r0.diagnostics


def test_synth_cli_offers_pg_nuts_and_its_particles(tmp_path):
    from bayes_talk.app.cli import build_parser
    from bayes_talk.pipeline import synth
    from bayes_talk.pipeline.talking_face import _sampler_args

    a = build_parser().parse_args(["synth", "M", "--audio", "x.wav", "--out", "o", "--posterior", "pg-nuts",
                                   "--pg-particles", "32"])
    assert (a.posterior, a.pg_particles) == ("pg-nuts", 32)
    assert _sampler_args({"chains": None, "pg_particles": a.pg_particles}) == {"sampler_kw": {"pg_particles": 32}}
    with pytest.raises(ValueError, match="--pg-particles applies to --posterior pg-nuts, not 'nuts'"):
        synth(tmp_path / "no-model", "x.wav", None, tmp_path / "out", posterior="nuts",
              sampler_options={"pg_particles": 32})
    # --all-draws: pg-nuts keeps drawing to --draws (the stopping rule off); refused for other methods
    b = build_parser().parse_args(["synth", "M", "--audio", "x.wav", "--out", "o", "--posterior", "pg-nuts",
                                   "--all-draws"])
    assert b.all_draws is True and build_parser().parse_args(["synth", "M", "--audio", "x.wav", "--out", "o"]).all_draws is False
    assert _sampler_args({"stop_at_targets": False}) == {"sampler_kw": {"stop_at_targets": False}}
    assert _sampler_args({"stop_at_targets": None}) == {}
    with pytest.raises(ValueError, match="--all-draws applies to --posterior pg-nuts, not 'laplace'"):
        synth(tmp_path / "no-model", "x.wav", None, tmp_path / "out", posterior="laplace",
              sampler_options={"stop_at_targets": False})


def _draws_match_their_density(q, q_ref, t, x_prev, bound, rng, N=20000):
    """N draws X of q_t given the neighbour x_prev, checked against ln q by importance weights
    against q_ref: w = q_ref/q ≤ ``bound`` and E_q[w] = 1 within 4 Monte-Carlo s.e. (a
    low-variance check that fails if ln q misses a term or the draws come from another
    density). Returns X and the repeated neighbour."""
    Xprev = np.repeat(np.asarray(x_prev)[None], N, 0)
    X, lq = q.sample_logq(t, Xprev, N, rng)
    _, lq_ref = q_ref.sample_logq(t, Xprev, N, rng, X)
    w = np.exp(lq_ref - lq)
    assert w.max() <= bound + 1e-9 and abs(w.mean() - 1) < 4 * w.std() / np.sqrt(N), (w.mean(), w.std())
    return X, Xprev


def test_multi_bandwidth_proposal_samples_from_the_density_it_reports(toy):
    """With bandwidths (0.005, 0.02, 0.05) the proposal's draws and its ln q agree: for
    q' the one-bandwidth (0.05) proposal, E_q[q'/q] = 1 (q'/q ≤ 3: a low-variance check that
    fails if ln q misses a term or the draws come from another mixture); ln q' by the
    one-bandwidth path equals the formula written out."""
    model, u = toy
    T = 12
    plan = make_plan(model, u.mfcc[:T], u.labels[:T])
    ff = FrameFactors(UtteranceDensity(plan))
    x_map = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="map", log_warnings=False).map_latents
    q = MixtureProposal(ff, plan, rho=0.5, h=(0.005, 0.02, 0.05))
    q1 = MixtureProposal(ff, plan, rho=0.5, h=0.05)
    rng = np.random.default_rng(0)
    t = next(t for t in range(1, T) if t in ff.smooth)      # a block start: entry and smoothness weights
    X, Xprev = _draws_match_their_density(q, q1, t, x_map[t - 1], 3.0, rng)
    # the one-bandwidth density written out: ρ entry + (1 − ρ) Σ_j π_j N(x; X_j, h² I)
    lw = q1._weights(t, Xprev[:5], 5)
    C = q1.centres[t]
    r2 = ((X[:5, None, :] - C[None]) ** 2).sum(-1)
    kern = np.exp(lw - 0.5 * r2 / 0.05**2).sum(1) / (2 * np.pi * 0.05**2) ** 1.5
    ref = np.log(0.5 * np.exp(ff.entry_logpdf(t, X[:5])) + 0.5 * kern)
    _, lq1 = q1.sample_logq(t, Xprev[:5], 5, rng, X[:5])
    np.testing.assert_allclose(lq1, ref, rtol=1e-9)
    with pytest.raises(ValueError, match="bandwidths h > 0"):
        MixtureProposal(ff, plan, h=(0.01, 0.0))


def test_lookahead_proposal_with_map_centres_is_a_normalised_density_of_its_draws(toy):
    """With lookahead weights and the MAP as an extra centre, at a frame starting a dynamics
    run: E_q[e(x)/q(x)] = 1 for e the entry density (e/q ≤ 1/ρ: the check fails if ln q and
    the draws disagree), the MAP's latent is the last centre, and the lookahead moves weight
    towards the centres whose continuation explains the run's audio (the weights differ)."""
    model, u = toy
    T = 20
    plan = make_plan(model, u.mfcc[:T], u.labels[:T])
    ff = FrameFactors(UtteranceDensity(plan))
    x_map = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="map", log_warnings=False).map_latents
    t = next(t for t in range(1, T - 1) if t in ff.entry and t not in ff.dyn_gp and t + 1 in ff.dyn_gp)
    q = MixtureProposal(ff, plan, rho=0.5, h=(0.005, 0.02, 0.05), lookahead=True, extra_centres=x_map[None])
    plain = MixtureProposal(ff, plan, rho=0.5, h=(0.005, 0.02, 0.05))
    np.testing.assert_array_equal(q.centres[t][-1], x_map[t])
    assert abs(logsumexp(q.logw[t])) < 1e-9 and not np.allclose(q.logw[t][:-1], plain.logw[t], atol=1e-3)
    N = 20000
    X, lq = q.sample_logq(t, np.repeat(x_map[t - 1:t], N, 0), N, np.random.default_rng(2))
    w = np.exp(ff.entry_logpdf(t, X) - lq)
    assert w.max() <= 2 + 1e-9 and abs(w.mean() - 1) < 4 * w.std() / np.sqrt(N), (w.mean(), w.std())
    with pytest.raises(ValueError, match="extra_centres"):
        MixtureProposal(ff, plan, extra_centres=x_map)


@pytest.mark.parametrize("block", ["isolated", "run"])
def test_block_modes_are_local_maxima_and_their_proposal_samples_the_density_it_reports(toy20, block):
    """``factor_modes`` on a block's own factor (``block_factor``: an isolated frame's audio
    and entry; a dynamics run's audio along its deterministic continuation): every returned
    mean is a local maximum (gradient ≈ 0; the factor lower at 40 points 0.5 sd away) and
    merged maxima are ≥ 1 sd apart. ``BlockModeProposal``: its draws and its ln q agree — for
    q⁰ the sweep's proposal (the defensive component), E_q[q⁰/q] = 1 with q⁰/q ≤ 1/δ = 5 (fails
    if ln q misses the modes' mixture or the draws come from another one) — and a (1 − δ)
    share of the draws lies within 3 sd of a mode."""
    from bayes_talk.posterior.frame_updates import BlockModeProposal, factor_modes

    T, ff, x_map, q = toy20
    if block == "isolated":
        s, e = next((s, e) for s, e in dynamics_blocks(ff, 1) if s in ff.entry and s in ff.smooth)
    else:
        s, e = next((s, e) for s, e in dynamics_blocks(ff, T) if 1 < e - s <= 6 and s > 0)

    def own(X):
        return block_factor(ff, s, e, X)

    m, S, lw = factor_modes(own, q.centres[s])
    assert len(m) >= 1 and S.shape == (len(m), 3, 3) and abs(logsumexp(lw)) < 1e-9
    rng = np.random.default_rng(3)
    g, gx = own(m)
    for k in range(len(m)):
        L = np.linalg.cholesky(S[k])
        assert np.linalg.norm(gx[k] @ L) < 1e-3, (k, gx[k])
        Z = rng.standard_normal((40, 3))
        P = m[k] + 0.5 * (Z / np.linalg.norm(Z, axis=1, keepdims=True)) @ L.T
        assert np.all(own(P)[0] < g[k])
        for j in range(k):
            r = np.linalg.solve(np.linalg.cholesky(S[j]), m[k] - m[j])
            assert r @ r > 1.0 - 1e-9
    fm = BlockModeProposal(q, [(s, e)], delta=0.2, scale=1.5)
    X, _ = _draws_match_their_density(fm, q, s, x_map[s - 1], 5.0, rng)
    Li = np.linalg.inv(np.linalg.cholesky(S * 1.5 ** 2))
    r2 = np.einsum("kij,nkj->nki", Li, X[:, None, :] - m[None])
    near = (np.sqrt((r2 ** 2).sum(-1)) < 3.0).any(1).mean()
    assert near > 0.8 * 0.95, near
    # several scales: each mode once per scale c, covariance c² Σ_k, an equal share of w_k
    fw = BlockModeProposal(q, [(s, e)], delta=0.2, scale=(1.0, 3.0))
    mw, Lw, lww = fw.modes[s]
    m1, P1, lw1 = fm.laplace[s]                                # the same modes at one scale
    S1, K = np.linalg.inv(P1), len(m1)
    np.testing.assert_allclose(mw, np.vstack([m1, m1]))
    np.testing.assert_allclose(np.einsum("kij,klj->kil", Lw, Lw), np.concatenate([S1, 9.0 * S1]), rtol=1e-8)
    np.testing.assert_allclose(lww, np.concatenate([lw1, lw1]) - np.log(2), atol=1e-12)
    Xw, _ = _draws_match_their_density(fw, q, s, x_map[s - 1], 5.0, rng)
    X1, _ = _draws_match_their_density(fm, q, s, x_map[s - 1], 5.0, rng)

    def far(X):   # the share of draws beyond 4 sd (scale 1) of every mode
        r = np.einsum("kij,nkj->nki", np.linalg.inv(Lw[:K]), X[:, None, :] - m1[None])
        return (np.sqrt((r ** 2).sum(-1)) > 4.0).all(1).mean()

    # modes' draws beyond 4 sd: at scale 3 0.4 · P(χ₃ > 4/3) ≈ 0.24, at 1.5 0.8 · P(χ₃ > 8/3) ≈ 0.02
    assert far(Xw) > far(X1) + 0.1, (far(Xw), far(X1))
    for bad in ({"delta": 0.0}, {"scale": (1.0, -1.0)}, {"scale": ()}):
        with pytest.raises(ValueError, match="delta"):
            BlockModeProposal(q, [(s, e)], **bad)


def _conditional_mode_masses(ff, bm, s, x, N, rng):
    """Importance estimate of the full conditional's mass at each of isolated frame s's own modes
    given the neighbours in x: draws from ``bm``'s proposal weighted by exp(f_s + f_{s+1}) / q,
    each assigned by its responsibilities under the modes' Laplace approximations (equal
    weights), written out here apart from ``BlockModeProposal.record``. Returns (masses, ESS)."""
    from bayes_talk.posterior.mode_adaptation import component_logpdf

    m, P, _ = bm.laplace[s]
    Y, lq = bm.sample_logq(s, np.repeat(x[s - 1][None], N, 0), N, rng)
    lw = ff.log_f(s, np.repeat(x[s - 1][None], N, 0), Y) + ff.link_logf(s + 1, Y, np.repeat(x[s + 1][None], N, 0)) - lq
    lr = component_logpdf(Y, m, np.linalg.cholesky(np.linalg.inv(P)))
    w = np.exp(lw - logsumexp(lw))
    return w @ np.exp(lr - logsumexp(lr, axis=1, keepdims=True)), 1.0 / np.sum(w * w)


def _adapt_from_the_heavy_mode(ff, bm, s, x, k, rng):
    """``bm``'s warm-up adaptation over 200 multiple-try updates of isolated frame s (neighbours
    as in x), started at own mode k → (the state after them, the own modes' means, the
    Cholesky factors of their Laplace covariances); the adaptation is left open."""
    m, P, _ = bm.laplace[s]
    bm.begin_adaptation()
    y = x.copy()
    y[s] = m[k]
    for _ in range(200):
        y, _ = block_mtm(ff, bm, y, [(s, s + 1)], 16, rng)
    return y, m, np.linalg.cholesky(np.linalg.inv(P))


def _assert_time_at_mode_matches_the_conditional(ff, bm, s, x, y, k, m, L, rng):
    """2,000 multiple-try updates of isolated frame s with the frozen proposal ``bm`` from state
    y (neighbours as in x): the chain's share of time at own mode k (nearest under the Laplace
    approximations m, L L^T) within 5 s.e. (batch means and the estimate's own from its ESS) of
    the conditional's mass there (:func:`_conditional_mode_masses`)."""
    from bayes_talk.posterior.mode_adaptation import component_logpdf

    at_k = []
    for _ in range(2000):
        y, _ = block_mtm(ff, bm, y, [(s, s + 1)], 16, rng)
        at_k.append(int(np.argmax(component_logpdf(y[s][None], m, L)[0])) == k)
    at_k = np.array(at_k)
    M, ess = _conditional_mode_masses(ff, bm, s, x, 40000, rng)
    assert ess > 200, ess
    B = at_k.reshape(40, -1).mean(1)
    se = np.hypot(max(B.std(ddof=1) / np.sqrt(len(B)), 1e-3), np.sqrt(M[k] * (1 - M[k]) / ess))
    assert abs(at_k.mean() - M[k]) < 5 * se, (at_k.mean(), M[k], se)


def _frame_at_a_light_mode(T, ff, x_map, q, rng):
    """(s, x, k): the first isolated frame s of the toy utterance and shift of its two neighbours
    in x (off the MAP) that put more than half of its full conditional's mass at an own mode k
    of own weight < 1 % (the held-out `utt0002` case)."""
    from bayes_talk.posterior.frame_updates import BlockModeProposal

    probe = BlockModeProposal(q, dynamics_blocks(ff, 1))
    for (s, e), shift in itertools.product(dynamics_blocks(ff, 1), (0.05, 0.1, -0.1)):
        if s == 0 or e == T or s not in probe.modes or len(probe.modes[s][0]) < 2:
            continue
        x = x_map.copy()
        x[s - 1] += shift
        x[e] += shift
        M, _ = _conditional_mode_masses(ff, probe, s, x, 20000, rng)
        k = int(np.argmax(M))
        if M[k] > 0.5 and np.exp(probe.own_weights[s][k]) < 0.01:
            return s, x, k
    raise AssertionError("the toy utterance needs a frame whose neighbours can move its conditional's mode")


def test_mode_weights_learnt_in_warmup_let_an_isolated_frame_switch_modes_and_keep_its_conditional(toy20):
    """``BlockModeProposal``'s warm-up adaptation on an isolated frame whose neighbours are moved
    off the MAP so that its full conditional sits at a mode of own weight < 1 % (the held-out
    `utt0002` case), chains started there: with the own weights the multiple-try updates
    almost never switch mode;
    after 200 adapting updates the frozen weights are (1 − ½) × the estimated masses + ½ × the
    own ones, the chain switches modes often, and its share of time at the heavy mode matches
    the conditional's mass (an importance estimate through the adapted proposal, which now
    covers that mode: 5 s.e., batch means and the estimate's own from its ESS). ``begin_adaptation`` restores the own weights;
    nothing is tallied outside adaptation; the pairs' weights follow (``refresh``)."""
    from bayes_talk.posterior.frame_updates import (
        BlockModeProposal,
        PairModeProposal,
        adjacent_pairs,
        component_logpdf,
    )

    T, ff, x_map, q = toy20
    rng = np.random.default_rng(21)
    s, x, k = _frame_at_a_light_mode(T, ff, x_map, q, rng)
    m, P, lw0 = BlockModeProposal(q, [(s, s + 1)]).laplace[s]
    L = np.linalg.cholesky(np.linalg.inv(P))

    def run(bm, y, n):
        at_k, switches, last = [], 0, None
        for _ in range(n):
            y, _ = block_mtm(ff, bm, y, [(s, s + 1)], 16, rng)
            j = int(np.argmax(component_logpdf(y[s][None], m, L)[0]))
            switches += last is not None and j != last
            at_k.append(j == k)
            last = j
        return y, np.array(at_k), switches

    y0 = x.copy()
    y0[s] = m[k]                                         # start where the conditional's mass is
    own = BlockModeProposal(q, [(s, s + 1)], moments=False, clusters=False)
    _, _, own_switches = run(own, y0.copy(), 1000)
    assert own.adapting is False and own.tally == {}
    ad = BlockModeProposal(q, [(s, s + 1)], moments=False, clusters=False)          # the weights alone
    ad.begin_adaptation()
    y, _, _ = run(ad, y0.copy(), 200)
    n = ad.tally[s].n
    tally = ad.tally[s].mass.copy()
    ad.end_adaptation()
    assert n == 200 and not ad.adapting
    np.testing.assert_allclose(np.exp(ad.laplace[s][2]), 0.5 * tally / n + 0.5 * np.exp(lw0), rtol=1e-10)
    assert np.exp(ad.laplace[s][2][k]) > np.exp(lw0[k]) + 0.02 and ad.weight_shift()[s] > 0.02
    np.testing.assert_allclose(ad.modes[s][2], ad.laplace[s][2] - np.log(len(ad.scales)), atol=1e-12)
    y, at_k, switches = run(ad, y, 2000)
    assert ad.tally[s].n == 200                          # frozen: nothing more tallied
    assert own_switches <= 5 and switches >= 50, (own_switches, switches)
    M, ess = _conditional_mode_masses(ff, ad, s, x, 40000, rng)
    assert ess > 200, ess
    B = at_k.reshape(40, -1).mean(1)
    se = np.hypot(max(B.std(ddof=1) / np.sqrt(len(B)), 1e-3), np.sqrt(M[k] * (1 - M[k]) / ess))
    assert abs(at_k.mean() - M[k]) < 5 * se, (at_k.mean(), M[k], se)
    ad.begin_adaptation()                                # a new warm-up starts from the own weights
    np.testing.assert_array_equal(ad.laplace[s][2], lw0)
    # pairs: refresh recomputes the pair weights from the adapted modes' weights
    blocks = dynamics_blocks(ff, 8)
    bm = BlockModeProposal(q, blocks, clusters=False)
    (s1, mid), (_, e1) = pair = next(p for p in adjacent_pairs(blocks) if p[0][0] in bm.modes and p[1][0] in bm.modes
                                             and len(bm.laplace[p[0][0]][0]) > 1)
    pq = PairModeProposal(bm, [pair])
    bm.begin_adaptation()
    a = bm.laplace[s1][0]
    bm.record(s1, a[[0]], np.zeros(1), a[-1])              # all the tally at the first and last modes
    bm.end_adaptation()
    pq.refresh()
    a, _, wa = bm.modes[s1]
    b, _, wb = bm.modes[mid]
    assert not np.allclose(wa, np.tile(bm.own_weights[s1], len(bm.scales)) - np.log(len(bm.scales)))
    np.testing.assert_allclose(pq.groups[(s1, e1)][-1], _pair_weights_by_hand(ff, s1, mid, a, wa, b, wb), rtol=1e-10)


def test_state_clusters_learnt_in_warmup_keep_the_isolated_frames_conditional(toy20):
    """``BlockModeProposal(clusters=True)`` on the isolated frame of the weights test above: after
    200 adapting updates (started at the conditional's heavy mode k) a Gaussian mixture of the
    late states joins the proposal (its components at each scale, ``CLUSTER_SHARE`` of the
    weight); the proposal's ln q matches its draws (E_q[u/q] = 1 for u the cluster components
    alone: fails if ln q misses them); and the chain's share of time at mode k over 2,000 further
    updates matches the conditional's mass (5 s.e., as above) — the frozen proposal keeps the
    conditional."""
    from bayes_talk.posterior.frame_updates import BlockModeProposal
    from bayes_talk.posterior.mode_adaptation import CLUSTER_SHARE, component_logpdf

    T, ff, x_map, q = toy20
    rng = np.random.default_rng(23)
    s, x, k = _frame_at_a_light_mode(T, ff, x_map, q, rng)
    bm = BlockModeProposal(q, [(s, s + 1)], moments=False, clusters=True)
    y, m, L = _adapt_from_the_heavy_mode(ff, bm, s, x, k, rng)
    bm.end_adaptation()
    mu, _, w = bm.clustered[s]
    means, Lc, lw = bm.modes[s]
    n_own, J = len(m), len(w)
    per_scale = n_own + J
    assert means.shape == (len(bm.scales) * per_scale, ff.d)
    is_cluster = np.arange(len(means)) % per_scale >= n_own
    assert np.exp(logsumexp(lw[is_cluster])) == pytest.approx(CLUSTER_SHARE, rel=1e-10)
    np.testing.assert_allclose(means[:per_scale][n_own:], mu, rtol=1e-12)
    Y, lq = bm.sample_logq(s, np.repeat(x[s - 1][None], 40000, 0), 40000, rng)
    lu = logsumexp(lw[is_cluster][None] + component_logpdf(Y, means[is_cluster], Lc[is_cluster]), axis=1) \
        - np.log(CLUSTER_SHARE)
    ratio = np.exp(lu - lq)
    assert abs(ratio.mean() - 1.0) < 5 * ratio.std() / np.sqrt(len(ratio)) + 1e-3, ratio.mean()
    _assert_time_at_mode_matches_the_conditional(ff, bm, s, x, y, k, m, L, rng)


def test_mode_moments_learnt_in_warmup_add_components_that_sample_their_density_and_keep_the_conditional(toy20):
    """``BlockModeProposal(moments=True)`` on the isolated frame of the weights test above: after
    200 adapting updates every mode that gathered enough mass (at least the conditional's heavy
    mode k) gets a component at the tally's mean and covariance, with half of the mode's learnt
    weight (the other half stays on its own Laplace component), every component at each scale;
    the proposal's draws and its ln q agree (E_q[u/q] = 1 for u the learnt components alone,
    equal weights: fails if ln q misses them or the draws come from another mixture); the chain
    then keeps the conditional (time at mode k against its mass, as above); a new warm-up drops
    the learnt components."""
    from bayes_talk.posterior.frame_updates import BlockModeProposal
    from bayes_talk.posterior.mode_adaptation import component_logpdf

    T, ff, x_map, q = toy20
    rng = np.random.default_rng(21)
    s, x, k = _frame_at_a_light_mode(T, ff, x_map, q, rng)
    bm = BlockModeProposal(q, [(s, s + 1)], moments=True, clusters=False)
    P = bm.laplace[s][1]
    y, m, L = _adapt_from_the_heavy_mode(ff, bm, s, x, k, rng)
    K, C = len(m), len(bm.scales)
    idx, mu, cov = bm.tally[s].moments(np.linalg.inv(P))
    bm.end_adaptation()
    assert k in idx and list(bm.learnt[s][0]) == list(idx)
    np.testing.assert_allclose(bm.learnt[s][1], mu, rtol=1e-12)
    np.testing.assert_allclose(bm.learnt[s][2], cov, rtol=1e-12)
    means, Lc, lw = bm.modes[s]
    J = len(idx)
    assert means.shape == (C * (K + J), ff.d)
    w = np.exp(bm.laplace[s][2])
    split = np.concatenate([w * np.where(np.isin(np.arange(K), idx), 0.5, 1.0), 0.5 * w[idx]]) / C
    np.testing.assert_allclose(np.exp(lw), np.tile(split, C), rtol=1e-10)
    np.testing.assert_allclose(means[K:K + J], mu, rtol=1e-12)
    np.testing.assert_allclose(Lc[K:K + J] @ np.swapaxes(Lc[K:K + J], 1, 2), bm.scales[0] ** 2 * cov, rtol=1e-10)
    N = 20000
    Y, lq = bm.sample_logq(s, np.repeat(x[s - 1][None], N, 0), N, rng)
    u = logsumexp(component_logpdf(Y, means[K:K + J], Lc[K:K + J]), axis=1) - np.log(J)
    r = np.exp(u - lq)
    assert abs(r.mean() - 1) < 4 * r.std() / np.sqrt(N), (r.mean(), r.std())
    _assert_time_at_mode_matches_the_conditional(ff, bm, s, x, y, k, m, L, rng)
    bm.begin_adaptation()
    assert bm.learnt == {} and len(bm.modes[s][0]) == C * K


def _pair_weights_by_hand(ff, s, mid, a, wa, b, wb):
    """ln π'_kl of a pair [s, mid), [mid, e): (1 − δ) w^a_k w^b_l exp(link) normalised + δ uniform
    (δ = 0.2), the link from a_k's path continued by the dynamics means, pair by pair."""
    lp = np.empty((len(a), len(b)))
    for k in range(len(a)):
        end = a[k][None]
        for u in range(s + 1, mid):
            end = ff.dynamics_mean_sd(u, end)[0]
        for j in range(len(b)):
            lp[k, j] = wa[k] + wb[j] + ff.link_logf(mid, end, b[j][None])[0]
    return np.log(0.8 * np.exp(lp - logsumexp(lp)) + 0.2 / lp.size)


def _pair_draws_match_their_density(pq, s, e, a, La, b, Lb, rng, N=20000, **neighbours):
    """A pair proposal's draws and ln q agree: E_q[q_u/q] = 1 (4 s.e.) and q_u/q ≤ 1/δ for q_u
    the mixture of the components (a, La) × (b, Lb) with uniform pair weights."""
    from bayes_talk.posterior.mode_adaptation import component_logpdf

    Y, lq = pq.sample_starts(s, e, N, rng, **neighbours)
    lu = (logsumexp(component_logpdf(Y[:, 0], a, La), axis=1) + logsumexp(component_logpdf(Y[:, 1], b, Lb), axis=1)
          - np.log(len(a) * len(b)))
    w = np.exp(lu - lq)
    assert w.max() <= 5 + 1e-9 and abs(w.mean() - 1) < 4 * w.std() / np.sqrt(N), (w.mean(), w.std())


def test_pair_proposal_matches_modes_through_the_link_and_samples_the_density_it_reports(toy20):
    """``PairModeProposal`` over two consecutive blocks of the toy utterance: its pair weights
    are (1 − δ) × the normalised w^a_k w^b_l exp(link between a_k's continued end and b_l) + δ
    uniform, the link recomputed pair by pair; its draws and ln q agree (E_q[q_u/q] = 1 for q_u
    the uniform-pair mixture, q_u/q ≤ 1/δ; fails if ln q misses the pairing or the draws come
    from another mixture); the reference replaces the last draw."""
    from bayes_talk.posterior.frame_updates import (
        BlockModeProposal,
        PairModeProposal,
        adjacent_pairs,
    )

    _, ff, x_map, q = toy20
    blocks = dynamics_blocks(ff, 8)
    bm = BlockModeProposal(q, blocks)
    pairs = [p for p in adjacent_pairs(blocks) if p[0][0] in bm.modes and p[1][0] in bm.modes
             and len(bm.modes[p[0][0]][0]) * len(bm.modes[p[1][0]][0]) > 1]
    assert pairs, "the toy utterance needs consecutive blocks with modes"
    (s, mid), (_, e) = pairs[0]
    pq = PairModeProposal(bm, [pairs[0]])
    assert pq.pairs == [(s, e)]
    a, La, wa = bm.modes[s]
    b, Lb, wb = bm.modes[mid]
    np.testing.assert_allclose(pq.groups[(s, e)][-1], _pair_weights_by_hand(ff, s, mid, a, wa, b, wb), rtol=1e-10)
    _pair_draws_match_their_density(pq, s, e, a, La, b, Lb, np.random.default_rng(7))
    rng = np.random.default_rng(8)
    Y2, lq2 = pq.sample_starts(s, e, 3, rng, ref=x_map[[s, mid]])
    assert np.array_equal(Y2[-1], x_map[[s, mid]])
    assert lq2[-1] == pytest.approx(pq.sample_starts(s, e, 1, rng, ref=x_map[[s, mid]])[1][0], rel=1e-12)
    with pytest.raises(ValueError, match="consecutive"):
        PairModeProposal(bm, [((0, 2), (3, 5))])


def test_pair_proposal_with_neighbours_conditions_each_block_on_its_outer_neighbour(toy20):
    """``PairModeProposal`` over modes with ``neighbours``: block [s, m)'s components are its
    modes conditioned on the factor from x_{s−1} only, block [m, e)'s on the one into x_e only
    (``BlockModeProposal.components``), the pair weights recomputed from them through the link;
    draws and ln q agree with that mixture (E_q[q_u/q] = 1 for q_u its uniform-pair version;
    fails if the draws or ln q use the unconditioned modes); without ``neighbours`` the
    neighbours change nothing."""
    from bayes_talk.posterior.frame_updates import (
        BlockModeProposal,
        PairModeProposal,
        adjacent_pairs,
    )

    T, ff, x_map, q = toy20
    blocks = dynamics_blocks(ff, 8)
    pairs = [p for p in adjacent_pairs(blocks) if p[0][0] > 0 and p[1][1] < T]
    plain = BlockModeProposal(q, blocks)
    cond = BlockModeProposal(q, blocks, neighbours=True)
    pair = next(p for p in pairs if p[0][0] in cond.modes and p[1][0] in cond.modes)
    (s, mid), (_, e) = pair
    x_prev, x_next = x_map[s - 1] + 0.1, x_map[e] - 0.1            # away from the MAP: a real pull
    pq = PairModeProposal(cond, [pair])
    a, La, wa = cond.components(s, x_prev, None)
    b, Lb, wb = cond.components(mid, None, x_next)
    assert not np.allclose(a, plain.modes[s][0]) and not np.allclose(b, plain.modes[mid][0])
    np.testing.assert_allclose(pq._pair_weights(s, mid, a, wa, b, wb), _pair_weights_by_hand(ff, s, mid, a, wa, b, wb),
                               rtol=1e-10)
    rng = np.random.default_rng(11)
    _pair_draws_match_their_density(pq, s, e, a, La, b, Lb, rng, x_prev=x_prev, x_next=x_next)
    ref = x_map[[s, mid]]
    pp = PairModeProposal(plain, [pair])
    r1 = pp.sample_starts(s, e, 1, np.random.default_rng(0), ref=ref)[1]
    r2 = pp.sample_starts(s, e, 1, np.random.default_rng(0), ref=ref, x_prev=x_prev, x_next=x_next)[1]
    assert r1[0] == r2[0]
    assert pq.sample_starts(s, e, 1, rng, ref=ref, x_prev=x_prev, x_next=x_next)[1][0] != r1[0]


def test_block_factor_is_the_own_factors_along_the_dynamics_means_with_their_gradient(toy):
    """``block_factor`` of a dynamics run equals the own factors summed along the path the
    dynamics means continue (written out frame by frame), its gradient matches central
    differences, and the dynamics' logpdf is the Gaussian of ``dynamics_mean_sd``."""
    model, u = toy
    T = 20
    plan = make_plan(model, u.mfcc[:T], u.labels[:T])
    ff = FrameFactors(UtteranceDensity(plan))
    x_map = sample_synthesis(model, u.mfcc[:T], u.labels[:T], method="map", log_warnings=False).map_latents
    s, e = next((s, e) for s, e in dynamics_blocks(ff, T) if e - s >= 3)
    rng = np.random.default_rng(5)
    X = x_map[s] + 0.02 * rng.standard_normal((4, 3))
    g, gx = block_factor(ff, s, e, X)
    ref, M = ff.own_factor(s, X)[0], X
    for v in range(s + 1, e):
        mu, sd = ff.dynamics_mean_sd(v, M)
        Y = mu + sd * rng.standard_normal(mu.shape)
        lp = (-0.5 * ((Y - mu) / sd) ** 2 - np.log(sd) - 0.5 * np.log(2 * np.pi)).sum(1)
        np.testing.assert_allclose(ff.dynamics_logpdf(v, M, Y), lp, rtol=1e-9)
        M = mu
        ref = ref + ff.own_factor(v, M)[0]
    np.testing.assert_allclose(g, ref, rtol=1e-12)
    h = 1e-6
    fd = np.stack([(block_factor(ff, s, e, X + h * np.eye(3)[j])[0] - block_factor(ff, s, e, X - h * np.eye(3)[j])[0])
                   / (2 * h) for j in range(3)], axis=1)
    np.testing.assert_allclose(gx, fd, rtol=1e-5, atol=1e-4 * np.abs(fd).max())


@pytest.mark.parametrize("block", ["isolated", "run"])
def test_neighbour_adjusted_modes_are_the_conditioned_laplace_approximation(toy20, block):
    """``BlockModeProposal(neighbours=True)``: each own-factor mode N(m_k, Σ_k) conditioned on
    the block's smoothness factors at both ends given x_{s−1} and x_e. Its mean is the maximum
    of F(x) = ln N(x; m_k, Σ_k) + the two smoothness factors (the end one at the path the
    dynamics means continue from x), found numerically, within 0.1 sd and 5× closer than m_k; its precision is F's
    curvature there (20 %); and the proposal's draws and ln q agree (E_q[q⁰/q] = 1, q⁰/q ≤ 1/δ).
    A sign error in the residual or the end factor's Jacobian fails the first check."""
    from scipy.optimize import minimize

    from bayes_talk.posterior.frame_updates import BlockModeProposal

    T, ff, x_map, q = toy20
    cap = 1 if block == "isolated" else T
    s, e = next((s, e) for s, e in dynamics_blocks(ff, cap) if s > 0 and e < T and s in ff.smooth and e in ff.smooth
                and (e - s == 1) == (block == "isolated"))
    x_prev, x_next = x_map[s - 1] + 0.1, x_map[e] - 0.1            # neighbours away from the MAP: a real pull
    plain = BlockModeProposal(q, [(s, e)], delta=0.2, scale=1.5)
    fm = BlockModeProposal(q, [(s, e)], delta=0.2, scale=1.5, neighbours=True)
    m0, L0, _ = plain.components(s, x_prev, x_next)
    m1, L1, lw1 = fm.components(s, x_prev, x_next)
    assert abs(logsumexp(lw1)) < 1e-9
    k = int(np.argmax(lw1))
    S0 = L0[k] @ L0[k].T / 1.5 ** 2
    P0 = np.linalg.inv(S0)

    def F(x):
        X = x[None]
        c = X
        for v in range(s + 1, e):
            c = ff.dynamics_mean_sd(v, c)[0]
        r = x - m0[k]
        return (-0.5 * r @ P0 @ r + ff.link_logf(s, x_prev[None], X)[0]
                + ff.link_logf(e, c, x_next[None])[0])

    x_star = minimize(lambda x: -F(x), m1[k], method="Nelder-Mead",
                      options={"xatol": 1e-9, "fatol": 1e-11, "maxiter": 20000}).x
    S1 = L1[k] @ L1[k].T / 1.5 ** 2
    z = np.linalg.solve(np.linalg.cholesky(S1), x_star - m1[k])
    z0 = np.linalg.solve(np.linalg.cholesky(S1), x_star - m0[k])
    # the conditioning moved the mean to F's maximum: within 0.1 sd, 5× closer than the own mode
    assert np.sqrt(z @ z) < min(0.1, 0.2 * np.sqrt(z0 @ z0)), (z, z0)
    h = 1e-4
    H = np.array([[(F(x_star + h * (a + b)) - F(x_star + h * (a - b)) - F(x_star - h * (a - b)) + F(x_star - h * (a + b)))
                   / (4 * h * h) for b in np.eye(3)] for a in np.eye(3)])
    ev = np.linalg.eigvalsh(np.linalg.solve(np.linalg.cholesky(np.linalg.inv(S1)), np.linalg.solve(
        np.linalg.cholesky(np.linalg.inv(S1)), -H).T))
    assert np.all(np.abs(ev - 1) < 0.2), ev
    N = 20000
    rng = np.random.default_rng(5)
    Xprev = np.repeat(x_prev[None], N, 0)
    X, lq = fm.sample_logq(s, Xprev, N, rng, x_next=x_next)
    _, lq0 = q.sample_logq(s, Xprev, N, rng, X)
    w = np.exp(lq0 - lq)
    assert w.max() <= 5.0 + 1e-9 and abs(w.mean() - 1) < 4 * w.std() / np.sqrt(N), (w.mean(), w.std())
