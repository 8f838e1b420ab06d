"""Gaussian-process core: kernels, likelihood terms, predictives, linear algebra.

Importing the package fixes MKL's thread count (no load-dependent thread reduction, see
:mod:`bayes_talk.gp.threads`), so every GP computation is repeatable under load.
"""
from bayes_talk.gp import threads  # noqa: F401  (imported for its side effect: MKL dynamic off)
