"""Exceptions shared by every layer of the package.

:class:`NotFittedError` is the one failure of a model or estimator used before ``fit``
(or ``load``). It subclasses scikit-learn's ``NotFittedError`` (itself a ``ValueError``
and an ``AttributeError``), so ``except ValueError`` and scikit-learn's own checks catch
it too.
"""
from __future__ import annotations

from sklearn.exceptions import NotFittedError as _SklearnNotFittedError

__all__ = ["NotFittedError", "not_fitted"]


class NotFittedError(_SklearnNotFittedError):
    """A model or estimator was used before ``fit`` or ``load``."""


def not_fitted(obj: object, how: str = "call fit() or load() first") -> NotFittedError:
    """The error for ``obj`` used before fitting, naming its class."""
    return NotFittedError(f"this {type(obj).__name__} is not fitted yet: {how}")
