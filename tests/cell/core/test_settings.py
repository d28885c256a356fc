"""One settings object per process (cell/core/settings.py): CLI over environment, unknown keys refused,
and every simulator option handed from ``up`` to the simulator process."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from cell.app import cli
from service import up
from tests.helpers.buses import private_bus
from cell import sim
from cell.core.errors import ConfigError
from cell.core.settings import Settings


def test_defaults_and_the_simulator_defaults():
    s = Settings.build({}, environ={})
    assert (s.engine, s.duty, s.seed, s.speed, s.port) == (None, None, 0, 1.0, 8000)
    r = s.for_simulator()
    assert (r.engine, r.duty) == ("large-diesel", "rated")


def test_unknown_setting_is_refused_by_name():
    with pytest.raises(ConfigError, match="unknown setting 'bp_limt'"):
        Settings.build({"bp_limt": 900}, environ={})
    with pytest.raises(ConfigError, match="TESTCELL_BP_LIMT: unknown setting 'bp_limt'"):
        Settings.build({}, environ={"TESTCELL_BP_LIMT": "900"})


def test_environment_gives_settings_and_the_command_line_wins():
    env = {"TESTCELL_BP_LIMIT": "900", "TESTCELL_SEED": "4", "TESTCELL_DBC": "a.dbc,b.dbc",
           "TESTCELL_NO_SIM": "yes", "PATH": "/bin"}
    s = Settings.build({"seed": 7}, environ=env)
    assert s.plant == {"bp_limit": 900.0} and s.seed == 7 and s.no_sim is True
    assert s.dbc == ("a.dbc", "b.dbc")
    with pytest.raises(ConfigError, match="TESTCELL_SEED='four'"):
        Settings.build({}, environ={"TESTCELL_SEED": "four"})


@pytest.mark.parametrize("given, needle", [
    ({"speed": 0.0}, "--speed"),
    ({"duration": -1.0}, "--duration"),
    ({"bp_limit": -3.0}, "--bp-limit"),
    ({"valve": 120.0}, "--valve"),
    ({"engine": "steam"}, "--engine 'steam'"),
    ({"engine": "large-diesel", "duty": "sprint"}, "--duty 'sprint'"),
    ({"log_level": "LOUD"}, "--log-level"),
])
def test_bad_values_name_the_option(given, needle):
    with pytest.raises(ConfigError, match=needle):
        Settings.build(given, environ={})


def test_up_hands_the_simulator_every_simulator_option(monkeypatch):
    """The command ``up`` starts the simulator with parses back to the same simulator settings,
    and the simulator it builds has the limit (seed 004's protection) it was given."""
    started = []

    class FakePopen:
        def __init__(self, cmd):
            started.append(cmd)

    monkeypatch.setattr(up.subprocess, "Popen", FakePopen)
    argv = ["up", "--bp-limit", "900", "--valve", "35", "--seed", "3", "--speed", "4",
            "--duty", "transient", "--duration", "60"]
    args = cli.build_parser().parse_args(argv)
    settings = Settings.from_args(args, environ={}).for_simulator()
    up._start_sim_process(settings, private_bus())  # argv only: no bus is opened
    cmd = started[0]
    if cmd[0] == "/bin/sh":  # up's wrapper that keeps Ctrl-C from the simulator: sh -c ... sh CMD
        cmd = cmd[4:]
    assert "--parent-pid" in cmd
    assert cmd[:3] == [sys.executable, "-m", "cell"] and "sim" in cmd
    child = cli.build_parser().parse_args(cmd[3:])
    got = Settings.from_args(child, environ={})
    for key in ("engine", "duty", "seed", "speed", "duration", "plant"):
        assert getattr(got, key) == getattr(settings, key), key
    assert got.bus == private_bus()
    banks = sim.build(got).plant.plant("exhaust")
    assert banks.bp_limit == 900.0 and banks.valves["L"].position == 35.0


def test_cli_refuses_an_unknown_environment_setting(tmp_path):
    r = subprocess.run([sys.executable, "-m", "cell", "sim", "--out", str(tmp_path / "x.log"),
                        "--duration", "0.1"], capture_output=True, text=True, timeout=60,
                       env={"PATH": "/usr/bin:/bin", "TESTCELL_BP_LIMT": "900"})
    assert r.returncode == 2
    assert "TESTCELL_BP_LIMT" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "x.log").exists()


def test_an_engine_asked_of_an_empty_registry_says_who_registers(monkeypatch):
    """Library code below the composition root gets a clear word, not an empty list."""
    from cell.core import registry

    monkeypatch.setattr(registry, "ENGINES", {})
    with pytest.raises(ConfigError, match=r"no engine profile is registered.*cell\.app\.load"):
        registry.engine_profile("large-diesel")


@pytest.mark.parametrize("argv,env,needle", [
    (["replay", "x.log", "--out", "x.csv", "--bias-design", "/no/such/design.json"], {},
     "bias design /no/such/design.json: no such file"),
    (["replay", "x.log", "--out", "x.csv"], {"TESTCELL_NO_CONTROLLERS": "maybe"},
     "TESTCELL_NO_CONTROLLERS='maybe': not a yes/no value"),
    (["replay", "x.log", "--out", "x.csv", "--osc-init", "abc"], {}, "--osc-init: invalid float"),
    (["replay", "x.log", "--out", "x.csv", "--osc-init", "9"], {}, "--osc-init must be in (0.05, 4]"),
])
def test_a_block_sets_own_option_refuses_bad_values_by_name(argv, env, needle, tmp_path):
    """Bad values of the block sets' options stop before any work, naming the option."""
    environ = {k: v for k, v in os.environ.items() if not k.startswith("TESTCELL_")}
    r = subprocess.run([sys.executable, "-m", "cell", *argv], capture_output=True, text=True,
                       env={**environ, **env}, cwd=tmp_path, timeout=120)
    assert r.returncode == 2 and needle in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "x.csv").exists()
