#!/usr/bin/env bash
# Run the benchmark suite and write BENCHMARKS.md (ratios measured side by side, with the
# machine). Arguments go to benchmarks/bench_suite.py (--quick for shorter runs).
set -euo pipefail
source "$(dirname "$0")/_bootstrap.sh"
bootstrap "[test]" || exit 1
PYTHONPATH="$PWD" .venv/bin/python benchmarks/bench_suite.py "$@"
