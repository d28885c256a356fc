"""Cost per cycle of seed 004's PUMA Kalman script, beside the same filter hand-written in
Python and filterpy's KalmanFilter, measured in one run.

Run: ``.venv/bin/python benchmarks/bench_scripts.py``. Goals: within 3x of the hand-written
filter, at least 10x faster than filterpy. The measurement lives in ``benchmarks.bench_formula``.
"""

from benchmarks.bench_formula import main

if __name__ == "__main__":
    main()
