"""From a corpus to a trained model directory, and from WAV + labels to a talking face:
the command line's workflow, split by idea:

* :mod:`~bayes_talk.pipeline.training`: ``train`` (corpus -> model directory), the model
  kinds (every registered family with a predictive distribution) and their defaults;
* :mod:`~bayes_talk.pipeline.trained`: ``load_trained`` (model directory -> model, AAM,
  front end, calibration);
* :mod:`~bayes_talk.pipeline.front_end`: the audio front end, built in one place with its
  settings (what ``train`` records, what ``synth`` applies to new audio);
* :mod:`~bayes_talk.pipeline.talking_face`: ``synth`` (WAV + labels -> face, bands, video);
* :mod:`~bayes_talk.pipeline.batch`: ``synth_many`` (many WAVs through one loaded model, with a
  summary of every file).

The model directory's descriptor is :mod:`bayes_talk.base.bundle`'s. The public names of the
five modules are importable from here (on first access, PEP 562, so that importing the
package for the command line's defaults loads no more than those).
"""
from __future__ import annotations

from bayes_talk.base.lazy import lazy_exports

_EXPORTS: dict[str, str] = {
    **dict.fromkeys(("DEFAULT_CALIBRATED_MODEL", "DEFAULT_CALIBRATION", "DEFAULT_MODEL", "MODEL_KINDS", "aam_offset", "calibrates_bands",
                     "fit_model", "model_kinds", "new_model", "select_holdout", "train"),
                    "bayes_talk.pipeline.training"),
    **dict.fromkeys(("TrainedModel", "load_trained"), "bayes_talk.pipeline.trained"),
    **dict.fromkeys(("audio_settings", "corpus_front_end", "front_end", "read_utterance", "utterance_from_intervals"),
                    "bayes_talk.pipeline.front_end"),
    **dict.fromkeys(("SYNTH_OUTPUT_NAMES", "synth"), "bayes_talk.pipeline.talking_face"),
    **dict.fromkeys(("BatchInput", "inputs_from_dir", "inputs_from_list", "synth_many"), "bayes_talk.pipeline.batch"),
}

__all__ = ["DEFAULT_CALIBRATED_MODEL", "DEFAULT_CALIBRATION", "DEFAULT_MODEL", "MODEL_KINDS", "SYNTH_OUTPUT_NAMES", "BatchInput",
           "TrainedModel", "aam_offset", "audio_settings", "calibrates_bands", "corpus_front_end", "fit_model",
           "front_end", "inputs_from_dir", "inputs_from_list", "load_trained", "model_kinds", "new_model",
           "read_utterance", "select_holdout", "synth", "synth_many", "train", "utterance_from_intervals"]


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals(), __all__)
