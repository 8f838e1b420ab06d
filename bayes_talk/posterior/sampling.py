"""The synthesis posterior of a whole utterance by any method of
:data:`~bayes_talk.posterior.methods.INFERENCE` (docs/uncertainty.md).

Every method reads one density, the whole-utterance synthesis model of
:mod:`bayes_talk.synthesis.joint` (every segment's latents jointly: entry distributions,
each state's dynamics, the audio GP, the smoothness factors across state changes, and
adjacent blocks of one state model linked by its dynamics), through its closed-form numpy
twin :class:`~bayes_talk.synthesis.joint.UtteranceDensity` (tested equal to the Pyro
program's log joint). Hyperparameters, training latents and entry distributions stay at
their trained MAP values.

:func:`sample_synthesis` does what every method needs, then runs the method through its
table entry (:meth:`~bayes_talk.posterior.methods.InferenceMethod.run`; the methods and
their interface: :mod:`bayes_talk.posterior.methods`):

1. the joint MAP (:func:`~bayes_talk.synthesis.joint_map.maximise_utterance`): start at
   deena2010's Algorithm 1 path (block by block, :func:`bayes_talk.synthesis.sequential.synthesize`),
   maximise the joint density by L-BFGS in coordinates whitened by the Laplace precision at
   that start, then by a trust-region Newton method with the exact Hessian; converged when
   max |∂ ln p/∂x| ≤ ``gtol`` or the Hessian is negative definite and the Newton decrement is
   ≤ ``dtol`` nats. With ``map_restarts`` (the method's default), restarts from draws of its
   Laplace approximation keep the highest mode (:func:`~bayes_talk.synthesis.joint_map.restart_map`);
2. the banded Cholesky factor R of the Laplace precision −∇² ln p at the MAP (block-tridiagonal:
   time and memory linear in the length; :mod:`bayes_talk.synthesis.banded`), whose
   L = R⁻ᵀ (L Lᵀ = (−∇² ln p)⁻¹) whitens the samplers' coordinates;
3. the method's draws (:class:`~bayes_talk.posterior.methods.Context` →
   :class:`~bayes_talk.posterior.methods.Output`);
4. the visual prediction at the draws: frame t's is the mixture over draws s of
   N(μ_Z(x_t^s), σ²_Z(x_t^s)/w²) under the frame's state model (:func:`visual_predictive`);
   with the R-hat/ESS diagnostics, those of the AAM parameters' means too; and one warning
   naming the failed checks of the method's diagnostics (:func:`_convergence_warnings`).

The result is the one result type of every synthesis path,
:class:`~bayes_talk.synthesis.result.SynthesisResult`: its mean, variance, exact mixture
quantiles (:meth:`~bayes_talk.synthesis.result.SynthesisResult.interval`) and ArviZ
InferenceData. ``method="map"`` gives the one-component "mixture" at the MAP path (the GP
predictive only).
"""
from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from bayes_talk.base import progress
from bayes_talk.gp.threads import torch_threads
from bayes_talk.posterior.diagnostics import (
    convergence_problems,
    frame_diagnostics,
    sampler_warning,
)
from bayes_talk.posterior.methods import (
    DEFAULT_METHOD,
    INFERENCE,
    NUTS_DEFAULTS,
    Context,
    check_method,
)
from bayes_talk.synthesis.joint import SMOOTHNESS, UtteranceDensity, make_plan
from bayes_talk.synthesis.joint_map import MAP_GTOL, MAP_MAX_ITER, maximise_utterance, restart_map
from bayes_talk.synthesis.result import SynthesisResult
from bayes_talk.synthesis.sequential import check_inputs, synthesize

if TYPE_CHECKING:
    from bayes_talk.models.switching import SwitchingModel as SwitchingSGPDM

log = logging.getLogger(__name__)


