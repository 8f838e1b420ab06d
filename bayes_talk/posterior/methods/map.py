"""``map``: the joint MAP path as a one-draw "posterior" (the GP predictive at the MAP only)."""
from __future__ import annotations

from dataclasses import dataclass

from bayes_talk.posterior.methods import Context, Output


@dataclass(frozen=True)
class Options:
    """The MAP has no options of its own (the joint MAP's are ``sample_synthesis``'s)."""


def run(context: Context, options: Options) -> Output:
    """One chain of one draw: the joint MAP's latents."""
    T, d = context.shape
    return Output(context.x_map.reshape(1, 1, T, d))
