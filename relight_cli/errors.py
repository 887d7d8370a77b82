"""The one error path of the toolkit.

Engine and format code raise these; the CLI turns them into one line on stderr,
``relight <cmd>: error: <what> (<path>)``, and an exit code (1 for bad data, 2
for usage).  Nothing here imports anything heavy.
"""

from __future__ import annotations


class RelightError(Exception):
    """A user-facing problem: bad data, bad usage.  Never shown as a traceback."""

    exit_code = 1

    def __init__(self, message: str, path: str | None = None, hint: str | None = None):
        super().__init__(message)
        self.message = message
        self.path = None if path is None else str(path)
        self.hint = hint

    def __str__(self) -> str:
        text = self.message
        if self.path is not None:
            text += f" ({self.path})"
        if self.hint:
            text += f"; hint: {self.hint}"
        return text


class DataError(RelightError):
    """An input file (or array) is missing, damaged, or has invalid content.  Exit 1."""

    exit_code = 1


class UsageProblem(RelightError):
    """An impossible option or combination of options.  Exit 2."""

    exit_code = 2


class OutputError(RelightError):
    """An output cannot be written (permissions, full disk, a FIFO with no reader...).  Exit 1."""

    exit_code = 1
