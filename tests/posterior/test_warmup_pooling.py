"""A NUTS chain split at the end of its warm-up, and the warm-ups' adaptation pooled over the
chains before any kept draw (issue 24; :mod:`bayes_talk.posterior.nuts_chain`)."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from toydata import make_utterances

from bayes_talk.posterior.frame_updates import BlockModeProposal, dynamics_blocks
from bayes_talk.posterior.mode_adaptation import ModeTally
from bayes_talk.posterior.nuts_chain import (
    MOVE_STREAM,
    ChainState,
    _kernel,
    draw_chain,
    run_kernel,
    warmup_chain,
)
from bayes_talk.posterior.particle_gibbs import FrameFactors, MixtureProposal
from bayes_talk.posterior.samplers import run_nuts
from bayes_talk.synthesis.joint import UtteranceDensity, make_plan


def _banana(x: torch.Tensor) -> torch.Tensor:
    """A curved 3-d density (not a Gaussian, so the mass matrix and step size matter)."""
    return -0.5 * (x[0] ** 2 + 4.0 * (x[1] - 0.3 * x[0] ** 2) ** 2 + x[2] ** 2 / 4.0)


class _RandomWalk:
    """A Metropolis random walk on the banana (posterior-invariant) that draws from the chain's
    numpy generator: if the split lost that generator's state, the draws would differ."""

    def __call__(self, x, rng):
        y = x + 0.3 * rng.standard_normal(x.shape)
        lp = float(_banana(torch.as_tensor(y))) - float(_banana(torch.as_tensor(x)))
        return (y if np.log(rng.random()) < lp else x), {"moved": not np.array_equal(y, x)}


def test_a_chain_split_at_its_warmup_draws_exactly_what_one_uninterrupted_run_draws():
    """Warm-up task, then draws task (step size, mass matrix, torch and numpy generators carried
    over in the ChainState) gives the draws, records and step size of one kernel run through
    warm-up and draws without a break — with mode jumps and an extra move drawing from the numpy
    generator; and the carried mass matrix is the adapted one, not the identity."""
    kw = {"target_accept": 0.8, "max_tree_depth": 6, "jumps": np.array([[0.5, 0.0, 0.0]]), "jump_attempts": 1,
          "extra_move": _RandomWalk(), "extra_every": 2}
    start, W, N, seed, c = np.array([1.0, -0.5, 2.0]), 60, 40, 7, 1
    state = warmup_chain((_banana, start, W, seed, c, kw))
    split = draw_chain((_banana, state, N, W, seed, c, kw))
    assert not np.allclose(state.inverse_mass, 1.0)

    import pyro

    pyro.set_rng_seed(seed + c)
    counter = [0]
    one = ChainState(start, rng=np.random.default_rng([seed, c, MOVE_STREAM]))
    kernel = _kernel(_banana, counter, one, kw, kw["extra_move"], adapt=True, t_offset=0)
    draws, _ = run_kernel(kernel, start, W, N, "uninterrupted")
    np.testing.assert_array_equal(split["samples"], draws)
    assert split["step_size"] == kernel.step_size
    for key in ("n_steps", "diverging", "energy", "lp", "jumps"):
        np.testing.assert_array_equal(split["records"][key], kernel.records[key])
    assert split["jump_counts"] == kernel.jump_counts


class _CountingMove:
    """An adaptive ``extra_move``: each chain's copy counts its calls while adapting; the frozen
    move keeps the chains' counts (``end_adaptation``) and reports them with every call."""

    def __init__(self):
        self.adapting, self.calls, self.pooled = False, 0, None

    def begin_adaptation(self):
        self.adapting, self.calls = True, 0

    def adaptation_state(self):
        return self.calls

    def end_adaptation(self, states=None):
        self.adapting, self.pooled = False, list(states)

    def __call__(self, x, rng):
        self.calls += self.adapting
        return x, {"adapting": self.adapting, "pooled": np.array(self.pooled or [-1] * 3)}

    def adaptation_summary(self):
        return {"pooled": self.pooled}


