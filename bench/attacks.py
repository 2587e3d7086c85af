"""The attack families the reviews of MODE_FAST's skin rules run, as a command: felt surges and dips on unseen
electrodes of the realistic board, case by case, to compare two versions of the core on the same draws.

Run: .venv/bin/python bench/attacks.py FAMILY [--seeds 31,7] [--electrodes 15] [--supervisor] [--no-tau]
     [--exact NOISE] [--out cases.jsonl] [--compare other.jsonl]

Families (MODE_FAST with the averaged 30-sweep fit, `bench/controllers.py`'s run; felt mQ relative to target):
- badread: one Rp read x0.5, x0.85, x1.15, x1.5 or x2, 1 or 2 pulses after each of the study's steps (gel on,
  gel off, half peel, press back), and the run without; window: the 40 pulses after the step's own pulse;
- smallpeel: a true peel to contact 0.9 / 0.93 / 0.95 / 0.97 at pulse 80 (gelled from pulse 20, or dry), then a
  gel step (h 0.3 <-> 1) 10, 25 or 40 pulses later; window: from pulse 81 to 40 pulses after the gel step;
- second: a second step 1..5 pulses after the first: gel off then a peel to 0.5 / 0.75 (A), a half peel while
  gelled, gel off, then a press back (B), gel on then a peel to 0.75 / 0.5 (C), a half peel then 25 % contact (D);
  window: the 40 pulses after the second step's pulse;
- ramp: a slow peel, contact 1 -> 0.5 over 20 or 60 pulses, -> 0.75 over 20, -> 0.25 over 40, from pulse 80,
  gelled from pulse 20 or dry; window: pulse 80 to the end (200).
The step's own pulse (measured before any controller could know) is left out of every window. Per case: pulses
felt above +5 % and below -20 %, the highest and lowest felt; the summary totals them, and --compare lists the
cases whose highest felt moved by more than 5 points against another run's file (same family and options).
Versions: run this file from each tree (it loads its own tree's bench and core), e.g. a `git archive` of the
other revision; docs/performance.md ("Rule 4's refit only on a move of 1/8 octave") has figures of each family.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent / "shared"), str(HERE.parent / "firmware"), str(HERE.parent)]
from study import _bench, seeds_of  # noqa: E402  (this tree's bench/controllers.py)

FAMILIES = ("badread", "smallpeel", "second", "ramp")
STEP_NAMES = ("gel on", "gel off", "half peel", "press back")


def cases(family, bench):
    """(name, events, n pulses, {pulse: read factor}, window start, window end) of every case of a family."""
    E = bench.Event
    if family == "badread":
        ev = bench.STUDY_EVENTS
        for j, e in enumerate(ev):
            p = e.pulse
            yield f"{STEP_NAMES[j]}/none", ev, p + 41, {}, p + 1, p + 41
            for d in (1, 2):
                for f in (0.5, 0.85, 1.15, 1.5, 2.0):
                    yield f"{STEP_NAMES[j]}/+{d}/x{f}", ev, p + 41, {p + d: f}, p + 1, p + 41
    elif family == "smallpeel":
        for gel in (True, False):
            for c in (0.9, 0.93, 0.95, 0.97):
                for lag in (10, 25, 40):
                    ev = ([E(20, h=0.3)] if gel else []) + [E(80, contact=c), E(80 + lag, h=1.0 if gel else 0.3)]
                    yield f"{'gelled' if gel else 'dry'}/{c}/+{lag}", ev, 80 + lag + 41, {}, 81, 80 + lag + 41
    elif family == "second":
        for d in range(1, 6):
            for c in (0.5, 0.75):
                yield f"A{c}/{d}", [E(50, h=0.3), E(100, h=1.0), E(100 + d, contact=c)], 100 + d + 41, {}, 101 + d, 141 + d
                yield f"C{c}/{d}", [E(50, h=0.3), E(50 + d, contact=c)], 50 + d + 41, {}, 51 + d, 91 + d
            yield f"B/{d}", [E(50, h=0.3), E(100, contact=0.5), E(150, h=1.0), E(150 + d, contact=1.0)], 150 + d + 41, \
                {}, 151 + d, 191 + d
            yield f"D/{d}", [E(60, contact=0.5), E(60 + d, contact=0.25)], 60 + d + 41, {}, 61 + d, 101 + d
    elif family == "ramp":
        for gel in (True, False):
            for end, length in ((0.5, 20), (0.5, 60), (0.75, 20), (0.25, 40)):
                ev = ([E(20, h=0.3)] if gel else []) + [E(80 + j, contact=1 - (1 - end) * (j + 1) / length)
                                                        for j in range(length)]
                yield f"{'gelled' if gel else 'dry'}/{end}/{length}", ev, 200, {}, 81, 200


def run_case(bench, sc, seed, k, mk, corr, case, supervisor, board, noise):
    name, ev, n, bad, a, b = case
    real = sc.Controller.update
    count = [0]

    def update(c, rp_ohm):  # a bad read: update call n + 1 measures pulse n
        f = bad.get(count[0])
        count[0] += 1
        return real(c, int(round(rp_ohm * f)) if f is not None else rp_ohm)

    sc.Controller.update = update
    try:
        rows, target, _ = bench.run(sc.MODE_FAST, ev, n, i0=1000, board=board, sweeps=30, electrode=mk,
                                    correction=corr, seed=1000 + k, supervisor=supervisor, noise=noise)
    finally:
        sc.Controller.update = real
    r = (rows[a:b, 4] - target) / target
    r = r[np.isfinite(r)]
    return {"case": f"{seed}/{k}/{name}", "trusted": bool(bench.FIT_INFO.get("trusted")),
            "above5": int(np.sum(r > 0.05)), "below20": int(np.sum(r < -0.2)),
            "max": float(r.max()) if len(r) else None, "min": float(r.min()) if len(r) else None,
            "stops": int(np.sum(rows[a:b, 1] == 0))}


def summary(recs) -> str:
    mx = [r["max"] for r in recs if r["max"] is not None]
    mn = [r["min"] for r in recs if r["min"] is not None]
    return (f"{len(recs)} cases: pulses above +5 % {sum(r['above5'] for r in recs)} (cases {sum(r['above5'] > 0 for r in recs)})"
            f", below -20 % {sum(r['below20'] for r in recs)}; highest {max(mx, default=float('nan')):+.1%}, lowest "
            f"{min(mn, default=float('nan')):+.1%}; cases with a stop {sum(r['stops'] > 0 for r in recs)}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("family", choices=FAMILIES)
    ap.add_argument("--seeds", default="31,7", help="seeds and ranges (default 31,7)")
    ap.add_argument("--electrodes", type=int, default=15, help="electrodes a seed (default 15)")
    ap.add_argument("--supervisor", action="store_true", help="through the firmware's raise rule")
    ap.add_argument("--no-tau", action="store_true", help="the model without the tau gain (rule 7 off)")
    ap.add_argument("--exact", type=float, default=None, metavar="NOISE",
                    help="exact reads (the core alone) with this relative noise instead of the realistic board")
    ap.add_argument("--out", default="", help="JSON lines, one a case, written as each case ends")
    ap.add_argument("--compare", default="", help="another --out file of the same family and options")
    a = ap.parse_args(argv)
    seeds = seeds_of(a.seeds)
    if not 1 <= a.electrodes <= 1000:
        raise SystemExit(f"attacks: --electrodes {a.electrodes}: accepted 1 to 1000")
    if a.exact is not None and not 0 <= a.exact <= 0.1:
        raise SystemExit(f"attacks: --exact {a.exact}: accepted 0 to 0.1 (relative noise)")
    other = {}
    if a.compare:
        try:
            other = {(r := json.loads(ln))["case"]: r for ln in Path(a.compare).read_text().splitlines() if ln.strip()}
        except (OSError, ValueError, KeyError) as e:
            raise SystemExit(f"attacks: --compare {a.compare}: cannot read it as --out's JSON lines ({e})")
    bench = _bench()
    sc = bench.sc
    bench.TAU = not a.no_tau
    board, noise = ("exact", a.exact) if a.exact is not None else ("real", 0.0)
    corr = bench.selftest_correction("real") if board == "real" else None
    out = open(a.out, "w") if a.out else None
    recs = []
    try:
        for seed in seeds:
            rng = np.random.default_rng(seed)
            for k in range(a.electrodes):
                mk = bench.random_electrode(rng)
                for case in cases(a.family, bench):
                    rec = run_case(bench, sc, seed, k, mk, corr, case, a.supervisor, board, noise)
                    recs.append(rec)
                    if out:
                        out.write(json.dumps(rec) + "\n")
                        out.flush()
            print(f"  seed {seed} done ({len(recs)} cases)", file=sys.stderr, flush=True)
    except KeyboardInterrupt:
        print(f"attacks: interrupted; the {len(recs)} cases that ended are counted below", file=sys.stderr)
    finally:
        if out:
            out.close()
    print(f"{a.family}: {summary(recs)}")
    if other:
        both = [r for r in recs if r["case"] in other]
        print(f"{a.compare} on the same cases: {summary([other[r['case']] for r in both])}")
        for r in both:
            o = other[r["case"]]
            if r["max"] is not None and o["max"] is not None and abs(r["max"] - o["max"]) > 0.05:
                print(f"  {r['case']}: highest {o['max']:+.1%} -> {r['max']:+.1%}")


if __name__ == "__main__":
    main()
