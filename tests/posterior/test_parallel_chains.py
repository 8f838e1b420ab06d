"""NUTS chains in parallel processes through the project's executor (issue 24, item 4): the
draws depend on the seed only, not on the number of workers."""
from __future__ import annotations

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.posterior.sampling import sample_synthesis


@pytest.fixture(scope="module")
def toy(toy_vlmm):
    return toy_vlmm, make_utterances(1, seed=1, mean_len=20)[0]


@pytest.fixture(scope="module")
def pool():
    """Two worker processes kept for the module: starting a pool of fresh interpreters
    (torch and pyro imported in each) costs more than the short chains below."""
    from bayes_talk.base.executor import ProcessExecutor

    with ProcessExecutor(2) as ex:
        yield ex


@pytest.mark.parametrize("coords", ["whitened", "noncentred"])
def test_one_worker_and_two_workers_give_identical_draws(toy, pool, coords):
    """Equality of the draws needs no mixed chain: trees are capped at depth 3 (≤ 7 leapfrog
    steps) and the chains are short. Three chains on two workers: one worker runs two of
    them. The two workers are one pool that the test owns (``executor=``; ``workers=2``
    would start a pool per ``run_nuts`` call, two with the whitened pilot phase, the most
    expensive part of this test), so a worker runs chains of both phases and of the other
    case before: the draws must not depend on what a worker ran before either."""
    model, u = toy
    labels, mfcc = u.labels[:8], u.mfcc[:8]
    kw = {"method": "nuts", "n_draws": 24, "warmup": 15, "chains": 3, "seed": 5, "map_restarts": 0,
          "log_warnings": False}
    skw = {"coords": coords, "pilot": 5, "max_tree_depth": 3}
    one = sample_synthesis(model, mfcc, labels, sampler_kw={**skw, "workers": 1}, **kw)
    two = sample_synthesis(model, mfcc, labels, sampler_kw={**skw, "executor": pool}, **kw)
    assert one.latent_draws.shape == (3, 8, 8, 3)
    assert one.diagnostics["pilot"] == (5 if coords == "whitened" else 0)
    assert np.array_equal(one.latent_draws, two.latent_draws)
    for k in ("lp", "n_steps", "energy"):
        assert np.array_equal(one.sample_stats[k], two.sample_stats[k]), k
    # the chains differ from each other (each has its own seed), so equality is not trivial
    assert not np.array_equal(one.latent_draws[0], one.latent_draws[1])


def test_pg_nuts_mode_searches_and_chains_do_not_depend_on_the_workers(toy, pool):
    """pg-nuts: the blocks' own-mode searches and the chains share one executor. On the pool's
    two workers (the blocks dealt round-robin into two tasks) or here, ``own_modes`` finds the
    same modes, in the blocks' order, to the last bit, and the chains give the same draws."""
    from bayes_talk.posterior.frame_updates import dynamics_blocks, own_modes
    from bayes_talk.posterior.particle_gibbs import FrameFactors, MixtureProposal
    from bayes_talk.synthesis.joint import UtteranceDensity, make_plan

    model, u = toy
    T = 10
    labels, mfcc = u.labels[:T], u.mfcc[:T]
    plan = make_plan(model, mfcc, labels)
    ff = FrameFactors(UtteranceDensity(plan))
    q = MixtureProposal(ff, plan, rho=0.5, h=0.05)
    jobs = [(s, e, q.centres[s][:16]) for s, e in dynamics_blocks(ff, 8)]
    here, there = own_modes(ff, jobs), own_modes(ff, jobs, pool)
    assert len(jobs) >= 3 and len(here) == len(there) == len(jobs)
    assert sum(len(m) > 0 for m, _, _ in here) >= 2, "the test needs blocks with modes"
    for a, b in zip(here, there, strict=True):
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    kw = {"method": "pg-nuts", "n_draws": 8, "warmup": 4, "chains": 2, "seed": 3, "map_restarts": 0,
          "log_warnings": False}
    skw = {"pg_particles": 8, "max_tree_depth": 3, "pg_mode_starts": 8}
    one = sample_synthesis(model, mfcc, labels, sampler_kw={**skw, "workers": 1}, **kw)
    two = sample_synthesis(model, mfcc, labels, sampler_kw={**skw, "executor": pool}, **kw)
    assert np.array_equal(one.latent_draws, two.latent_draws)
    assert one.diagnostics["pg_blocks_without_modes"] == two.diagnostics["pg_blocks_without_modes"]
