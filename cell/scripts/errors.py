"""Load errors of the script dialects (seed 004, Figures 2, 3, 5 and 6).

A script that cannot be compiled raises :class:`ScriptError`. The exception raised is the
first error found; ``errors`` lists every error the loader collected (up to
:data:`MAX_ERRORS`), so the HTTP layer can return them all.
"""

from __future__ import annotations

from typing import Any

from cell.core.errors import TestcellError

#: The loader stops collecting after this many errors.
MAX_ERRORS = 50


class ScriptError(TestcellError, ValueError):
    """A script could not be loaded.

    Parameters
    ----------
    file:
        Script name as given to the loader (for example ``kalman.fdv``).
    line, column:
        1-based position of the offending text.
    message:
        What was wrong, and where possible what was expected.
    expected:
        Short description of what the parser expected there, if it was expecting something.

    Attributes
    ----------
    errors:
        Every error collected while loading the script, this one first.

    Notes
    -----
    ``str(error)`` is ``file:line:column: message``, the form compilers use, so editors can
    jump to the place.
    """

    def __init__(
        self,
        file: str,
        line: int,
        column: int,
        message: str,
        expected: str | None = None,
    ) -> None:
        super().__init__(f"{file}:{line}:{column}: {message}")
        self.file = file
        self.line = line
        self.column = column
        self.message = message
        self.expected = expected
        self.errors: list[ScriptError] = [self]

    def __str__(self) -> str:
        return f"{self.file}:{self.line}:{self.column}: {self.message}"

    def as_dict(self) -> dict[str, Any]:
        """The error as a JSON-ready dict: file, line, column, message, expected."""
        return {
            "file": self.file,
            "line": self.line,
            "column": self.column,
            "message": self.message,
            "expected": self.expected,
        }

    def report(self) -> str:
        """All collected errors, one ``file:line:column: message`` per line."""
        return "\n".join(str(e) for e in self.errors)

    @classmethod
    def collect(cls, errors: list[ScriptError]) -> ScriptError:
        """Return the first of ``errors`` carrying the whole list in ``errors``."""
        first = errors[0]
        first.errors = list(errors[:MAX_ERRORS])
        return first


class ErrorList:
    """Collects load errors, stopping the load once :data:`MAX_ERRORS` are found."""

    def __init__(self) -> None:
        self.items: list[ScriptError] = []

    def add(self, error: ScriptError) -> None:
        self.items.append(error)
        if len(self.items) >= MAX_ERRORS:
            raise ScriptError.collect(self.items)

    def __bool__(self) -> bool:
        return bool(self.items)

    def raise_if_any(self) -> None:
        if self.items:
            raise ScriptError.collect(self.items)
