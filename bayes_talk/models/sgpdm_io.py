"""Persistence of a fitted :class:`~bayes_talk.models.sgpdm.SGPDM`: its state as
(JSON-able metadata, named arrays), written as ``<base>.json`` + ``<base>.npz`` by
:func:`bayes_talk.files.write_model_files` (the JSON records the NPZ's SHA-256)."""
from __future__ import annotations

from dataclasses import asdict
from typing import TYPE_CHECKING

import numpy as np
import torch

from bayes_talk.files import check_format
from bayes_talk.gp.backconstraint import MLPBackConstraint
from bayes_talk.models.sgpdm_program import FitHistory

if TYPE_CHECKING:
    from collections.abc import Mapping

    from bayes_talk.models.sgpdm import SGPDM

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "sgpdm_from_state", "sgpdm_state"]

FORMAT_VERSION = 1
FORMAT_NAME = "bayes_talk.sgpdm"


def sgpdm_state(model: SGPDM) -> tuple[dict, dict[str, np.ndarray]]:
    """(JSON-able metadata, arrays) that fully describe a fitted :class:`SGPDM`."""
    model._require_fitted()
    meta = {
        "format": model.format_name,
        "version": model.format_version,
        "config": asdict(model.config),
        "views": model.view_names,
        "seq_lengths": model.seq_lengths_,
        "history": model.history.log_joint,
        "history_monitor": model.history.monitor,
        "history_best_step": model.history.best_step,
    }
    arrays: dict[str, np.ndarray] = {"X": model.X_}
    for v in model.view_names:
        arrays[f"Y/{v}"] = model._Y[v].numpy()
        arrays[f"mean/{v}"] = model.means_[v]
    for k, val in model.hyper_.items():
        arrays[f"hyper/{k}"] = np.asarray(val, dtype=np.float64)
    if model.backconstraint is not None:
        for k, val in model.backconstraint.state().items():
            arrays[f"bc/{k}"] = val
    for v, c in model.var_scale_.items():
        arrays[f"varscale/{v}"] = c
    return meta, arrays


def sgpdm_from_state(cls: type[SGPDM], meta: dict, arrays: Mapping[str, np.ndarray]) -> SGPDM:
    """A fitted model from :meth:`state`'s metadata and arrays (ValueError if incomplete)."""
    check_format(meta, cls.format_name, cls.format_version, f"{cls.__name__} model")
    try:
        obj = cls(**meta["config"])
        obj.view_names = list(meta["views"])
        obj.seq_lengths_ = [int(t) for t in meta["seq_lengths"]]
        obj.history = FitHistory(list(meta.get("history", [])), list(meta.get("history_monitor", [])),
                                 meta.get("history_best_step"))
        obj.X_ = np.asarray(arrays["X"], dtype=np.float64)
        obj._Y = {v: torch.as_tensor(np.asarray(arrays[f"Y/{v}"], dtype=np.float64)) for v in obj.view_names}
        obj.means_ = {v: np.asarray(arrays[f"mean/{v}"], dtype=np.float64) for v in obj.view_names}
        hyper = {k[len("hyper/"):]: torch.as_tensor(np.asarray(a, dtype=np.float64))
                 for k, a in arrays.items() if k.startswith("hyper/")}
        bc_keys = {k[3:]: arrays[k] for k in arrays if k.startswith("bc/")}
    except (KeyError, TypeError) as exc:
        raise ValueError(f"SGPDM model is incomplete or corrupt: missing {exc}") from None
    obj.backconstraint = MLPBackConstraint.from_state(bc_keys) if bc_keys else None
    if obj.backconstraint is not None:
        obj._bc_params = obj.backconstraint.parameters()
    obj._X = torch.as_tensor(obj.X_)
    obj._log = {}
    obj._fixed = hyper
    obj._restore_extra(arrays)
    obj._finalise()
    obj.var_scale_ = {k[len("varscale/"):]: np.asarray(a, dtype=np.float64)
                      for k, a in arrays.items() if k.startswith("varscale/")}
    return obj

