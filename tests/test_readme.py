"""The README tells a new user how to reach the tools, warns of the long gain map, documents
isolation and security, and links the benchmarks, which exist."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_readme_says_how_to_reach_the_tools():
    assert "source .venv/bin/activate" in README
    for tool in (".venv/bin/testcell", ".venv/bin/cantools", ".venv/bin/python -m\ncan.player"):
        assert tool in README, tool


def test_readme_warns_that_the_gain_map_takes_minutes():
    i = README.index("`--gain-map` runs")
    assert "about 2 minutes" in README[i:i + 200]


def test_readme_documents_isolation_security_and_links_the_benchmarks():
    assert "## Two cells on one machine" in README and "udp_multicast:239.74.163.3:43114" in README
    assert "## Security" in README and "TESTCELL_TOKEN" in README and "413" in README
    assert "[BENCHMARKS.md](BENCHMARKS.md)" in README and (ROOT / "BENCHMARKS.md").exists()
    assert "scripts/soak.sh MINUTES" in README


def _fenced_commands() -> list[str]:
    """Every ``testcell ...`` command line in the README's shell blocks."""
    import re

    out, block = [], False
    for line in README.splitlines():
        if line.startswith("```"):
            block = line.strip() in ("```sh", "```bash", "```console")
            continue
        if block:
            cmd = line.split("#")[0].strip()
            cmd = re.sub(r"^(\.venv/bin/|\$ )", "", cmd)
            if cmd.startswith("testcell "):
                out.append(cmd)
    return out


def test_every_path_the_readme_names_exists():
    import re

    paths = set(re.findall(r"`((?:cell|service|tests|benchmarks|scripts|docs|dbc)/[\w./-]+)`", README))
    assert len(paths) > 40
    missing = sorted(p for p in paths if "<" not in p and not (ROOT / p.rstrip("/")).exists())
    assert missing == []


def test_every_module_the_readme_names_imports():
    import importlib
    import re

    names = {n for n in re.findall(r"`(cell(?:\.\w+)+)`", README) if not n.endswith(".py")}
    for name in sorted(names):
        parts = name.split(".")
        for i in range(len(parts), 1, -1):  # a module, or an attribute of one
            try:
                obj = importlib.import_module(".".join(parts[:i]))
            except ModuleNotFoundError:
                continue
            for attr in parts[i:]:
                obj = getattr(obj, attr)
            break
        else:
            raise AssertionError(f"README names {name}, which does not import")


def test_every_testcell_command_in_the_readme_parses():
    """Each ``testcell ...`` example names a command and options the command line has."""
    import shlex

    from cell.app.cli import build_parser

    commands = _fenced_commands()
    assert len(commands) > 10
    parser = build_parser()
    for cmd in commands:
        argv = shlex.split(cmd)[1:]
        argv = [a for a in argv if not a.startswith(("$(", "&", "["))]  # [--optional] shown
        try:
            parser.parse_args(argv)
        except SystemExit as exc:
            raise AssertionError(f"README command does not parse: {cmd}") from exc


def test_the_architecture_and_extending_docs_exist_and_name_real_paths():
    import re

    for name in ("architecture.md", "extending.md"):
        text = (ROOT / "docs" / name).read_text()
        assert f"docs/{name}" in README  # the README's layout section points to both
        paths = set(re.findall(r"`((?:cell|service|tests|benchmarks|scripts|docs|dbc)/[\w./-]+)`", text))
        missing = sorted(p for p in paths if not (ROOT / p.rstrip("/")).exists())
        assert paths and missing == [], (name, missing)
