#!/usr/bin/env bash
# Set up (.venv, install) and start the cell: simulator + runtime + HTTP API on :8000.
# Extra arguments go to `testcell up`, e.g. scripts/run.sh --duty transient --port 8080
set -euo pipefail
source "$(dirname "$0")/_bootstrap.sh"
bootstrap ""
exec .venv/bin/testcell up "$@"
