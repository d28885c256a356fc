#!/usr/bin/env bash
# Soak the cell for MINUTES (default 2, over all engines): each engine profile in turn at
# --speed 20 (crank streams on), /channels polled at 20 Hz and a WebSocket on /stream; reports
# frames lost (sent by the simulator vs counted by the runtime), tick overruns, the stream's
# p50/p99 lag and RSS. Options go to benchmarks/soak.py (--speed, --group, --port, --engine).
set -euo pipefail
source "$(dirname "$0")/_bootstrap.sh"
bootstrap "[test]" || exit 1
PYTHONPATH="$PWD" .venv/bin/python benchmarks/soak.py "${@:-2}"
