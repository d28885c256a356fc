"""The cell's own parts, registered like a plugin's (see :mod:`cell.registry`)."""

from __future__ import annotations
