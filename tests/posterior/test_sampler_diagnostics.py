"""Diagnostics on what users consume (issue 24, item 5): R-hat, ESS and MCSE of the AAM
parameters per frame beside the latents, per-draw ``sample_stats`` for every sampler, and the
per-frame update rate of pg-nuts' particle Gibbs sweeps."""
from __future__ import annotations

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.posterior.diagnostics import (
    convergence_problems,
    frame_diagnostics,
    frame_update_diagnostics,
    frame_update_rate,
)
from bayes_talk.posterior.sampling import sample_synthesis
from bayes_talk.synthesis.joint import UtteranceDensity, make_plan


def test_frame_diagnostics_find_the_frame_where_chains_disagree():
    rng = np.random.default_rng(0)
    s = rng.standard_normal((4, 200, 6, 2))
    s[0, :, 2] += 3.0                           # chain 0 sits elsewhere in frame 2 only
    fd = frame_diagnostics(s, "aam_")
    r = np.array(fd["aam_rhat_per_frame"])
    assert r.shape == (6,) and r[2] > 1.2 and np.all(np.delete(r, 2) < 1.05), r
    assert fd["aam_rhat_max"] == pytest.approx(r.max())
    assert np.argmin(fd["aam_ess_bulk_per_frame"]) == 2 and len(fd["aam_ess_tail_per_frame"]) == 6
    assert any("AAM-parameter R-hat" in p for p in convergence_problems(fd))
    assert not convergence_problems({"aam_rhat_max": 1.005, "aam_ess_bulk_min": 500.0, "aam_ess_tail_min": 450.0})


@pytest.fixture(scope="module")
def toy(toy_vlmm):
    u = make_utterances(1, seed=1, mean_len=20)[0]
    return toy_vlmm, u.mfcc[:8], u.labels[:8]


@pytest.mark.parametrize("method", ["laplace", "vi", "emcee"])
def test_every_sampler_records_the_log_density_of_each_draw(toy, method):
    model, mfcc, labels = toy
    kw = {"emcee": {"warmup": 20, "n_draws": 32, "sampler_kw": {"max_steps": 60}},
          "vi": {"n_draws": 16, "sampler_kw": {"steps": 30}}, "laplace": {"n_draws": 16}}[method]
    r = sample_synthesis(model, mfcc, labels, method=method, seed=2, log_warnings=False, map_restarts=0, **kw)
    C, S = r.latent_draws.shape[:2]
    lp = r.sample_stats["lp"]
    assert lp.shape == (C, S)
    dens = UtteranceDensity(make_plan(model, mfcc, labels))
    np.testing.assert_allclose(lp, dens.values(r.latent_draws.reshape(C * S, 8, 3)).reshape(C, S), rtol=1e-9)
    idata = r.to_inference_data()
    assert "lp" in idata.sample_stats
    if method == "emcee":
        assert len(r.diagnostics["aam_rhat_per_frame"]) == 8 and len(r.diagnostics["rhat_per_frame"]) == 8
        assert np.isfinite(r.diagnostics["aam_ess_bulk_min"])
    else:
        assert r.sample_stats["log_weight"].shape == (C, S)


def test_frame_update_rate_counts_the_sweeps_that_ran():
    moved = np.zeros((2, 6, 3), bool)
    swept = np.ones((2, 6), bool)
    swept[1, 1::2] = False                   # chain 1: a sweep at every other iteration
    moved[0, :3, 0] = True                   # chain 0: frame 0 moved in 3 of 6 sweeps
    moved[1, 0, 1] = moved[1, 2, 1] = True   # chain 1: frame 1 in 2 of its 3 sweeps
    moved[:, :, 2] = False                   # frame 2 never
    rate = frame_update_rate(moved, swept)
    np.testing.assert_array_equal(rate, [[0.5, 0.0, 0.0], [0.0, 2 / 3, 0.0]])
    np.testing.assert_array_equal(frame_update_rate(moved), moved.mean(1))
    fd = frame_update_diagnostics(rate)
    assert fd["pg_frames_never_updated"] == [2] and fd["pg_frame_update_rate_min"] == 0.0
    assert fd["pg_frame_update_rate_mean"] == pytest.approx((0.5 + 2 / 3) / 6)
    bad = moved.copy()
    bad[1, 1, 0] = True                      # a change where no sweep ran
    with pytest.raises(ValueError, match="without a sweep"):
        frame_update_rate(bad, swept)


