"""The inference methods of the synthesis posterior and their defaults, in one torch-free table.

:data:`INFERENCE` names every method that :func:`~bayes_talk.posterior.sampling.sample_synthesis`
(and so ``synth --posterior`` and the evaluation harness) can run: the callable that draws,
its default draws and joint-MAP restarts, its options, which convergence diagnostics apply to
it and what to try when they fail. The library, the CLI's choices and help text, the
pipeline and docs/uncertainty.md (its "Inference methods" table is :func:`markdown_table`,
checked by a test) read it, so they cannot drift apart; importing this module pulls in
neither torch nor pyro (``bayes-talk --help`` stays fast).
"""
from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field

#: NUTS defaults of the library and the CLI (docs/uncertainty.md "Sampler options"): chains,
#: warm-up iterations per chain, draws kept per chain, target acceptance statistic of the
#: step-size adaptation, max tree depth, mode-jumping Metropolis attempts per displacement per
#: iteration, warm-up iterations of the synthesis posterior's pilot phase (after which the
#: modes the chains reached are searched for and turned into jumps; part of ``warmup``)
NUTS_DEFAULTS = {"chains": 4, "warmup": 500, "draws_per_chain": 250, "target_accept": 0.8, "max_tree_depth": 10,
                 "jump_attempts": 2, "pilot": 150}
#: particle Gibbs ∘ NUTS ∘ mode jumps (``--posterior pg-nuts``): NUTS in the non-centred
#: coordinates with the NUTS defaults above, and a conditional-SMC sweep with ancestor sampling
#: (``pg_particles`` particles) after every ``pg_every``-th iteration, its proposal's kernels
#: of bandwidths ``pg_h`` around the training latents and, with ``pg_mode_centres``, around the
#: joint MAP and its restarts' modes, weighted with ``pg_lookahead`` by the audio of a dynamics
#: run's continuation (short toy runs: frames never updated 5 → 0 only with both;
#: docs/uncertainty.md "The proposal at the modes"); ``pg_backward``: backward simulation
#: instead of ancestor sampling (off); ``pg_frame_tries`` = K > 0: after each sweep a K-try
#: Metropolis update of every frame without dynamics on either side (16), its tries with
#: ``pg_frame_modes`` from the frame's own modes (on; toy utterance: rank R-hat 1.060 → 1.014,
#: AAM 1.077 → 1.020, docs/uncertainty.md "The isolated frames' own modes"), and with
#: ``pg_block_len`` = 8 of every dynamics run of at most 8 frames, its first frame's tries from
#: the run's own modes (held-out ``utt0001``: R-hat 1.22 → 1.12, bulk ESS per second +60 %,
#: wall +32 %; toy 1.014 → 1.025, with the modes' new convergence filter; docs/uncertainty.md
#: "Short dynamics blocks' own modes"); ``pg_neighbours``: those modes conditioned on the
#: smoothness factors into and out of the block given its current neighbours (off); ``pg_pairs``: then
#: every pair of consecutive blocks updated together, their modes matched through the smoothness
#: factor between them (on: held-out ``utt0002`` R-hat 1.084 → 1.043 at 500 + 250, and with
#: ``PG_NUTS_BUDGET`` ``utt0002`` 1.017, ``utt0001`` 1.014 with bulk ESS ≥ 425 on every frame;
#: docs/uncertainty.md "Pairs of blocks"); the own-mode
#: proposal's defensive weight δ ``pg_mode_delta`` (0.2), its Laplace covariances' scale c
#: ``pg_mode_scale`` (1.5; several factors: a copy of each mode per factor) and the mode ascents' starts per block of more than one frame
#: ``pg_mode_starts`` (64; :class:`~bayes_talk.posterior.frame_updates.BlockModeProposal`);
#: ``pg_adapt_weights``: the own modes' weights learnt during the warm-up from the block updates
#: and the chain (the full conditional's mode masses; since session 31 pooled over all the
#: chains' warm-ups, :mod:`~bayes_talk.posterior.nuts_chain`), then frozen (on since session 28, with two
#: passes: held-out ``utt0001`` R-hat 1.008 → 1.005, tail ESS 442 → 583, ``utt0002`` 1.082 → 1.011;
#: docs/uncertainty.md "Mode weights learnt in the warm-up"); ``pg_block_sweeps``: passes of the
#: block and pair updates after each sweep (2: ``utt0001`` R-hat 1.014 → 1.008, minimum tail ESS
#: 181 → 442, its short dynamics block 45–49 no longer the limit, wall +8 %; docs/uncertainty.md
#: "Two passes of the block updates"); ``pg_adapt_moments``: with ``pg_adapt_weights``, each mode
#: that gathers enough of the full conditional's mass in the warm-up also proposed from its mean
#: and covariance under that conditional (:mod:`~bayes_talk.posterior.mode_adaptation`; on since
#: session 29: held-out ``utt0002`` minimum bulk ESS 301 → 712, ``utt0004`` minimum tail ESS
#: 116 → 1,124, R-hat ≤ 1.010 on both; docs/uncertainty.md "Modes moved to the full conditional");
#: ``pg_adapt_clusters``: with ``pg_adapt_weights``, a Gaussian mixture (BIC, ≤ 3 components) fitted
#: to each block's warm-up states, pooled over the chains, proposed too — modes of the full
#: conditional that are none of the own factor's (on since session 31: held-out ``utt0002`` at
#: seed 0 R-hat 1.031 → 1.005, tail ESS 28 → 781; ``utt0001`` 1.005, tail ESS 429;
#: docs/uncertainty.md "Clusters of the warm-up states").
#: pg-nuts's own budget, in place of NUTS's warm-up and draws per chain (the other NUTS defaults
#: apply): its sweeps and block updates move the chains between the modes, so NUTS's adaptation
#: needs fewer iterations and the time goes to draws. Held-out ``utt0002`` (dev40), pairs of
#: blocks on: 500 + 250 → 200 + 500 per chain, rank R-hat 1.043 → 1.017, bulk ESS 75 → 293, wall
#: 26 → 32 min (docs/uncertainty.md "A shorter warm-up, more draws"). ``draws_per_chain`` is the
#: most a chain draws: with ``stop_at_targets`` the chains stop once the latents' and the AAM
#: parameters' rank R-hat ≤ 1.01 and bulk and tail ESS ≥ 400
#: (:class:`~bayes_talk.posterior.sampling.TargetCheck`), asked after ``min_draws_per_chain``
#: draws and every ``check_every`` after (session 36: test-set ``utt0002`` took 55 min at 500
#: draws with ESS three times the target; docs/uncertainty.md "Stopping at the targets")
PG_NUTS_BUDGET = {"warmup": 200, "draws_per_chain": 500, "stop_at_targets": True, "min_draws_per_chain": 250,
                  "check_every": 50}