def sample_synthesis(
    model: SwitchingSGPDM,
    mfcc: np.ndarray,
    labels,
    method: str = DEFAULT_METHOD,
    n_draws: int | None = None,
    seed: int = 0,
    smoothness: str | bool = "frame",
    warmup: int | None = None,
    chains: int = NUTS_DEFAULTS["chains"],
    map_iter: int = MAP_MAX_ITER,
    map_restarts: int | None = None,
    emcee_thin: int = 5,
    sampler_kw: dict | None = None,
    log_warnings: bool = True,
    audio_view: bool = False,
    smooth_shift: np.ndarray | None = None,
) -> SynthesisResult:
    """The synthesis posterior of one utterance by ``method``, a name in
    :data:`~bayes_talk.posterior.methods.INFERENCE` (see the module docstring).

    n_draws: draws kept in all, pooled over chains (default the method's
        :attr:`~bayes_talk.posterior.methods.InferenceMethod.draws`: Laplace 64, NUTS 4 × 250,
        pg-nuts 4 × 500; NUTS: ceil(n_draws / chains) per chain after ``warmup`` adaptation
        steps, default 500 (pg-nuts 200, :data:`~bayes_talk.posterior.methods.PG_NUTS_BUDGET`);
        emcee: burn-in ``warmup`` steps, default 500, then draws of 16 reported walkers
        thinned by ``emcee_thin``).
    chains: NUTS chains (default 4), started overdispersed at z ~ N(0, 2² I) in the
        whitened coordinates (X = X_MAP + L z).
    map_iter: trust-region Newton iterations of the joint MAP (after L-BFGS; Algorithm 1's
        path is the start).
    map_restarts: restarts of the joint MAP per round from draws of its Laplace
        approximation, keeping the highest mode (:func:`restart_map`; default
        ``INFERENCE[method].map_restarts``: 6 for NUTS, pg-nuts and emcee, none for MAP,
        Laplace and VI).
    sampler_kw: the method's own options, the fields of its ``Options``
        (e.g. :class:`bayes_talk.posterior.methods.nuts.Options`,
        :class:`bayes_talk.posterior.methods.pg_nuts.Options`,
        :class:`bayes_talk.posterior.methods.emcee.Options`,
        :class:`bayes_talk.posterior.methods.vi.Options`,
        :class:`bayes_talk.posterior.methods.laplace.Options`; ``INFERENCE[method].options``
        lists them with their defaults); checked before any work.
    log_warnings: log every failed convergence check (also kept in ``.warnings``).
    audio_view: ``mfcc`` is already the audio view the state models explain
        (``model.audio_input(mfcc)``; audio simulated from the synthesis model, as in
        simulation-based calibration), used as it is. With ``audio_context`` > 0 the view
        is a projection of spliced MFCCs, and transforming it a second time would condition
        on different audio.
    smooth_shift: (T, D_z) pseudo-observations u of the smoothness factors
        (:mod:`bayes_talk.synthesis.joint`, (S)); None: u = 0, the product of the papers.
        Only simulation-based calibration with smoothness on sets it (simulated u). The
        sampler's start (Algorithm 1's path) ignores it; the density does not.
    """
    spec = check_method(method)
    smoothness = "frame" if smoothness is True else "off" if smoothness is False else smoothness
    if smoothness not in SMOOTHNESS:
        raise ValueError(f"smoothness must be one of {SMOOTHNESS}, got {smoothness!r}")
    n_draws = spec.draws if n_draws is None else int(n_draws)
    if spec.draws > 1 and n_draws < 8:
        raise ValueError(f"n_draws must be >= 8, got {n_draws}")
    if chains < 1:
        raise ValueError(f"chains must be >= 1, got {chains}")
    if warmup is not None and warmup < 0:
        raise ValueError(f"warmup must be >= 0, got {warmup}")
    map_restarts = spec.map_restarts if map_restarts is None else int(map_restarts)
    if map_restarts < 0:
        raise ValueError(f"map_restarts must be >= 0, got {map_restarts}")
    options = spec.make_options(sampler_kw)
    mfcc = check_inputs(model, mfcc, labels, audio_view)
    t0 = time.perf_counter()
    with torch_threads(1):
        res = _sample(model, mfcc, labels, method, options, n_draws, seed, smoothness, warmup, chains, map_iter,
                      emcee_thin, map_restarts, audio_view, smooth_shift)
    res.seconds = time.perf_counter() - t0
    if log_warnings:
        for w in res.warnings:
            log.warning("%s", w)
    return res


