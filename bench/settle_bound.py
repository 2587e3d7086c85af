"""Can any controller settle within 2 pulses after the gel drop? An ambiguity test.

Run: .venv/bin/python bench/settle_bound.py [--skins 3000] [--seed 1]

A controller that keeps the paper's target (pulses on the mE curve) and
measures one Rp per pulse knows, when it chooses pulse 2 after a step, three
numbers about the skin: Rp at calibration, Rp of pulse 0 (the old pulse on the
changed skin) and Rp of pulse 1 (its own choice). This script draws skins of
the electrode model (firmware/sim_electrode.py) with the plausible parameters
of docs/simulation.md -- beta 0.5-0.9, c 2-6 nF/cm^2, Rs 0.3-1.5 kohm -- and
solves for each its rho_ref so that it reads exactly like the default person at
calibration (1 mA, 1000 us), and the hydration h so that pulse 0 after the
drop reads exactly like the default skin with gel (h = 0.3). All of them are
therefore the same to the controller after pulse 0.

For every pulse-1 charge Q1 a controller could choose (a grid along the mE
curve), it then looks for two skins whose pulse-1 readings agree to 1 ohm but
whose pulse-2 charges that settle (|mQ - target| < 25 fC/ohm, or the pulse's
resolution) do not overlap: no pulse 2 settles both, so no controller can
guarantee 2 pulses on this family, whatever its rule. It prints, per Q1, the
widest such gap (in % of mQ) or "-" where it found none.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT / "bench"), str(ROOT / "shared"), str(ROOT / "firmware")]
import controllers as bench  # noqa: E402

I0, T0 = 1000, 1000
ME = I0 * I0 * T0
AREA = 5.6


def skin(beta, c, rs, rho_ref, h=1.0):
    """An electrode of firmware/sim_electrode.py with these parameters."""
    e = bench.Electrode(area_cm2=AREA, rs_kohm=rs, rho_ref=rho_ref, beta=beta, c_nf_cm2=c)
    e.h = h
    return e


def _solve(f, lo, hi):
    """Root of an increasing-or-decreasing f on [lo, hi] by bisection (log scale)."""
    a = f(lo)
    if (a > 0) == (f(hi) > 0):
        return None
    for _ in range(60):
        m = math.sqrt(lo * hi)
        if (f(m) > 0) == (a > 0):
            lo = m
        else:
            hi = m
    return math.sqrt(lo * hi)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skins", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    d = bench.Electrode()
    cal_ohm = d.rp_kohm(I0, T0) * 1000
    d.h = 0.3
    pulse0_ohm = d.rp_kohm(I0, T0) * 1000
    mq = (I0 * T0 - bench.Y) / (round(cal_ohm) - bench.X)  # pC/ohm
    thr = 25e-3  # pC/ohm

    rng = np.random.default_rng(a.seed)
    skins = []
    for beta, c, rs in zip(rng.uniform(0.5, 0.9, a.skins), rng.uniform(2, 6, a.skins), rng.uniform(0.3, 1.5, a.skins)):
        rho = _solve(lambda x: bench._rp_on(skin(beta, c, rs, x), I0, T0) - cal_ohm, 20, 2000)
        if rho is None:
            continue
        h = _solve(lambda x: bench._rp_on(skin(beta, c, rs, rho, x), I0, T0) - pulse0_ohm, 0.01, 1.0)
        if h is None:
            continue
        p = skin(beta, c, rs, rho, h)

        def on_curve(q, p=p):  # Rp of the mE-curve pulse of charge q
            return bench._rp_on(p, ME / q, q * q / ME)

        def err(q, on_curve=on_curve):  # mQ(q) - target, pC/ohm
            return (q - bench.Y) / (on_curve(q) - bench.X) - mq

        q_star = _solve(lambda q: bench.Y + mq * (on_curve(q) - bench.X) - q, 1e5, 1e6)
        if q_star is None:
            continue
        # the pulse-2 charges that settle: |mQ - target| below the threshold or the
        # pulse's own resolution (the bench's rule)
        i_s, t_s = ME / q_star, q_star * q_star / ME
        tol = max(thr, (0.5 * i_s + 0.5 * t_s) / (on_curve(q_star) - bench.X))
        lo = _solve(lambda q: err(q) + tol, q_star / 2, q_star)
        hi = _solve(lambda q: err(q) - tol, q_star, q_star * 2)
        if lo is None or hi is None:
            continue
        skins.append((p, on_curve, q_star, lo, hi))
    print(f"{len(skins)} skins that read like the default person at calibration and at pulse 0 "
          f"(Rp {cal_ohm:.0f} and {pulse0_ohm:.0f} ohm); their settled charge Q* spans "
          f"{min(s[2] for s in skins) / 1e3:.0f}-{max(s[2] for s in skins) / 1e3:.0f} nC")
    print()
    print("| pulse 1 charge Q1 (nC) | widest gap between the settling pulse-2 charges of two skins "
          "that read alike at pulse 1 (% of mQ) |")
    print("|---|---|")
    ok_everywhere = True
    for q1 in np.geomspace(min(s[2] for s in skins) * 0.8, 1e6, 25):
        reads = np.array([s[1](q1) for s in skins])
        order = np.argsort(reads)
        best = 0.0
        for j in range(len(order)):  # pairs whose readings agree to 1 ohm
            for k in range(j + 1, len(order)):
                sa, sb = order[j], order[k]
                if reads[sb] - reads[sa] > 1.0:
                    break
                a_, b_ = skins[sa], skins[sb]
                gap = max(a_[3], b_[3]) - min(a_[4], b_[4])  # > 0: the intervals do not overlap
                if gap > 0:
                    best = max(best, gap / max(a_[2], b_[2]) * 100)
        ok_everywhere &= best > 0
        print(f"| {q1 / 1e3:.0f} | {best:.2f} |" if best > 0 else f"| {q1 / 1e3:.0f} | - |")
    print()
    print("no pulse-1 choice on this grid lets every skin settle at pulse 2" if ok_everywhere
          else "some pulse-1 choices left no such pair on this sample")


if __name__ == "__main__":
    main()
