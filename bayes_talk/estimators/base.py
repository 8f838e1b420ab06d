"""The estimator protocol every method implements (docs/architecture.md).

An estimator turns the audio and phone labels of an utterance into visual features,
with scikit-learn conventions:

* the constructor only stores its arguments, as given (validation may reject bad values,
  but never rewrites them), so ``get_params`` / ``set_params`` and
  ``sklearn.base.clone`` work (:class:`sklearn.base.BaseEstimator`);
* ``fit(train) -> self`` learns from training utterances (``mfcc``, ``aam``, ``labels``);
  fitted attributes end in ``_``;
* ``predict(utt) -> (T, D_z)`` mean trajectory, from ``utt.mfcc`` / ``utt.labels`` only;
* ``predict_dist(utt)``: the predictive distribution, a
  :class:`~bayes_talk.synthesis.result.SynthesisResult` (``.mean``, ``.var``, bands);
  NotImplementedError for a point predictor (no variance: Voice Puppetry, SLDS, DPDS);
* ``save(directory)`` / ``load(directory)``: a model bundle, JSON + NPZ, never pickle;
* anything but ``fit``/``load`` before fitting raises :class:`~bayes_talk.base.errors.NotFittedError`.

One layout for every estimator: :meth:`Estimator.save` writes a directory with
``estimator.json`` (the descriptor: format and version, the method name, the estimator's
module and class, its constructor parameters, the fitted metadata), ``arrays.npz`` (the
fitted arrays) and ``bundle_manifest.json`` (SHA-256 of every file, written last;
:mod:`bayes_talk.base.bundle`). A constructor parameter that is itself an estimator (a
wrapper's, :class:`~bayes_talk.estimators.calibrated.BandCalibrated`) is saved the same
way in the sub-directory named after the parameter. :meth:`Estimator.load` reads the
descriptor and builds the class it names, with no class to pass in (``Estimator.load(d)``;
:func:`bayes_talk.estimators.registry.load_estimator` is the public entry, which also names
the layouts of earlier versions). It refuses a bundle whose file was swapped from another
model or truncated, naming the file. Never pickle.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, ClassVar, Self

import numpy as np
from sklearn.base import BaseEstimator

from bayes_talk.base.bundle import (
    BUNDLE_MANIFEST,
    begin_bundle,
    verify_bundle,
    write_bundle_manifest,
)
from bayes_talk.base.errors import NotFittedError, not_fitted
from bayes_talk.base.files import check_format, read_model_files, write_json, write_npz
from bayes_talk.data.utterance import Utterance
from bayes_talk.synthesis.result import SynthesisResult

__all__ = ["ARRAYS_FILE", "ESTIMATOR_FILE", "FORMAT_NAME", "FORMAT_VERSION", "READ_VERSIONS", "Estimator", "NotFittedError",
           "estimator_class"]

FORMAT_NAME = "bayes_talk.estimator"
#: version 2: the descriptor names the module and class, and nested estimators;
#: version 1 (the baselines' bundles before it) is read too
FORMAT_VERSION = 2
READ_VERSIONS = (1, 2)
ESTIMATOR_FILE = "estimator.json"
ARRAYS_FILE = "arrays.npz"


class Estimator(BaseEstimator):
    """Base class of every estimator; see the module docstring for the protocol."""

    #: method-family name in :data:`bayes_talk.estimators.registry.ESTIMATORS`
    name: ClassVar[str] = ""
    #: a floor or ceiling of an evaluation (``zero``, ``oracle``), not a method: its mean is
    #: the target methods are measured against, so ``evaluate`` never post-filters it
    reference: ClassVar[bool] = False
    #: the choice options :meth:`predict_dist` takes and their values, as ``synth`` offers
    #: them (``algorithm``, ``init``, ``posterior``: a whole-utterance posterior); {}: none
    synthesis_options: ClassVar[dict[str, tuple[str, ...]]] = {}
    #: ``synth`` low-passes its mean by default (deena2010 §4.2.3's post-filter)
    post_filter: ClassVar[bool] = False

    @classmethod
    def has_distribution(cls) -> bool:
        """Whether :meth:`predict_dist` gives a predictive distribution (False: a point
        predictor, whose ``predict_dist`` raises NotImplementedError)."""
        return hasattr(cls, "predict_var") or cls.predict_dist is not Estimator.predict_dist

    def fit(self, train: list[Utterance]) -> Self:
        """Learn from training utterances (with ``aam``); returns ``self``."""
        raise NotImplementedError

    def predict(self, utt: Utterance) -> np.ndarray:
        """The (T, D_z) mean visual trajectory of ``utt`` (``utt.aam`` is not used)."""
        raise NotImplementedError

    def predict_dist(self, utt: Utterance) -> SynthesisResult:
        """The predictive distribution of ``utt``'s visual features, the one synthesis result
        type (:class:`~bayes_talk.synthesis.result.SynthesisResult`). The default: a Gaussian
        per frame and dimension from :meth:`predict` and ``predict_var``; an estimator without
        ``predict_var`` is a point predictor and raises NotImplementedError."""
        if not hasattr(self, "predict_var"):
            raise NotImplementedError(f"{type(self).__name__} ({self.name}) is a point predictor: it defines "
                                      "no predictive distribution (use predict)")
        return SynthesisResult.gaussian(self.predict(utt), self.predict_var(utt), method=self.name)

    # ------------------------------------------------------------------ fitted state
    def _is_fitted(self) -> bool:
        return any(k.endswith("_") and not k.startswith("_") for k in vars(self))

    def _require_fitted(self) -> None:
        if not self._is_fitted():
            raise not_fitted(self, "call fit(train) or load() first")

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """(JSON-able metadata, arrays) of the fitted model; every estimator saved by
        :meth:`save` implements it with :meth:`_set_state`."""
        raise NotImplementedError(f"{type(self).__name__} defines no saved state")

    def _set_state(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        """Restore what :meth:`_get_state` returned (raise KeyError/TypeError if incomplete)."""
        raise NotImplementedError(f"{type(self).__name__} defines no saved state")

    # ------------------------------------------------------------------ persistence
    def saved_params(self) -> dict[str, Any]:
        """The constructor parameters :meth:`save` records (an estimator-valued one is saved
        in its own sub-directory instead, :meth:`saved_estimators`)."""
        return {k: v for k, v in self.get_params(deep=False).items() if not isinstance(v, Estimator)}

    def saved_estimators(self) -> dict[str, Estimator]:
        """Parameter name -> the *fitted* estimator saved in the sub-directory of that name
        (a wrapper's; none by default)."""
        return {}

    def save(self, directory: str | os.PathLike, overwrite: bool = False) -> Path:
        """Write the bundle (module docstring) into ``directory``; an existing bundle there is
        refused (FileExistsError) unless ``overwrite``. Returns the directory."""
        self._require_fitted()
        d = Path(directory)
        if (d / ESTIMATOR_FILE).exists() and not overwrite:
            raise FileExistsError(f"{d / ESTIMATOR_FILE} exists; pass overwrite=True to replace it")
        meta, arrays = self._get_state()
        d.mkdir(parents=True, exist_ok=True)
        begin_bundle(d, ESTIMATOR_FILE)
        for sub, est in self.saved_estimators().items():
            est.save(d / sub, overwrite=True)
        write_npz(d / ARRAYS_FILE, arrays)
        write_json(d / ESTIMATOR_FILE, {"format": FORMAT_NAME, "version": FORMAT_VERSION, "name": self.name,
                                        "module": type(self).__module__, "class": type(self).__qualname__,
                                        "params": _jsonable(self.saved_params()),
                                        "estimators": sorted(self.saved_estimators()), "state": meta})
        write_bundle_manifest(d)
        return d

    @classmethod
    def load(cls, directory: str | os.PathLike) -> Self:
        """Read a bundle written by :meth:`save`, as the class its descriptor names (which
        must be ``cls`` or a subclass: ``Estimator.load`` reads any). FileNotFoundError for a
        missing file; :class:`~bayes_talk.base.bundle.BundleError` (a ValueError) naming the file
        when one was swapped from another model, truncated or changed; ValueError for
        another class's bundle, a wrong format or version, or an incomplete descriptor."""
        d = Path(directory)
        if not (d / BUNDLE_MANIFEST).is_file() and not (d / ESTIMATOR_FILE).is_file():
            raise FileNotFoundError(f"{d} holds no saved estimator (no {ESTIMATOR_FILE})")
        verify_bundle(d)
        meta, arrays = read_model_files(d / ESTIMATOR_FILE, d / ARRAYS_FILE)
        where = str(d / ESTIMATOR_FILE)
        version = meta.get("version") if isinstance(meta, dict) else None
        check_format(meta, FORMAT_NAME, version if version in READ_VERSIONS else FORMAT_VERSION, where)
        target = estimator_class(meta, where)
        if not issubclass(target, cls):
            raise ValueError(f"{where}: a saved {target.__name__} ({meta.get('name')!r}), not a {cls.__name__}")  # noqa: TRY004 - a bad file is a ValueError
        subs = {k: Estimator.load(d / k) for k in meta.get("estimators", [])}
        try:
            obj = target(**_from_json(meta["params"]), **subs)
            for k, est in subs.items():   # a nested estimator is saved fitted: its fitted attribute too
                setattr(obj, k + "_", est)
            obj._set_state(meta["state"], arrays)
        except (KeyError, TypeError) as exc:
            raise ValueError(f"{where}: incomplete or corrupt (missing {exc})") from None
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        return obj


def estimator_class(meta: dict[str, Any], where: str) -> type[Estimator]:
    """The estimator class a descriptor names: by module and qualified name (version 2), by
    class name alone (version 1, the baselines'), among the imported subclasses of
    :class:`Estimator` (:mod:`bayes_talk.estimators.registry` imports every registered one).
    ValueError naming ``where`` when none or several match."""
    module, name = meta.get("module"), meta.get("class")
    found, todo = set(), [Estimator]
    while todo:
        c = todo.pop()
        todo.extend(c.__subclasses__())
        if (c.__module__, c.__qualname__) == (module, name) if module else c.__name__ == name:
            found.add(c)
    if len(found) != 1:
        what = f"{module}.{name}" if module else repr(name)
        why = ("which is not imported (read it with bayes_talk.estimators.registry.load_estimator)" if not found
               else f"which is ambiguous ({sorted(c.__module__ for c in found)})")
        raise ValueError(f"{where}: names the estimator class {what}, {why}")
    return found.pop()


def _jsonable(v: Any) -> Any:
    """Constructor parameters as JSON holds them (tuples become lists)."""
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.generic, np.ndarray)):
        return _jsonable(v.tolist()) if isinstance(v, np.ndarray) else v.item()
    return v


def _from_json(v: Any) -> Any:
    """Inverse of :func:`_jsonable` for constructor parameters (lists become tuples)."""
    if isinstance(v, dict):
        return {k: _from_json(x) for k, x in v.items()}
    if isinstance(v, list):
        return tuple(_from_json(x) for x in v)
    return v