PG_NUTS_DEFAULTS = {"pg_every": 1, "pg_particles": 64, "pg_h": (0.005, 0.02, 0.05), "pg_lookahead": True,
                    "pg_mode_centres": True, "pg_backward": False, "pg_frame_tries": 16,
                    "pg_frame_modes": True, "pg_block_len": 8, "pg_neighbours": False,
                    "pg_pairs": True, "pg_mode_delta": 0.2, "pg_mode_scale": 1.5, "pg_mode_starts": 64,
                    "pg_adapt_weights": True, "pg_block_sweeps": 2, "pg_adapt_moments": True,
                    "pg_adapt_clusters": True}
#: variational inference (Pyro SVI, full-rank Gaussian guide): optimisation steps, ELBO
#: particles per step, Adam's learning rate (decayed tenfold over the steps)
VI_DEFAULTS = {"steps": 1000, "particles": 4, "lr": 0.02}
#: emcee burn-in steps
EMCEE_WARMUP = 500

#: the diagnostics a method can have: those checked by
#: :func:`~bayes_talk.posterior.diagnostics.convergence_problems` — Pareto k̂ of the importance
#: weights p/q of iid proposal draws; R-hat, bulk/tail ESS and MCSE across chains (latents and
#: AAM parameters, per frame); NUTS divergences and E-BFMI; emcee's chain length ≥ 50 τ — and
#: the per-frame update rate of particle Gibbs sweeps
#: (:func:`~bayes_talk.posterior.diagnostics.frame_update_rate`; reported, no threshold)
DIAGNOSTICS = ("khat", "rhat_ess", "divergences_bfmi", "autocorrelation", "frame_update_rate")


@dataclass(frozen=True)
class InferenceMethod:
    """One way to infer the whole-utterance synthesis posterior (docs/uncertainty.md).

    runner: ``"module:function"`` of the callable that draws (imported by :meth:`load`, so
    this table stays torch-free); draws: default draws kept, pooled over chains;
    map_restarts: restarts of the joint MAP per round from draws of its Laplace
    approximation before the method runs; diagnostics: those of :data:`DIAGNOSTICS` that
    apply; options: the method's own defaults (``sampler_kw``); advice: what to try when its
    checks fail (added to the warning)."""

    name: str
    summary: str
    runner: str
    draws: int
    map_restarts: int
    diagnostics: tuple[str, ...]
    advice: str = ""
    options: dict = field(default_factory=dict)

    def load(self) -> Callable:
        """The callable named by :attr:`runner`."""
        module, _, name = self.runner.partition(":")
        return getattr(importlib.import_module(module), name)


