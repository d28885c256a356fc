"""``pip install .`` installs the two top-level packages, ``cell`` and ``service``, and
nothing else; ``testcell --help`` works from the installed copy."""

from __future__ import annotations

import os
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "-q", "-w", str(out), str(ROOT)], check=True, capture_output=True, text=True,
                   timeout=300)
    (found,) = out.glob("testcell-*.whl")
    return found


def test_the_wheel_holds_cell_and_service_only(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert top == {"cell", "service"}
    # the DBC files, the shipped scripts, the estimators' tables and the page come along
    assert "cell/_dbc/testcell.dbc" in names
    assert "cell/scripts/shipped/kalman.fdv" in names
    assert any(n.startswith("cell/estimators/data/") and n.endswith(".json") for n in names)
    assert "service/static/index.html" in names
    entry = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    with zipfile.ZipFile(wheel) as z:
        points = z.read(entry).decode()
    assert "testcell = cell.app.cli:main" in points and "service.up" in points


@pytest.mark.slow
def test_pip_install_into_a_clean_venv_gives_a_working_testcell(wheel, tmp_path):
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    py = env_dir / "bin" / "python"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    subprocess.run([str(py), "-m", "pip", "install", "-q", str(wheel)], check=True, env=env,
                   capture_output=True, text=True, timeout=1200)
    site = subprocess.run([str(py), "-c", "import cell, service, sys; print(cell.__file__); "
                           "print(service.__file__)"], capture_output=True, text=True, env=env,
                          cwd=tmp_path, check=True).stdout.split()
    assert all(str(env_dir) in p for p in site), site  # the installed copy, not this tree
    r = subprocess.run([str(env_dir / "bin" / "testcell"), "--help"], capture_output=True,
                       text=True, env=env, cwd=tmp_path, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "up" in r.stdout and "replay" in r.stdout and "experiment" in r.stdout
    r = subprocess.run([str(env_dir / "bin" / "testcell"), "up", "--help"], capture_output=True,
                       text=True, env=env, cwd=tmp_path, timeout=120)
    assert r.returncode == 0 and "--osc-init" in r.stdout and "--no-controllers" in r.stdout
