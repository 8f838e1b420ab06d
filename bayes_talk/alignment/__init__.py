"""Speech in, phone labels out: transcript alignment and phone recognition.

deena2010 §6 names its limitation: phonetic labels are needed for the test audio. This
package supplies them:

* :mod:`.transcript` -- transcript -> phones via espeak-ng's own G2P (the corpus's mapping);
* :mod:`.forced` -- HMM forced alignment (default), :mod:`.dtw` -- DTW against espeak's
  rendition of the transcript;
* :mod:`.model` -- the bundle (phone HMMs, phone-bigram LM, recogniser settings) saved in
  a trained model directory; :meth:`AlignmentModel.recognise` decodes phones from audio alone;
* :mod:`.scoring` -- phone error rate and boundary errors.

See docs/alignment.md.
"""
from bayes_talk.alignment.errors import (
    AlignmentError,
    EmptyTranscriptError,
    MissingAlignmentModelError,
    TranscriptTooLongError,
    UnpronounceableWordError,
)
from bayes_talk.alignment.model import (
    ALIGN_METHODS,
    AlignmentModel,
    AlignmentResult,
    load_alignment_model,
)

__all__ = ["ALIGN_METHODS", "AlignmentError", "AlignmentModel", "AlignmentResult",
           "EmptyTranscriptError", "MissingAlignmentModelError", "TranscriptTooLongError",
           "UnpronounceableWordError", "load_alignment_model"]
