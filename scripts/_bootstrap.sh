# Sourced by run.sh and test.sh: create .venv if missing and install testcell into it.
# Usage: bootstrap "" (runtime only) or bootstrap "[test]" (with the test dependencies).
bootstrap() {
    local extras="$1"
    cd "$(dirname "${BASH_SOURCE[0]}")/.."
    local py="${PYTHON:-python3}"
    if [ ! -x .venv/bin/python ]; then
        echo "testcell: creating .venv with $($py --version)" >&2
        "$py" -m venv .venv
    fi
    local stamp=".venv/.testcell-installed$extras"
    if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
        echo "testcell: installing into .venv (pip install -e .$extras)" >&2
        .venv/bin/python -m pip install -q -e ".$extras"
        touch "$stamp"
    fi
    # Keep the cell's udp_multicast group on this machine when we may (see setup-multicast.sh).
    bash scripts/setup-multicast.sh --if-root || true
}
