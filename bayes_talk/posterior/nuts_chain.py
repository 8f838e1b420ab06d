"""One NUTS chain run as two executor tasks, its warm-up and its kept draws.

Both run the recording Pyro NUTS kernel (:class:`RecordingNUTS`).

:func:`warmup_chain` adapts NUTS's step size and diagonal mass matrix (Stan's windowed schedule,
Pyro's adapter) and lets an adaptive ``extra_move`` (the particle Gibbs sweep with
``pg_adapt_weights``) learn during those iterations; it returns the chain's :class:`ChainState`:
its position, step size, inverse mass matrix, the states of its random generators (torch's, and
the numpy generator of its jumps and move) and what its copy of the move learnt.
:func:`draw_chain` continues from that state with every adaptation off. In between,
:func:`~bayes_talk.posterior.samplers.run_nuts` pools what the chains' moves learnt and freezes
one move for all of them (:meth:`ParticleGibbsMove.end_adaptation
<bayes_talk.posterior.particle_gibbs.ParticleGibbsMove.end_adaptation>`): a chain whose own
warm-up never reached a mode still proposes it (with each chain's own proposal, the four chains
of held-out `utt0002` proposed different modes and R-hat stayed at 1.06; docs/uncertainty.md). The kept draws come from one fixed
kernel, so each chain leaves the posterior invariant; only its warm-up depends on the others'.
Without an adaptive move the split changes nothing: the generators continue where the warm-up
left them, and the draws equal those of one uninterrupted run (tested).
"""
from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass

import numpy as np
import torch

from bayes_talk.base import progress
from bayes_talk.gp.threads import torch_threads

log = logging.getLogger(__name__)

#: the numpy generator of chain c's jumps and extra move: ``default_rng([seed, c, MOVE_STREAM])``
MOVE_STREAM = 0x6A756D70
#: how the chains share what an adaptive extra move learnt in their warm-ups (pooled over the
#: chains, not each chain's own); ``benchmarks/sbc.py`` records it so that SBC runs of
#: different schemes are never pooled together
WARMUP_ADAPTATION = "pooled over the chains"


