"""Errors the CLI turns into exit codes.

`SplatError` and its subclasses are *user* errors: bad input, a missing earlier
step, an option out of range. The CLI prints them as one line, `error: ...`, and
exits 2. Anything else escaping the core is a bug and exits 1.
"""

from __future__ import annotations


class SplatError(Exception):
    """A problem with the user's input or environment; exit code 2.

    The message must be one line and name the file or option at fault.
    """

    exit_code = 2

    def __init__(self, message: str, *, hint: str | None = None) -> None:
        message = " ".join(str(message).split())  # one line, always
        self.hint = " ".join(hint.split()) if hint else None  # also given alone to --json readers
        if self.hint:
            message = f"{message} ({self.hint})"
        super().__init__(message)


class NotReadyError(SplatError):
    """A command needs the output of an earlier one that has not run."""

    def __init__(self, what: str, command: str) -> None:
        hint = f"run `splatcli {command}` first"
        super().__init__(f"{what}; {hint}")
        self.command = command
        self.hint = hint  # kept in the message as "; ...", not in parentheses


class ProjectBusy(SplatError):
    """Another command holds the project's writer lock."""


class Interrupted(Exception):
    """SIGINT/SIGTERM was received; state was saved. Exit code 130."""

    exit_code = 130


class TrainingDiverged(SplatError):
    """Too many consecutive non-finite steps; the last good checkpoint is kept."""
