"""Subjects: the ER-NeRF/TalkingGaussian processed layout reader and the bundled subjects."""

from lmgs_eval.data.subject import Subject

__all__ = ["Subject"]
