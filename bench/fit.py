"""Time of `fit` (load + convergence point + statistics) on simulated Exp. 1 data
(10 participants x 8 conditions x 11 points), and its recovery of the true point.

Run: .venv/bin/python bench/fit.py [--seeds 5]
"""

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from steadytouch import fit as F
from steadytouch.participant import SimParticipant, write_rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    a = ap.parse_args()
    times, errs = [], []
    with tempfile.TemporaryDirectory() as d:
        for seed in range(1, a.seeds + 1):
            path = Path(d) / f"exp1-{seed}.csv"
            write_rows(path, SimParticipant(seed=seed).exp1_rows(10))
            F.fit(F.load(path))  # warm-up (imports)
            t = time.perf_counter()
            r = F.fit(F.load(path))
            times.append(time.perf_counter() - t)
            errs.append((r.x_star_ohm + 1670, (r.y_star_pc - 186000) / 1000))
    print(f"fit on 80 data sets x 11 points, {a.seeds} seeds: median {statistics.median(times) * 1000:.0f} ms, "
          f"max {max(times) * 1000:.0f} ms")
    print("recovery error (x* ohm, y* nC): " + ", ".join(f"({x:+.0f}, {y:+.1f})" for x, y in errs))


if __name__ == "__main__":
    main()