@pytest.mark.parametrize("workers", [1, 2])
def test_every_chain_draws_with_one_move_frozen_from_all_the_chains_warmups(workers):
    """``run_nuts`` with an adaptive move: each chain's copy adapts during exactly its warm-up
    (the warm-up tasks' states, in chain order, are what the frozen move pooled), every kept
    draw of every chain comes from that one frozen move, the caller's move is untouched, and the
    draws are the same whatever the worker count; without a warm-up nothing is learnt."""
    move = _CountingMove()
    d = run_nuts(_banana, np.zeros(3), n_draws=4, warmup=5, chains=3, seed=0, extra_move=move, workers=workers)
    np.testing.assert_array_equal(d.sample_stats["adapting"], False)
    np.testing.assert_array_equal(d.sample_stats["pooled"], np.broadcast_to([5, 5, 5], (3, 4, 3)))
    assert d.stats["extra_move_adaptation"] == {"pooled": [5, 5, 5]}
    assert (move.adapting, move.calls, move.pooled) == (False, 0, None)
    ref = run_nuts(_banana, np.zeros(3), n_draws=4, warmup=5, chains=3, seed=0, extra_move=move, workers=1)
    np.testing.assert_array_equal(d.samples, ref.samples)
    d0 = run_nuts(_banana, np.zeros(3), n_draws=3, warmup=0, chains=1, seed=0, extra_move=move)
    assert d0.stats["extra_move_adaptation"] == {"pooled": [None]}


@pytest.fixture(scope="module")
def block_proposal(toy_vlmm):
    """The own-mode proposal of the toy utterance's isolated frames (first 20 frames) and one
    frame s of it with at least two modes."""
    u = make_utterances(1, seed=1, mean_len=20)[0]
    T = 20
    plan = make_plan(toy_vlmm, u.mfcc[:T], u.labels[:T])
    ff = FrameFactors(UtteranceDensity(plan))
    q = MixtureProposal(ff, plan, rho=0.5, h=(0.005, 0.02, 0.05))
    bm = BlockModeProposal(q, dynamics_blocks(ff, 1), moments=True)
    s = next(s for s in bm.modes if len(bm.laplace[s][0]) >= 2)
    return bm, s


def test_pooled_warmup_tallies_freeze_the_proposal_one_chain_recording_every_update_would(block_proposal):
    """Two chains' tallies pooled (``end_adaptation(tallies)``) give the weights, learnt means and
    covariances, and proposal components that one proposal recording both chains' updates gives
    (round-off); a chain's tallies alone give others; tallies of different shapes are refused."""
    base, s = block_proposal
    m = base.laplace[s][0]
    rng = np.random.default_rng(5)
    updates = []
    for i in range(60):   # tries around the modes, their log weights, the state after the update
        Y = m[rng.integers(len(m), size=8)] + 0.02 * rng.standard_normal((8, m.shape[1]))
        updates.append((Y, rng.standard_normal(8), Y[rng.integers(8)] if i % 3 else m[-1]))
    a, b, one, pooled = (copy.deepcopy(base) for _ in range(4))
    for p in (a, b, one, pooled):
        p.begin_adaptation()
    for i, (Y, lw, x) in enumerate(updates):
        (a if i < 25 else b).record(s, Y, lw, x)
        one.record(s, Y, lw, x)
    pooled.end_adaptation([a.adaptation_state(), b.adaptation_state()])
    one.end_adaptation()
    a.end_adaptation()
    assert s in one.learnt
    for k in range(3):
        np.testing.assert_allclose(pooled.learnt[s][k], one.learnt[s][k], rtol=1e-12, atol=1e-14)
    for k in range(3):
        np.testing.assert_allclose(pooled.modes[s][k], one.modes[s][k], rtol=1e-12, atol=1e-14)
    assert not np.allclose(a.laplace[s][2], one.laplace[s][2])
    with pytest.raises(ValueError, match="cannot pool"):
        ModeTally.pooled([ModeTally(2, 3), ModeTally(3, 3)])


