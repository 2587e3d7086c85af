"""The core as the firmware's frame calls it, on the emulated RP2040 (MicroPython v1.28.0
in rp2040js), every mode: emulated us per call, median / mean / worst.

Run: .venv/bin/python bench/core_frame_chip.py [-n 1000] [--pad N ...] [--core-rev REV ...]

Per mode (MODE_OPEN_LOOP ... MODE_FAST, and MODE_FAST with a skin model), n updates
with Rp alternating 20/10 kOhm (the skin model's row: Rp jumping every pulse, as
bench_sc.py's scenario c), timed with ticks_us on the emulated clock less the empty
timing window:
- `update`: `c.update(rp)` alone, the bound method fetched once (as bench_sc.py);
- `frame`: what stim.Stimulator._control spends in the core for a channel:
  `ctl.i_ua = c.di`, `ctl.t_us = c.dt`, `ctl.status = c.ds` (properties over the words `stim._control` stores
  by ptr32 since session 16: this bench's figure is an upper bound), `ctl.update(c.rp)`, then
  `ctl.i_ua`, `ctl.t_us` read,
  from a plain function, the controller an attribute of a channel object (the
  pulse delivered = the controller's own last output);
- `rp_from_vp`: `sc.rp_from_vp(vp, c.di)` (stim.Stimulator._measure now computes it inline).
The chip's pulses are checked against CPython's (hash of I, T, status per update).
--core-rev REV (repeatable) times git revision REV's core instead (its shared/
modules); the hashes are still CPython's of the working tree (same answers expected).
rp2040js is installed with npm into ~/.cache/steadytouch-rp2040js (once), as by
bench/core_chip.py, whose runner and compiler this script uses.
"""

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT / "bench"), str(ROOT / "shared")]
import core_chip  # noqa: E402  (runner, compile_core: the same set-up as bench/core_chip.py)
import sensation_core as sc  # noqa: E402

SEQ_ALT = (20000, 10000)
SEQ_JUMP = (20000, 9000, 30000, 12000, 25000, 8000, 40000, 15000, 60000, 5000, 18000, 11000)
SKIN = (500, 45875, 20000)
# (label, mode, skin, Rp sequence)
ROWS = [(name, m, None, SEQ_ALT) for name, m in (
    ("MODE_OPEN_LOOP", sc.MODE_OPEN_LOOP), ("MODE_CONSTANT_CHARGE", sc.MODE_CONSTANT_CHARGE),
    ("MODE_CONSTANT_ENERGY", sc.MODE_CONSTANT_ENERGY), ("MODE_PULSE_WIDTH_LINEAR", sc.MODE_PULSE_WIDTH_LINEAR),
    ("MODE_AKHTAR", sc.MODE_AKHTAR), ("MODE_FAST", sc.MODE_FAST))]
ROWS.append(("MODE_FAST + skin model, Rp jumping", sc.MODE_FAST, SKIN, SEQ_JUMP))

# the same on the chip and in CPython (ROWS, N and PAD are put in front of it)
SCRIPT = """
import time, gc
import sensation_core as sc
from array import array
_pad = bytearray(PAD)
tu = time.ticks_us
td = time.ticks_diff


class Chan:  # what stim's _control and _measure read of a channel
    def __init__(self, ctl):
        self.ctl = ctl
        self.di = 0
        self.dt = 0
        self.ds = 0  # the status of the pulse delivered
        self.rp = 0
        self.vp = 0


def make(mode, skin):
    c = sc.Controller(500, 10000, 100, 4000, 30000000)
    c.calibrate(1000, 1000, 20000, -1670, 186000)
    c.set_mode(mode)
    if skin:
        c.set_skin(skin[0], skin[1], skin[2])
    return c


def control(ch):  # the core's part of stim.Stimulator._control for one channel
    ctl = ch.ctl
    ctl.i_ua = ch.di  # delivered(), inline as in _control
    ctl.t_us = ch.dt
    ctl.status = ch.ds
    st = ctl.update(ch.rp)
    ni = ctl.i_ua
    nt = ctl.t_us
    return st + ni + nt


def summary(d, off):
    s = sorted(d)
    n = len(s)
    return "%d %d %d" % (s[n // 2] - off, sum(s) // n - off, s[-1] - off)


def main():
    e = array("i", bytes(4 * 400))
    for k in range(400):
        t0 = tu()
        e[k] = td(tu(), t0)
    off = sorted(e)[200]
    d = array("i", bytes(4 * N))
    for label, mode, skin, seq in ROWS:
        L = len(seq)
        c = make(mode, skin)
        gc.collect()
        upd = c.update
        h = 0
        for k in range(N):
            rp = seq[k % L]
            t0 = tu()
            st = upd(rp)
            d[k] = td(tu(), t0)
            h = (h * 31 + c.i_ua * 7 + c.t_us * 3 + st) & 0xFFFFF
        a = summary(d, off)
        ch = Chan(make(mode, skin))
        gc.collect()
        h2 = 0
        for k in range(N):
            ch.rp = seq[k % L]
            ch.di = ch.ctl.i_ua
            ch.ds = ch.ctl.status
            ch.dt = ch.ctl.t_us
            t0 = tu()
            v = control(ch)
            d[k] = td(tu(), t0)
            h2 = (h2 * 31 + v) & 0xFFFFF
        b = summary(d, off)
        for k in range(N):
            ch.vp = seq[k % L] // 5
            t0 = tu()
            ch.rp = sc.rp_from_vp(ch.vp, ch.di)
            d[k] = td(tu(), t0)
        print("ROW|%s|%s|%s|%s|%d|%d" % (label, a, b, summary(d, off), h, h2))


main()
"""


