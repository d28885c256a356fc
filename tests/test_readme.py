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


# -- "Two cells on one machine": the README's commands, run (issue 24, point 4) -------------
def _two_cells_commands() -> list[str]:
    """The shell block of the README's "Two cells on one machine" section, line by line."""
    section = README[README.index("## Two cells on one machine"):]
    section = section[:section.index("\n## ", 1)]
    block = section[section.index("```sh\n") + 6:]
    return [line.strip() for line in block[:block.index("```")].splitlines() if line.strip()]


def test_the_two_cells_section_says_each_cell_has_its_own_state():
    section = README[README.index("## Two cells on one machine"):]
    section = section[:section.index("\n## ", 1)]
    for words in ("--name NAME", "--state FILE", "$XDG_STATE_HOME/testcell/<cell>/tuning.json",
                  "-- file.log"):
        assert words in section, words
    up1, up2, player = _two_cells_commands()
    assert up1.startswith("testcell up ") and up2.startswith("testcell up ")
    assert player.startswith("python -m can.player ") and player.endswith(" -- file.log")


def test_the_default_state_folder_is_per_cell(monkeypatch, tmp_path):
    from cell.app.tuning import cell_key, default_path

    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    a = default_path("large-diesel", "udp_multicast:239.74.163.3:43114", 8001)
    assert a == tmp_path / "testcell" / "large-diesel_udp_multicast-239.74.163.3-43114_8001" / \
        "tuning.json"
    assert f"{a.parent.name}/tuning.json" in README.replace("\n", " ")  # as the README says
    others = {default_path("large-diesel", "udp_multicast:239.74.163.3:43114", 8002),
              default_path("large-diesel", "udp_multicast:239.74.163.4:43114", 8001),
              default_path("si-turbo", "udp_multicast:239.74.163.3:43114", 8001)}
    assert a not in others and len(others) == 3
    assert default_path("x", "y", 1, name="bench-3") == tmp_path / "testcell" / "bench-3" / \
        "tuning.json"
    assert cell_key("large-diesel", "socketcan:vcan0", 8000) == "large-diesel_socketcan-vcan0_8000"


def test_a_bad_cell_name_is_refused_by_name():
    import pytest

    from cell.core.errors import ConfigError
    from cell.core.settings import Settings

    for bad in ("../x", "a/b", "", ".hidden", "x" * 65):
        with pytest.raises(ConfigError, match="--name"):
            Settings.build({"name": bad}, environ={})
    assert Settings.build({"name": "bench-3"}, environ={}).name == "bench-3"


def test_the_readme_two_cells_commands_run_with_separate_tuning_files(tmp_path):
    """The README's three commands, on this test process's private groups and free ports,
    with default settings (no --state): each cell writes its own tuning file, and the
    can.player line (``--bus-kwargs port=... -- file.log``) reaches the first cell only."""
    import json
    import os
    import shlex
    import signal
    import socket
    import subprocess
    import sys
    import time
    import urllib.request

    import can
    import pytest

    from tests.helpers.buses import NOT_ROUTED, private_group, routed_over_loopback

    if not routed_over_loopback():
        pytest.skip(NOT_ROUTED)
    up1, up2, player = _two_cells_commands()
    group, port = private_group()

    def free_port() -> int:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            return s.getsockname()[1]

    api = [free_port(), free_port()]
    log = tmp_path / "file.log"
    with can.Logger(str(log)) as w:  # frames of an ID the cell does not know: counted by ID
        for k in range(50):
            w.on_message_received(can.Message(timestamp=k * 0.01, arbitration_id=0x7AB,
                                              is_extended_id=False, data=bytes(8)))

    def local(cmd: str) -> list[str]:
        """A README line on this process's group, ports and files."""
        cmd = (cmd.replace("239.74.163.3:43114", f"{group}:{port}")
               .replace("239.74.163.4:43115", f"{group}:{port + 1}")
               .replace("-c 239.74.163.3", f"-c {group}").replace("port=43114", f"port={port}")
               .replace("--port 8001", f"--port {api[0]}").replace("--port 8002", f"--port {api[1]}")
               .replace("file.log", str(log)))
        assert "239.74.163.3" not in cmd and "239.74.163.4" not in cmd, cmd
        argv = shlex.split(cmd)
        if argv[0] == "testcell":
            return [sys.executable, "-m", "cell", "--log-level", "WARNING", *argv[1:]]
        return [sys.executable, *argv[1:]]  # python -m can.player ...

    env = {**os.environ, "XDG_STATE_HOME": str(tmp_path / "state")}
    env.pop("TESTCELL_STATE", None)

    def call(method: str, url: str, body: dict | None = None):
        req = urllib.request.Request(url, data=json.dumps(body).encode() if body else None,
                                     method=method, headers={"content-type": "application/json"})
        with urllib.request.urlopen(req, timeout=5) as r:
            return json.loads(r.read())

    procs = []
    try:
        for i, cmd in enumerate((up1, up2)):
            out = open(tmp_path / f"up{i}.log", "w")
            procs.append(subprocess.Popen(local(cmd), env=env, stdout=out,
                                          stderr=subprocess.STDOUT, start_new_session=True))
        for i, p in enumerate(procs):
            end = time.monotonic() + 60
            while True:
                assert p.poll() is None, (tmp_path / f"up{i}.log").read_text()[-2000:]
                try:
                    call("GET", f"http://127.0.0.1:{api[i]}/health")
                    break
                except OSError:
                    assert time.monotonic() < end, "cell did not come up"
                    time.sleep(0.3)
        for i, kp in enumerate((0.011, 0.022)):
            r = call("PATCH", f"http://127.0.0.1:{api[i]}/controllers/PI_R", {"kp": kp})
            assert r["params"]["kp"] == kp
        files = sorted((tmp_path / "state" / "testcell").glob("*/tuning.json"))
        assert len(files) == 2, files
        kps = {f.parent.name: json.loads(f.read_text())["controllers"]["PI_R"]["kp"]
               for f in files}
        assert kps == {f"large-diesel_udp_multicast-{group}-{port}_{api[0]}": 0.011,
                       f"large-diesel_udp_multicast-{group}-{port + 1}_{api[1]}": 0.022}
        subprocess.run(local(player), check=True, timeout=60, stdin=subprocess.DEVNULL,
                       stdout=subprocess.DEVNULL, env=env)
        time.sleep(0.5)
        seen = [call("GET", f"http://127.0.0.1:{a}/health").get("unknown_ids", {}) for a in api]
        assert seen[0].get("0x7AB", 0) > 0 and "0x7AB" not in seen[1], seen
    finally:
        for p in procs:
            try:
                os.killpg(p.pid, signal.SIGTERM)
                p.wait(20)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                os.killpg(p.pid, signal.SIGKILL)
