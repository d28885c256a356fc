"""The composition root: the command line, the cell's own parts registered, settings in use,
the tuning store, the live loop and the :class:`~cell.app.cell.Cell` façade the HTTP
service is handed. Nothing in ``cell`` below this package imports it."""

from __future__ import annotations

from collections.abc import Sequence


def load(extra: Sequence[str] = ()) -> list[str]:
    """Register the cell's own parts (:mod:`cell.app.builtin`), then every plugin; returns
    the plugin names. Safe to call again."""
    from cell.app import builtin  # noqa: F401  (registers on import)
    from cell.core import registry

    return registry.load_plugins(extra)
