#!/usr/bin/env bash
# Set up (.venv, install with test dependencies) and run the whole test suite.
# Extra arguments go to pytest. "No tests collected" is a failure, not a pass.
set -uo pipefail
source "$(dirname "$0")/_bootstrap.sh"
bootstrap "[test]" || exit 1
# The dashboard tests drive Debian's chromium; install it where we may (root with apt-get).
# Where it cannot be installed those tests skip and say why.
if [ ! -x /usr/bin/chromium ]; then
    bash scripts/setup-browser.sh --if-root || echo "test.sh: no chromium; the browser tests will skip" >&2
fi
.venv/bin/python -m pytest "$@"
rc=$?
if [ "$rc" = 5 ]; then
    echo "test.sh: pytest collected no tests; failing" >&2
    exit 1
fi
exit "$rc"
