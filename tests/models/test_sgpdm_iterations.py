"""SGPDM.fit runs at most ``max_iter`` L-BFGS iterations (it used to run blocks of 20, so a
budget below 20 ran 20)."""
from __future__ import annotations

import numpy as np
import pytest

from bayes_talk.models.sgpdm import SGPDM


@pytest.mark.parametrize("max_iter", [1, 3, 23])
def test_fit_runs_at_most_max_iter_lbfgs_iterations(max_iter):
    rng = np.random.default_rng(0)
    t = np.linspace(0, 4 * np.pi, 60)
    audio = np.c_[np.sin(t), np.cos(t), 0.1 * t] + 0.05 * rng.normal(size=(60, 3))
    video = np.c_[np.sin(t + 0.3), np.cos(2 * t)] + 0.05 * rng.normal(size=(60, 2))
    m = SGPDM(latent_dim=2, max_iter=max_iter, tol=0.0).fit({"audio": audio, "visual": video})
    assert 1 <= m.history.n_iter <= max_iter
    if max_iter == 23:  # the budget spans two blocks: more than one block of 20 was used
        assert m.history.n_iter > 20
