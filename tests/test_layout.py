"""The repository's shape: layout, docker-compose structure, CLI wiring, README commands."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


def test_top_level_layout():
    for name in ("pyproject.toml", "cell", "dbc", "service", "scripts", "tests", "docker-compose.yml"):
        assert (ROOT / name).exists(), name
    for script in ("run.sh", "test.sh", "setup-vcan.sh"):
        assert (ROOT / "scripts" / script).stat().st_mode & 0o111, f"{script} is not executable"


def test_docker_compose_structure():
    spec = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = spec["services"]
    assert set(services) == {"sim", "runtime"}
    for svc in services.values():
        assert svc["network_mode"] == "host"  # vcan0 lives in the host's network namespace
        assert "socketcan:vcan0" in svc["command"]
    assert services["sim"]["command"][0] == "sim"
    rt = services["runtime"]["command"]
    assert rt[0] == "up" and "--no-sim" in rt and "--port" in rt
    assert (ROOT / "Dockerfile").exists()


def _docker_engine() -> bool:
    return bool(shutil.which("docker")) and subprocess.run(
        ["docker", "info"], capture_output=True).returncode == 0


@pytest.mark.skipif(not _docker_engine(), reason="no Docker engine on this machine (the docker "
                    "client alone cannot validate or run docker-compose.yml)")
def test_docker_compose_config_validates():
    subprocess.run(["docker", "compose", "config", "-q"], cwd=ROOT, check=True)


def test_readme_gives_the_two_commands():
    text = (ROOT / "README.md").read_text()
    assert "scripts/run.sh" in text and "scripts/test.sh" in text
    assert "bash scripts/test.sh" in (ROOT / ".ci" / "run").read_text()


@pytest.mark.parametrize(
    "argv,needle",
    [
        (["up", "--port", "0"], "--port"),
        (["up", "--port", "http"], "--port"),
        (["up", "--speed", "-2"], "--speed"),
        (["up", "--duty", "sprint"], "--duty"),
        (["replay"], "LOG"),
        (["fly"], "COMMAND"),
    ],
)
def test_bad_cli_arguments_name_the_option(argv, needle):
    r = subprocess.run([sys.executable, "-m", "cell", *argv], capture_output=True, text=True)
    assert r.returncode == 2
    assert needle.lower() in r.stderr.lower()
    assert "Traceback" not in r.stderr


def test_bad_bus_is_one_line_naming_the_fix(tmp_path):
    r = subprocess.run([sys.executable, "-m", "cell", "up", "--bus", "socketcan:vcan9", "--no-sim",
                        "--state", str(tmp_path / "t.json"), "--port", "18999"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert "vcan9" in line and "setup-vcan.sh" in line
    r = subprocess.run([sys.executable, "-m", "cell", "up", "--bus", "nosuchbus", "--no-sim"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "unknown bus" in r.stderr and "Traceback" not in r.stderr


def test_a_listing_into_a_closed_pipe_ends_quietly():
    """``testcell experiment --list | head -1``: the reader leaves early; no traceback."""
    r, w = os.pipe()
    os.close(r)  # the reader is gone before the listing is written
    proc = subprocess.run([sys.executable, "-m", "cell", "experiment", "--list"], stdout=w,
                          stderr=subprocess.PIPE, text=True, timeout=60)
    os.close(w)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
