"""``GET /families``: the block families the cell knows, and the dashboard built from them."""

from __future__ import annotations

from pathlib import Path

from tests.helpers.client import local_client

from cell.app.cell import Cell
from cell.core import registry
from cell.core.registry import BlockFamily
from cell.estimators.backpressure import native_filters
from cell.runtime.scheduler import Runtime
from service.main import create_app

STATIC = Path(__file__).resolve().parents[2] / "service" / "static"


def test_families_lists_every_registered_family_with_the_cells_blocks(db):
    c = Cell(runtime=Runtime(db, native_filters()))
    client = local_client(create_app(c))
    r = client.get("/families")
    assert r.status_code == 200
    fams = {f["name"]: f for f in r.json()}
    assert list(fams) == list(registry.FAMILIES)
    for name, fam in registry.FAMILIES.items():
        assert fams[name] == {"name": name, "section": fam.section, "description": fam.description,
                              "examples": [dict(e) for e in fam.examples], "blocks": c.names(name)}
    assert fams["filter"]["blocks"] == [b["name"] for b in client.get("/filters").json()]
    # a family with no block in this cell has no resource
    assert fams["controller"]["blocks"] == [] and client.get("/controllers").status_code == 404


def test_a_plugins_family_is_listed_and_gets_its_resource(db, monkeypatch):
    monkeypatch.setattr(registry, "FAMILIES", dict(registry.FAMILIES))
    registry.family(BlockFamily("probe", "probes", "test probes", ({"samples": 3},)))
    blocks = native_filters()
    blocks[0].family = "probe"
    client = local_client(create_app(Cell(runtime=Runtime(db, blocks))))
    probe = next(f for f in client.get("/families").json() if f["name"] == "probe")
    assert probe["section"] == "probes" and probe["blocks"] == [blocks[0].name]
    assert [b["name"] for b in client.get("/probes").json()] == [blocks[0].name]


def test_families_is_documented_in_the_openapi(db):
    spec = local_client(create_app(Cell(runtime=Runtime(db)))).get("/openapi.json").json()
    op = spec["paths"]["/families"]["get"]
    assert list(spec["paths"]["/families"]) == ["get"]  # read only
    schema = op["responses"]["200"]["content"]["application/json"]["schema"]
    assert schema["items"]["$ref"].endswith("/FamilyOut")
    fields = spec["components"]["schemas"]["FamilyOut"]["properties"]
    assert set(fields) == {"name", "section", "description", "examples", "blocks"}


def test_the_dashboard_asks_for_the_families_rather_than_naming_them():
    js = (STATIC / "dashboard.js").read_text()
    assert '"/families"' in js
    for section in ("filters", "controllers", "observers"):
        assert f'"{section}"' not in js, section
