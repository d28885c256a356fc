"""Shared fixtures. The test process composes the cell as the command line does: the cell's
own parts and the plugins are registered before any test runs (:func:`cell.app.load`)."""

import pytest

from cell import app
from cell.bus.dbc import load

app.load()


@pytest.fixture(scope="session")
def db():
    return load()
