"""Record the core's golden traces (tests/test_core_golden.py replays them).

Run: .venv/bin/python tests/golden/make_golden.py [--coverage] [--answers]

Writes tests/golden/core_traces.json.gz: op streams (tests/golden/replay.py's format)
with the sha256 of what the core answered after every op, from
- "hyp": tests/strategies.py's scenarios, every mode, and MODE_FAST with skin_model(),
  drawn by hypothesis with derandomize=True (the streams are stored, so the corpus does
  not depend on the hypothesis version);
- "ops": seeded random op streams shaped like those strategies, with the calls the
  firmware makes between updates (delivered, stop, set_mode, set_skin, calibrate,
  set_limits, rp_from_vp), and Rp sequences that drift, step or are drawn at random;
- "skin": closed loops on a float electrode of the skin model's form (hydration and
  contact steps, drifts), every mode, MODE_FAST with a skin model that fits or not;
- "hand": the benchmarks' sequences (bench/core_step.py's walk, the emulator's
  bench_sc.py scenarios, tests/test_core_micropython.py's heap-lock loop);
and "bench": the sha256 of every bench/controllers.py scenario x core mode (recomputed
closed loop by the test, then replayed in MicroPython).
Every "step"-th case keeps its full trace ("out") so a mismatch can show where.
Record with the core you trust; rerun only when a behaviour change is intended.
"""

import argparse
import collections
import gzip
import hashlib
import json
import math
import random
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
for p in (ROOT / "shared", ROOT / "tests", HERE, ROOT / "bench", ROOT / "firmware", ROOT):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import sensation_core as sc  # noqa: E402
import replay  # noqa: E402

OUT = HERE / "core_traces.json.gz"
KEEP_EVERY = 40  # every 40th case keeps its full trace


def sha(records):
    return hashlib.sha256("\n".join(records).encode()).hexdigest()[:32]


def op(k, *a):
    return k + "," + ",".join(str(int(x)) for x in a)


# ---- "hyp": the strategies of tests/strategies.py, drawn by hypothesis ----

def hyp_cases(n_modes=1600, n_skin=800):
    from hypothesis import HealthCheck, Phase, given, settings
    from hypothesis import strategies as st

    from strategies import scenario, skin_model

    got = []

    def head(lim, cal):
        return [op("L", lim.i_min_ua, lim.i_max_ua, lim.t_min_us, lim.t_max_us, lim.q_max_pc), op("C", cal.i0_ua, cal.t0_us, cal.rp0_ohm, cal.x_star_ohm, cal.y_star_pc)]

    def cfg(n):
        return settings(derandomize=True, database=None, deadline=None, max_examples=n,
                        phases=[Phase.explicit, Phase.generate], suppress_health_check=list(HealthCheck))

    @cfg(n_modes)
    @given(scenario(max_updates=16), st.sampled_from(sc.MODES))
    def modes(case, mode):
        lim, cal, rps = case
        got.append(" ".join(head(lim, cal) + [op("M", mode)] + [str(r) for r in rps]))

    @cfg(n_skin)
    @given(scenario(max_updates=16), skin_model())
    def skins(case, skin):
        lim, cal, rps = case
        got.append(" ".join(head(lim, cal) + [op("M", sc.MODE_FAST), op("S", *skin)] + [str(r) for r in rps]))

    modes()
    skins()
    return got


# ---- "ops": seeded random op streams shaped like the strategies ----

def r_limits(r):
    if r.random() < 0.5:
        return (1, sc.I_LIMIT_UA, 1, sc.T_LIMIT_US, sc.Q_LIMIT_PC)
    i_max = r.randint(100, sc.I_LIMIT_UA)
    i_min = r.randint(1, min(i_max, 2000))
    t_max = r.randint(50, sc.T_LIMIT_US)
    t_min = r.randint(1, min(t_max, 200))
    return (i_min, i_max, t_min, t_max, r.randint(max(i_min * t_min, 1), sc.Q_LIMIT_PC))