def _sample(model, mfcc, labels, method, options, n_draws, seed, smoothness, warmup, chains, map_iter, emcee_thin,
            map_restarts: int = 0, audio_view: bool = False, smooth_shift=None) -> SynthesisResult:
    spec = INFERENCE[method]
    plan = make_plan(model, mfcc, labels, smoothness, audio_view, smooth_shift)
    dens = UtteranceDensity(plan)
    T, d = plan.n_frames, plan.latent_dim
    with progress.stage("Algorithm 1 path", total=T, unit="frames") as st:
        start = synthesize(model, mfcc, labels, algorithm="optimise", smoothness=smoothness,
                           audio_view=audio_view).latents
        st.update(T)
    with progress.stage("joint MAP", total=T, unit="frames") as st:
        # long paths report the frames their window sweeps have reached; short ones the end
        mp = maximise_utterance(dens, start, max_iter=map_iter,
                                progress=lambda kind, k: st.update(max(st.done, k)) if kind == "window" else None)
        st.update(T)
    start_carried, start_rms_z = mp.carried, mp.start_rms_z
    start_rms_z = start_rms_z if np.isfinite(start_rms_z) else None      # no dynamics steps
    first_log_density = mp.log_density
    modes: list = []
    if map_restarts:
        mp, modes = restart_map(dens, mp, map_restarts, seed, max_iter=map_iter)
    factor = mp.laplace_factor()              # Laplace precision = R Rᵀ, covariance L Lᵀ with L = R⁻ᵀ
    n_mod = mp.hessian_modified
    diag: dict = {"map_converged": mp.converged, "map_grad_norm": mp.grad_norm, "map_iter": mp.n_iter,
                  "map_decrement": mp.decrement,
                  "map_log_density": mp.log_density, "algorithm1_log_density": mp.start_log_density,
                  "algorithm1_dynamics_rms_z": start_rms_z, "map_start_carried": start_carried,
                  "hessian_modified": n_mod, "laplace_shift": factor.shift, "dim": T * d, "n_segments": len(plan.blocks),
                  "map_restarts": map_restarts, "map_first_log_density": first_log_density,
                  "map_restart_log_densities": [r.log_density for r in modes]}
    warn: list[str] = []
    if not mp.converged:
        warn.append(f"synthesis MAP did not converge: max |gradient| {mp.grad_norm:.3g} > {MAP_GTOL}, "
                    f"Newton decrement {mp.decrement:.3g} nats, {n_mod} non-positive Hessian eigenvalues, "
                    f"after {mp.n_iter} iterations")
    context = Context(plan=plan, density=dens, map=mp, modes=modes, factor=factor, rng=np.random.default_rng(seed),
                      seed=int(seed), n_draws=n_draws, chains=chains, warmup=warmup, map_iter=map_iter,
                      thin=emcee_thin)
    out = spec.run(context, options)
    diag.update(out.diagnostics)
    mp = mp if out.map is None else out.map
    Xs = np.asarray(out.latents).reshape(-1, out.latents.shape[1], T, d)
    zm, zv = visual_predictive(plan, Xs)
    if "rhat_ess" in spec.diagnostics:
        # what users consume: the AAM parameters' means at the draws, per frame, beside the latents'
        diag.update(frame_diagnostics(zm, "aam_"))
    if spec.diagnostics:
        warn += _convergence_warnings(method, diag)
    return SynthesisResult(method, Xs, zm, zv, mp, plan.segments, plan.model_states, diag, int(seed),
                           warnings=warn, sample_stats=out.sample_stats, mean_function=plan.visual_offset)


