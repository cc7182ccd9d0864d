"""Errors raised for bad user input, shared by the whole project.

:class:`InputError` is what a command-line user sees as a one-line message (exit code 2,
no traceback). :class:`TrainingDiverged` is a training run that failed (non-finite or
collapsed loss): one line too, exit code 1. Everything else is a bug and keeps its traceback.
"""


class InputError(ValueError):
    """Bad input from the user: a file, a shape or a value. The message names which."""


class TrainingDiverged(RuntimeError):
    """The loss became non-finite or collapsed; the message names the step and the last good checkpoint."""