def cpython_hashes(n):
    """The hashes of CPython's core (the working tree) for the same rows: [(h, h2)]."""
    import time

    src = SCRIPT.replace("main()\n", "").replace("PAD", "0")
    g = {"ROWS": ROWS, "N": n}
    time.ticks_us = lambda: 0  # CPython has no ticks: the hashes only
    time.ticks_diff = lambda a, b: 0
    exec(compile(src, "core_frame_chip", "exec"), g)
    out = []
    for label, mode, skin, seq in ROWS:
        c = g["make"](mode, skin)
        h = 0
        for k in range(n):
            st = c.update(seq[k % len(seq)])
            h = (h * 31 + c.i_ua * 7 + c.t_us * 3 + st) & 0xFFFFF
        ch = g["Chan"](g["make"](mode, skin))
        h2 = 0
        for k in range(n):
            ch.rp = seq[k % len(seq)]
            ch.di = ch.ctl.i_ua
            ch.ds = ch.ctl.status
            ch.dt = ch.ctl.t_us
            h2 = (h2 * 31 + g["control"](ch)) & 0xFFFFF
        out.append((h, h2))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", type=int, default=1000, help="updates per mode")
    ap.add_argument("--pad", type=int, action="append", default=[], help="bytes allocated after the import")
    ap.add_argument("--core-rev", action="append", default=[], metavar="REV",
                    help="time git revision REV's core instead of the working tree's (repeatable)")
    a = ap.parse_args()
    if not (core_chip.EMU / "rp2run.mjs").exists():
        sys.exit(f"no emulator at {core_chip.EMU}: it is the shared reference folder beside the checkout "
                 "(../shared/emulator)")
    if not 10 <= a.n <= 5000:
        sys.exit(f"-n {a.n}: out of range [10, 5000]")
    run = core_chip.runner()
    want = cpython_hashes(a.n)
    for rev in a.core_rev or [None]:
        with tempfile.TemporaryDirectory() as d:
            d = Path(d)
            puts = core_chip.compile_core(d, rev)
            for pad in [0] + a.pad:
                script = d / f"frame_pad{pad}.py"
                rows = repr([(r[0], r[1], r[2], r[3]) for r in ROWS])
                script.write_text(f"ROWS = {rows}\nN = {a.n}\n" + SCRIPT.replace("PAD", str(pad)))
                r = subprocess.run(["node", str(run), "--uf2", str(core_chip.EMU / "firmware.uf2"), "--bootrom",
                                    str(core_chip.EMU / "bootrom-b1.bin"), *puts, str(script)],
                                   capture_output=True, text=True)
                if r.returncode:
                    sys.exit(f"the emulator failed (exit {r.returncode}): {r.stderr.strip().splitlines()[-3:]}")
                got = [ln.split("|")[1:] for ln in r.stdout.splitlines() if ln.startswith("ROW|")]
                if len(got) != len(ROWS):
                    sys.exit(f"the chip answered {len(got)} of {len(ROWS)} rows: {r.stdout[-400:]}")
                core = "working tree" if rev is None else f"git {rev}"
                print(f"## core of the {core}, pad {pad} B: emulated us per call, median / mean / worst ({a.n} calls)")
                print("| mode | update | frame: delivered + update | rp_from_vp | chip = CPython |")
                print("|---|---|---|---|---|")
                for (label, upd, frame, rpv, h, h2), (wh, wh2) in zip(got, want):
                    same = "yes" if (int(h), int(h2)) == (wh, wh2) else "NO"
                    print(f"| {label} | {' / '.join(upd.split())} | {' / '.join(frame.split())} | "
                          f"{' / '.join(rpv.split())} | {same} |")


if __name__ == "__main__":
    main()
