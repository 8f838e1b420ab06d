"""Default settings of the synthesis posterior's samplers, in one torch-free module.

The library (:mod:`bayes_talk.synthesis.samplers`, :mod:`bayes_talk.synthesis.posterior`)
and the CLI's help text read these, so the two cannot drift apart; importing this
module pulls in neither torch nor pyro (``bayes-talk --help`` stays fast).
"""
from __future__ import annotations

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
#: docs/uncertainty.md "The proposal at the modes")
PG_NUTS_DEFAULTS = {"pg_every": 1, "pg_particles": 64, "pg_h": (0.005, 0.02, 0.05), "pg_lookahead": True,
                    "pg_mode_centres": True}
#: draws kept by default, pooled over chains (NUTS, pg-nuts: chains × draws_per_chain)
DEFAULT_DRAWS = {"map": 1, "laplace": 64, "nuts": NUTS_DEFAULTS["chains"] * NUTS_DEFAULTS["draws_per_chain"],
                 "pg-nuts": NUTS_DEFAULTS["chains"] * NUTS_DEFAULTS["draws_per_chain"], "emcee": 320, "vi": 64}
#: variational inference (Pyro SVI, full-rank Gaussian guide): optimisation steps, ELBO
#: particles per step, Adam's learning rate (decayed tenfold over the steps)
VI_DEFAULTS = {"steps": 1000, "particles": 4, "lr": 0.02}
#: emcee burn-in steps
EMCEE_WARMUP = 500


def draws_help() -> str:
    """The default draws of each sampler as the CLI's ``--draws`` help states them."""
    n = NUTS_DEFAULTS
    return (f"default: laplace {DEFAULT_DRAWS['laplace']}, nuts and pg-nuts {n['chains']} x {n['draws_per_chain']}, "
            f"emcee {DEFAULT_DRAWS['emcee']}, vi {DEFAULT_DRAWS['vi']}")


__all__ = ["DEFAULT_DRAWS", "EMCEE_WARMUP", "NUTS_DEFAULTS", "PG_NUTS_DEFAULTS", "VI_DEFAULTS", "draws_help"]
