"""bayes_talk: speech-driven talking faces with switching shared GP dynamical models."""
__version__ = "0.1.0"
