"""Shared fixtures and markers. The test process composes the cell as the command line does:
the cell's own parts and the plugins are registered before any test runs (:func:`cell.app.load`)."""

from pathlib import Path

import pytest

from cell import app
from cell.bus.dbc import load

app.load()

HERE = Path(__file__).resolve().parent

#: Test files that run long experiments, soaks or several processes: marked ``slow``, so
#: ``scripts/test.sh --fast`` skips them (each paper's numbers are still checked there on the
#: estimators' own tests; these reproduce the papers' runs end to end).
SLOW = (
    "cell/experiments/",
    "test_soak.py",
    "test_multiprocess.py",
    "test_bus_isolation.py",
    "test_golden_experiments.py",
)


def pytest_collection_modifyitems(config, items):
    for item in items:
        rel = Path(str(item.fspath)).resolve().relative_to(HERE).as_posix()
        if any(rel == s or (s.endswith("/") and rel.startswith(s)) for s in SLOW):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session")
def db():
    return load()
