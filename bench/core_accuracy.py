"""Worst-case error of the integer core against the exact law, and the largest
intermediate value, over random draws of the envelope.

Run: .venv/bin/python bench/core_accuracy.py [--n 50000] [--seed 1]
Envelope: i0 100-10000 uA, t0 50-2000 us, Rp and Rp0 500 ohm-200 kohm,
x* -20 kohm-0, 0 <= y* < i0*t0; limits wide (1..20000 uA, 1..8000 us, 2**25 pC)
so that the law is mostly unbounded ("interior").
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "shared"))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "bench"))

import sensation_core as sc  # noqa: E402
from core_checked import load_core  # noqa: E402
from steadytouch.reference import Calibration, Limits, exact_step  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=50000)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    mods, track = load_core()  # sensation_core and the modules it imports, all checked
    core = mods["sensation_core"]
    rng = np.random.default_rng(a.seed)
    lim = Limits(1, sc.I_LIMIT_UA, 1, sc.T_LIMIT_US, sc.Q_LIMIT_PC)
    worst_i = worst_t = 0.0
    worst_case = None
    interior = 0
    t0_ = time.perf_counter()
    for k in range(a.n):
        i0 = int(rng.integers(100, 10001))
        t0 = int(rng.integers(50, 2001))
        rp0, rp = (int(v) for v in np.exp(rng.uniform(np.log(500), np.log(200000), 2)).round())
        x = int(rng.integers(-20000, 1))
        y = int(rng.integers(0, i0 * t0)) if k % 3 else [0, i0 * t0 - 1, i0 * t0 // 2][k % 9 // 3]
        c = core.Controller(lim.i_min_ua, lim.i_max_ua, lim.t_min_us, lim.t_max_us, lim.q_max_pc)
        c.calibrate(i0, t0, rp0, x, y)
        c.update(rp)
        ex = exact_step(lim, Calibration(i0, t0, rp0, x, y), rp)
        if ex.status == 0 and c.status == 0:
            interior += 1
            ei, et = abs(c.i_ua - ex.i_ua), abs(c.t_us - ex.t_us)
            if ei > worst_i or et > worst_t:
                worst_case = (i0, t0, rp0, x, y, rp)
            worst_i, worst_t = max(worst_i, float(ei)), max(worst_t, float(et))
    dt = time.perf_counter() - t0_
    print(f"cases {a.n} (seed {a.seed}), interior {interior}, {dt:.1f} s")
    print(f"worst |I - I_exact| = {worst_i:.4f} uA, worst |T - T_exact| = {worst_t:.4f} us (interior)")
    print(f"largest |intermediate| = {track.max_abs} = 2**{np.log2(track.max_abs):.3f} at {track.where}"
          f" ({track.checks} checked results)")
    print(f"last worst case (i0, t0, rp0, x*, y*, rp) = {worst_case}")


if __name__ == "__main__":
    main()
