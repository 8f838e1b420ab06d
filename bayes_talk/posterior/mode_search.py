"""Modes of the whole-utterance synthesis posterior, for NUTS (docs/uncertainty.md).

The synthesis density is multimodal. :func:`mode_jumps` turns the modes a search found into
displacements for NUTS's mode-jumping Metropolis moves
(:func:`~bayes_talk.posterior.samplers.run_nuts`), and :func:`nuts_with_mode_search` runs
NUTS with a pilot phase that searches for the modes the chains reach, re-whitens at the
highest and rebuilds the jumps (docs/uncertainty.md "Mode-jumping moves and the pilot mode
search").
"""
from __future__ import annotations

import time

import numpy as np

from bayes_talk.posterior.methods import NUTS_DEFAULTS
from bayes_talk.posterior.samplers import run_nuts
from bayes_talk.synthesis.joint import UtteranceDensity
from bayes_talk.synthesis.joint_map import (
    MapResult,
    as_block_hessian,
    laplace_factor,
    maximise_utterance,
)
from bayes_talk.synthesis.whitening import Whitened, whitening

#: frames whose latents differ between two modes by more than this (max over coordinates)
#: belong to the switch between them (:func:`mode_jumps`)
JUMP_FRAME_TOL = 1e-2
#: at most this many mode-jumping displacements are kept (from the highest modes first)
MAX_JUMPS = 16


def mode_jumps(best: MapResult, modes: list[MapResult], frame_tol: float = JUMP_FRAME_TOL,
               max_jumps: int = MAX_JUMPS) -> np.ndarray:
    """Displacements (K, T, d) that carry the best mode onto the local switches the other
    converged modes show, for the NUTS sampler's mode-jumping Metropolis moves
    (:func:`~bayes_talk.posterior.samplers.run_nuts`).

    On a whole utterance the modes :func:`restart_map` finds differ from the best in a few
    short stretches of frames each (a 3-s held-out utterance: frames 0–4, 33–36, 44, 50–52),
    and a mode is a combination of such local switches, so one displacement per switch lets
    a chain flip each independently. For each converged mode m (highest first), the frames
    where max |x_m − x_best| > ``frame_tol`` are grouped into runs S (a gap of one frame
    joins two runs). A displacement moves S by δ_S = (x_m − x_best)_S and every other
    coordinate R by the shift that keeps the Laplace approximation at the best mode
    (precision P = −∇² ln p) at its conditional optimum, δ_R = −P_RR⁻¹ P_RS δ_S: the
    latents are strongly coupled from frame to frame (GP dynamics), so moving S alone
    would cost tens of nats (a measured 38 against 1.3 on that utterance) where the
    relaxed move lands within 0.05 nats of the other mode. Displacements equal to within
    ``frame_tol`` are kept once, at most ``max_jumps`` of them. The moves x → x ± δ_k
    (k and the sign uniform) form a symmetric proposal independent of the chain's state,
    so Metropolis acceptance keeps the posterior invariant."""
    if best.hessian is None:
        raise ValueError("mode_jumps needs the best mode's Hessian (MapResult.hessian)")
    xb = best.latents
    T, d = xb.shape
    P = laplace_factor(as_block_hessian(best.hessian, d)).matrix.dense()   # short paths: dense
    out: list[np.ndarray] = []
    for m in sorted((m for m in modes if m.converged), key=lambda m: -m.log_density):
        diff = m.latents - xb
        frames = np.flatnonzero(np.abs(diff).max(axis=1) > frame_tol)
        if frames.size == 0:
            continue
        for run in np.split(frames, np.flatnonzero(np.diff(frames) > 2) + 1):
            S = np.zeros((T, d), dtype=bool)
            S[run[0]:run[-1] + 1] = True
            S = S.reshape(-1)
            delta = np.zeros(T * d)
            delta[S] = diff.reshape(-1)[S]
            if (~S).any():
                delta[~S] = -np.linalg.solve(P[np.ix_(~S, ~S)], P[np.ix_(~S, S)] @ delta[S])
            delta = delta.reshape(T, d)
            if len(out) < max_jumps and all(np.abs(delta - o).max() > frame_tol for o in out):
                out.append(delta)
    return np.array(out).reshape(-1, T, d)


def nuts_with_mode_search(dens: UtteranceDensity, mp: MapResult, modes: list, z0: np.ndarray, per_chain: int,
                           warmup: int, chains: int, seed: int, map_iter: int, skw: dict):
    """NUTS with mode-jumping moves, the modes searched for in a pilot phase of the warm-up.

    The chains run ``pilot`` (default ``NUTS_DEFAULTS["pilot"]``, at most a third of
    ``warmup``) warm-up iterations from their overdispersed starts, with jumps between the modes the
    restarts found; the joint MAP is then maximised from each chain's state. The modes the
    chains reached are far above those the restarts find (a 3-s held-out utterance: ln p
    −3158 … −3201 against −3217), so the highest of all becomes the whitening mode, and
    :func:`mode_jumps` turns the differences from it into jumps. The chains go on from
    their pilot states (re-expressed in the new whitening) for the rest of the warm-up and
    the draws, with those jumps. Only the second phase's kernel yields draws, so it is a
    fixed Markov kernel. Returns (draws with the pilot's gradients and seconds added, the
    whitening mode, its :class:`~bayes_talk.synthesis.whitening.Whitened`, the modes maximised from the pilot states)."""
    T, d = dens.T, dens.d
    pilot = min(int(skw.pop("pilot", NUTS_DEFAULTS["pilot"])), warmup // 3)
    L, Linv = whitening(mp)
    g = Whitened(dens, mp.latents, L)
    jumps = mode_jumps(mp, modes).reshape(-1, T * d) @ Linv.T
    found: list = []
    pilot_gradients, pilot_seconds = 0, 0.0
    if pilot > 0:
        t0 = time.perf_counter()
        pd = run_nuts(g, z0, n_draws=1, warmup=pilot, chains=chains, seed=seed, jumps=jumps, **skw)
        ends = g.to_x(pd.samples[:, -1])
        found = [maximise_utterance(dens, e.reshape(T, d), max_iter=map_iter) for e in ends]
        top = max([mp] + [r for r in found if r.converged], key=lambda r: r.log_density)
        if top is not mp:
            top.start_log_density = mp.start_log_density
            mp = top
            L, Linv = whitening(mp)
            g = Whitened(dens, mp.latents, L)
        z0 = (ends - g.x_map) @ Linv.T
        jumps = mode_jumps(mp, list(modes) + found).reshape(-1, T * d) @ Linv.T
        pilot_gradients, pilot_seconds = pd.stats["n_gradients"], time.perf_counter() - t0
    draws = run_nuts(g, z0, n_draws=per_chain, warmup=warmup - pilot, chains=chains, seed=seed + chains,
                     jumps=jumps, **skw)
    st = draws.stats
    st["pilot"], st["warmup"] = pilot, warmup
    st["n_gradients"] += pilot_gradients
    st["warmup_seconds"] += pilot_seconds
    st["pilot_seconds"] = pilot_seconds        # in warmup_seconds and seconds, not in chain_seconds
    draws.seconds += pilot_seconds
    return draws, mp, g, found


__all__ = ["JUMP_FRAME_TOL", "MAX_JUMPS", "mode_jumps", "nuts_with_mode_search"]
