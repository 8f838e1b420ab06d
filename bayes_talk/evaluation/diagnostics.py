"""Re-export of :mod:`bayes_talk.synthesis.diagnostics` (the ArviZ adapter moved there so
that synthesis never imports evaluation). Import from ``bayes_talk.synthesis.diagnostics``."""
from __future__ import annotations

from bayes_talk.synthesis.diagnostics import (
    DIAGNOSTIC_KEYS,
    ESS_MIN,
    KHAT_MAX,
    RHAT_MAX,
    chain_diagnostics,
    convergence_problems,
    psis_khat,
)

__all__ = ["DIAGNOSTIC_KEYS", "ESS_MIN", "KHAT_MAX", "RHAT_MAX", "chain_diagnostics", "convergence_problems",
           "psis_khat"]