def r_cal(r, lim):
    i_lo, i_hi = max(100, lim[0]), min(10000, lim[1])
    t_lo, t_hi = max(50, lim[2]), min(2000, lim[3])
    if i_lo > i_hi:
        i_lo, i_hi = lim[0], lim[1]
    if t_lo > t_hi:
        t_lo, t_hi = lim[2], lim[3]
    i0 = r.randint(i_lo, i_hi)
    t_top = min(t_hi, lim[4] // i0)
    if t_top < t_lo:
        i0, t0 = lim[0], lim[2]
    else:
        t0 = r.randint(t_lo, t_top)
    q0 = i0 * t0
    y = r.choice([0, q0 - 1, q0 // 2, r.randint(0, q0 - 1), r.randint(0, q0 - 1)])
    return (i0, t0, r.randint(sc.RP_MIN_OHM, sc.RP_MAX_OHM), r.randint(sc.X_STAR_MIN_OHM, 0), y)


def r_skin(r):
    if r.random() < 0.1:
        return (0, 0, 0)
    return (r.randint(0, sc.SKIN_RS_MAX_OHM), r.randint(sc.SKIN_BETA_MIN_Q16, sc.SKIN_BETA_MAX_Q16),
            r.randint(sc.SKIN_CP_MIN_PF, sc.SKIN_CP_MAX_PF) if r.random() < 0.5 else r.randint(5000, 60000))


def r_rps(r, n, rp0):
    kind = r.choice(["iid", "drift", "drift", "step", "step", "walk"])
    rp = rp0
    out = []
    rate = r.uniform(-0.03, 0.03)
    for k in range(n):
        if kind == "iid":
            rp = r.choice([r.randint(sc.RP_MIN_OHM, sc.RP_MAX_OHM), r.randint(-(2**20), 2**20),
                           r.choice([sc.RP_MIN_OHM - 1, sc.RP_MAX_OHM + 1, 0, sc.RP_OVER, sc.RP_INVALID])])
        elif kind == "drift":
            rp = rp * (1 + rate + r.gauss(0, 0.002))
        elif kind == "step":
            if r.random() < 0.15:
                rp = rp * r.uniform(0.3, 2.5)
            else:
                rp = rp * (1 + r.gauss(0, 0.001))
        else:
            rp = rp * math.exp(r.gauss(0, 0.1))
        rp = int(round(rp))
        if kind != "iid":
            rp = max(200, min(rp, 250000))
        out.append(rp)
    return out


def ops_cases(n=1500, seed=14):
    r = random.Random(seed)
    r_st = random.Random(seed + 1)  # the statuses delivered() is told (its own stream: the other ops as before)
    got = []
    for _ in range(n):
        lim = r_limits(r)
        cal = r_cal(r, lim)
        ops = [op("L", *lim)]
        if r.random() < 0.97:
            ops.append(op("C", *cal))
        ops.append(op("M", r.choice(sc.MODES + (sc.MODE_FAST, sc.MODE_FAST, sc.MODE_AKHTAR))))
        if r.random() < 0.5:
            ops.append(op("S", *r_skin(r)))
        for rp in r_rps(r, r.randint(4, 40), cal[2]):
            x = r.random()
            if x < 0.04:
                d = (r.randint(0, lim[1] + 5), r.randint(0, lim[3] + 5))
                x_st = r_st.random()  # the firmware's: a pulse's bounds (some with any bits; a third none: as it is)
                ops.append(op("D", *d) if x_st < 0.3 else op("D", *d, r_st.randint(0, sc.ST_BOUND_MASK))
                           if x_st < 0.9 else op("D", *d, r_st.randint(0, 0x1FF)))
            elif x < 0.06:
                ops.append(op("X", r.choice([sc.ST_RP_HIGH, sc.ST_RP_LOW, sc.ST_Q_NONPOS])))
            elif x < 0.08:
                ops.append(op("M", r.randint(-1, 6)))
            elif x < 0.10:
                ops.append(op("S", *r_skin(r)) if r.random() < 0.8 else op("S", r.randint(-5, 6000),
                                                                               r.randint(0, 100000), r.randint(0, 3000000)))
            elif x < 0.115:
                c2 = r_cal(r, lim) if r.random() < 0.7 else (r.randint(0, 30000), r.randint(0, 9000), r.randint(0, 250000),
                                                             r.randint(-25000, 5), r.randint(-5, 10**6))
                ops.append(op("C", *c2))
            elif x < 0.125:
                ops.append(op("L", *(r_limits(r) if r.random() < 0.7 else tuple(r.randint(0, 40000) for _ in range(5)))))
            elif x < 0.14:
                ops.append(op("V", r.randint(-5, sc.VP_LIMIT_MV + 5), r.randint(-5, 20000)))
            ops.append(str(rp))
        got.append(" ".join(ops))
    return got


# ---- "skin": closed loops on a float electrode of the model's form ----

def rp_float(i_ua, t_us, rs, beta, s_ohm, cp_pf):
    rr = s_ohm * (i_ua / 1000.0) ** (-beta)
    return rs + rr * (1 - math.exp(-t_us / (rr * cp_pf * 1e-6)))


def skin_cases(n=500, seed=15):
    r = random.Random(seed)
    got = []
    for _ in range(n):
        rs = r.uniform(0, 3000)
        beta = r.uniform(0.3, 0.95)
        s = r.uniform(8000, 120000)
        cp = math.exp(r.uniform(math.log(3000), math.log(80000)))
        lim = (r.choice([100, 300, 500]), r.choice([5000, 10000, 20000]), r.choice([20, 50, 100]),
               r.choice([2000, 4000, 8000]), r.choice([10_000_000, 20_000_000, sc.Q_LIMIT_PC]))
        i0 = r.randint(max(lim[0], 300), 3000)
        t0 = r.randint(max(lim[2], 100), min(lim[3], 1500))
        rp0 = int(round(rp_float(i0, t0, rs, beta, s, cp)))
        if not sc.RP_MIN_OHM <= rp0 <= sc.RP_MAX_OHM:
            continue
        q0 = i0 * t0
        cal = (i0, t0, rp0, r.randint(-5000, 0), r.choice([0, q0 // 5, q0 // 2, r.randint(0, q0 - 1)]))
        mode = r.choice(sc.MODES + (sc.MODE_FAST,) * 6)
        ops = [op("L", *lim), op("C", *cal), op("M", mode)]
        if mode == sc.MODE_FAST and r.random() < 0.8:
            e = r.choice([0.0, 0.0, 0.05, 0.2])  # the fit's error
            ops.append(op("S", min(sc.SKIN_RS_MAX_OHM, rs * (1 + r.uniform(-e, e))),
                          max(sc.SKIN_BETA_MIN_Q16, round(beta * (1 + r.uniform(-e, e)) * 65536)),
                          max(sc.SKIN_CP_MIN_PF, cp * (1 + r.uniform(-e, e)))))
        c = sc.Controller(*lim)
        c.calibrate(*cal)
        c.set_mode(mode)
        if ops[-1][0] == "S":
            c.set_skin(*[int(w) for w in ops[-1][2:].split(",")])
        contact, h, h_to, h_rate = 1.0, 1.0, 1.0, 0.0
        noise = r.choice([0.0, 0.0, 0.001, 0.003])
        for k in range(r.randint(20, 120)):
            x = r.random()
            if x < 0.04:  # hydration step
                h = h_to = r.uniform(0.3, 2.0)
            elif x < 0.07:  # contact step (peel): S ~ a**(beta - 1), Cp ~ a
                contact = r.uniform(0.2, 1.0)
            elif x < 0.09:  # a drift begins
                h_to, h_rate = r.uniform(0.3, 1.5), r.uniform(0.02, 0.2)
            h += (h_to - h) * h_rate
            i, t = c.i_ua, c.t_us
            if i == 0:
                i, t = i0, t0
                ops.append(op("D", i, t))
                c.delivered(i, t, c.status)
            a = max(contact, 1e-3)
            v = rp_float(i, t, rs, beta, s * h * a ** (beta - 1), cp * a) * (1 + r.gauss(0, noise))
            rp = int(round(min(v, 1e6)))
            ops.append(str(rp))
            c.update(rp)
        got.append(" ".join(ops))
    return got


# ---- "hand": the benchmarks' sequences ----

BENCH_SC_ALT = (20000, 10000)
BENCH_SC_JUMP = (20000, 9000, 30000, 12000, 25000, 8000, 40000, 15000, 60000, 5000, 18000, 11000)


def hand_cases():
    got = []
    # /work/shared/emulator/bench_sc.py: Controller(500, 10000, 100, 4000, 30000000), 1000 updates each
    head = [op("L", 500, 10000, 100, 4000, 30000000), op("C", 1000, 1000, 20000, -1670, 186000)]
    for mode, skin, seq in ((None, None, BENCH_SC_ALT), (sc.MODE_FAST, None, BENCH_SC_ALT),
                            (sc.MODE_FAST, (500, 45875, 20000), BENCH_SC_JUMP)):
        ops = list(head)
        if mode is not None:
            ops.append(op("M", mode))
        if skin is not None:
            ops.append(op("S", *skin))
        got.append(" ".join(ops + [str(seq[i % len(seq)]) for i in range(1000)]))
    # bench/core_step.py: the walk over 3..123 kohm, default mode and MODE_FAST with a skin model
    walk = [str(3000 + (k * 7919) % 120000) for k in range(2000)]
    head = [op("L", 500, 20000, 50, 2000, 20000000), op("C", 1000, 1000, 30000, -1670, 186000)]
    got.append(" ".join(head + walk))
    for mode in sc.MODES:
        got.append(" ".join(head + [op("M", mode)] + walk[:500]))
    got.append(" ".join(head + [op("M", sc.MODE_FAST), op("S", 500, 36045, 14000)] + walk))
    # tests/test_core_micropython.py's heap-lock loop: every mode, skin on and off, faults
    ops = list(head)
    rp = 30000
    for n in range(10000):
        if n % 500 == 0:
            ops.append(op("M", sc.MODES[(n // 500) % len(sc.MODES)]))
        if n % 1000 == 0:
            ops.append(op("S", 500, 36045, 14000) if n % 2000 else op("S", 0, 0, 0))
        rp = 3000 + (rp * 7 + n * 131) % 120000
        if n % 997 == 0:
            rp = 250000
        ops.append(str(rp))
    got.append(" ".join(ops))
    # corners: rp_from_vp's edges, an estimate that floors to 0 pC (ST_Q_NONPOS), a charge
    # ceiling below i_max * t_min
    got.append(" ".join(op("V", vp, i) for vp in (-1, 0, 1, 2, 999999, 1000000, 1000001, 2**29)
                        for i in (-1, 0, 1, 3, 1000, 20000)))
    for mode in sc.MODES:
        got.append(" ".join([op("L", 1, 20000, 1, 8000, 1000), op("C", 1, 1, 200000, 0, 0), op("M", mode),
                             "500", "200000", "500", "100000", "500"]))
        got.append(" ".join([op("L", 1, 20000, 100, 8000, 200000), op("C", 1000, 100, 30000, 0, 0), op("M", mode)]
                            + [str(30000 >> k) for k in range(6)] + ["30000", "200000", "500", "200000"]))
    return got


# ---- "bench": bench/controllers.py's scenarios, recorded closed loop ----

def bench_scenarios():
    import controllers as b
    from sim_electrode import Electrode

    cases = []
    for name in ("gel-step", "gel", "peel", "exercise", "off"):
        ev, n = b.scenario_events(name)
        cases.append((name, 1000, ev, n))
    for i0 in (700, 1000, 2000):
        for d in (-30, -20, -10, 10, 20, 50):
            if Electrode().rp_kohm(i0, 1000) + d < 3:
                continue
            ev, n = b.step_events(i0, d)
            cases.append((f"step {d:+d} kohm @ {i0}", i0, ev, n))
    return b, cases


def record_bench(only=None):
    """{"scenario/mode": (ops, records)}: each (scenario, core mode) of bench/controllers.py
    run closed loop on CPython, every call to the core recorded."""
    b, cases = bench_scenarios()
    real = sc.Controller
    log = []

    class Recording(real):
        def __init__(self, *a):
            self.golden_on = False  # __init__'s own set_limits is not a call of the bench's
            super().__init__(*a)
            self.golden_on = True
            log.append((op("L", *a), replay.snap(self)))

        def _rec(self, text, f, *a):
            on = self.golden_on  # (update's own stop() is no call of the bench's either)
            self.golden_on = False
            r = f(*a)
            self.golden_on = on
            if on:
                log.append((text, replay.snap(self)))
            return r

        def calibrate(self, *a):
            return self._rec(op("C", *a), super().calibrate, *a)

        def set_mode(self, m):
            return self._rec(op("M", m), super().set_mode, m)

        def set_skin(self, *a):
            return self._rec(op("S", *a), super().set_skin, *a)

        def delivered(self, i, t, s):  # (the status as it is: replay's "D,i,t")
            return self._rec(op("D", i, t) if s == self.status else op("D", i, t, s), super().delivered, i, t, s)

        def stop(self, s):
            return self._rec(op("X", s), super().stop, s)

        def set_limits(self, *a):
            return self._rec(op("L", *a), super().set_limits, *a)

        def update(self, rp):
            return self._rec(str(rp), super().update, rp)

    out = {}
    sc.Controller = Recording
    try:
        for name, i0, ev, n in cases:
            for mode, mname in b.ALL_NAMES.items():
                if mode == b.ORACLE:  # not a core mode (it overrides the core's proposal)
                    continue
                key = f"{name}/{mname}"
                if only is not None and key not in only:
                    continue
                del log[:]
                b.run(mode, ev, n, i0=i0)
                out[key] = (" ".join(x[0] for x in log), [x[1] for x in log])
    finally:
        sc.Controller = real
    return out


def record_all(hyp=None):
    """Every section's streams and the core's answers to them; hyp: the hypothesis section's streams
    to keep (else drawn again)."""
    sections = {"hyp": hyp_cases() if hyp is None else hyp, "ops": ops_cases(), "skin": skin_cases(),
                "hand": hand_cases()}
    cases = []
    for sec, lines in sections.items():
        for k, line in enumerate(lines):
            recs = []
            replay.run(line, recs)
            c = {"name": f"{sec}/{k}", "ops": line, "sha": sha(recs)}
            if k % KEEP_EVERY == 0:
                c["out"] = recs
            cases.append(c)
    bench = {key: sha(recs) for key, (ops, recs) in record_bench().items()}
    return {"format": 1, "cases": cases, "bench": bench}


def rerecord_answers(old):
    """The hypothesis section's stored streams kept (drawing them again changes them: hypothesis's
    draws are not the same from run to run), the seeded sections made again (the skin section's
    Rp comes from closed loops through the core, so a behaviour change changes its streams), and
    every stream's answers recorded with the core as it is now: an intended behaviour change then
    shows as the streams whose answers changed. Returns (data, names of the changed ones)."""
    data = record_all([c["ops"] for c in old["cases"] if c["name"].startswith("hyp/")])
    before = {c["name"]: c["sha"] for c in old["cases"]}
    changed = [c["name"] for c in data["cases"] if before.get(c["name"]) != c["sha"]]
    changed += [f"bench/{k}" for k, v in data["bench"].items() if old["bench"].get(k) != v]
    return data, changed


def line_coverage(fn):
    """Run fn with a line tracer on shared/*.py; return {file: set of lines run}."""
    hit = {}
    shared = str(ROOT / "shared")

    def tracer(frame, event, arg):
        f = frame.f_code.co_filename
        if not f.startswith(shared):
            return None
        if event == "line":
            hit.setdefault(Path(f).name, set()).add(frame.f_lineno)
        return tracer

    sys.settrace(tracer)
    try:
        fn()
    finally:
        sys.settrace(None)
    return hit


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--coverage", action="store_true", help="also list the core's lines no case runs")
    ap.add_argument("--answers", action="store_true",
                    help="keep the stored hypothesis streams, make the seeded ones again, record every answer "
                         "(an intended behaviour change: says how many streams' answers changed)")
    a = ap.parse_args()
    if a.answers:
        data, changed = rerecord_answers(json.loads(gzip.decompress(OUT.read_bytes())))
        by = collections.Counter(name.split("/")[0] for name in changed)
        print(f"answers changed in {len(changed)} of {len(data['cases']) + len(data['bench'])} streams: "
              f"{dict(by) or 'none'}")
    else:
        data = record_all()
    raw = json.dumps(data, separators=(",", ":")).encode()
    OUT.write_bytes(gzip.compress(raw, 9, mtime=0))
    print(f"{len(data['cases'])} cases, {len(data['bench'])} bench runs, "
          f"{sum(c['ops'].count(' ') + 1 for c in data['cases'])} ops -> {OUT} ({OUT.stat().st_size} bytes)")
    if a.coverage:
        import ast

        hit = line_coverage(lambda: [replay.run(c["ops"], []) for c in data["cases"]])
        for src in sorted((ROOT / "shared").glob("*.py")):
            if src.name == "hid_protocol.py":
                continue
            body = set()
            for node in ast.walk(ast.parse(src.read_text())):
                if isinstance(node, ast.stmt) and not isinstance(node, (ast.FunctionDef, ast.ClassDef)):
                    body.add(node.lineno)
            seen = hit.get(src.name, set())
            missed = sorted(x for x in body if x not in seen)
            print(f"{src.name}: {len(body) - len(missed)}/{len(body)} statement lines run; never: {missed}")


if __name__ == "__main__":
    main()
