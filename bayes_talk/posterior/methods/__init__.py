"""The posterior methods of a whole utterance behind one interface, and their table.

:data:`INFERENCE` names every method that :func:`~bayes_talk.posterior.sampling.sample_synthesis`
runs (and so ``synth --posterior``, the evaluation harness's posterior methods and
``predict_dist(posterior=...)``): the table *is* the dispatch. Each entry names the module
that implements the method, in this package, and that module has one shape:

* ``Options``: a dataclass of the method's own settings (``sample_synthesis``'s
  ``sampler_kw``), with their defaults, checked when it is made (a ``ValueError`` saying
  what is wrong);
* ``run(context, options) -> Output``: the draws, in the latents x, from the :class:`Context`
  every method starts from (the whole-utterance density, its joint MAP and the restarts'
  modes, the Laplace scale, the seed and the draws asked for).

``sample_synthesis`` does the steps common to every method (the density, the joint MAP and
its restarts, the Laplace scale, the visual predictive at the draws, the AAM parameters'
diagnostics and the warnings from :attr:`InferenceMethod.diagnostics`) and calls
:meth:`InferenceMethod.run` in between. A new method is one module here and one
:class:`InferenceMethod` line in :data:`INFERENCE`; the CLI's ``--posterior`` choices, the
switching model's ``synthesis_options`` and docs/uncertainty.md's "Inference methods" table
(:func:`markdown_table`, checked by a test) read the table.

Importing this package pulls in neither torch nor pyro (``bayes-talk --help`` stays fast):
a method's module is imported when the method runs.
"""
from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

    from bayes_talk.synthesis.banded import BandedFactor
    from bayes_talk.synthesis.joint import UtteranceDensity, UtterancePlan
    from bayes_talk.synthesis.joint_map import MapResult

#: NUTS defaults of the library and the CLI (docs/uncertainty.md, "Sampler options and
#: defaults"): chains, warm-up iterations per chain, draws kept per chain, target acceptance
#: statistic of the step-size adaptation, max tree depth, mode-jumping Metropolis attempts per
#: displacement per iteration, warm-up iterations of the pilot phase (after which the modes
#: the chains reached are searched for and turned into jumps; part of ``warmup``)
NUTS_DEFAULTS = {"chains": 4, "warmup": 500, "draws_per_chain": 250, "target_accept": 0.8, "max_tree_depth": 10,
                 "jump_attempts": 2, "pilot": 150}
#: pg-nuts's budget in place of NUTS's warm-up and draws per chain (the other NUTS defaults
#: apply): its sweeps and block updates move the chains between the modes, so NUTS's
#: adaptation needs fewer iterations and the time goes to draws. ``draws_per_chain`` is the
#: most a chain draws: with ``stop_at_targets`` the chains stop once the latents' and the AAM
#: parameters' rank R-hat ≤ 1.01 and bulk and tail ESS ≥ 400
#: (:class:`~bayes_talk.posterior.sampling.TargetCheck`), asked after ``min_draws_per_chain``
#: draws and every ``check_every`` after (docs/uncertainty.md, "Stopping at the targets")
PG_NUTS_BUDGET = {"warmup": 200, "draws_per_chain": 500, "stop_at_targets": True, "min_draws_per_chain": 250,
                  "check_every": 50}
#: particle Gibbs ∘ NUTS ∘ mode jumps (``--posterior pg-nuts``; the settings of
#: :class:`~bayes_talk.posterior.methods.nuts.Options`, docs/uncertainty.md "Which sampler"):
#: a conditional-SMC sweep with ancestor sampling (``pg_backward``: backward simulation) of
#: ``pg_particles`` particles after every ``pg_every``-th NUTS iteration, its proposal's kernels
#: of bandwidths ``pg_h`` around the training latents and (``pg_mode_centres``) around the joint
#: MAP and its restarts' modes, weighted (``pg_lookahead``) by the audio of a dynamics run's
#: continuation; then ``pg_block_sweeps`` passes of a ``pg_frame_tries``-try Metropolis update
#: of every frame without dynamics on either side and of every dynamics run of at most
#: ``pg_block_len`` frames, the tries of its first frame from the block's own modes
#: (``pg_frame_modes``; optionally conditioned on its neighbours, ``pg_neighbours``), and of
#: every pair of consecutive blocks (``pg_pairs``); the own-mode proposal's defensive weight
#: ``pg_mode_delta``, Laplace covariance scale(s) ``pg_mode_scale`` and mode-ascent starts
#: ``pg_mode_starts`` (:class:`~bayes_talk.posterior.frame_updates.BlockModeProposal`); the
#: modes' weights learnt from all chains' warm-ups and then frozen (``pg_adapt_weights``), each
#: mode with enough mass also proposed from its full conditional's mean and covariance
#: (``pg_adapt_moments``, :mod:`~bayes_talk.posterior.mode_adaptation`) and a Gaussian mixture
#: fitted to the warm-up states proposed too (``pg_adapt_clusters``)
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
#: draws of an iid approximation (Laplace, VI) its PSIS k̂ is estimated from (at least the
#: draws kept)
KHAT_DRAWS = 200

