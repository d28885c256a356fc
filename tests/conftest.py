import pytest

from cell.dbc import load


@pytest.fixture(scope="session")
def db():
    return load()
