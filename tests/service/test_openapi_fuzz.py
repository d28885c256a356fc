"""schemathesis against /openapi.json: generated requests to every operation get no 5xx, and
every response matches the schema the API publishes."""

import math
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

schemathesis = pytest.importorskip("schemathesis")

from schemathesis.checks import not_a_server_error  # noqa: E402
from schemathesis.specs.openapi.checks import (  # noqa: E402
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from cell.app.cli import build_runtime  # noqa: E402
from cell.app.cell import Cell  # noqa: E402
from cell.core.settings import Settings  # noqa: E402
from cell.app.tuning import TuningStore  # noqa: E402
from service.main import create_app  # noqa: E402


def _app():
    state = Path(tempfile.mkdtemp(prefix="testcell-schemathesis-")) / "tuning.json"
    store = TuningStore(state)
    settings = Settings.build({"engine": "large-diesel"}, environ={})
    rt, scripts = build_runtime(settings, store)
    db = rt.db
    t = 0.0
    while t < 30.0:
        rt.ingest(db.encode("EXH_BP", {"EXH_BP_L": 600.0 + 5 * math.sin(t),
                                        "EXH_BP_R": 650.0 + 5 * math.cos(t)}, t))
        t = round(t + 0.01, 6)
    rt.advance(30.0)
    return create_app(Cell(runtime=rt, bus="virtual:schemathesis", tuning=store,
                           scripts=scripts))


# the cell answers only to its own host names: 127.0.0.1, not schemathesis' "testserver"
schema = schemathesis.openapi.from_asgi("/openapi.json", _app(), headers={"Host": "127.0.0.1"})


@schema.parametrize()
@settings(max_examples=15, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
def test_api_never_errors_and_matches_its_schema(case):
    case.call_and_validate(base_url="http://127.0.0.1", checks=[not_a_server_error, status_code_conformance,
                                   content_type_conformance, response_schema_conformance])
