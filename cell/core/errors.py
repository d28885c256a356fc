"""The project's exceptions, in one short hierarchy.

Each subclasses a builtin so callers that do not know testcell can still catch it.
"""

from __future__ import annotations


class TestcellError(Exception):
    """Base of every error testcell raises on purpose."""

    __test__ = False  # not a pytest test class


class BusError(TestcellError, OSError):
    """The CAN bus could not be opened or used. The message names the fix."""


class ConfigError(TestcellError, ValueError):
    """A setting, option or configuration file is wrong. The message names it."""


class ParamError(TestcellError, ValueError):
    """A block parameter was refused. ``field`` names the offending parameter."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


class UnknownBlockError(TestcellError, KeyError):
    """No block of that name exists."""

    def __init__(self, kind: str, name: str, known: list[str]) -> None:
        super().__init__(name)
        self.kind = kind
        self.name = name
        self.known = known

    def __str__(self) -> str:
        known = ", ".join(self.known) or "none"
        return f"no {self.kind} named {self.name!r}; known: {known}"


class LogFormatError(TestcellError, ValueError):
    """A CAN log line could not be read. Carries the file and 1-based line number."""

    def __init__(self, path: str, line: int, message: str) -> None:
        super().__init__(f"{path}:{line}: {message}")
        self.path = path
        self.line = line
        self.message = message