def test_clusters_of_the_pooled_late_warmup_states_become_proposal_components(block_proposal):
    """With ``clusters`` on, the warm-up states of the chains' second halves (pooled) are fitted
    by a Gaussian mixture whose number of components BIC picks: states from two separated
    clusters (70 / 30 %, neither at an own mode) give two components at their means with their
    weights, proposed with ``CLUSTER_SHARE`` of the mixture (the mixture's weights still sum to
    one); the first halves (the chains' starts) are left out; one cluster gives one component,
    and too few states none."""
    from scipy.special import logsumexp

    from bayes_talk.posterior.mode_adaptation import CLUSTER_SHARE

    base, s = block_proposal
    m = base.laplace[s][0]
    d = m.shape[1]
    rng = np.random.default_rng(11)
    A, B = m[0] + 0.3, m[0] - 0.3
    chains = []
    for c in range(2):
        p = copy.deepcopy(base)
        p.learn_clusters = True
        p.begin_adaptation()
        for i in range(200):   # first half far off (the start), second half 70 % at A and 30 % at B
            x = m[0] + 5.0 if i < 100 else (A if rng.random() < 0.7 else B) + 0.01 * rng.standard_normal(d)
            p.record(s, m[:1], np.zeros(1), x)
        chains.append(p)
    pooled = copy.deepcopy(base)
    pooled.learn_clusters = True
    pooled.begin_adaptation()
    pooled.end_adaptation([p.adaptation_state() for p in chains])
    mu, C, w = pooled.clustered[s]
    order = np.argsort(-w)
    assert len(w) == 2 and np.all(np.linalg.eigvalsh(C) > 0)
    np.testing.assert_allclose(mu[order], [A, B], atol=0.01)
    np.testing.assert_allclose(w[order], [0.7, 0.3], atol=0.06)
    means, _, lw = pooled.modes[s]
    assert logsumexp(lw) == pytest.approx(0.0, abs=1e-12)
    at_clusters = np.isin(np.arange(len(means)) % (len(means) // len(pooled.scales)),
                          np.arange(len(means) // len(pooled.scales) - 2, len(means) // len(pooled.scales)))
    assert np.exp(logsumexp(lw[at_clusters])) == pytest.approx(CLUSTER_SHARE, rel=1e-10)
    assert pooled.tally[s].late_states().shape == (200, d)
    one = copy.deepcopy(base)
    one.learn_clusters = True
    one.begin_adaptation()
    for _ in range(120):
        one.record(s, m[:1], np.zeros(1), A + 0.01 * rng.standard_normal(d))
    one.end_adaptation()
    assert len(one.clustered[s][2]) == 1
    few = copy.deepcopy(base)
    few.learn_clusters = True
    few.begin_adaptation()
    for _ in range(20):
        few.record(s, m[:1], np.zeros(1), A)
    few.end_adaptation()
    assert s not in few.clustered


class _Never:
    """A stopping rule that never stops, keeping what it was shown."""

    def __init__(self):
        self.seen = []

    def __call__(self, samples):
        self.seen.append(samples.copy())
        return False


@pytest.mark.parametrize("warmup", [30, 0])
def test_draws_in_batches_between_checks_equal_one_uninterrupted_run(warmup):
    """A stopping rule that never fires: the chains draw in batches (20, then 15, 15, 10 per chain),
    each continuing its ChainState, and the draws, records, jump counts and step sizes equal
    those of one batch — with jumps and a move drawing from the numpy generator, with and
    without a warm-up (the step size found at the start carried too); the rule saw the draws so
    far at 20, 35 and 50 per chain, each a prefix of the final ones."""
    kw = {"n_draws": 60, "warmup": warmup, "chains": 2, "seed": 3, "jumps": np.array([[0.5, 0.0, 0.0]]),
          "jump_attempts": 1, "extra_move": _RandomWalk(), "extra_every": 2}
    one = run_nuts(_banana, np.zeros(3), **kw)
    rule = _Never()
    batched = run_nuts(_banana, np.zeros(3), enough=rule, min_draws=20, check_every=15, **kw)
    np.testing.assert_array_equal(batched.samples, one.samples)
    for key in one.sample_stats:   # the acceptance statistic is unpicked from Pyro's running mean: round-off
        check = np.testing.assert_array_equal if key != "acceptance_rate" else \
            lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
        check(batched.sample_stats[key], one.sample_stats[key])
    assert batched.stats["jumps_accepted"] == one.stats["jumps_accepted"]
    assert batched.stats["step_size"] == one.stats["step_size"]
    assert batched.stats["checks"] == [20, 35, 50] and batched.stats["stopped_early"] is False
    assert [s.shape[1] for s in rule.seen] == [20, 35, 50]
    for s in rule.seen:
        np.testing.assert_array_equal(s, one.samples[:, :s.shape[1]])


@pytest.mark.parametrize("workers", [1, 2])
def test_a_stopping_rule_ends_the_draws_where_it_first_passes(workers):
    """A rule that passes from 30 draws per chain on ends the draws at the second check (30 of at
    most 80), the same draws whatever the worker count, a prefix of the full run's; the per-draw
    statistics have the draws' length."""
    def rule(samples):
        return samples.shape[1] >= 30

    kw = {"n_draws": 80, "warmup": 10, "chains": 2, "seed": 1}
    d = run_nuts(_banana, np.zeros(3), enough=rule, min_draws=20, check_every=10, workers=workers, **kw)
    assert d.samples.shape == (2, 30, 3)
    assert d.stats["checks"] == [20, 30] and d.stats["stopped_early"] is True and d.stats["max_draws_per_chain"] == 80
    assert all(v.shape[:2] == (2, 30) for v in d.sample_stats.values())
    full = run_nuts(_banana, np.zeros(3), **kw)
    np.testing.assert_array_equal(d.samples, full.samples[:, :30])
    with pytest.raises(ValueError, match="min_draws >= 1 and check_every >= 1"):
        run_nuts(_banana, np.zeros(3), enough=rule, check_every=0, **kw)
