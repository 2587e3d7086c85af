"""How well can pulse 2 after a step be placed from two points of the new skin?

Run: .venv/bin/python bench/two_point.py

Settling within 2 pulses means pulse 2 lands within 25 fC/ohm (0.1 % of mQ) of
the Q-Rp line on the changed skin. A controller that measures one Rp per pulse
knows, when it chooses pulse 2, two points of the new skin along the mE curve:
pulse 0 (the old pulse, measured on the new skin) and pulse 1 (MODE_FAST's first
step, taken here by the real core). This script fits five two-parameter local
models of Rp(Q) through those two points, solves the law on each model
(Q = y* + mQ (Rp(Q) - x*)), and prints the mQ error a pulse of that charge
actually has on the simulated skin ("-": the model has no solution near the
law's point). The oracle (bench/controllers.py) gives 1 pulse; this shows why
local models of two points do not give 2.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT / "bench"), str(ROOT / "shared"), str(ROOT / "firmware")]
import controllers as bench  # noqa: E402
import sensation_core as sc  # noqa: E402

# model: coordinates (u(Q), v(Rp)) in which Rp(Q) is taken to be a straight line
MODELS = {
    "linear": (lambda q: q, lambda r: r, lambda v: v),
    "log-log": (math.log, math.log, math.exp),
    "semi-log": (math.log, lambda r: r, lambda v: v),
    "Rp vs I": (lambda q: 1 / q, lambda r: r, lambda v: v),
    "log Rp vs I": (lambda q: 1 / q, math.log, math.exp),
}


def pulse2_errors(i0, event):
    """Q1 / Q* of FAST's pulse 1, the mQ error (% of mQ) of pulse 2 for each model,
    and whether the law's point itself needs T > t_max."""
    e = bench.Electrode()
    c = sc.Controller(*bench.LIMITS)
    c.calibrate(i0, 1000, round(e.rp_kohm(i0, 1000) * 1000), bench.X, bench.Y)
    c.set_mode(sc.MODE_FAST)
    mq = bench.mq_of(c)
    me = i0 * i0 * 1000
    pts = []
    for k in range(event.pulse + 2):
        if k == event.pulse:
            e.h = event.h
        q, rp = c.i_ua * c.t_us, round(e.rp_kohm(c.i_ua, c.t_us) * 1000)
        if k >= event.pulse:
            pts.append((q, rp))
        c.update(rp)
    q_star = bench.oracle_charge(c, e, pts[-1][0])
    (q0, r0), (q1, r1) = pts
    out = {}
    for name, (u, v, v_inv) in MODELS.items():
        slope = (v(r1) - v(r0)) / (u(q1) - u(q0))

        def f(lq):
            try:
                return bench.Y + mq * (v_inv(v(r1) + slope * (u(math.exp(lq)) - u(q1))) - bench.X) - math.exp(lq)
            except (ValueError, OverflowError):  # outside the model's domain
                return math.nan

        lq2 = bench.nearest_root(f, math.log(q1), step=0.03, n=60)  # the root nearest pulse 1
        if lq2 is None:
            out[name] = None
            continue
        q2 = math.exp(lq2)
        rp2 = bench._rp_on(e, me / q2, q2 * q2 / me)
        out[name] = ((q2 - bench.Y) / (rp2 - bench.X) - mq) / mq * 100
    return q1 / q_star, out, q_star * q_star / me > c.t_max_us


def main():
    print("| step | FAST pulse 1: Q1/Q* | " + " | ".join(MODELS) + " |")
    print("|---|---|" + "---|" * len(MODELS))
    within = dict.fromkeys(MODELS, 0)
    n = 0
    for i0 in (700, 1000, 2000):
        for d in (-30, -20, -10, 10, 20):
            if bench.Electrode().rp_kohm(i0, 1000) + d < 3:
                continue
            events, _ = bench.step_events(i0, d)
            ratio, errs, beyond = pulse2_errors(i0, events[0])
            if beyond:  # the law's pulse is at the duration ceiling: not a point on the mE curve
                print(f"| {d:+d} kohm @ {i0} uA | (the law's point is at the duration ceiling, off the mE curve) |" + " |" * len(MODELS))
                continue
            n += 1
            cells = []
            for name in MODELS:
                x = errs[name]
                cells.append("-" if x is None else f"{x:+.2f} %")
                if x is not None and abs(x) < 0.1:
                    within[name] += 1
            print(f"| {d:+d} kohm @ {i0} uA | {ratio:.3f} | " + " | ".join(cells) + " |")
    print()
    print(f"pulse 2 within 0.1 % of mQ, of {n} steps: " + ", ".join(f"{k} {v}" for k, v in within.items()))


if __name__ == "__main__":
    main()
