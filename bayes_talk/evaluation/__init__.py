"""Evaluation: error, correlation and calibration metrics (DESIGN §9)."""
from bayes_talk.evaluation.metrics import (
                                           acc,
                                           amse,
                                           correlation,
                                           coverage,
                                           crps_ensemble,
                                           crps_gaussian,
                                           l1,
                                           linf,
                                           mse,
                                           nlpd_gaussian,
                                           normalised_mse,
                                           rms,
                                           summarise,
)

__all__ = [
                                           "acc",
                                           "amse",
                                           "correlation",
                                           "coverage",
                                           "crps_ensemble",
                                           "crps_gaussian",
                                           "l1",
                                           "linf",
                                           "mse",
                                           "nlpd_gaussian",
                                           "normalised_mse",
                                           "rms",
                                           "summarise",
]
