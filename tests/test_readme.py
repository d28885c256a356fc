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