#: the diagnostics a method can have: those checked by
#: :func:`~bayes_talk.posterior.diagnostics.convergence_problems` — Pareto k̂ of the importance
#: weights p/q of iid proposal draws; R-hat, bulk/tail ESS and MCSE across chains (latents and
#: AAM parameters, per frame); NUTS divergences and E-BFMI; emcee's chain length ≥ 50 τ — and
#: the per-frame update rate of particle Gibbs sweeps
#: (:func:`~bayes_talk.posterior.diagnostics.frame_update_rate`; reported, no threshold)
DIAGNOSTICS = ("khat", "rhat_ess", "divergences_bfmi", "autocorrelation", "frame_update_rate")


@dataclass
class Context:
    """What every posterior method starts from, made by
    :func:`~bayes_talk.posterior.sampling.sample_synthesis` before it runs the method.

    plan, density: the whole-utterance synthesis model and its closed-form log density
    (:class:`~bayes_talk.synthesis.joint.UtteranceDensity`); map: the joint MAP (the highest
    mode of its restarts) and modes: the restarts' modes; factor: the banded Cholesky factor R
    of the Laplace precision at the MAP (:meth:`~bayes_talk.synthesis.joint_map.MapResult.laplace_factor`;
    the whitening X = X_MAP + L z with L = R⁻ᵀ, applied in linear time by its
    ``scale_matvec``; :attr:`scale` is L as a dense matrix, for the samplers that move in
    whitened coordinates on short utterances); rng: a generator
    seeded by ``seed`` (the methods that draw with numpy take theirs from it); n_draws: draws
    to keep, pooled over chains; chains: chains of the MCMC methods; warmup: their warm-up
    (None: the method's default); map_iter: Newton iterations of a joint MAP the method runs
    itself; thin: emcee's thinning."""

    plan: UtterancePlan
    density: UtteranceDensity
    map: MapResult
    modes: list
    factor: BandedFactor
    rng: np.random.Generator
    seed: int
    n_draws: int
    chains: int
    warmup: int | None
    map_iter: int
    thin: int

    @property
    def scale(self) -> np.ndarray:
        """L (T·d × T·d, dense) with L Lᵀ the Laplace covariance at the MAP: the whitening of
        the samplers that move in whitened coordinates (quadratic memory: short utterances)."""
        if "scale" not in self.__dict__.setdefault("_dense", {}):
            self.__dict__["_dense"]["scale"] = self.factor.dense_scale()[0]
        return self.__dict__["_dense"]["scale"]

    @property
    def x_map(self) -> np.ndarray:
        """The joint MAP's latents, flat (T·d,)."""
        return self.map.latents.reshape(-1)

    @property
    def shape(self) -> tuple[int, int]:
        """(T, d): frames and latent dimensions."""
        return self.plan.n_frames, self.plan.latent_dim


@dataclass
class Output:
    """What a method's ``run`` returns: latents (chains, draws, T, d), its diagnostics
    (JSON-ready; added to the result's), the per-draw statistics for
    ``InferenceData.sample_stats`` ((chains, draws) arrays; may be empty) and map: the joint
    MAP when the method moved it (NUTS's pilot mode search), else None."""

    latents: np.ndarray
    diagnostics: dict = field(default_factory=dict)
    sample_stats: dict = field(default_factory=dict)
    map: MapResult | None = None


@dataclass(frozen=True)
class InferenceMethod:
    """One way to infer the whole-utterance synthesis posterior (docs/uncertainty.md).

    module: the module implementing it (``Options`` and ``run``, the package docstring),
    imported when the method runs; draws: default draws kept, pooled over ``chains`` chains;
    map_restarts: restarts of the joint MAP per round from draws of its Laplace approximation
    before the method runs; diagnostics: those of :data:`DIAGNOSTICS` that apply (the warnings
    are made from them); advice: what to try when its checks fail (added to the warning)."""

    name: str
    summary: str
    module: str
    draws: int
    map_restarts: int
    diagnostics: tuple[str, ...]
    advice: str = ""
    chains: int = 1

    def load(self) -> ModuleType:
        """The module named by :attr:`module`."""
        return importlib.import_module(self.module)

    def make_options(self, sampler_kw: dict | None = None) -> Any:
        """The method's ``Options`` from ``sampler_kw`` (the rest at their defaults); a
        ValueError names keys that are not its options."""
        cls = self.load().Options
        kw = dict(sampler_kw or {})
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(kw) - set(names))
        if unknown:
            raise ValueError(f"sampler_kw {unknown} are not options of {self.name!r}; its options: "
                             f"{', '.join(names) or 'none'}")
        return cls(**kw)

    @property
    def options(self) -> dict:
        """The method's options and their defaults (``Options()`` as a dict)."""
        return dataclasses.asdict(self.load().Options())

    def run(self, context: Context, options: Any) -> Output:
        """The method's draws from ``context`` with ``options`` (:meth:`make_options`)."""
        return self.load().run(context, options)