class RecordingNUTS:
    """Builds a Pyro NUTS kernel that records, for every post-warm-up iteration, the
    acceptance statistic (the mean Metropolis acceptance probability min(1, e^{−ΔH}) over
    the trajectory's proposals, Hoffman & Gelman 2014 §3.2.1: what the step-size adaptation
    targets; Pyro's ``diagnostics()["acceptance rate"]`` is the fraction of iterations that
    moved, a different number), the number of leapfrog steps and the tree depth, whether
    the iteration diverged, the Hamiltonian energy after the momentum draw (for E-BFMI)
    and ln p at the draw.

    Mode-jumping moves (``jumps``: (K, n) displacements δ_k, e.g. between the modes a
    multi-start optimisation found; ``jump_attempts`` per displacement per iteration):
    after each NUTS transition, propose z' = z + s δ_k with k uniform and s = ±1 with
    probability ½ each, and accept with probability min(1, p(z')/p(z)). The proposal is
    symmetric and does not depend on z, so the move leaves the target invariant (a
    Metropolis kernel; composed with NUTS, the chain keeps its stationary distribution),
    and it lets a chain cross between modes whose barrier NUTS cannot cross
    (Tjelmeland & Hegstad 2001, "Mode jumping proposals in MCMC"). Runs in warm-up too;
    recorded per iteration as ``jumps`` (accepted moves)."""

    @staticmethod
    def make(potential, counter: list, jumps: np.ndarray | None = None, jump_attempts: int = 0,
             rng: np.random.Generator | None = None, extra_move=None, extra_every: int = 1,
             inverse_mass: torch.Tensor | None = None, t_offset: int = 0, **kw):
        """The kernel on ``potential`` (−ln p of {"x": tensor}; ``counter[0]`` counts its
        calls): mode jumps from the rows of ``jumps``, ``jump_attempts`` each, and
        ``extra_move`` after every ``extra_every``-th iteration (counted from ``t_offset``: a
        chain's draws continue its warm-up's count), both drawing from ``rng``;
        ``inverse_mass`` (n,) replaces the identity as the diagonal inverse mass matrix (a
        warm-up's, carried over); ``kw`` go to Pyro's ``NUTS``."""
        from pyro.infer.mcmc import NUTS
        from pyro.ops.integrator import potential_grad

        n_jump = 0 if jumps is None else len(jumps) * int(jump_attempts)
        jump_t = None if jumps is None else torch.as_tensor(np.asarray(jumps, dtype=np.float64))

        class Kernel(NUTS):
            def _initialize_adapter(self):
                super()._initialize_adapter()
                if inverse_mass is not None:   # a warm-up's diagonal mass matrix, carried over
                    self.mass_matrix_adapter.inverse_mass_matrix = {("x",): inverse_mass}

            def _sample_r(self, name):
                r, r_unscaled = super()._sample_r(name)
                if name.startswith("r_t="):
                    self._energy_now = float(self._kinetic_energy(r_unscaled)) + float(self._potential_energy_last)
                return r, r_unscaled

            def _jump(self, z):
                accepted = 0
                pe = float(self._potential_energy_last)
                for _ in range(n_jump):
                    k, sign = int(rng.integers(len(jump_t))), (1.0 if rng.random() < 0.5 else -1.0)
                    z_new = {"x": z["x"] + sign * jump_t[k]}
                    grads, pe_new = potential_grad(self.potential_fn, z_new)
                    pe_new = float(pe_new)
                    if np.isfinite(pe_new) and np.log(rng.random()) < pe - pe_new:
                        z, pe, accepted = z_new, pe_new, accepted + 1
                        self._cache(z, torch.as_tensor(pe, dtype=torch.float64), grads)
                self.jump_counts[0] += n_jump
                self.jump_counts[1] += accepted
                return z, accepted

            def _extra(self, z):
                """Another posterior-invariant kernel (e.g. a particle Gibbs sweep) on the state;
                a move returning (x', record) has its record kept for this iteration."""
                x = z["x"].detach().numpy()
                out = extra_move(x, rng)
                x_new, self._extra_record = out if isinstance(out, tuple) else (out, None)
                x_new = np.asarray(x_new, dtype=np.float64)
                if np.array_equal(x_new, x):
                    return z
                z = {"x": torch.as_tensor(x_new)}
                grads, pe = potential_grad(self.potential_fn, z)
                self._cache(z, pe, grads)
                return z

            def sample(self, params):
                m_prev, n_div, n_grad = self._mean_accept_prob, len(self._divergences), counter[0]
                self._extra_record = None
                z = super().sample(params)
                z, accepted = self._jump(z) if n_jump else (z, 0)
                if extra_move is not None and (self._t + t_offset) % extra_every == 0:
                    z = self._extra(z)
                if self._t > self._warmup_steps:
                    n = self._t - self._warmup_steps   # the running mean restarts after warm-up
                    rec = self.records
                    # undo Pyro's running mean m_n = m_{n-1} + (a_n − m_{n-1})/n (rounding: clip)
                    rec["acceptance_rate"].append(min(1.0, max(0.0, m_prev + n * (self._mean_accept_prob - m_prev))))
                    steps = counter[0] - n_grad
                    rec["n_steps"].append(steps)
                    rec["tree_depth"].append(int(np.ceil(np.log2(steps + 1))))
                    rec["diverging"].append(len(self._divergences) > n_div)
                    rec["energy"].append(self._energy_now)
                    rec["lp"].append(-float(self._potential_energy_last))
                    rec["jumps"].append(accepted)
                    if extra_move is not None:
                        rec["extra"].append(self._extra_record)
                return z

        k = Kernel(potential_fn=potential, **kw)
        k.jump_counts = [0, 0]  # attempted, accepted (warm-up included)
        k.records = {key: [] for key in ("acceptance_rate", "n_steps", "tree_depth", "diverging", "energy", "lp",
                                         "jumps", *(("extra",) if extra_move is not None else ()))}
        return k



