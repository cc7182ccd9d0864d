"""Errors raised for bad user input, shared by the whole project.

:class:`InputError` is what a command-line user sees as a one-line message (exit code 2,
no traceback). Everything else is a bug and keeps its traceback.
"""


class InputError(ValueError):
    """Bad input from the user: a file, a shape or a value. The message names which."""