class TargetCheck:
    """The stopping rule of ``sampler_kw["stop_at_targets"]`` (pg-nuts's default,
    :data:`~bayes_talk.posterior.methods.PG_NUTS_BUDGET`): called with the latent draws so far,
    (chains, n, T·d), it is True when they pass the R-hat and ESS checks that every sampler run
    is judged by (:func:`~bayes_talk.posterior.diagnostics.convergence_problems`: rank R-hat ≤
    1.01, bulk and tail ESS ≥ 400) on the latents and on the AAM parameters' means at the draws
    (what users consume), so the chains stop drawing once the posterior is sampled as well as the
    library asks and not ``n_draws`` later (held-out ``utt0002`` of test set 3: ESS three times
    the target after the fixed 500 draws per chain, 55 min). Divergences and E-BFMI are not part of
    the rule (more draws do not mend them); they are checked on the final draws as always.

    Checking after every batch and stopping at the first pass makes a pass slightly likelier than
    one check at a fixed length would (optional stopping): the first check comes only after
    ``min_draws_per_chain`` draws (half the maximum by default), where the estimates of R-hat and
    ESS are settled. ``history``: per check, the draws per chain, the six numbers and the failed
    checks (JSON-ready; ``diagnostics.json``'s ``stop_checks``)."""

    KEYS = ("rhat_max", "ess_bulk_min", "ess_tail_min", "aam_rhat_max", "aam_ess_bulk_min", "aam_ess_tail_min")

    def __init__(self, plan=None):
        self.plan, self.history = plan, []

    def __call__(self, X: np.ndarray) -> bool:
        C, n = X.shape[:2]
        Xs = np.asarray(X, dtype=np.float64).reshape(C, n, self.plan.n_frames, self.plan.latent_dim)
        return self.judge(Xs, visual_predictive(self.plan, Xs)[0])

    def judge(self, latents: np.ndarray, aam: np.ndarray) -> bool:
        """The rule on latent draws (chains, n, T, d) and the AAM parameters' means at them
        (chains, n, T, D_z) (e.g. draws saved by ``benchmarks/posterior.py --save-draws``)."""
        n = latents.shape[1]
        diag = {**frame_diagnostics(latents), **frame_diagnostics(aam, "aam_")}
        fails = convergence_problems({k: diag[k] for k in self.KEYS})
        self.history.append({"draws_per_chain": int(n), **{k: float(diag[k]) for k in self.KEYS}, "failed": fails})
        log.info("after %d draws per chain: %s", n, "; ".join(fails) if fails else "R-hat and ESS targets met")
        return not fails


def visual_predictive(plan, Xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """μ_Z and σ²_Z/w² (C, S, T, D_z) at latent draws Xs (C, S, T, d), frame by frame under
    the frame's state model, plus the plan's explicit mean function c_t where it has one."""
    C, S, T, d = Xs.shape
    Dz = plan.blocks[0].model.predictors_["visual"].out_dim
    zm, zv = np.zeros((C, S, T, Dz)), np.zeros((C, S, T, Dz))
    for b in plan.blocks:
        a, e = b.start, b.stop
        mu, var = b.model.predict_view("visual", Xs[:, :, a:e].reshape(-1, d))
        zm[:, :, a:e] = mu.reshape(C, S, e - a, Dz)
        zv[:, :, a:e] = var.reshape(C, S, e - a, Dz)
    if plan.visual_offset is not None:
        zm += plan.visual_offset
    return zm, zv


def _convergence_warnings(method: str, diag: dict) -> list[str]:
    """The failed sampler checks (:func:`~bayes_talk.posterior.diagnostics.convergence_problems`:
    R-hat ≤ 1.01, bulk and tail ESS ≥ 400, no divergences, k̂ ≤ 0.7, E-BFMI ≥ 0.3, emcee's
    chain ≥ 50 τ) as one warning naming them."""
    fails = convergence_problems(diag)
    if not fails:
        return []
    # the whole-utterance posterior is multimodal (docs/uncertainty.md): no sampler here is a
    # sure cure, so the advice says what to try and what the bands then are
    return sampler_warning(method, fails, INFERENCE[method].advice)


__all__ = ["TargetCheck", "sample_synthesis", "visual_predictive"]