def extra_records(records: list) -> dict:
    """The per-iteration records of an ``extra_move`` (one dict of arrays, or None where the
    move did not run or returned no record) as arrays (draws, ...): each key stacked over the
    iterations, zeros (False) where there was no record; {} when there was none at all."""
    have = [r for r in records if r is not None]
    if not have:
        return {}
    out = {}
    for key in have[0]:
        blank = np.zeros_like(np.asarray(have[0][key]))
        out[key] = np.stack([blank if r is None else np.asarray(r[key]) for r in records])
    return out


@dataclass
class ChainState:
    """Where a chain stands between its warm-up and its kept draws: position ``x`` (n,), NUTS's
    ``step_size`` and diagonal ``inverse_mass`` (n,) (None before a warm-up: found at the start,
    identity), ``torch_rng`` (``pyro.util.get_rng_state()``, None: seeded afresh), ``rng`` (the
    numpy generator of the jumps and the move), ``adaptation`` (what the chain's copy of an
    adaptive move learnt, its ``adaptation_state()``; dropped before the draws), ``jump_counts`` (attempted, accepted),
    ``n_gradients`` and ``seconds`` so far."""

    x: np.ndarray
    step_size: float | None = None
    inverse_mass: np.ndarray | None = None
    torch_rng: dict | None = None
    rng: np.random.Generator | None = None
    adaptation: object = None
    jump_counts: tuple[int, int] = (0, 0)
    n_gradients: int = 0
    seconds: float = 0.0


def _kernel(log_prob, counter: list, state: ChainState, kw: dict, move, adapt: bool, t_offset: int):
    """The recording kernel of one phase, counting gradients in ``counter``: step size and mass
    matrix adapted (``adapt``: a warm-up), else taken from ``state`` (a step size found at the
    start and the identity mass matrix when it has none: no warm-up)."""
    def potential(params):
        counter[0] += 1
        return -log_prob(params["x"])

    carried = {}
    if not adapt and state.step_size is not None:
        carried = {"step_size": state.step_size, "inverse_mass": torch.as_tensor(state.inverse_mass)}
    return RecordingNUTS.make(potential, counter, adapt_step_size=adapt or not carried, adapt_mass_matrix=adapt,
                              full_mass=False, target_accept_prob=kw["target_accept"],
                              max_tree_depth=kw["max_tree_depth"], jumps=kw["jumps"],
                              jump_attempts=kw["jump_attempts"], extra_move=move,
                              extra_every=kw.get("extra_every", 1), rng=state.rng, t_offset=t_offset, **carried)


def run_kernel(kernel, x: np.ndarray, warmup: int, n_draws: int, desc: str) -> tuple[np.ndarray, np.ndarray]:
    """Pyro's sampling loop (``pyro.infer.mcmc.api._gen_samples``) on ``kernel`` from ``x``:
    ``warmup`` adapting iterations, then ``n_draws`` kept ones → the kept draws (n_draws, n)
    and the last state (n,)."""
    kernel.initial_params = {"x": torch.as_tensor(np.asarray(x, dtype=np.float64))}
    kernel.setup(warmup)
    params = kernel.initial_params
    out = np.empty((n_draws, np.size(x)))
    for i in progress.bar(range(warmup + n_draws), total=warmup + n_draws, desc=desc, unit="it"):
        params = kernel.sample(params)
        if i >= warmup:
            out[i - warmup] = params["x"].detach().numpy().reshape(-1)
    return out, params["x"].detach().numpy().reshape(-1).copy()


