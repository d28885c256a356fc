"""The layers of ``cell/`` (docs/architecture.md), read from every module's imports with ``ast``.

A module may import its own subpackage and the layers below it, never a layer above it nor
a sibling of its own rank; ``cell`` never imports ``service``. Every import counts: at module
level, inside functions, and under ``TYPE_CHECKING``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: The layers of ``cell/``, bottom first; subpackages in one tuple share a rank and do not
#: import each other.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("core",),
    ("bus",),
    ("plant",),
    ("runtime",),
    ("sim",),
    ("estimators", "control", "scripts"),
    ("analysis",),
    ("design",),
    ("experiments",),
    ("app",),
)
RANK = {name: i for i, names in enumerate(LAYERS) for name in names}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path, source: str | None = None) -> list[tuple[int, str]]:
    """``(line, module)`` of every import in the file, relative ones made absolute."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    text = path.read_text() if source is None else source
    for node in ast.walk(ast.parse(text, str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out.append((node.lineno, target))
            # ``from cell import app`` imports the subpackage ``cell.app``
            out += [(node.lineno, f"{target}.{a.name}") for a in node.names
                    if (ROOT / Path(*target.split("."), a.name)).is_dir()
                    or (ROOT / Path(*target.split("."), a.name + ".py")).is_file()]
    return out


def subpackage(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "cell" and len(parts) > 1 else None


def test_every_subpackage_of_cell_has_a_layer():
    found = {p.name for p in (ROOT / "cell").iterdir() if (p / "__init__.py").is_file()}
    assert found == set(RANK), "add the new subpackage to LAYERS and docs/architecture.md"
    flat = sorted(p.name for p in (ROOT / "cell").glob("*.py")
                  if p.name not in ("__init__.py", "__main__.py"))
    assert not flat, f"modules directly under cell/: {flat}; put each in its layer"


def violations(files: list[Path], sources: dict[Path, str] | None = None) -> list[str]:
    found = []
    for path in files:
        here = subpackage(module_name(path))
        for line, target in imports_of(path, (sources or {}).get(path)):
            if target.split(".")[0] == "service" and module_name(path).startswith("cell"):
                found.append(f"{path.relative_to(ROOT)}:{line}: cell imports {target}")
                continue
            there = subpackage(target)
            if here not in RANK or there not in RANK or there == here:
                continue
            if RANK[there] >= RANK[here]:
                kind = "a sibling" if RANK[there] == RANK[here] else "a layer above"
                found.append(f"{path.relative_to(ROOT)}:{line}: {here} imports {target} ({kind})")
    return found


def test_no_upward_or_sibling_import():
    files = sorted((ROOT / "cell").rglob("*.py"))
    assert len(files) > 50
    assert violations(files) == []


def test_no_cycle_between_subpackages():
    """The subpackage graph drawn from the imports has no cycle (the ranks above already
    forbid one; this reads the graph itself, so it holds for any order of LAYERS)."""
    graph: dict[str, set[str]] = {}
    for path in (ROOT / "cell").rglob("*.py"):
        here = subpackage(module_name(path))
        for _, target in imports_of(path):
            there = subpackage(target)
            if here and there and there != here:
                graph.setdefault(here, set()).add(there)
    state: dict[str, int] = {}

    def visit(node: str, trail: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                pytest.fail("cycle between subpackages: " + " -> ".join([*trail, node, nxt]))
            if nxt not in state:
                visit(nxt, [*trail, node])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [])


def test_the_checker_catches_upward_sibling_and_service_imports():
    """The checker itself, on sources written here: each bad import is reported with its line."""
    probe = ROOT / "cell" / "runtime" / "_layer_probe.py"
    sources = {probe: "import os\nfrom cell.app.cli import main\n\n\ndef f():\n"
                      "    from cell.scripts import expr\n    import service.main\n"
                      "    from cell.core import registry\n    from . import blocks\n"}
    assert violations([probe], sources) == [
        "cell/runtime/_layer_probe.py:2: runtime imports cell.app.cli (a layer above)",
        "cell/runtime/_layer_probe.py:6: runtime imports cell.scripts (a layer above)",
        "cell/runtime/_layer_probe.py:6: runtime imports cell.scripts.expr (a layer above)",
        "cell/runtime/_layer_probe.py:7: cell imports service.main",
    ]
    sibling = ROOT / "cell" / "estimators" / "_layer_probe.py"
    assert violations([sibling], {sibling: "from cell.control.backpressure import controllers\n"}) == [
        "cell/estimators/_layer_probe.py:1: estimators imports cell.control.backpressure (a sibling)"]


def test_service_imports_nothing_private_of_the_runtime():
    """The HTTP service reaches the cell through its façade, :class:`cell.app.cell.Cell`: no
    ``x._private`` of anything but its own objects."""
    bad = []
    for path in sorted((ROOT / "service").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr.startswith("_") \
                    and not node.attr.startswith("__") \
                    and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: .{node.attr}")
    assert bad == []
