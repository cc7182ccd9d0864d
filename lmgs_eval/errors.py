"""User-facing errors of the toolkit (one line, exit code 2, no traceback in the CLI)."""

from lmgs.errors import InputError


class UserError(InputError):
    """Bad input from the user; the message names the file, shape or value at fault."""
