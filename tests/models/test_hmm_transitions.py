"""SGPLVM B's HMM initialiser: its transition table, computed from the dynamics predictive
at the M hidden states once (the M² pairwise evaluation took ~4 GB at M = 300, N = 1500),
equals ln p(x_j | x_i) evaluated pair by pair.

The two routes sum in different orders, and entries reach -3·10⁴ nats: they agree to
~2·10⁻¹² relative (the last few bits, machine-dependent), so the check is at 1e-10
relative; a wrong row/column layout is off by thousands of nats."""
from __future__ import annotations

import numpy as np
import torch
from scipy.special import logsumexp

from bayes_talk.models.sgpdm import SGPDM
from bayes_talk.synthesis.initialisers import HMMViterbi


def test_transitions_equal_the_pairwise_dynamics_density():
    rng = np.random.default_rng(5)
    t = np.linspace(0, 4 * np.pi, 90)[:, None]
    audio = np.hstack([np.sin(t), np.cos(t), np.sin(2 * t)]) + 0.02 * rng.normal(size=(90, 3))
    video = np.hstack([np.cos(t) ** 2, np.sin(3 * t)]) + 0.02 * rng.normal(size=(90, 2))
    m = SGPDM(latent_dim=2, max_iter=30).fit({"audio": audio, "visual": video}, seq_lengths=[45, 45])
    dyn = m.dynamics_predictor_
    assert dyn is not None
    idx, trans = HMMViterbi(n_states=40, seed=2)._states(m)
    M = len(idx)
    S = torch.as_tensor(m.X_[idx])
    with torch.no_grad():  # row i: source x_i (input), column j: target x_j (output)
        pair = dyn.log_lik(S.repeat(M, 1), S.repeat_interleave(M, 0)).reshape(M, M).numpy()
    np.testing.assert_allclose(trans, pair - logsumexp(pair, axis=1, keepdims=True), rtol=1e-10, atol=1e-10)
    assert not np.allclose(trans, trans.T)  # the table is not symmetric: the layout matters
