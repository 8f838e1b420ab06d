"""Evaluation: error, correlation and calibration metrics (docs/evaluation.md), protocols, reports.

The metrics live in :mod:`bayes_talk.evaluation.metrics` (its ``__all__`` is re-exported
here); protocols in :mod:`~bayes_talk.evaluation.protocols`.
"""
from bayes_talk.evaluation import metrics
from bayes_talk.evaluation.metrics import *

__all__ = list(metrics.__all__)
