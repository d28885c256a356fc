"""Script text to logical lines: comments, ``\\`` continuations and size limits.

Both dialects are line based (seed 004, Figures 2, 3, 5, 6): a trailing backslash joins
a physical line to the next one, and a comment marker (``//`` in ``.fdv`` files, ``#`` in
``.labels`` and ``.ravg`` files) ends the line's text. Every character of a logical line
keeps the 1-based line and column it came from, so errors point into the file as written.
"""

from __future__ import annotations

from dataclasses import dataclass

from cell.scripts.errors import ErrorList, ScriptError

#: Largest script accepted, in characters. The paper's listings are about 1 kB.
MAX_SOURCE_CHARS = 256 * 1024
#: Largest number of physical lines accepted.
MAX_LINES = 20_000


@dataclass
class LogicalLine:
    """One logical line: text with comments removed and continuations joined.

    ``pos[i]`` is the ``(line, column)`` of ``text[i]``; ``pos[len(text)]`` is the position
    just after the text, used for "got end of line" errors.
    """

    text: str
    pos: list[tuple[int, int]]

    @property
    def line(self) -> int:
        return self.pos[0][0]

    def at(self, index: int) -> tuple[int, int]:
        return self.pos[min(max(index, 0), len(self.pos) - 1)]


def check_size(file: str, text: str) -> None:
    """Refuse text that is not a string or is too large, before any parsing work."""
    if not isinstance(text, str):
        raise ScriptError(file, 1, 1, f"script text must be a string, got {type(text).__name__}")
    if len(text) > MAX_SOURCE_CHARS:
        raise ScriptError(
            file, 1, 1, f"script is {len(text)} characters; the limit is {MAX_SOURCE_CHARS}"
        )
    lines = text.count("\n") + 1
    if lines > MAX_LINES:
        raise ScriptError(file, 1, 1, f"script has {lines} lines; the limit is {MAX_LINES}")


def strip_comment(line: str, marker: str) -> str:
    """Text of ``line`` before the comment ``marker``."""
    cut = line.find(marker)
    return line if cut < 0 else line[:cut]


def logical_lines(file: str, text: str, marker: str, errors: ErrorList) -> list[LogicalLine]:
    """Split ``text`` into non-blank logical lines.

    Comments are removed first, then a line whose remaining text ends in ``\\`` is joined
    to the next physical line (the backslash becomes a space). A continuation on the last
    line is recorded in ``errors``.
    """
    check_size(file, text)
    out: list[LogicalLine] = []
    buf: list[str] = []
    pos: list[tuple[int, int]] = []
    physical = text.splitlines()
    for number, raw in enumerate(physical, start=1):
        body = strip_comment(raw, marker).rstrip()
        continued = body.endswith("\\")
        for col, ch in enumerate(body, start=1):
            buf.append(" " if (continued and col == len(body)) else ch)
            pos.append((number, col))
        if continued:
            continue
        if buf and "".join(buf).strip():
            pos.append((number, len(body) + 1))
            out.append(LogicalLine("".join(buf), pos))
        buf, pos = [], []
    if buf:
        line, col = pos[-1]
        errors.add(
            ScriptError(file, line, col, "a trailing '\\' continues past the end of the file",
                        expected="another line after '\\'")
        )
    return out