def warmup_chain(task) -> ChainState:
    """Chain c's warm-up (an executor task): (log_prob, start (n,), warmup, seed, c, kernel
    keywords) → its :class:`ChainState`. Seeded by (seed, c) alone: Pyro's generators by
    ``seed + c``, the jumps and the move by ``default_rng([seed, c, MOVE_STREAM])``. An adaptive
    ``extra_move`` is deep-copied (the chain learns on its own copy, whatever the executor) and
    adapts from the first iteration to the last."""
    import pyro

    log_prob, start, warmup, seed, c, kw = task
    t0, counter = time.perf_counter(), [0]
    move = kw.get("extra_move")
    adaptive = hasattr(move, "begin_adaptation")
    if adaptive:
        move = copy.deepcopy(move)
        move.begin_adaptation()
    state = ChainState(np.asarray(start, dtype=np.float64), rng=np.random.default_rng([seed, c, MOVE_STREAM]))
    with torch_threads(1):
        pyro.set_rng_seed(seed + c)
        kernel = _kernel(log_prob, counter, state, kw, move, adapt=True, t_offset=0)
        log.info("NUTS chain %d: %d warm-up iterations", c + 1, warmup)
        _, state.x = run_kernel(kernel, start, warmup, 0, f"NUTS chain {c + 1} warm-up")
        state.step_size = float(kernel.step_size)
        state.inverse_mass = kernel.inverse_mass_matrix[("x",)].detach().numpy().copy()
        state.torch_rng = pyro.util.get_rng_state()
    state.adaptation = move.adaptation_state() if adaptive and hasattr(move, "adaptation_state") else None
    state.jump_counts, state.n_gradients = tuple(kernel.jump_counts), counter[0]
    state.seconds = time.perf_counter() - t0
    return state


def draw_chain(task) -> dict:
    """Chain c's kept draws (an executor task): (log_prob, its :class:`ChainState`, n_draws,
    iterations before these (the warm-up's length, plus the draws of earlier batches), seed, c,
    kernel keywords; ``extra_move`` fixed) → its draws, step size, per-draw records, jump counts,
    gradients and seconds so far (warm-up included), and ``state``: the :class:`ChainState` after
    the last draw, from which a further call continues — batches of draws equal one call's draws
    (tested). Continues the generators of ``state`` (fresh ones, seeded as in
    :func:`warmup_chain`, without a warm-up)."""
    import pyro

    log_prob, state, n_draws, done, seed, c, kw = task
    t0, counter = time.perf_counter(), [0]
    state = copy.copy(state)
    if state.rng is None:
        state.rng = np.random.default_rng([seed, c, MOVE_STREAM])
    with torch_threads(1):
        if state.torch_rng is None:
            pyro.set_rng_seed(seed + c)
        else:
            pyro.util.set_rng_state(state.torch_rng)
        kernel = _kernel(log_prob, counter, state, kw, kw.get("extra_move"), adapt=False, t_offset=done)
        log.info("NUTS chain %d: %d draws", c + 1, n_draws)
        samples, _ = run_kernel(kernel, state.x, 0, n_draws, f"NUTS chain {c + 1}")
        state.torch_rng = pyro.util.get_rng_state()
        if state.step_size is None:   # no warm-up: the step size found at the start, the identity mass
            state.step_size = float(kernel.step_size)
            state.inverse_mass = kernel.inverse_mass_matrix[("x",)].detach().numpy().copy()
    kernel.records.update(extra_records(kernel.records.pop("extra", [])))
    state.x = samples[-1].copy() if n_draws else state.x
    state.jump_counts = tuple(a + b for a, b in zip(state.jump_counts, kernel.jump_counts, strict=True))
    state.n_gradients += counter[0]
    state.seconds += time.perf_counter() - t0
    return {"samples": samples, "step_size": float(kernel.step_size), "records": kernel.records,
            "jump_counts": list(state.jump_counts), "n_gradients": state.n_gradients, "seconds": state.seconds,
            "state": state}


__all__ = ["MOVE_STREAM", "WARMUP_ADAPTATION", "ChainState", "RecordingNUTS", "draw_chain", "extra_records", "run_kernel",
           "warmup_chain"]
