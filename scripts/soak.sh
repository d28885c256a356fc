#!/usr/bin/env bash
# Soak the cell for MINUTES (default 2): simulator, runtime and API under >= 5000 frames/s,
# each engine profile in turn; reports frames lost, tick overruns, p99 latency and RSS.
set -euo pipefail
source "$(dirname "$0")/_bootstrap.sh"
bootstrap "[test]" || exit 1
PYTHONPATH="$PWD" .venv/bin/python benchmarks/soak.py "${1:-2}"