#: every inference method, by name; the first with draws is the default of switching models
INFERENCE: dict[str, InferenceMethod] = {m.name: m for m in (
    InferenceMethod(
        "map", "a point estimate: the joint MAP path (`sample_synthesis`); `synth --posterior map` runs "
               "the paper's sequential path (Algorithm 1/2) instead",
        "bayes_talk.synthesis.joint_map:maximise_utterance", draws=1, map_restarts=0, diagnostics=()),
    InferenceMethod(
        "laplace", "iid draws of the Gaussian at the joint MAP (closed-form Hessian, floored eigenvalues)",
        "bayes_talk.posterior.samplers:run_laplace", draws=64, map_restarts=0, diagnostics=("khat",),
        advice="the Gaussian approximation is poor here (the posterior is multimodal); its calibrated bands "
               "are calibrated empirically (train --calibrate-bands), not by the approximation; "
               "--posterior pg-nuts samples the posterior itself (25–45 min for 3–4 s of speech on 2 cores "
               "with --workers 2)",
        options={"khat_draws": 200}),
    InferenceMethod(
        "nuts", "NUTS in coordinates whitened at the MAP, with a pilot mode search and mode-jumping moves",
        "bayes_talk.posterior.mode_search:nuts_with_mode_search",
        draws=NUTS_DEFAULTS["chains"] * NUTS_DEFAULTS["draws_per_chain"], map_restarts=6,
        diagnostics=("rhat_ess", "divergences_bfmi"),
        advice="run more draws/warm-up (or raise the target acceptance for divergences); chains in different "
               "modes of a multimodal posterior will not agree: --posterior pg-nuts moves between them",
        options={**NUTS_DEFAULTS, "coords": "whitened"}),
    InferenceMethod(
        "pg-nuts", "particle Gibbs (conditional SMC with ancestor sampling) and multiple-try updates of the "
                   "isolated frames from their own modes, composed with NUTS in the non-centred coordinates "
                   "and the mode jumps",
        "bayes_talk.posterior.noncentred:nuts_noncentred",
        draws=NUTS_DEFAULTS["chains"] * PG_NUTS_BUDGET["draws_per_chain"], map_restarts=6,
        diagnostics=("rhat_ess", "divergences_bfmi", "frame_update_rate"),
        advice="run more draws (synth --draws, the most drawn when the chains stop at the R-hat/ESS targets; the "
               "ESS grows with them once R-hat is within 1.01) or a longer "
               "warm-up (--warmup) if R-hat is not; the frames with the lowest update rate "
               "(pg_frame_update_rate in diagnostics.json) are the slowest to mix; on 3-4-s held-out utterances the "
               "defaults reach R-hat <= 1.01 with bulk and tail ESS >= 400 (docs/uncertainty.md)",
        options={**NUTS_DEFAULTS, **PG_NUTS_BUDGET, **PG_NUTS_DEFAULTS, "coords": "noncentred"}),
    InferenceMethod(
        "emcee", "emcee's ensemble (differential-evolution moves) in whitened coordinates",
        "bayes_talk.posterior.samplers:run_emcee", draws=320, map_restarts=6,
        diagnostics=("rhat_ess", "autocorrelation"),
        advice="run it longer (max_steps) or use --posterior pg-nuts",
        options={"warmup": EMCEE_WARMUP}),
    InferenceMethod(
        "vi", "full-rank Gaussian variational inference (Pyro SVI) in whitened coordinates",
        "bayes_talk.posterior.variational:run_vi", draws=64, map_restarts=0, diagnostics=("khat",),
        advice="the Gaussian q fitted within one mode is a poor importance proposal here (the posterior is "
               "multimodal and non-Gaussian); more steps will not change that",
        options={**VI_DEFAULTS, "khat_draws": 200}),
)}
#: the default method for a switching model (the SGPLVM has only "map")
DEFAULT_METHOD = "laplace"
#: draws kept by default, pooled over chains, by method (from :data:`INFERENCE`)
DEFAULT_DRAWS = {n: m.draws for n, m in INFERENCE.items()}


def check_method(name: str) -> InferenceMethod:
    """The method called ``name``; ValueError listing the valid names otherwise."""
    try:
        return INFERENCE[name]
    except (KeyError, TypeError):
        raise ValueError(f"posterior must be one of {tuple(INFERENCE)}, got {name!r}") from None


def draws_help() -> str:
    """The default draws of each sampler as the CLI's ``--draws`` help states them."""
    n = NUTS_DEFAULTS
    parts = [f"{m.name} {n['chains']} x {m.options['draws_per_chain']}" if m.name in ("nuts", "pg-nuts") else f"{m.name} {m.draws}"
             for m in INFERENCE.values() if m.name != "map"]
    return "default: " + ", ".join(parts)


def markdown_table() -> str:
    """The "Inference methods" table of docs/uncertainty.md."""
    rows = ["| method | what it does | callable | default draws | MAP restarts | diagnostics |",
            "|---|---|---|---|---|---|"]
    for m in INFERENCE.values():
        diag = ", ".join(m.diagnostics) or "–"
        rows.append(f"| `{m.name}` | {m.summary} | `{m.runner.replace(':', '.')}` | {m.draws} | {m.map_restarts} "
                    f"| {diag} |")
    return "\n".join(rows)


__all__ = ["DEFAULT_DRAWS", "DEFAULT_METHOD", "DIAGNOSTICS", "EMCEE_WARMUP", "INFERENCE", "NUTS_DEFAULTS",
           "PG_NUTS_BUDGET", "PG_NUTS_DEFAULTS", "VI_DEFAULTS", "InferenceMethod", "check_method", "draws_help", "markdown_table"]
