"""For the analysis scripts: train every switching family of the evaluation registry with an
audio context window of half-width k (SwitchingConfig.audio_context), which SystemConfig
does not expose. Import from a script in this folder and call ``use_audio_context(k)``."""
from bayes_talk.evaluation import systems


def use_audio_context(k: int) -> None:
    """Make ``systems._build`` give every ``ssgpdm-*`` model ``audio_context = k``."""
    build0 = systems._build

    def _build(family, cfg):
        m = build0(family, cfg)
        if family.startswith("ssgpdm-"):
            m.audio_context = k
        return m

    systems._build = _build