#: every inference method, by name; the first with draws is the default of switching models
INFERENCE: dict[str, InferenceMethod] = {m.name: m for m in (
    InferenceMethod(
        "map", "a point estimate: the joint MAP path (`sample_synthesis`); `synth --posterior map` runs "
               "the paper's sequential path (Algorithm 1/2) instead",
        "bayes_talk.posterior.methods.map", draws=1, map_restarts=0, diagnostics=()),
    InferenceMethod(
        "laplace", "iid draws of the Gaussian at the joint MAP (closed-form block-tridiagonal Hessian, banded "
                   "Cholesky factor: linear in the length)",
        "bayes_talk.posterior.methods.laplace", draws=64, map_restarts=0, diagnostics=("khat",),
        advice="the Gaussian approximation is poor here (the posterior is multimodal); the bands include "
               "the model's observation term, fitted on held-out training utterances, beside the "
               "approximation's spread; "
               "--posterior pg-nuts samples the posterior itself (25–45 min for 3–4 s of speech on 2 cores "
               "with --workers 2)"),
    InferenceMethod(
        "nuts", "NUTS in coordinates whitened at the MAP, with a pilot mode search and mode-jumping moves",
        "bayes_talk.posterior.methods.nuts",
        draws=NUTS_DEFAULTS["chains"] * NUTS_DEFAULTS["draws_per_chain"], map_restarts=6,
        diagnostics=("rhat_ess", "divergences_bfmi"),
        advice="run more draws/warm-up (or raise the target acceptance for divergences); chains in different "
               "modes of a multimodal posterior will not agree: --posterior pg-nuts moves between them",
        chains=NUTS_DEFAULTS["chains"]),
    InferenceMethod(
        "pg-nuts", "particle Gibbs (conditional SMC with ancestor sampling) and multiple-try updates of the "
                   "isolated frames from their own modes, composed with NUTS in the non-centred coordinates "
                   "and the mode jumps",
        "bayes_talk.posterior.methods.pg_nuts",
        draws=NUTS_DEFAULTS["chains"] * PG_NUTS_BUDGET["draws_per_chain"], map_restarts=6,
        diagnostics=("rhat_ess", "divergences_bfmi", "frame_update_rate"),
        advice="run more draws (synth --draws, the most drawn when the chains stop at the R-hat/ESS targets; the "
               "ESS grows with them once R-hat is within 1.01) or a longer "
               "warm-up (--warmup) if R-hat is not; the frames with the lowest update rate "
               "(pg_frame_update_rate in diagnostics.json) are the slowest to mix; on 3-4-s held-out utterances the "
               "defaults reach R-hat <= 1.01 with bulk and tail ESS >= 400 (docs/uncertainty.md)",
        chains=NUTS_DEFAULTS["chains"]),
    InferenceMethod(
        "emcee", "emcee's ensemble (differential-evolution moves) in whitened coordinates",
        "bayes_talk.posterior.methods.emcee", draws=320, map_restarts=6,
        diagnostics=("rhat_ess", "autocorrelation"),
        advice="run it longer (max_steps) or use --posterior pg-nuts"),
    InferenceMethod(
        "vi", "full-rank Gaussian variational inference (Pyro SVI) in whitened coordinates",
        "bayes_talk.posterior.methods.vi", draws=64, map_restarts=0, diagnostics=("khat",),
        advice="the Gaussian q fitted within one mode is a poor importance proposal here (the posterior is "
               "multimodal and non-Gaussian); more steps will not change that"),
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
    """The default draws of each method as the CLI's ``--draws`` help states them."""
    parts = [f"{m.name} {m.chains} x {m.draws // m.chains}" if m.chains > 1 else f"{m.name} {m.draws}"
             for m in INFERENCE.values() if m.draws > 1]
    return "default: " + ", ".join(parts)


def markdown_table() -> str:
    """The "Inference methods" table of docs/uncertainty.md."""
    rows = ["| method | what it does | module | default draws | MAP restarts | diagnostics |",
            "|---|---|---|---|---|---|"]
    for m in INFERENCE.values():
        diag = ", ".join(m.diagnostics) or "–"
        rows.append(f"| `{m.name}` | {m.summary} | `{m.module}` | {m.draws} | {m.map_restarts} | {diag} |")
    return "\n".join(rows)


__all__ = ["DEFAULT_DRAWS", "DEFAULT_METHOD", "DIAGNOSTICS", "EMCEE_WARMUP", "INFERENCE", "KHAT_DRAWS",
           "NUTS_DEFAULTS", "PG_NUTS_BUDGET", "PG_NUTS_DEFAULTS", "VI_DEFAULTS", "Context", "InferenceMethod",
           "Output", "check_method", "draws_help", "markdown_table"]
