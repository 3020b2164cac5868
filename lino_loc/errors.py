"""User-facing errors.

A :class:`LinoLocError` is a mistake in what the user gave us (a file, a field, a value),
not a bug: the command line prints its one-line message and exits with status 2, without a
traceback. Anything else that escapes is an internal failure (exit status 1).
"""


class LinoLocError(Exception):
    """Bad input from the user. The message is one line and names the file, field or value."""
