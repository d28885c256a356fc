#!/usr/bin/env bash
# Set up (.venv, install with test dependencies) and run the whole test suite on two
# pytest-xdist workers (each test file on one worker, so its recordings are made once).
#   scripts/test.sh            every test (CI runs this)
#   scripts/test.sh --fast     skip the tests marked slow (long experiments, soak, processes)
# Other arguments go to pytest (e.g. a test file, -k NAME, -n 0 for one process).
# "No tests collected" is a failure, not a pass.
set -uo pipefail
source "$(dirname "$0")/_bootstrap.sh"
bootstrap "[test]" || exit 1
# The dashboard tests drive Debian's chromium; install it where we may (root with apt-get).
# Where it cannot be installed those tests skip and say why.
if [ ! -x /usr/bin/chromium ]; then
    bash scripts/setup-browser.sh --if-root || echo "test.sh: no chromium; the browser tests will skip" >&2
fi
args=()
fast=0
for a in "$@"; do
    if [ "$a" = "--fast" ]; then fast=1; else args+=("$a"); fi
done
if [ "$fast" = 1 ]; then
    args=(-m "not slow" "${args[@]}")
fi
.venv/bin/python -m pytest -n "${TESTCELL_TEST_WORKERS:-2}" --dist loadfile "${args[@]}"
rc=$?
if [ "$rc" = 5 ]; then
    echo "test.sh: pytest collected no tests; failing" >&2
    exit 1
fi
exit "$rc"