def test_an_extra_moves_records_are_kept_per_draw_and_blank_where_it_did_not_run():
    """``run_nuts``'s ``extra_move`` returning (x', record): each record key becomes a per-draw
    statistic, zero where the move did not run (every second iteration here)."""
    import torch

    from bayes_talk.posterior.samplers import run_nuts

    def move(x, rng):
        return x, {"ran": True, "value": np.full(2, 7.0)}

    d = run_nuts(lambda x: -0.5 * torch.sum(x * x), np.zeros(2), n_draws=6, warmup=3, chains=2, seed=0,
                 extra_move=move, extra_every=2)
    # iterations 4..9 are the draws; the move runs where the iteration is even
    np.testing.assert_array_equal(d.sample_stats["ran"], np.tile([True, False] * 3, (2, 1)))
    assert d.sample_stats["value"].shape == (2, 6, 2)
    np.testing.assert_array_equal(d.sample_stats["value"][:, 1::2], 0.0)
    np.testing.assert_array_equal(d.sample_stats["value"][:, ::2], 7.0)


def test_pg_nuts_reports_how_often_its_sweeps_changed_each_frame(toy, monkeypatch, tmp_path):
    """The sweeps' per-frame record (``pg_frame_moved``) equals a recount from the states before
    and after every sweep, the draw is the state after the sweep of its iteration, the update
    rate and its summary are in the diagnostics, and the record is in posterior.nc. A frame the
    sweep may never change (pinned to its reference value) has rate 0 in every chain (the
    multiple-try block updates after the sweep are off here: they would move it)."""
    import bayes_talk.posterior.particle_gibbs as pg
    from bayes_talk.base.arviz_compat import from_netcdf
    from bayes_talk.pipeline.uncertainty_outputs import write_posterior_netcdf
    from bayes_talk.posterior.noncentred import NonCentred

    model, mfcc, labels = toy
    T, pinned, warmup, chains, per_chain = 6, 2, 3, 2, 4
    csmc = pg.csmc_as

    def pinned_csmc(ff, q, x_ref, *a, **k):
        out, _ = csmc(ff, q, x_ref, *a, **k)
        out[pinned] = x_ref[pinned]
        return out, None

    monkeypatch.setattr(pg, "csmc_as", pinned_csmc)
    calls = []
    call = pg.ParticleGibbsMove.__call__

    def spy(self, u, rng):
        out = call(self, u, rng)
        calls.append((np.array(u, copy=True), np.array(out[0], copy=True)))
        return out

    monkeypatch.setattr(pg.ParticleGibbsMove, "__call__", spy)
    r = sample_synthesis(model, mfcc[:T], labels[:T], method="pg-nuts", n_draws=chains * per_chain, warmup=warmup,
                         chains=chains, seed=3, map_restarts=0, log_warnings=False,
                         sampler_kw={"pg_particles": 8, "max_tree_depth": 3, "pg_frame_tries": 0})
    assert len(calls) == chains * (warmup + per_chain)    # one sweep per iteration: warm-ups in turn, then draws
    kept = calls[chains * warmup:]
    nc = NonCentred(UtteranceDensity(make_plan(model, mfcc[:T], labels[:T])))
    before = nc.to_x(np.stack([b for b, _ in kept])).reshape(chains, per_chain, T, 3)
    after = nc.to_x(np.stack([a for _, a in kept])).reshape(chains, per_chain, T, 3)
    np.testing.assert_array_equal(after, r.latent_draws)  # the draw is the state after its iteration's sweep
    recount = np.abs(after - before).max(axis=3) > 1e-9
    ss, d = r.sample_stats, r.diagnostics
    assert ss["pg_frame_moved"].shape == (chains, per_chain, T) and ss["pg_sweep"].all()
    np.testing.assert_array_equal(ss["pg_frame_moved"], recount)
    rate = np.array(d["pg_frame_update_rate"])
    assert rate.shape == (chains, T) and np.all((rate >= 0) & (rate <= 1))
    np.testing.assert_array_equal(rate, recount.mean(axis=1))
    assert np.all(rate[:, pinned] == 0) and rate.max() > 0 and pinned in d["pg_frames_never_updated"]
    assert d["pg_frame_update_rate_min"] == 0.0 and d["pg_frame_update_rate_mean"] == pytest.approx(rate.mean())
    assert d["pg_sweeps_per_chain"] == [per_chain] * chains and len(d["ebfmi"]) == chains
    secs = ss["pg_seconds"]     # the move's own time per draw, summed per chain
    assert secs.shape == (chains, per_chain) and np.all(secs > 0)
    np.testing.assert_allclose(d["pg_seconds_per_chain"], secs.sum(1))
    assert all(0 < s < c for s, c in zip(d["pg_seconds_per_chain"], d["chain_seconds"], strict=True))
    idata = from_netcdf(write_posterior_netcdf(tmp_path / "posterior.nc", r))
    moved = idata.sample_stats["pg_frame_moved"]
    assert moved.dims == ("chain", "draw", "frame")
    np.testing.assert_array_equal(moved.values, recount)
